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


def server_address(scene):
    """The scene's server, else $SPRINGBLEND_SERVER, else 127.0.0.1:50051 (as the CLI and the Python client)."""
    client = client_module().client
    return (scene.springblend.server.strip() or os.environ.get(client.SERVER_VARIABLE, "").strip()
            or client.DEFAULT_SERVER)


def client_options(scene):
    """springblend.Client's arguments: the scene's server and timeout, and the preferences' TLS files and token
    (an empty token field: $SPRINGBLEND_TOKEN)."""
    options = {"address": server_address(scene), "timeout": float(scene.springblend.timeout)}
    preferences = _preferences()
    if preferences is not None:
        def path(value):
            return bpy.path.abspath(value) if value else None

        options.update(tls=preferences.use_tls, tls_ca=path(preferences.tls_ca), tls_cert=path(preferences.tls_cert),
                       tls_key=path(preferences.tls_key), tls_server_name=preferences.tls_server_name.strip() or None,
                       token=preferences.token.strip() or None)
    return options


def connect(scene):
    """A springblend.Client for the scene's server, with the add-on preferences' TLS and token."""
    return client_module().Client(**client_options(scene))


def _preferences():
    addon = bpy.context.preferences.addons.get(ADDON)
    return addon.preferences if addon and addon.preferences else None


def _preferred_path():
    preferences = _preferences()
    return bpy.path.abspath(preferences.python_path) if preferences is not None else ""
