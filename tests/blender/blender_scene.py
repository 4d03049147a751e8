"""Shared by the scripts that run inside Blender (bake_in_blender.py, live_in_blender.py): installing the
add-on from its zip, the cylinder scene with keyed shape keys and colliders, error reports, and what Blender
shows of a mesh. Runs in Blender's Python; the test data come from springblend_testing (tests/python).
"""

import json
import pathlib
import sys
import time
import types

import bmesh
import bpy
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "python"))
from springblend_testing import load_obj  # noqa: E402

ADDON = "springblend_blender"


def check(condition, message):
    if not condition:
        raise AssertionError(message)


def install_addon(zip_path):
    bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
    bpy.ops.preferences.addon_enable(module=ADDON)
    check(ADDON in bpy.context.preferences.addons, "the add-on did not enable")


def new_character(rest_obj):
    """A mesh object "Cylinder" of an OBJ file, linked to the scene, with a Basis shape key."""
    rest, faces = load_obj(rest_obj)
    mesh = bpy.data.meshes.new("cylinder")
    mesh.from_pydata(rest.tolist(), [], faces.tolist())
    mesh.update()
    obj = bpy.data.objects.new("Cylinder", mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.shape_key_add(name="Basis", from_mix=False)
    return obj


def build_cylinder(config):
    """The cylinder mesh with a Basis and one shape key per target, values keyed per frame."""
    directory = pathlib.Path(config["cylinder"])
    obj = new_character(directory / "cylinder.obj")
    mesh = obj.data
    for name in config["targets"]:
        key = obj.shape_key_add(name=name, from_mix=False)
        key.data.foreach_set("co", load_obj(directory / f"{name}.obj")[0].astype(np.float32).ravel())
    for frame, weights in zip(config["frames"], config["weights"]):
        for name, weight in zip(config["targets"], weights):
            key = mesh.shape_keys.key_blocks[name]
            key.value = weight
            key.keyframe_insert("value", frame=frame)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return obj


def build_colliders(config):
    """A 'Colliders' collection: a UV sphere ("Ball", keyed along its path) and a cube empty ("Crate")."""
    collection = bpy.data.collections.new("Colliders")
    bpy.context.scene.collection.children.link(collection)
    ball_mesh = bpy.data.meshes.new("ball")
    shape = bmesh.new()
    bmesh.ops.create_uvsphere(shape, u_segments=16, v_segments=8, radius=1.0)
    shape.to_mesh(ball_mesh)
    shape.free()
    ball = bpy.data.objects.new("Ball", ball_mesh)
    collection.objects.link(ball)
    ball.scale = (config["ball_radius"],) * 3
    for frame, location in zip(config["frames"], config["ball_locations"]):
        ball.location = location
        ball.keyframe_insert("location", frame=frame)
    crate = bpy.data.objects.new("Crate", None)
    crate.empty_display_type = "CUBE"
    crate.empty_display_size = 1.0
    crate.scale = config["box_half_extents"]
    crate.location = config["box_location"]
    collection.objects.link(crate)
    return collection


def expect_error_report(operator, fragment):
    """Runs an operator that must fail: Blender turns its ERROR report into a RuntimeError for scripts."""
    try:
        operator()
    except RuntimeError as report:
        check(fragment in str(report), f"expected '{fragment}' in the report, got: {report}")
        check("Traceback" not in str(report), f"the report carries a traceback: {report}")
        print(f"bake_in_blender: reported as expected: {str(report).strip()}")
        return
    raise AssertionError(f"{operator} should have failed with a report containing '{fragment}'")


def setup():
    """Reads the CONFIG.json given after "--", installs the add-on and builds the cylinder scene over the
    config's frames with its colliders collection. Returns (config, scene, cylinder object)."""
    config = json.loads(pathlib.Path(sys.argv[sys.argv.index("--") + 1]).read_text())
    install_addon(config["addon_zip"])
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = config["frames"][0], config["frames"][-1]
    obj = build_cylinder(config)
    scene.springblend.colliders = build_colliders(config)
    return config, scene, obj


def shown_positions(obj):
    """The vertices Blender shows for an object now (shape keys and modifiers evaluated), #V by 3 float64."""
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = evaluated.to_mesh()
    flat = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", flat)
    evaluated.to_mesh_clear()
    return flat.reshape(-1, 3).astype(np.float64)


class Stand:
    """What the modal path touches of Blender's context besides the scene: the window manager's timer and
    progress bar and the status bar, recorded."""

    def __init__(self):
        self.scene, self.active_object, self.window = bpy.context.scene, bpy.context.active_object, None
        self.window_manager, self.workspace = self, self
        self.texts, self.progress = [], []

    def event_timer_remove(self, timer):
        pass

    def progress_update(self, value):
        self.progress.append(value)

    def progress_end(self):
        pass

    def status_text_set(self, text):
        self.texts.append(text)


def run_modal(operator_class, escape_first=False, seconds=120, properties=None):
    """Runs an operator's modal path on stand-ins: prepare, (Esc,) start, TIMER events until it ends. properties:
    the operator's property values ({name: value}). Returns (result, reports, status texts)."""
    from springblend_blender import jobs, operators

    driven = types.SimpleNamespace(bl_label=operator_class.bl_label, reports=[], _timer=None,
                                   _read_frames=operator_class._read_frames if hasattr(operator_class, "_read_frames")
                                   else None)
    driven.__dict__.update(properties or {})
    driven.report = lambda kinds, message: driven.reports.append((set(kinds), message))
    for name, function in [("prepare", operator_class.prepare), ("apply", operator_class.apply),
                           ("finish", operator_class.finish), ("failed", operators._Guarded.failed),
                           ("modal", jobs.ModalJob.modal), ("_end", jobs.ModalJob._end)]:
        setattr(driven, name, types.MethodType(function, driven))
    context = Stand()
    driven._job = driven.prepare(context)
    if escape_first:
        check(driven.modal(context, types.SimpleNamespace(type="ESC")) == {"PASS_THROUGH"}, "Esc was not passed on")
    driven._job.start()
    deadline = time.monotonic() + seconds
    while True:
        result = driven.modal(context, types.SimpleNamespace(type="TIMER"))
        if result != {"RUNNING_MODAL"}:
            check(not jobs.RUNNING, "a finished job is still listed as running")
            return result, driven.reports, context.texts
        check(time.monotonic() < deadline, f"the modal {operator_class.bl_label} did not end within {seconds} s")
        time.sleep(0.05)
