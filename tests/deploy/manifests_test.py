"""deploy/'s numbers agree with the server's: the memory limit of a replica (Kubernetes and compose) covers its
two budgets plus the process margin, the grace period covers the preStop pause and the drain, the drain fits the
longest upload measured, and kustomization.yaml applies every manifest, the PodDisruptionBudget included.
Reads the files as text (no YAML library needed); when kubectl is installed, also renders the kustomization."""

import pathlib
import re
import shutil
import subprocess
import unittest

DEPLOY = pathlib.Path(__file__).parents[2] / "deploy"
K8S = DEPLOY / "k8s"
# What neither budget counts (code, threads, allocator slack, rig builds in progress); deployment.yaml says why.
PROCESS_MARGIN_MIB = 1024
# The longest work measured on 2 cores: a face rig file upload with a fixed rim (9 min 14 s).
LONGEST_UPLOAD_SECONDS = 554
# After the drain: stopping builds in progress (within a second) and exiting.
EXIT_MARGIN_SECONDS = 10


def number(pattern, text, what):
    found = re.findall(pattern, text)
    if len(found) != 1:
        raise AssertionError(f"{what}: expected one match of {pattern!r}, found {found}")
    return int(found[0])


def mebibytes(quantity):
    value, unit = re.fullmatch(r"(\d+)(Gi|Mi|g|m)", quantity).groups()
    return int(value) * (1024 if unit in ("Gi", "g") else 1)


class KubernetesTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.deployment = (K8S / "deployment.yaml").read_text()

    def test_the_memory_limit_covers_both_budgets_and_the_process(self):
        budget = number(r"--memory-budget-mb=(\d+)", self.deployment, "deployment.yaml")
        requests = number(r"--request-memory-mb=(\d+)", self.deployment, "deployment.yaml")
        resources = self.deployment[self.deployment.index("resources:"):]
        limit = mebibytes(re.search(r"limits:\s+cpu: \"\d+\"\s+memory: (\w+)", resources).group(1))
        request = mebibytes(re.search(r"requests:\s+cpu: \"\d+\"\s+memory: (\w+)", resources).group(1))
        self.assertGreaterEqual(limit, budget + requests + PROCESS_MARGIN_MIB,
                                f"--memory-budget-mb {budget} + --request-memory-mb {requests} + "
                                f"{PROCESS_MARGIN_MIB} MiB exceed the limit of {limit} MiB")
        self.assertEqual(request, limit, "the memory request should be the limit (deployment.yaml says why)")

    def test_the_grace_period_covers_the_pause_and_the_drain_and_the_drain_the_longest_upload(self):
        drain = number(r"--drain-seconds=(\d+)", self.deployment, "deployment.yaml")
        grace = number(r"terminationGracePeriodSeconds: (\d+)", self.deployment, "deployment.yaml")
        pause = number(r'command: \["sleep", "(\d+)"\]', self.deployment, "deployment.yaml (preStop)")
        self.assertGreaterEqual(drain, LONGEST_UPLOAD_SECONDS)
        self.assertGreaterEqual(grace, pause + drain + EXIT_MARGIN_SECONDS)

    def test_kustomization_applies_every_manifest_and_the_budget_selects_the_servers(self):
        listed = re.findall(r"^  - (\S+\.yaml)$", (K8S / "kustomization.yaml").read_text(), re.MULTILINE)
        present = sorted(p.name for p in K8S.glob("*.yaml") if p.name != "kustomization.yaml")
        self.assertEqual(sorted(listed), present)
        self.assertIn("pdb.yaml", listed)
        pdb = (K8S / "pdb.yaml").read_text()
        self.assertIn("kind: PodDisruptionBudget", pdb)
        self.assertEqual(number(r"maxUnavailable: (\d+)", pdb, "pdb.yaml"), 1)
        for label in ("app.kubernetes.io/name: springblend", "app.kubernetes.io/component: server"):
            self.assertIn(label, pdb[pdb.index("selector:"):])
            self.assertIn(label, self.deployment[self.deployment.index("selector:"):])

    @unittest.skipIf(shutil.which("kubectl") is None, "kubectl is not installed (the text checks above still ran)")
    def test_kubectl_renders_the_kustomization(self):
        rendered = subprocess.run(["kubectl", "kustomize", str(K8S)], capture_output=True, text=True, check=True)
        for kind in ("Deployment", "Service", "HorizontalPodAutoscaler", "PersistentVolumeClaim",
                     "PodDisruptionBudget"):
            self.assertIn(f"kind: {kind}", rendered.stdout)


class ComposeTest(unittest.TestCase):
    def test_the_local_farm_agrees_too(self):
        compose = (DEPLOY / "compose.yaml").read_text()
        budget = number(r'"--memory-budget-mb", "(\d+)"', compose, "compose.yaml")
        requests = number(r'"--request-memory-mb", "(\d+)"', compose, "compose.yaml")
        drain = number(r'"--drain-seconds", "(\d+)"', compose, "compose.yaml")
        limit = mebibytes(re.search(r"memory: (\w+)", compose).group(1))
        grace = number(r"stop_grace_period: (\d+)s", compose, "compose.yaml")
        self.assertGreaterEqual(limit, budget + requests + PROCESS_MARGIN_MIB)
        self.assertGreaterEqual(drain, LONGEST_UPLOAD_SECONDS)
        self.assertGreaterEqual(grace, drain + EXIT_MARGIN_SECONDS)


if __name__ == "__main__":
    unittest.main()
