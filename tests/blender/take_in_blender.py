"""Runs inside Blender (see take_test.py): installs the add-on, builds a character whose shape keys carry the edge
take's target names, imports the take through the add-on's Import Take (headless: synchronously), then again
through its modal path (the worker thread polled as the timer would) with lost rows skipped from frame 101, and
onto the sliders of a rig brought in with Import Rig File; saves every slider's keys, the scene's frame rate and
range for take_test.py to compare with the CLI's reading of the same take.

blender --background --factory-startup --python-exit-code 1 --python take_in_blender.py -- CONFIG.json
"""

import json
import pathlib
import sys

import bpy
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from blender_scene import check, expect_error_report, install_addon, new_character, run_modal  # noqa: E402
from springblend_testing import load_obj  # noqa: E402  (blender_scene put tests/python on sys.path)


def keys(owner, data_path):
    """[[frame, value], ...] of an F-curve of owner's action."""
    curve = owner.animation_data.action.fcurves.find(data_path)
    check(curve is not None, f"no F-curve {data_path} on {owner.name}")
    co = np.empty(len(curve.keyframe_points) * 2, dtype=np.float32)
    curve.keyframe_points.foreach_get("co", co)
    check(all(k.interpolation == "LINEAR" for k in curve.keyframe_points), f"{data_path}: keys not linear")
    return co.reshape(-1, 2).astype(np.float64).tolist()


def timing(scene):
    return {"fps": scene.render.fps / scene.render.fps_base, "range": [scene.frame_start, scene.frame_end]}


def main():
    config = json.loads(pathlib.Path(sys.argv[sys.argv.index("--") + 1]).read_text())
    install_addon(config["addon_zip"])
    scene = bpy.context.scene
    obj = new_character(pathlib.Path(config["cylinder"]) / "cylinder.obj")
    for name, pose in zip(config["targets"], config["poses"]):
        kb = obj.shape_key_add(name=name, from_mix=False)
        kb.data.foreach_set("co", load_obj(pose)[0].astype(np.float32).ravel())
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    result = {}

    # A bad take is an ERROR report naming the line and column; nothing is keyed.
    expect_error_report(lambda: bpy.ops.springblend.import_take(filepath=config["bad_take"]), "line 5, column 6")
    check(obj.data.shape_keys.animation_data is None, "a refused take keyed something")

    check(bpy.ops.springblend.import_take(filepath=config["take"], map_path=config["map"], lost="HOLD",
                                          start_frame=1) == {"FINISHED"}, "Import Take did not finish")
    shape_keys = obj.data.shape_keys
    result["hold"] = {name: keys(shape_keys, f'key_blocks["{name}"].value') for name in config["targets"]}
    result["hold_timing"] = timing(scene)
    # The weight above 1 plays as written: the slider's range was widened.
    above = config["above_one"]
    scene.frame_set(above["frame"])
    result["shown_above_one"] = shape_keys.key_blocks[above["target"]].value

    # The modal path: read on a worker thread, keyed on the main thread, progress shown; it replaces the keys.
    from springblend_blender import operators
    outcome, reports, texts = run_modal(operators.SPRINGBLEND_OT_import_take, properties={
        "filepath": config["take"], "map_path": config["map"], "lost": "SKIP", "start_frame": 101})
    check(outcome == {"FINISHED"}, f"the modal Import Take ended {outcome}: {reports}")
    check(any("keying" in (t or "") for t in texts), f"no progress shown: {texts}")
    check(any("WARNING" in kinds and "tracking lost in 8 rows" in message for kinds, message in reports),
          f"the take's report was not given: {reports}")
    result["skip"] = {name: keys(shape_keys, f'key_blocks["{name}"].value') for name in config["targets"]}
    result["skip_timing"] = timing(scene)

    # A rig brought in with Import Rig File: its sliders are custom properties.
    bpy.ops.springblend.import_rig(filepath=config["rig"])
    rig = bpy.context.active_object
    check(bpy.ops.springblend.import_take(filepath=config["take"], map_path=config["rig_map"]) == {"FINISHED"},
          "Import Take on an imported rig did not finish")
    result["rig"] = {name: keys(rig, f'["{name}"]') for name in ("bend", "twist")}
    with open(config["result"], "w") as out:
        json.dump(result, out)
    print("take_in_blender: OK")


main()
