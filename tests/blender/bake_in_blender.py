"""Runs inside Blender (see bake_test.py): installs the add-on from its zip, builds the cylinder scene with
shape keys and colliders, checks that errors come back as reports, uploads and bakes through the operators,
first into shape keys, then into a PC2 point cache next to the saved .blend played by a Mesh Cache modifier,
and saves what Blender shows on each baked frame in both modes (#frames by #V by 3) for bake_test.py to compare.
Upload and bake also run through their modal path (what the UI runs: the calls on a worker thread, polled by a
timer), driven here with the timer events Blender's event loop would send: the same character and the same
frames as the synchronous path, progress shown, and a cancelled bake ends cancelled.

blender --background --factory-startup --python-exit-code 1 --python bake_in_blender.py -- CONFIG.json
"""

import os
import pathlib
import sys

import bpy
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from blender_scene import check, expect_error_report, run_modal, setup, shown_positions  # noqa: E402


def shown_frames(scene, obj, frames):
    shown = []
    for frame in frames:
        scene.frame_set(frame)
        shown.append(shown_positions(obj))
    return np.stack(shown)




def check_modal(config, scene, obj, synchronous):
    from springblend_blender import operators
    character = obj.springblend_character
    obj.springblend_character = ""
    result, reports, texts = run_modal(operators.SPRINGBLEND_OT_upload)
    check(result == {"FINISHED"}, f"modal upload: {result} {reports}")
    check(obj.springblend_character == character, "the modal upload gave another character than the synchronous one")
    check(any("uploading 'Cylinder'" in (t or "") for t in texts), f"the modal upload showed no progress: {texts}")
    check(texts[-1] is None, "the status bar was not cleared")
    result, reports, texts = run_modal(operators.SPRINGBLEND_OT_bake)
    check(result == {"FINISHED"}, f"modal bake: {result} {reports}")
    check(any("baking 'Cylinder': frame" in (t or "") for t in texts), f"the modal bake showed no progress: {texts}")
    np.testing.assert_array_equal(shown_frames(scene, obj, config["frames"]), synchronous,
                                  err_msg="the modal bake's frames differ from the synchronous bake's")
    result, reports, texts = run_modal(operators.SPRINGBLEND_OT_bake, escape_first=True)
    check(result == {"CANCELLED"}, f"a cancelled modal bake ended {result}")
    check(any("WARNING" in kinds and "bake frames cancelled" in message for kinds, message in reports),
          f"the cancelled bake said {reports}")
    check(not [kb for kb in obj.data.shape_keys.key_blocks if kb.name.startswith("springblend_frame_")],
          "a cancelled bake stored frames")


def main():
    config, scene, obj = setup()

    # Errors are reports: nobody listening; not uploaded yet.
    scene.springblend.server = "127.0.0.1:1"
    scene.springblend.timeout = 5
    expect_error_report(bpy.ops.springblend.check_server, "no springblend server")
    expect_error_report(bpy.ops.springblend.upload, "UNAVAILABLE")
    expect_error_report(bpy.ops.springblend.bake, "Upload Character first")

    scene.springblend.server = config["server"]
    scene.springblend.timeout = 120
    check(bpy.ops.springblend.check_server() == {"FINISHED"}, "check_server failed")
    check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload failed")
    check(len(obj.springblend_character) == 64, "upload stored no character id")

    # Shape keys: one corrective key per frame.
    scene.springblend.bake_mode = "SHAPE_KEYS"
    check(bpy.ops.springblend.bake() == {"FINISHED"}, "bake failed")
    # Baking again replaces the keys of the first bake.
    check(bpy.ops.springblend.bake() == {"FINISHED"}, "second bake failed")
    baked = [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith("springblend_frame_")]
    check(baked == [f"springblend_frame_{f:04d}" for f in config["frames"]], f"unexpected baked keys {baked}")

    # An unknown character comes back as the server's NOT_FOUND, as a report.
    character, obj.springblend_character = obj.springblend_character, "0" * 64
    expect_error_report(bpy.ops.springblend.bake, "NOT_FOUND")
    obj.springblend_character = character
    synchronous = shown_frames(scene, obj, config["frames"])
    np.save(config["output"], synchronous)
    check_modal(config, scene, obj, synchronous)

    # Point cache: an unsaved .blend has no directory to put it next to.
    scene.springblend.bake_mode = "POINT_CACHE"
    expect_error_report(bpy.ops.springblend.bake, "save the .blend first")
    bpy.ops.wm.save_as_mainfile(filepath=config["blend"])
    check(bpy.ops.springblend.bake() == {"FINISHED"}, "point-cache bake failed")
    cache = os.path.join(os.path.dirname(config["blend"]), "Cylinder.pc2")
    check(os.path.isfile(cache), f"no point cache at {cache}")
    modifiers = [(m.name, m.type) for m in obj.modifiers]
    check(modifiers == [("springblend_cache", "MESH_CACHE")], f"unexpected modifiers {modifiers}")
    modifier = obj.modifiers["springblend_cache"]
    check(modifier.cache_format == "PC2" and modifier.filepath == "//Cylinder.pc2",
          f"the modifier reads {modifier.cache_format} {modifier.filepath}")
    leftover = [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith("springblend_frame_")]
    check(not leftover, f"the point-cache bake left the shape-key bake behind: {leftover}")
    # Rebaking replaces the file and keeps one modifier; a failed bake (unknown character) leaves both.
    check(bpy.ops.springblend.bake() == {"FINISHED"}, "second point-cache bake failed")
    obj.springblend_character = "0" * 64
    expect_error_report(bpy.ops.springblend.bake, "NOT_FOUND")
    obj.springblend_character = character
    check(len(obj.modifiers) == 1 and os.path.isfile(cache), "a failed bake removed the earlier point cache")
    check(sorted(os.listdir(os.path.dirname(cache))) == sorted(["Cylinder.pc2", os.path.basename(config["blend"])]),
          f"files beside the .blend: {os.listdir(os.path.dirname(cache))}")
    np.save(config["output_cache"], shown_frames(scene, obj, config["frames"]))
    print("bake_in_blender: baked and saved", len(config["frames"]), "frames in both modes")


main()
