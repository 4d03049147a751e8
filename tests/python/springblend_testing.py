"""Shared by the Python client tests and the Blender add-on test: a real springblend-server on a free
loopback port, the springblend CLI, and the cylinder test data as numpy arrays.

Paths come from the environment CTest sets (tests/CMakeLists.txt): SPRINGBLEND_SERVER_BINARY, SPRINGBLEND_CLI and
SPRINGBLEND_TEST_DATA ($SPRINGBLEND_SERVER is the clients' default address, so it never names the binary).
Nothing here imports the springblend package, so Blender can use it too.
"""

import json
import os
import pathlib
import shutil
import subprocess
import tempfile
import threading

import numpy as np

DATA = pathlib.Path(os.environ.get("SPRINGBLEND_TEST_DATA", pathlib.Path(__file__).parents[1] / "data"))
CYLINDER = DATA / "cylinder"
# The quickstart's rig: a bend and a twist target.
CYLINDER_TARGETS = ("poses-2_cylinder-1", "poses-2_cylinder-3")


def required_path(variable):
    """The file named by an environment variable, or an error saying how tests get it."""
    value = os.environ.get(variable, "")
    if not value or not os.path.exists(value):
        raise RuntimeError(f"${variable} must name an existing file (got {value!r}); run the tests with "
                           "ctest --preset release, which sets it")
    return value


def load_obj(path):
    """(vertices #V by 3 float64, faces #F by 3 int32) of an OBJ file, polygons split into fans like the
    C++ loader, in file order."""
    vertices, faces = [], []
    with open(path) as obj:
        for line in obj:
            fields = line.split()
            if not fields:
                continue
            if fields[0] == "v":
                vertices.append([float(v) for v in fields[1:4]])
            elif fields[0] == "f":
                corners = [int(f.split("/")[0]) - 1 for f in fields[1:]]
                faces += [[corners[0], corners[k], corners[k + 1]] for k in range(1, len(corners) - 1)]
    return np.array(vertices, dtype=np.float64), np.array(faces, dtype=np.int32)


def cylinder():
    """(rest, faces, {target name: positions}) of the cylinder rig, names as the CLI gives them (file stems).

    Coordinates are rounded to float32 as the C++ loader (OpenMesh's OBJ reader) does, so an upload of these
    arrays is the very character the CLI uploads from the files (same content id)."""
    def positions(name):
        return load_obj(CYLINDER / f"{name}.obj")[0].astype(np.float32).astype(np.float64)

    faces = load_obj(CYLINDER / "cylinder.obj")[1]
    return positions("cylinder"), faces, {name: positions(name) for name in CYLINDER_TARGETS}


def bounding_box_diagonal(points):
    """The length of the bounding box's diagonal of #V by 3 points."""
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


class Server:
    """springblend-server on 127.0.0.1 with a free port and a temporary cache directory; a context manager."""

    def __init__(self, startup_seconds=30.0, arguments=()):
        self.directory = tempfile.mkdtemp(prefix="springblend-test-")
        self.log_path = os.path.join(self.directory, "server.log")
        self._log = open(self.log_path, "w")
        self.process = subprocess.Popen(
            [required_path("SPRINGBLEND_SERVER_BINARY"), "--listen", "127.0.0.1:0",
             "--cache-dir", os.path.join(self.directory, "cache"), *arguments],
            stdout=subprocess.PIPE, stderr=self._log, text=True)
        self.address = self._wait_for_address(startup_seconds)

    def _wait_for_address(self, seconds):
        found = []

        def read():
            for line in self.process.stdout:
                if "listening on" in line:
                    found.append(line.rsplit(" ", 1)[-1].strip())
                    return

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        reader.join(seconds)
        if not found:
            self.stop()
            raise RuntimeError(f"springblend-server did not start within {seconds} s; its log:\n{self.log()}")
        return found[0]

    def log(self):
        """The server's stderr so far."""
        with open(self.log_path) as log:
            return log.read()

    def stop(self):
        """SIGTERM, then SIGKILL if it does not exit; removes the temporary directory."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process.stdout.close()
        self._log.close()
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def cli(*arguments, timeout=300):
    """Runs the springblend CLI; returns its stdout, raising with its stderr when it fails."""
    result = subprocess.run([required_path("SPRINGBLEND_CLI"), *arguments], capture_output=True, text=True,
                            timeout=timeout)
    if result.returncode != 0:
        raise RuntimeError(f"springblend {' '.join(arguments)} exited {result.returncode}:\n{result.stderr}")
    return result.stdout


def cli_upload_cylinder(address):
    """Uploads the cylinder rig with the CLI; returns the character id."""
    arguments = ["upload", "--server", address, "--rest", str(CYLINDER / "cylinder.obj")]
    for name in CYLINDER_TARGETS:
        arguments += ["--target", str(CYLINDER / f"{name}.obj")]
    return json.loads(cli(*arguments).splitlines()[-1])["id"]


def cli_solve(address, character, frames, colliders, directory):
    """Solves a scene with the CLI (frames as in a --frames JSON file, collider specs as for --collider).
    Returns the solved positions, #frames by #V by 3, read back from its OBJ files, and its per-frame summaries
    (the JSON lines it prints: converged, contacts, ...)."""
    scene = os.path.join(directory, "scene.json")
    with open(scene, "w") as out:
        json.dump({"colliders": list(colliders), "frames": frames}, out)
    out_dir = os.path.join(directory, "frames")
    lines = cli("solve", "--server", address, "--character", character, "--frames", scene, "--out", out_dir)
    summaries = [json.loads(line) for line in lines.splitlines() if line.startswith("{")]
    positions = np.stack([load_obj(os.path.join(out_dir, f"frame_{i:04d}.obj"))[0] for i in range(len(frames))])
    return positions, summaries


def cli_blend_rig(rig, weights, directory):
    """Solves frames of a rig file locally with the CLI (`blend --rig RIG --frames`); returns the positions,
    #frames by #V by 3, read back from its OBJ files."""
    scene = os.path.join(directory, "rig_scene.json")
    with open(scene, "w") as out:
        json.dump({"frames": [{"weights": w} for w in weights]}, out)
    out_dir = os.path.join(directory, "rig_local")
    cli("blend", "--rig", str(rig), "--frames", scene, "--out", out_dir)
    return np.stack([load_obj(os.path.join(out_dir, f"frame_{i:04d}.obj"))[0] for i in range(len(weights))])


class Certificates:
    """A test CA with a server certificate for localhost and 127.0.0.1 and a client certificate, and a second
    CA the server does not know, made with the openssl command (as tests/integration/security_test.cc makes
    them). file(name) is the path of "ca.pem", "server.pem", "server.key", "client.pem", "client.key",
    "rogue-ca.pem"; a context manager that removes them."""

    _KEY = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]

    def __init__(self):
        self.directory = tempfile.mkdtemp(prefix="springblend-certs-")
        self._ca("ca", "springblend test CA")
        self._ca("rogue-ca", "another CA")
        self._issue("server", "ca", "localhost",
                    "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth")
        self._issue("client", "ca", "a trusted artist", "extendedKeyUsage=clientAuth")

    def file(self, name):
        return os.path.join(self.directory, name)

    def _openssl(self, *arguments):
        result = subprocess.run(["openssl", *arguments], capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"openssl {' '.join(arguments)} failed:\n{result.stderr}")

    def _ca(self, name, subject):
        self._openssl("req", "-x509", *self._KEY, "-days", "2", "-subj", f"/CN={subject}",
                      "-addext", "basicConstraints=critical,CA:TRUE",
                      "-addext", "keyUsage=critical,keyCertSign,cRLSign",
                      "-keyout", self.file(f"{name}.key"), "-out", self.file(f"{name}.pem"))

    def _issue(self, name, ca, subject, extensions):
        with open(self.file(f"{name}.ext"), "w") as ext:
            ext.write(f"basicConstraints=CA:FALSE\n{extensions}\n")
        self._openssl("req", "-new", *self._KEY, "-subj", f"/CN={subject}", "-keyout", self.file(f"{name}.key"),
                      "-out", self.file(f"{name}.csr"))
        self._openssl("x509", "-req", "-days", "2", "-in", self.file(f"{name}.csr"), "-CA", self.file(f"{ca}.pem"),
                      "-CAkey", self.file(f"{ca}.key"), "-CAcreateserial", "-extfile", self.file(f"{name}.ext"),
                      "-out", self.file(f"{name}.pem"))

    def close(self):
        shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
