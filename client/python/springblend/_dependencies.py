"""Checks, before anything else is imported, that the client's three dependencies are importable, so that a
Python without them says which one is missing and how to get it rather than "No module named 'numpy'"."""

import importlib

# (module, the distribution pip installs, Debian's package)
DEPENDENCIES = (("numpy", "numpy", "python3-numpy"), ("grpc", "grpcio", "python3-grpcio"),
                ("google.protobuf", "protobuf", "python3-protobuf"))


def check():
    """Raises ModuleNotFoundError naming every missing dependency and how to install it."""
    missing = []
    for module, distribution, debian in DEPENDENCIES:
        try:
            importlib.import_module(module)
        except ImportError as error:
            missing.append((module, distribution, debian, error))
    if not missing:
        return
    names = ", ".join(m[0] for m in missing)
    raise ModuleNotFoundError(
        f"springblend needs {names}, which this Python ({_interpreter()}) cannot import: on Debian or Ubuntu "
        f"run `sudo apt install {' '.join(m[2] for m in missing)}` and use /usr/bin/python3 (or a virtual "
        "environment made with --system-site-packages); elsewhere `python -m pip install "
        f"{' '.join(m[1] for m in missing)}`. ({'; '.join(f'{m[0]}: {m[3]}' for m in missing)})",
        name=missing[0][0])


def _interpreter():
    import sys
    return sys.executable or "python"
