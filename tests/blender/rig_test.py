"""The Blender add-on with a production rig (issue 18), headless in a real Blender: rig_in_blender.py builds the
cylinder from the bundled rig file as shape keys (an in-between key bend@0.5, a vertex group as twist's mask, a
combination key bend*twist), exports it with the add-on's Export Rig File, uploads and bakes 3 frames through
the operators. Then the exported rig file uploaded by the C++ CLI must be the add-on's character (same id), and
what Blender shows on each baked frame must equal the CLI's local `blend --rig` of the exported file.

Run by CTest with /usr/bin/python3; needs $BLENDER, $SPRINGBLEND_ADDON_ZIP and what springblend_testing reads.
"""

import json
import os
import pathlib
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import blender_runner as runner  # noqa: E402
from blender_runner import testing  # noqa: E402
from springblend import rigfile  # noqa: E402

FRAMES = [1, 2, 3]
# bend, twist per frame: a mix, the in-between alone, both drivers at 1 (the combination's sculpt).
WEIGHTS = [[0.25, 0.5], [0.5, 0.0], [1.0, 1.0]]


def main():
    runner.blender_executable()
    with testing.Server() as server, tempfile.TemporaryDirectory(prefix="springblend-blender-rig-") as directory:
        config = {"server": server.address, "addon_zip": testing.required_path("SPRINGBLEND_ADDON_ZIP"),
                  "rig": str(testing.CYLINDER / "rig.json"), "frames": FRAMES, "weights": WEIGHTS,
                  "export": os.path.join(directory, "exported", "cylinder.json"),
                  "output": os.path.join(directory, "baked.npy"), "result": os.path.join(directory, "result.json")}
        # A rig baked by the CLI (in-betweens and the combination, solved frames), imported with Import Rig
        # File: its sliders play it without the server.
        summary = json.loads(testing.cli("bake-rig", "--rig", str(testing.CYLINDER / "rig.json"), "--samples", "8",
                                         "--inbetweens", "2", "--solved-inbetweens",
                                         "--out", os.path.join(directory, "baked")))
        inbetween = summary["targets"][0]["inbetweens"][0]
        config.update({"baked": summary["rig"], "baked_output": os.path.join(directory, "baked_shown.npy"),
                       "baked_weights": [[inbetween, 0.0], [1.0, 1.0], [0.3, 0.7], [1.2, -0.1], [0.9, 0.4]]})
        runner.run_blender("rig_in_blender.py", config, directory, server)
        baked_shown = np.load(config["baked_output"])
        baked_rig = rigfile.load_rig(summary["rig"])
        played = np.stack([rigfile.linear_blend(baked_rig, w) for w in config["baked_weights"]])
        runner.largest_error(baked_shown, played, "rig_test (the imported baked rig's sliders, against linear_blend)")
        solved = testing.cli_blend_rig(str(testing.CYLINDER / "rig.json"), config["baked_weights"][:2], directory)
        runner.largest_error(baked_shown[:2], solved, "rig_test (the imported baked rig at an in-between and at 1, 1)")
        baked = np.load(config["output"])
        with open(config["result"]) as text:
            character = json.load(text)["character"]
        exported = config["export"]
        line = testing.cli("upload", "--server", server.address, "--rig", exported).splitlines()[-1]
        if json.loads(line)["id"] != character:
            raise SystemExit(f"rig_test: the CLI's upload of the exported rig is {line}, not the add-on's {character}")
        # The vertex group springblend_fixed and Hold Outer Rim are the CLI's --fixed and --hold-outer-rim.
        held = json.loads(testing.cli("upload", "--server", server.address, "--rig", exported, "--fixed", "0,1,2",
                                      "--hold-outer-rim").splitlines()[-1])
        if held["id"] != json.load(open(config["result"]))["held_character"]:
            raise SystemExit(f"rig_test: the CLI's upload with --fixed 0,1,2 --hold-outer-rim is {held['id']}, not "
                             "the add-on's character with the group springblend_fixed and Hold Outer Rim")
        if held["rim_vertices"] <= 0:
            raise SystemExit(f"rig_test: no outer rim held: {held}")
        dense = json.loads(testing.cli("upload", "--server", server.address, "--rig", exported, "--fixed", "0,1,2",
                                       "--hold-outer-rim", "--path-intervals", "8").splitlines()[-1])
        if dense["id"] != json.load(open(config["result"]))["dense_character"] or dense["id"] == held["id"]:
            raise SystemExit(f"rig_test: the CLI's upload with --path-intervals 8 is {dense['id']}, not the add-on's "
                             "character with Path Steps 8")
        expected = testing.cli_blend_rig(exported, WEIGHTS, directory)
    runner.largest_error(baked, expected, "rig_test (shape keys of a production rig)")
    sculpt = testing.load_obj(testing.CYLINDER / "poses-2_cylinder-4.obj")[0]
    runner.largest_error(baked[2:], sculpt[None], "rig_test (the combination's sculpt with its drivers at 1)")
    print("rig_test: OK")


if __name__ == "__main__":
    main()
