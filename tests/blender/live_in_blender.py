"""Runs inside Blender (see live_test.py): the add-on's live preview, driven headless through the code its
handlers and timer call (live.update / the handlers, live.poll), against a real server.

Steps: a shape-key bake exists and is hidden while previewing; start on frame 2; scrub to frames 3 and 4;
drag a slider through several values; move the ball; an unconverged answer shows at once and the converged
one replaces it; the server ends the idle session (--idle-seconds) and the next change opens a new one; off
leaves the mesh as it was; a file saved while previewing and opened again comes back without the preview; a
server killed mid-session stops the preview with a report. What Blender shows after each solved step is saved
with that step's scene values (weights, ball location) for live_test.py to compare with the CLI's solve.

blender --background --factory-startup --python-exit-code 1 --python live_in_blender.py -- CONFIG.json
"""

import json
import pathlib
import sys
import time
import types

import bpy
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from blender_scene import check, setup, shown_positions  # noqa: E402
import springblend_testing as testing  # noqa: E402

WAIT_SECONDS = 30


def wait_for(live, condition, what, seconds=WAIT_SECONDS):
    """Runs the add-on's timer function (what bpy.app.timers runs in the UI) until condition() holds."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        live.poll()
        if condition():
            return
        time.sleep(0.005)
    raise AssertionError(f"live_in_blender: timed out waiting for {what}; status: "
                         f"{live.active() and live.active().status()} / {live.last_report()}")


def settled(live):
    """A condition: the preview shows the converged answer to the newest request it sent."""
    def condition():
        preview = live.active()
        shown = preview and preview.shown
        return bool(shown) and shown.request == preview.last_request and shown.converged
    return condition


class PanelLayout:
    """Stands in for a panel's UILayout (there is no window headless) and records the labels drawn."""

    def __init__(self, labels=None):
        self.labels = [] if labels is None else labels
        self.enabled = True

    def label(self, text="", **_):
        self.labels.append(text)

    def prop(self, *_, **__):
        pass

    def operator(self, *_, **__):
        pass

    def row(self, **_):
        return PanelLayout(self.labels)

    column = box = row


def panel_labels(context):
    """The labels the springblend panel draws now."""
    layout = PanelLayout()
    panel = types.SimpleNamespace(layout=layout)
    bpy.types.SPRINGBLEND_PT_main.draw(panel, context)
    return layout.labels


def key_values(obj, names):
    return [float(obj.data.shape_keys.key_blocks[n].value) for n in names]


def main():
    config, scene, obj = setup()
    from springblend_blender import live, scene_data  # noqa: E402 - importable once the add-on is enabled

    ball = bpy.data.objects["Ball"]
    names = config["targets"]
    scene.springblend.server = config["server"]
    scene.springblend.timeout = 120
    check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload failed")
    scene.springblend.bake_mode = "SHAPE_KEYS"
    check(bpy.ops.springblend.bake() == {"FINISHED"}, "bake failed")
    baked = [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith(scene_data.BAKE_PREFIX)]

    steps, latencies = [], []

    def record(step, started):
        preview = live.active()
        weights = key_values(obj, names)
        check(preview.shown.request.weights == tuple(weights), f"{step}: shows {preview.shown.request.weights}, "
                                                               f"the keys are {weights}")
        latencies.append({"step": step, "update_to_shown_ms": (preview.applied_at - started) * 1000.0,
                          "sent_to_received_ms": preview.shown.latency_ms})
        steps.append({"step": step, "weights": weights, "ball": [float(x) for x in ball.matrix_world.translation],
                      "shown": shown_positions(obj).tolist()})
        print(f"live_in_blender: {step}: {preview.status()}, update to shown "
              f"{latencies[-1]['update_to_shown_ms']:.1f} ms")

    # Start on frame 2: the preview connects, sends the frame's weights and ball, and shows the answer.
    scene.frame_set(2)
    started = time.monotonic()
    check(bpy.ops.springblend.live_preview() == {"FINISHED"}, "live preview did not start")
    preview = live.active()
    check(preview is not None, "no preview running")
    check(all(obj.data.shape_keys.key_blocks[n].mute for n in baked), "the shape-key bake is not hidden")
    wait_for(live, settled(live), "the first answer")
    check(np.allclose(preview.shown.request.weights, config["weights"][1], atol=1e-6), "not frame 2's weights")
    check("connected" in preview.status() and "converged" in preview.status(), preview.status())
    record("start on frame 2", started)
    status = [label for label in panel_labels(bpy.context) if label.startswith("Cylinder: connected")]
    check(status and status[0].endswith(" ms") and "converged" in status[0], f"the panel shows {status}")

    # Scrub: frame changes run the frame-change handler; only the newest frame must end up shown.
    started = time.monotonic()
    scene.frame_set(3)
    scene.frame_set(4)
    live.on_frame_change(scene)
    wait_for(live, settled(live), "the answer of frame 4")
    check(np.allclose(preview.shown.request.weights, config["weights"][3], atol=1e-6), "not frame 4's weights")
    record("scrub to frame 4", started)

    # Drag a slider (no animation now): many values in a row, as a drag sends them.
    obj.data.shape_keys.animation_data_clear()
    bend = obj.data.shape_keys.key_blocks[names[0]]
    started = time.monotonic()
    for value in np.linspace(0.2, 0.7, 6):
        bend.value = float(value)
        live.on_depsgraph_update(scene, bpy.context.evaluated_depsgraph_get())
    wait_for(live, settled(live), "the dragged slider's answer")
    record("drag the bend slider", started)

    # Move the collider into the cylinder.
    ball.animation_data_clear()
    started = time.monotonic()
    ball.location = (-1.55, 0.7, 0.75)
    bpy.context.view_layer.update()
    live.update(scene)
    wait_for(live, settled(live), "the moved ball's answer")
    record("move the ball", started)

    # An answer marked not converged shows at once; the converged answer of the same frame replaces it; older
    # answers, or an unconverged one after the converged, are dropped.
    shown = preview.shown
    generation, index = shown.serial
    serial = (generation, index + 0.5)  # after the last real answer, before the next
    rough = shown.positions + np.array([0.0, 0.0, 0.05])
    unconverged = types.SimpleNamespace(converged=False, termination="max_iterations")
    converged = types.SimpleNamespace(converged=True, termination="converged")
    check(preview.channel.deliver(serial, rough, unconverged, request=shown.request), "unconverged answer refused")
    live.poll()
    check(np.abs(shown_positions(obj) - rough).max() < 1e-5, "the unconverged answer is not shown")
    check("not converged (max_iterations)" in preview.status(), preview.status())
    check(preview.channel.deliver(serial, shown.positions, converged, request=shown.request), "converged refused")
    live.poll()
    check(np.abs(shown_positions(obj) - np.array(steps[-1]["shown"])).max() < 1e-5, "not replaced by converged")
    check(preview.status().endswith(f"converged, {preview.shown.latency_ms:.0f} ms"), preview.status())
    check(not preview.channel.deliver((generation, index), rough, converged, request=shown.request), "older kept")
    check(not preview.channel.deliver(serial, rough, unconverged, request=shown.request), "unconverged kept")

    # The server ends a session idle for --idle-seconds; the next change opens a new one without a report.
    time.sleep(config["idle_seconds"] + 1.5)
    live.poll()
    check(live.active() is preview, f"the idle session stopped the preview: {live.last_report()}")
    started = time.monotonic()
    bend.value = 0.55
    live.update(scene)
    wait_for(live, settled(live), "the answer after the idle session")
    check(preview.channel.reopened == 1, f"sessions reopened: {preview.channel.reopened}")
    record("change after the server ended the idle session", started)

    # Off: the mesh is as it was, the bake shows again, the threads end.
    check(bpy.ops.springblend.live_preview() == {"FINISHED"}, "live preview did not stop")
    check(live.active() is None, "still previewing")
    check(not preview.channel.alive(), "the preview's threads still run")
    check(scene_data.LIVE_KEY not in obj.data.shape_keys.key_blocks, "the live key stayed")
    check(not any(obj.data.shape_keys.key_blocks[n].mute for n in baked), "the bake stayed hidden")
    check(live.RESTORE_PROPERTY not in obj, "the restore note stayed")
    check("turned off" in live.last_report(), live.last_report())
    shape_keys_only = scene_data.linear_blend(
        scene_data.key_positions(obj.data.shape_keys.reference_key),
        [scene_data.key_positions(obj.data.shape_keys.key_blocks[n]) for n in names + [baked[-1]]],
        key_values(obj, names) + [obj.data.shape_keys.key_blocks[baked[-1]].value])
    check(np.abs(shown_positions(obj) - shape_keys_only).max() < 1e-5, "off did not leave the keys' mesh")

    # A file saved while previewing, closed and opened again: the preview stops, the file comes back without it.
    bpy.ops.springblend.live_preview()
    preview = live.active()
    wait_for(live, lambda: live.active().shown is not None, "an answer before saving")
    bpy.ops.wm.save_as_mainfile(filepath=config["blend"])
    bpy.ops.wm.open_mainfile(filepath=config["blend"])
    check(live.active() is None and not preview.channel.alive(), "closing the file left the preview running")
    check("file was closed" in live.last_report(), live.last_report())
    obj = bpy.data.objects["Cylinder"]
    check(scene_data.LIVE_KEY not in obj.data.shape_keys.key_blocks, "the reopened file kept the live key")
    check(live.RESTORE_PROPERTY not in obj, "the reopened file kept the restore note")
    check(not any(obj.data.shape_keys.key_blocks[n].mute for n in baked), "the reopened file hides the bake")

    # A server that goes away (killed mid-session) stops the preview with a report; the mesh is as it was.
    scene = bpy.context.scene
    bpy.context.view_layer.objects.active = obj
    before = shown_positions(obj)
    with testing.Server() as spare:
        scene.springblend.server = spare.address
        check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload to the spare server failed")
        bpy.ops.springblend.live_preview()
        preview = live.active()
        wait_for(live, lambda: live.active().shown is not None, "an answer from the spare server")
        spare.process.kill()
        spare.process.wait()
        killed = time.monotonic()
        obj.data.shape_keys.key_blocks[names[1]].value = 0.2
        live.update(scene)
        wait_for(live, lambda: live.active() is None, "the preview to stop")
        stopped_ms = (time.monotonic() - killed) * 1000.0
    report = live.last_report()
    check("UNAVAILABLE" in report and spare.address in report, f"the report does not say what happened: {report}")
    check(not preview.channel.alive(), "the preview's threads still run")
    check(scene_data.LIVE_KEY not in obj.data.shape_keys.key_blocks, "the live key stayed")
    obj.data.shape_keys.key_blocks[names[1]].value = float(steps[-1]["weights"][1])
    check(np.abs(shown_positions(obj) - before).max() < 1e-6, "the mesh is not as it was")
    print(f"live_in_blender: server killed: stopped {stopped_ms:.0f} ms later: {report}")

    with open(config["output"], "w") as out:
        json.dump({"steps": steps, "latencies": latencies, "server_gone_stop_ms": stopped_ms}, out)
    print("live_in_blender: OK,", len(steps), "steps saved")


main()
