"""Builds the springblend package: the hand-written modules, the gRPC modules generated from proto/ and
_version.py from the top-level CMakeLists.txt's project(VERSION). Metadata is in pyproject.toml.

    pip install --no-index --no-build-isolation client/python            # into the current environment
    pip wheel --no-deps --no-index --no-build-isolation -w dist client/python   # dist/springblend-*.whl

The generated modules come from the first of these that is there (SPRINGBLEND_GENERATOR=protoc, grpc_tools or
cmake picks one and fails when it is not there):
  protoc    Debian's protoc and grpc_python_plugin on PATH (protobuf-compiler, protobuf-compiler-grpc): what the
            CMake build uses, the same protobuf release as Debian's python3-protobuf runtime;
  grpc_tools  python -m grpc_tools.protoc (Debian's python3-grpc-tools, or grpcio-tools from a package index);
  cmake     the modules a CMake build already generated: $SPRINGBLEND_GENERATED_DIR (build/<preset>/python),
            else the newest build*/*/python or build*/python under the source tree.
Nothing is downloaded. $SPRINGBLEND_SOURCE_DIR names the repository when this directory is not at client/python.
"""

import glob
import os
import pathlib
import re
import shutil
import subprocess
import sys

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = pathlib.Path(__file__).resolve().parent
SOURCE = pathlib.Path(os.environ.get("SPRINGBLEND_SOURCE_DIR") or HERE.parents[1])
PROTO = SOURCE / "proto"
SERVICE_PROTO = "springblend/v1/springblend.proto"
HEALTH_PROTO = "grpc/health/v1/health.proto"
# What the package imports (springblend/_generated.py), relative to the directory that holds springblend/.
GENERATED = ("springblend/v1/springblend_pb2.py", "springblend/v1/springblend_pb2_grpc.py",
             "springblend/_health/grpc/health/v1/health_pb2.py")


def project_version():
    """The VERSION of project(springblend ...) in the top-level CMakeLists.txt."""
    cmake_lists = SOURCE / "CMakeLists.txt"
    try:
        text = cmake_lists.read_text()
    except OSError as error:
        sys.exit(f"springblend setup: cannot read {cmake_lists} for the version ({error.strerror}); build from "
                 "the repository's client/python, or set $SPRINGBLEND_SOURCE_DIR to the repository")
    match = re.search(r"project\(\s*springblend\s+VERSION\s+([0-9][0-9A-Za-z.]*)", text)
    if not match:
        sys.exit(f"springblend setup: no project(springblend VERSION ...) in {cmake_lists}")
    return match.group(1)


def run(command):
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"springblend setup: {' '.join(map(str, command))} failed:\n{result.stderr}")


def generate_with_protoc(out):
    protoc, plugin = shutil.which("protoc"), shutil.which("grpc_python_plugin")
    if not (protoc and plugin):
        return None
    service = [protoc, f"--plugin=protoc-gen-grpc_python={plugin}", "--grpc_python_out", out]
    generate(out, service, [protoc])
    return f"{protoc} with {plugin}"


def generate_with_grpc_tools(out):
    try:
        import grpc_tools.protoc  # noqa: F401
    except ImportError:
        return None
    command = [sys.executable, "-m", "grpc_tools.protoc"]
    generate(out, [*command, "--grpc_python_out", out], command)
    return "grpc_tools.protoc"


def generate(out, service_command, messages_command):
    run([*service_command, "--python_out", out, "-I", PROTO, PROTO / SERVICE_PROTO])
    health = out / "springblend" / "_health"
    health.mkdir(parents=True, exist_ok=True)
    run([*messages_command, "--python_out", health, "-I", PROTO, PROTO / HEALTH_PROTO])


def copy_from_cmake_build(out):
    given = os.environ.get("SPRINGBLEND_GENERATED_DIR")
    candidates = [pathlib.Path(given)] if given else sorted(
        (pathlib.Path(p) for pattern in ("build*/*/python", "build*/python")
         for p in glob.glob(str(SOURCE / pattern))),
        key=lambda p: (p / GENERATED[0]).stat().st_mtime if (p / GENERATED[0]).exists() else 0, reverse=True)
    for directory in candidates:
        if all((directory / name).exists() for name in GENERATED):
            for name in GENERATED:
                (out / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(directory / name, out / name)
            return f"the CMake build's {directory}"
    return None


GENERATORS = {"protoc": generate_with_protoc, "grpc_tools": generate_with_grpc_tools, "cmake": copy_from_cmake_build}


class BuildWithGeneratedModules(build_py):
    """build_py, then the generated gRPC modules and _version.py next to the copied package."""

    def run(self):
        super().run()
        out = pathlib.Path(self.build_lib)
        chosen = os.environ.get("SPRINGBLEND_GENERATOR", "")
        if chosen and chosen not in GENERATORS:
            sys.exit(f"springblend setup: SPRINGBLEND_GENERATOR={chosen} is none of {', '.join(GENERATORS)}")
        (out / "springblend" / "v1").mkdir(parents=True, exist_ok=True)
        source = None
        for name in [chosen] if chosen else GENERATORS:
            source = GENERATORS[name](out)
            if source:
                break
        if not source:
            sys.exit("springblend setup: cannot generate the gRPC modules from proto/: install Debian's "
                     "protobuf-compiler and protobuf-compiler-grpc (protoc, grpc_python_plugin) or python3-grpc-tools,"
                     " or build the project with CMake first (cmake --build --preset release)"
                     + (f" [SPRINGBLEND_GENERATOR={chosen}]" if chosen else ""))
        (out / "springblend" / "v1" / "__init__.py").touch()
        for name in GENERATED:
            if not (out / name).exists():
                sys.exit(f"springblend setup: {source} did not write {name}")
        (out / "springblend" / "_version.py").write_text(
            "# Generated from project(VERSION) in CMakeLists.txt; do not edit.\n"
            f'__version__ = "{project_version()}"\n')
        self.announce(f"springblend: gRPC modules from {source}", level=2)


setup(version=project_version(), cmdclass={"build_py": BuildWithGeneratedModules})
