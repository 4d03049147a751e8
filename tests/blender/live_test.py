"""The Blender add-on's live preview, headless in a real Blender: starts a springblend server that ends
sessions idle for 2 s, runs Blender (live_in_blender.py) to preview the cylinder scene while scrubbing,
dragging a slider and moving the ball (and the failure cases: off, the file closed, the server killed), then
checks that what Blender showed after each step equals the CLI's one-frame solve of that step's weights and
ball to 1e-5 of the diagonal, and prints the latencies measured in Blender.

Run by CTest (tests/CMakeLists.txt) with /usr/bin/python3; fails, never skips, when Blender is missing.
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

FRAMES = [1, 2, 3, 4]
WEIGHTS = [[0.0, 0.0], [0.3, 0.1], [0.6, 0.3], [0.9, 0.45]]
BALL_LOCATIONS = [[-1.9, 0.75, 0.75], [-1.8, 0.75, 0.75], [-1.7, 0.75, 0.75], [-1.6, 0.72, 0.75]]
IDLE_SECONDS = 2


def main():
    runner.blender_executable()
    with testing.Server(arguments=["--idle-seconds", str(IDLE_SECONDS)]) as server, \
            tempfile.TemporaryDirectory(prefix="springblend-live-") as directory:
        config = dict(runner.scene_config(server, WEIGHTS, BALL_LOCATIONS, FRAMES), idle_seconds=IDLE_SECONDS,
                      output=os.path.join(directory, "live.json"), blend=os.path.join(directory, "live.blend"))
        runner.run_blender("live_in_blender.py", config, directory, server)
        with open(config["output"]) as saved:
            result = json.load(saved)
        steps = result["steps"]
        character = testing.cli_upload_cylinder(server.address)
        expected, summaries = runner.expected_positions(server, character, [s["weights"] for s in steps],
                                                        [s["ball"] for s in steps], directory)
    shown = np.array([s["shown"] for s in steps])
    runner.largest_error(shown, expected, "live_test (" + "; ".join(s["step"] for s in steps) + ")")
    if sum(s["contacts"] for s in summaries) == 0:
        raise SystemExit("live_test: the ball never touches the cylinder; the colliders would go untested")
    for latency in result["latencies"]:
        print(f"live_test: {latency['step']}: update to shown {latency['update_to_shown_ms']:.1f} ms, sent to "
              f"received {latency['sent_to_received_ms']:.1f} ms")
    print(f"live_test: server killed: the preview stopped {result['server_gone_stop_ms']:.0f} ms later")
    print("live_test: OK")


if __name__ == "__main__":
    main()
