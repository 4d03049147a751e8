"""The Blender add-on's bakes, headless in a real Blender: starts a springblend server, solves 4 cylinder
frames with the C++ CLI, then runs Blender (bake_in_blender.py) to install the add-on from its zip, build the
cylinder scene with shape keys, a moving ball and a box, upload and bake the frames through the add-on's
operators into shape keys and into a PC2 point cache played by a Mesh Cache modifier, and checks that what
Blender shows on each frame in both modes, and the PC2 file itself, equal the CLI's result.

Run by CTest (tests/CMakeLists.txt) with /usr/bin/python3; needs $BLENDER, $SPRINGBLEND_ADDON_ZIP and what
springblend_testing reads. Fails, never skips, when Blender is missing.
"""

import os
import pathlib
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import blender_runner as runner  # noqa: E402
from blender_runner import testing  # noqa: E402
from springblend import pointcache  # noqa: E402  (the Python client, on PYTHONPATH from CTest)

FRAMES = [1, 2, 3, 4]
# Keyed shape-key values per frame (bend, twist).
WEIGHTS = [[0.0, 0.0], [0.3, 0.1], [0.6, 0.3], [0.9, 0.45]]
# The ball moves along x; the box stays out of reach.
BALL_LOCATIONS = [[-1.9, 0.75, 0.75], [-1.8, 0.75, 0.75], [-1.7, 0.75, 0.75], [-1.6, 0.72, 0.75]]


def main():
    runner.blender_executable()
    with testing.Server() as server, tempfile.TemporaryDirectory(prefix="springblend-blender-") as directory:
        character = testing.cli_upload_cylinder(server.address)
        expected, summaries = runner.expected_positions(server, character, WEIGHTS, BALL_LOCATIONS, directory)
        if not all(s["converged"] for s in summaries) or sum(s["contacts"] for s in summaries) == 0:
            raise SystemExit(f"bake_test: the CLI's frames should converge with the ball in contact: {summaries}")
        os.makedirs(os.path.join(directory, "shot"))
        config = dict(runner.scene_config(server, WEIGHTS, BALL_LOCATIONS, FRAMES),
                      output=os.path.join(directory, "baked.npy"), output_cache=os.path.join(directory, "cache.npy"),
                      blend=os.path.join(directory, "shot", "shot.blend"))
        runner.run_blender("bake_in_blender.py", config, directory, server)
        baked, played = np.load(config["output"]), np.load(config["output_cache"])
        cache = pointcache.read_pc2(os.path.join(directory, "shot", "Cylinder.pc2"))
    runner.largest_error(baked, expected, "bake_test (shape keys)")
    runner.largest_error(played, expected, "bake_test (point cache played by the Mesh Cache modifier)")
    runner.largest_error(cache.positions.astype(np.float64), expected, "bake_test (the PC2 file)")
    if (cache.start_frame, cache.sample_rate) != (FRAMES[0], 1.0):
        raise SystemExit(f"bake_test: the PC2 starts at {cache.start_frame} by {cache.sample_rate}, not "
                         f"{FRAMES[0]} by 1")
    moved = np.abs(expected[-1] - expected[0]).max()
    if moved < 0.01 * testing.bounding_box_diagonal(expected[0]):
        raise SystemExit(f"bake_test: the frames barely move ({moved}); the comparison would prove little")
    print("bake_test: OK")


if __name__ == "__main__":
    main()
