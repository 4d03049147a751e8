"""Imports the modules protoc generates at build time, or explains how to get them.

pip install client/python (setup.py) generates them into the installed package. The CMake build (target
springblend_python) also writes springblend/v1/springblend_pb2.py and
springblend_pb2_grpc.py (protoc with Debian's grpc_python_plugin) and the health protocol's messages under
springblend/_health/ next to a copy of this package in build/<preset>/python. Nothing generated is committed.
"""

try:
    from springblend.v1 import springblend_pb2 as pb  # noqa: F401
    from springblend.v1 import springblend_pb2_grpc as pb_grpc  # noqa: F401
    from springblend._health.grpc.health.v1 import health_pb2  # noqa: F401
except ImportError as error:  # pragma: no cover - only without a build
    raise ImportError(
        "springblend: the generated gRPC modules are missing. Install the package (python -m pip install "
        "--no-build-isolation client/python), or build the project (cmake --preset release && cmake --build "
        "--preset release) and put build/release/python, not client/python, on sys.path "
        f"(import failed: {error})") from error
