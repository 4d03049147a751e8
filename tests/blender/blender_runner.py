"""Shared by the Blender tests' drivers (bake_test.py, live_test.py), which run outside Blender: finding
Blender, running a script in it headless with a private user directory, and the CLI's solve of the cylinder
scene those scripts build (the keyed ball and the still box).
"""

import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "python"))
import springblend_testing as testing  # noqa: E402

# The ball (a UV sphere of radius 1 scaled by 0.3) and the box (a cube empty) of the scenes.
BALL_RADIUS = 0.3
BOX_LOCATION, BOX_HALF_EXTENTS = [0.0, 3.0, 0.0], [0.5, 1.0, 0.5]


def blender_executable():
    blender = os.environ.get("BLENDER", "blender")
    found = shutil.which(blender)
    if found is None:
        raise SystemExit(f"{blender!r} is not installed; deploy/install-deps.sh installs Debian's blender")
    return found


def run_blender(script, config, directory, server, timeout=300):
    """Runs tests/blender/SCRIPT in Blender headless with CONFIG (written as JSON into directory); the add-on
    is installed into a private user directory, never into the machine's Blender. Exits on failure, with the
    server's log when there is a server (None: the script needs none)."""
    config_path = os.path.join(directory, f"{pathlib.Path(script).stem}.json")
    with open(config_path, "w") as out:
        json.dump(config, out)
    environment = dict(os.environ, BLENDER_USER_SCRIPTS=os.path.join(directory, "scripts"),
                       BLENDER_USER_CONFIG=os.path.join(directory, "config"), PYTHONDONTWRITEBYTECODE="1")
    environment.pop("PYTHONPATH", None)  # the add-on must bring its own client
    result = subprocess.run([blender_executable(), "--background", "--factory-startup", "--python-exit-code", "1",
                             "--python", str(pathlib.Path(__file__).with_name(script)), "--", config_path],
                            env=environment, capture_output=True, text=True, timeout=timeout)
    print(result.stdout)
    print(result.stderr, file=sys.stderr)
    if result.returncode != 0:
        raise SystemExit(f"{script}: Blender exited {result.returncode}"
                         + (f"; server log:\n{server.log()}" if server is not None else ""))
    return result.stdout


def expected_positions(server, character, weights, ball_locations, directory):
    """The CLI's solve of the frames (each alone) with the ball at each location and the box in place.
    Blender stores locations as float32, so the CLI gets those values."""
    as_float32 = lambda v: [float(x) for x in np.float32(v)]  # noqa: E731
    frames = [{"weights": w, "colliders": [{"translation": as_float32(loc)}, {"translation": as_float32(BOX_LOCATION)}]}
              for w, loc in zip(weights, ball_locations)]
    radius = float(np.float32(BALL_RADIUS))
    colliders = [f"sphere:0,0,0,{radius!r}",
                 "box:0,0,0,{},{},{}".format(*(float(np.float32(h)) for h in BOX_HALF_EXTENTS))]
    return testing.cli_solve(server.address, character, frames, colliders, directory)


def scene_config(server, weights, ball_locations, frames):
    """What blender_scene.py needs to build the cylinder scene."""
    return {"server": server.address, "addon_zip": testing.required_path("SPRINGBLEND_ADDON_ZIP"),
            "cylinder": str(testing.CYLINDER), "targets": list(testing.CYLINDER_TARGETS), "frames": frames,
            "weights": weights, "ball_locations": ball_locations, "ball_radius": BALL_RADIUS,
            "box_location": BOX_LOCATION, "box_half_extents": BOX_HALF_EXTENTS}


def largest_error(shown, expected, what):
    """Largest vertex coordinate difference per frame, checked against 1e-5 of the bounding-box diagonal."""
    diagonal = testing.bounding_box_diagonal(expected[0])
    error = np.abs(shown - expected).max(axis=(1, 2)) if shown.shape == expected.shape else None
    print(f"{what}: largest difference per frame from the CLI: {None if error is None else error.tolist()} "
          f"(tolerance {1e-5 * diagonal:.3g}, 1e-5 of the diagonal)")
    if error is None or np.any(error > 1e-5 * diagonal):
        raise SystemExit(f"{what}: differs from the CLI's result (shapes {shown.shape} and {expected.shape})")
    return error
