"""The Blender add-on, headless in a real Blender: starts a springblend server, solves 4 cylinder frames with
the C++ CLI, then runs Blender (bake_in_blender.py) to install the add-on from its zip, build the cylinder
scene with shape keys, a moving ball and a box, upload and bake the frames through the add-on's operators, and
checks that what Blender shows on each frame equals the CLI's result.

Run by CTest (tests/CMakeLists.txt) with /usr/bin/python3; needs $BLENDER, $SPRINGBLEND_ADDON_ZIP and what
springblend_testing reads. Fails, never skips, when Blender is missing.
"""

import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "python"))
import springblend_testing as testing  # noqa: E402

FRAMES = [1, 2, 3, 4]
# Keyed shape-key values per frame (bend, twist).
WEIGHTS = [[0.0, 0.0], [0.3, 0.1], [0.6, 0.3], [0.9, 0.45]]
# The ball (a UV sphere of radius 1 scaled by 0.3) moves along x; the box (a cube empty) stays out of reach.
BALL_LOCATIONS = [[-1.9, 0.75, 0.75], [-1.8, 0.75, 0.75], [-1.7, 0.75, 0.75], [-1.6, 0.72, 0.75]]
BALL_RADIUS = 0.3
BOX_LOCATION, BOX_HALF_EXTENTS = [0.0, 3.0, 0.0], [0.5, 1.0, 0.5]


def blender_executable():
    blender = os.environ.get("BLENDER", "blender")
    found = shutil.which(blender)
    if found is None:
        raise SystemExit(f"bake_test: Blender ({blender!r}) is not installed; deploy/install-deps.sh installs "
                         "Debian's blender")
    return found


def expected_positions(server, character, directory):
    """The CLI's solve of the same frames. Blender stores locations as float32, so the CLI gets those values."""
    as_float32 = lambda v: [float(x) for x in np.float32(v)]  # noqa: E731
    frames = [{"weights": w, "colliders": [{"translation": as_float32(loc)}, {"translation": as_float32(BOX_LOCATION)}]}
              for w, loc in zip(WEIGHTS, BALL_LOCATIONS)]
    radius = float(np.float32(BALL_RADIUS))
    colliders = [f"sphere:0,0,0,{radius!r}", "box:0,0,0,{},{},{}".format(*(float(np.float32(h)) for h in BOX_HALF_EXTENTS))]
    return testing.cli_solve(server.address, character, frames, colliders, directory)


def main():
    blender = blender_executable()
    zip_path = testing.required_path("SPRINGBLEND_ADDON_ZIP")
    with testing.Server() as server, tempfile.TemporaryDirectory(prefix="springblend-blender-") as directory:
        character = testing.cli_upload_cylinder(server.address)
        expected, summaries = expected_positions(server, character, directory)
        if not all(s["converged"] for s in summaries) or sum(s["contacts"] for s in summaries) == 0:
            raise SystemExit(f"bake_test: the CLI's frames should converge with the ball in contact: {summaries}")
        config = {
            "server": server.address, "addon_zip": zip_path, "cylinder": str(testing.CYLINDER),
            "targets": list(testing.CYLINDER_TARGETS), "frames": FRAMES, "weights": WEIGHTS,
            "ball_locations": BALL_LOCATIONS, "ball_radius": BALL_RADIUS, "box_location": BOX_LOCATION,
            "box_half_extents": BOX_HALF_EXTENTS, "output": os.path.join(directory, "baked.npy"),
        }
        config_path = os.path.join(directory, "config.json")
        with open(config_path, "w") as out:
            json.dump(config, out)
        # A private user directory: the add-on is installed there, never into the machine's Blender.
        environment = dict(os.environ, BLENDER_USER_SCRIPTS=os.path.join(directory, "scripts"),
                           BLENDER_USER_CONFIG=os.path.join(directory, "config"), PYTHONDONTWRITEBYTECODE="1")
        environment.pop("PYTHONPATH", None)  # the add-on must bring its own client
        script = pathlib.Path(__file__).with_name("bake_in_blender.py")
        result = subprocess.run([blender, "--background", "--factory-startup", "--python-exit-code", "1",
                                 "--python", str(script), "--", config_path],
                                env=environment, capture_output=True, text=True, timeout=300)
        print(result.stdout)
        print(result.stderr, file=sys.stderr)
        if result.returncode != 0:
            raise SystemExit(f"bake_test: Blender exited {result.returncode}; server log:\n{server.log()}")
        baked = np.load(config["output"])
    diagonal = testing.bounding_box_diagonal(expected[0])
    error = np.abs(baked - expected).max(axis=(1, 2))
    print(f"bake_test: largest difference per frame from the CLI: {error.tolist()} "
          f"(tolerance {1e-5 * diagonal:.3g}, 1e-5 of the diagonal)")
    if baked.shape != expected.shape or np.any(error > 1e-5 * diagonal):
        raise SystemExit("bake_test: the baked vertices differ from the CLI's result")
    moved = np.abs(expected[-1] - expected[0]).max()
    if moved < 0.01 * diagonal:
        raise SystemExit(f"bake_test: the frames barely move ({moved}); the comparison would prove little")
    print("bake_test: OK")


if __name__ == "__main__":
    main()
