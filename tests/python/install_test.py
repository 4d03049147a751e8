"""python_install_test: the Python package installs with pip, offline, into a fresh virtual environment.

What a pipeline team does: a virtual environment with --system-site-packages (Debian's python3-grpcio,
python3-protobuf and python3-numpy come from the system), then `pip install --no-index --no-build-isolation`
of client/python, and of the wheel docs/python.md's command builds. Each installed package must import from
the environment, not from the source or the build tree (PYTHONPATH is cleared), print the project's version
with `python -m springblend --version`, carry its generated gRPC modules, and name a missing numpy or grpcio
with the Debian package that provides it. The wheel is built once with each generator setup.py knows
(protoc, grpc_tools when Debian's python3-grpc-tools is installed, the CMake build's modules).

Runs from a copy of client/python, proto/ and CMakeLists.txt in a temporary directory, so the source tree
gets no build/ or egg-info, and the package is shown to need nothing else of the repository.
Environment (tests/CMakeLists.txt): SPRINGBLEND_VERSION, SPRINGBLEND_PYTHON_DIR (the CMake build's package).
"""

import glob
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import unittest

REPOSITORY = pathlib.Path(__file__).resolve().parents[2]
PYTHON = "/usr/bin/python3" if os.path.exists("/usr/bin/python3") else sys.executable

# Imports the client as a user would and checks that it is the environment's copy with its gRPC modules.
IMPORT_CHECK = """
import sys, springblend
from springblend.v1 import springblend_pb2, springblend_pb2_grpc
assert springblend.__file__.startswith(sys.prefix), (springblend.__file__, sys.prefix)
client = springblend.Client("127.0.0.1:1", timeout=1)
assert not client.healthy(timeout=0.5)
client.close()
print(springblend.__version__, springblend.pb.BuildProgress(stage="paths").stage)
"""


def clean_environment(**extra):
    environment = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "SPRINGBLEND_GENERAT"))}
    environment.update(PYTHONDONTWRITEBYTECODE="1", PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1", **extra)
    return environment


class InstallTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.directory = pathlib.Path(tempfile.mkdtemp(prefix="springblend-install-"))
        cls.source = cls.directory / "src"
        shutil.copytree(REPOSITORY / "client" / "python", cls.source / "client" / "python",
                        ignore=shutil.ignore_patterns("build", "dist", "*.egg-info", "__pycache__"))
        shutil.copytree(REPOSITORY / "proto", cls.source / "proto")
        shutil.copy(REPOSITORY / "CMakeLists.txt", cls.source / "CMakeLists.txt")
        cls.version = os.environ.get("SPRINGBLEND_VERSION", "")

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.directory, ignore_errors=True)

    def run_command(self, command, environment=None, cwd=None):
        result = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=240,
                                cwd=cwd or self.directory, env=environment or clean_environment())
        if result.returncode != 0:
            self.fail(f"{' '.join(map(str, command))} exited {result.returncode}:\n{result.stdout}\n{result.stderr}")
        return result.stdout

    def fresh_environment(self, name):
        """A virtual environment with the system's site packages; returns its python."""
        venv = self.directory / name
        self.run_command([PYTHON, "-m", "venv", "--system-site-packages", venv])
        return venv / "bin" / "python"

    def check_installed(self, python):
        self.assertEqual(self.run_command([python, "-m", "springblend", "--version"]).strip(),
                         f"springblend {self.version}")
        self.assertEqual(self.run_command([python, "-c", IMPORT_CHECK]).split(), [self.version, "paths"])
        for module, debian in (("numpy", "python3-numpy"), ("grpc", "python3-grpcio")):
            hidden = f"import sys; sys.modules[{module!r}] = None\nimport springblend"
            result = subprocess.run([str(python), "-c", hidden], capture_output=True, text=True, timeout=60,
                                    cwd=self.directory, env=clean_environment())
            self.assertNotEqual(result.returncode, 0)
            last = result.stderr.strip().splitlines()[-1]
            self.assertIn("ModuleNotFoundError: springblend needs " + module, last)
            self.assertIn(f"apt install {debian}", last)
            self.assertIn("pip install", last)

    def test_pip_install_of_the_source(self):
        python = self.fresh_environment("venv-source")
        self.run_command([python, "-m", "pip", "install", "--no-index", "--no-build-isolation",
                          self.source / "client" / "python"])
        self.check_installed(python)
        self.assertIn("Version: " + self.version, self.run_command([python, "-m", "pip", "show", "springblend"]))

    def test_wheel_from_each_generator(self):
        generators = ["protoc"]
        if subprocess.run([PYTHON, "-c", "import grpc_tools.protoc"], capture_output=True).returncode == 0:
            generators.append("grpc_tools")
        cmake_package = os.environ.get("SPRINGBLEND_PYTHON_DIR", "")
        if cmake_package:
            generators.append("cmake")
        for generator in generators:
            with self.subTest(generator=generator):
                dist = self.directory / f"dist-{generator}"
                extra = {"SPRINGBLEND_GENERATOR": generator}
                if generator == "cmake":
                    extra["SPRINGBLEND_GENERATED_DIR"] = cmake_package
                shutil.rmtree(self.source / "client" / "python" / "build", ignore_errors=True)
                # The command docs/python.md gives, run from the repository root (here: the copy).
                self.run_command([PYTHON, "-m", "pip", "wheel", "--no-deps", "--no-index", "--no-build-isolation",
                                  "-w", dist, "client/python"], clean_environment(**extra), cwd=self.source)
                (wheel,) = glob.glob(str(dist / f"springblend-{self.version}-py3-none-any.whl"))
                python = self.fresh_environment(f"venv-{generator}")
                self.run_command([python, "-m", "pip", "install", "--no-index", wheel])
                self.check_installed(python)


if __name__ == "__main__":
    unittest.main()
