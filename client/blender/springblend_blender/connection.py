"""Finds the springblend Python client and opens connections to the server."""

import importlib
import os
import sys

import bpy

from .scene_data import UserError

ADDON = __package__


def client_module():
    """Imports the springblend client package: from Blender's sys.path, the copy bundled in the add-on's
    vendor/ directory, the add-on preference 'Client package', or $SPRINGBLEND_PYTHON."""
    try:
        return importlib.import_module("springblend")
    except ImportError:
        pass
    candidates = [os.path.join(os.path.dirname(__file__), "vendor"), _preferred_path(),
                  os.environ.get("SPRINGBLEND_PYTHON", "")]
    for path in candidates:
        if path and os.path.isfile(os.path.join(path, "springblend", "__init__.py")):
            if path not in sys.path:
                sys.path.insert(0, path)
            try:
                return importlib.import_module("springblend")
            except ImportError as error:
                raise UserError(f"the springblend client in {path} cannot be imported: {error} (Blender's Python "
                                "needs grpcio, protobuf and numpy; Debian's blender uses python3-grpcio)")
    raise UserError("the springblend Python client is not found: install the add-on from "
                    "build/release/blender/springblend_blender.zip, which bundles it, or set the add-on "
                    "preference 'Client package' to build/release/python")


def connect(scene):
    """A springblend.Client for the scene's server address."""
    settings = scene.springblend
    address = settings.server.strip()
    if not address:
        raise UserError("set the springblend server address (host:port) first")
    return client_module().Client(address, timeout=float(settings.timeout))


def _preferred_path():
    addon = bpy.context.preferences.addons.get(ADDON)
    return bpy.path.abspath(addon.preferences.python_path) if addon and addon.preferences else ""
