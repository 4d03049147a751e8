"""Runs inside Blender (see rig_test.py): installs the add-on, builds the cylinder of the bundled rig file as
shape keys following the add-on's conventions (TARGET@W in-betweens, A*B combinations, a vertex group as a
key's mask), exports the rig file, uploads and bakes shape keys, and saves what Blender shows on each frame.

blender --background --factory-startup --python-exit-code 1 --python rig_in_blender.py -- CONFIG.json
"""

import json
import os
import pathlib
import sys

import bpy
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from blender_scene import check, expect_error_report, install_addon, new_character, shown_positions  # noqa: E402
from springblend_testing import load_obj  # noqa: E402  (blender_scene put tests/python on sys.path)


def build_rig(config):
    """The rig file's meshes as Basis and shape keys; bend and twist keyed per frame."""
    doc = json.loads(pathlib.Path(config["rig"]).read_text())
    base = pathlib.Path(config["rig"]).parent
    obj = new_character(base / doc["rest"])
    mesh = obj.data

    def key(name, file):
        kb = obj.shape_key_add(name=name, from_mix=False)
        kb.data.foreach_set("co", load_obj(base / file)[0].astype(np.float32).ravel())
        return kb

    for target in doc["targets"]:
        name = "*".join(target["combination"]) if "combination" in target else target["name"]
        kb = key(name, target["mesh"])
        for inbetween in target.get("inbetweens", []):
            key(f"{name}@{inbetween['weight']:g}", inbetween["mesh"])
        if "mask" in target:
            weights = [float(v) for v in (base / target["mask"]).read_text().split("\n")
                       if v.strip() and not v.startswith("#")]
            group = obj.vertex_groups.new(name=f"{name}_mask")
            for vertex, weight in enumerate(weights):
                if weight > 0.0:
                    group.add([vertex], weight, "REPLACE")
            kb.vertex_group = group.name
    for frame, weights in zip(config["frames"], config["weights"]):
        for name, weight in zip(("bend", "twist"), weights):
            kb = mesh.shape_keys.key_blocks[name]
            kb.value = weight
            kb.keyframe_insert("value", frame=frame)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return obj


def import_baked(config):
    """Imports the baked rig file with Import Rig File and saves what Blender shows for each of its weights (set
    on the target sliders, the object's custom properties)."""
    before = set(bpy.data.objects)
    check(bpy.ops.springblend.import_rig(filepath=config["baked"]) == {"FINISHED"}, "import of the baked rig failed")
    (obj,) = set(bpy.data.objects) - before
    keys = [kb.name for kb in obj.data.shape_keys.key_blocks]
    check(keys[0] == "Basis" and "bend*twist" in keys and any(k.startswith("bend@") for k in keys),
          f"unexpected keys of the imported rig {keys}")
    shown = []
    for weights in config["baked_weights"]:
        obj["bend"], obj["twist"] = weights
        obj.update_tag()  # as the Properties editor tags an edited custom property
        bpy.context.view_layer.update()
        shown.append(shown_positions(obj))
    np.save(config["baked_output"], np.stack(shown))
    expect_error_report(lambda: bpy.ops.springblend.import_rig(filepath=config["baked"] + ".missing"),
                        "springblend: " + config["baked"] + ".missing: cannot open")


def main():
    config = json.loads(pathlib.Path(sys.argv[sys.argv.index("--") + 1]).read_text())
    install_addon(config["addon_zip"])
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = config["frames"][0], config["frames"][-1]
    obj = build_rig(config)
    keys = [kb.name for kb in obj.data.shape_keys.key_blocks]
    check(keys == ["Basis", "bend", "bend@0.5", "twist", "bend*twist"], f"unexpected keys {keys}")

    # A broken convention is a report naming the key.
    stray = obj.shape_key_add(name="smile@0.5", from_mix=False)
    expect_error_report(lambda: bpy.ops.springblend.export_rig(filepath=config["export"]),
                        "in-between key 'smile@0.5'")
    obj.shape_key_remove(stray)

    check(bpy.ops.springblend.export_rig(filepath=config["export"]) == {"FINISHED"}, "export failed")
    check(os.path.isfile(config["export"]), "no rig file written")
    scene.springblend.server = config["server"]
    scene.springblend.timeout = 180
    check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload failed")
    scene.springblend.bake_mode = "SHAPE_KEYS"
    check(bpy.ops.springblend.bake() == {"FINISHED"}, "bake failed")
    shown = []
    for frame in config["frames"]:
        scene.frame_set(frame)
        shown.append(shown_positions(obj))
    np.save(config["output"], np.stack(shown))
    character = obj.springblend_character
    # Held vertices: the vertex group springblend_fixed and Hold Outer Rim make another character.
    group = obj.vertex_groups.new(name="springblend_fixed")
    group.add([0, 1, 2], 1.0, "REPLACE")
    group.add([3], 0.25, "REPLACE")  # below 0.5: not held
    obj.springblend_hold_outer_rim = True
    check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload with held vertices failed")
    held_character = obj.springblend_character
    # The paths' density too.
    obj.springblend_path_intervals = 8
    check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload with denser paths failed")
    pathlib.Path(config["result"]).write_text(json.dumps({"character": character, "held_character": held_character,
                                                          "dense_character": obj.springblend_character}))
    import_baked(config)
    print("rig_in_blender: exported, uploaded and baked", len(config["frames"]), "frames; imported the baked rig")


main()
