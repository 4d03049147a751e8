"""The Blender add-on's Import Take (issue 59), headless in a real Blender: take_in_blender.py imports
tests/data/take/edge_take.csv (lost rows, a weight above 1, split symmetric shapes, a map, unknown columns) onto a
character's shape keys and onto an imported rig's sliders. Every key must be the CLI's weight of that frame (as
Blender stores keys: float32), at frames 1, 2, ... (101, ... with lost rows skipped), and the scene's frame rate
and range the take's.

Run by CTest with /usr/bin/python3; needs $BLENDER, $SPRINGBLEND_ADDON_ZIP and what springblend_testing reads.
"""

import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import blender_runner as runner  # noqa: E402
from blender_runner import testing  # noqa: E402

TAKE = testing.DATA / "take" / "edge_take.csv"
MAP = testing.DATA / "take" / "edge_map.json"
TARGETS = ["eyeBlink_L", "EyeBlink.R", "browInnerUp_L", "browInnerUp_R", "cheekPuff", "jawOpen", "eyeLookOut_L",
           "smile_L", "smile_R", "sneer_L"]
POSES = ["poses-1_cylinder-1", "poses-1_cylinder-2", "poses-1_cylinder-3", "poses-1_cylinder-4",
         "poses-2_cylinder-1", "poses-2_cylinder-2", "poses-2_cylinder-3", "poses-2_cylinder-4"]


def cli_weights(arguments):
    """The weights the CLI reads for each frame (its --linear blend's JSON lines)."""
    result = subprocess.run([testing.required_path("SPRINGBLEND_CLI"), "blend", "--linear", *arguments],
                            capture_output=True, text=True, timeout=120)
    if result.returncode != 0:
        raise SystemExit(f"take_test: springblend blend exited {result.returncode}: {result.stderr}")
    return np.array([json.loads(line)["weights"] for line in result.stdout.splitlines()], dtype=np.float64)


def compare(keys, names, weights, first_frame, what):
    for i, name in enumerate(names):
        got = np.array(keys[name], dtype=np.float64)
        frames = first_frame + np.arange(len(weights), dtype=np.float64)
        expected = np.stack([frames, weights[:, i].astype(np.float32).astype(np.float64)], axis=1)
        if got.shape != expected.shape or not np.array_equal(got, expected):
            raise SystemExit(f"take_test: {what}: the keys of '{name}' are not the CLI's weights:\n{got[:5]}\n"
                             f"{expected[:5]}")


def main():
    runner.blender_executable()
    with tempfile.TemporaryDirectory(prefix="springblend-blender-take-") as directory:
        poses = [str(testing.CYLINDER / f"{POSES[i % len(POSES)]}.obj") for i in range(len(TARGETS))]
        arguments = ["--rest", str(testing.CYLINDER / "cylinder.obj")]
        for name, pose in zip(TARGETS, poses):
            shutil.copy(pose, os.path.join(directory, f"{name}.obj"))
            arguments += ["--target", os.path.join(directory, f"{name}.obj")]
        out = ["--out", os.path.join(directory, "out.pc2")]
        hold = cli_weights([*arguments, "--take", str(TAKE), "--map", str(MAP), *out])
        skip = cli_weights([*arguments, "--take", str(TAKE), "--map", str(MAP), "--lost", "skip", *out])
        rig_map = os.path.join(directory, "rig_map.json")
        with open(rig_map, "w") as text:
            json.dump({"JawOpen": "bend", "CheekPuff": {"twist": 0.5}, "BrowInnerUp": {"twist": -0.25}}, text)
        rig = cli_weights(["--rig", str(testing.CYLINDER / "rig.json"), "--take", str(TAKE), "--map", rig_map, *out])
        bad = os.path.join(directory, "bad.csv")
        lines = TAKE.read_text().splitlines()
        lines[4] = ",".join(lines[4].split(",")[:5])
        pathlib.Path(bad).write_text("\n".join(lines) + "\n")
        column = TARGETS.index("eyeLookOut_L")
        frame = int(np.argmax(hold[:, column]))
        config = {"addon_zip": testing.required_path("SPRINGBLEND_ADDON_ZIP"), "cylinder": str(testing.CYLINDER),
                  "targets": TARGETS, "poses": poses, "take": str(TAKE), "map": str(MAP), "bad_take": bad,
                  "rig": str(testing.CYLINDER / "rig.json"), "rig_map": rig_map,
                  "above_one": {"target": "eyeLookOut_L", "frame": frame + 1},
                  "result": os.path.join(directory, "result.json")}
        runner.run_blender("take_in_blender.py", config, directory, server=None)
        with open(config["result"]) as text:
            result = json.load(text)
    if hold[frame, column] <= 1.0 or result["shown_above_one"] != float(np.float32(hold[frame, column])):
        raise SystemExit(f"take_test: eyeLookOut_L shows {result['shown_above_one']} at frame {frame + 1}, not the "
                         f"take's {hold[frame, column]}")
    compare(result["hold"], TARGETS, hold, 1, "lost rows held, from frame 1")
    compare(result["skip"], TARGETS, skip, 101, "lost rows skipped, from frame 101")
    compare(result["rig"], ["bend", "twist"], rig, 1, "an imported rig's sliders")
    if result["hold_timing"] != {"fps": 30.0, "range": [1, 24]} or result["skip_timing"]["range"] != [101, 116]:
        raise SystemExit(f"take_test: the scene's timing is {result['hold_timing']}, then {result['skip_timing']}")
    print("take_test: OK")


if __name__ == "__main__":
    main()
