"""springblend for Blender: upload the active mesh with its shape keys to a springblend server, preview the
physically based blendshape live while the artist drags sliders, scrubs or moves colliders, and bake a frame
range into a PC2 point cache (played by a Mesh Cache modifier) or corrective shape keys.

The add-on is a thin layer over the springblend Python client (client/python), which it bundles when
installed from build/<preset>/blender/springblend_blender.zip.
"""

bl_info = {
    "name": "springblend",
    "author": "springblend",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "3D View > Sidebar > springblend",
    "description": "Physically based blendshapes from a springblend farm server: upload a mesh with its shape "
                   "keys, preview live, bake a frame range to a point cache",
    "category": "Animation",
}

if "bpy" in locals():  # Blender's "Reload Scripts"
    import importlib
    for _module in (connection, settings, scene_data, store, live, take_import, operators, panel):  # noqa: F821
        importlib.reload(_module)

import bpy  # noqa: E402

from . import connection, live, operators, panel, scene_data, settings, store, take_import  # noqa: E402,F401

_classes = settings.CLASSES + operators.CLASSES + panel.CLASSES


def register():
    for cls in _classes:
        bpy.utils.register_class(cls)
    settings.register_properties()
    live.register()


def unregister():
    live.unregister()
    settings.unregister_properties()
    for cls in reversed(_classes):
        bpy.utils.unregister_class(cls)
