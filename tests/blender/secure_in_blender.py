"""Runs inside Blender (see secure_test.py): the add-on's preferences reach a TLS server with tokens; what is
missing or wrong comes back as a report naming it.

blender --background --factory-startup --python-exit-code 1 --python secure_in_blender.py -- CONFIG.json
"""

import os
import pathlib
import sys
import time

import bpy

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from blender_scene import check, expect_error_report, setup  # noqa: E402


def wait_for_live_answer(live, seconds=60.0):
    """Runs the add-on's timer function (what bpy.app.timers runs in the UI) until the preview shows a frame."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        live.poll()
        preview = live.active()
        check(preview is not None, f"the live preview stopped: {live.last_report()}")
        if preview.shown is not None:
            return preview.shown
        time.sleep(0.01)
    raise AssertionError(f"secure_in_blender: no live answer within {seconds} s: {live.active().status()}")


def main():
    config, scene, obj = setup()
    preferences = bpy.context.preferences.addons["springblend_blender"].preferences
    scene.springblend.server = config["server"]
    scene.springblend.timeout = 10

    # Plaintext to a TLS port: nobody answers there, and the report says TLS may be what is missing.
    expect_error_report(bpy.ops.springblend.check_server, "no springblend server answers at " + config["server"])
    expect_error_report(bpy.ops.springblend.upload, "tls=True or tls_ca")
    # A CA file that is not there is named.
    preferences.tls_ca = config["missing_ca"]
    expect_error_report(bpy.ops.springblend.upload, config["missing_ca"])
    # The wrong CA: the TLS handshake fails, and the report says so.
    preferences.tls_ca = config["rogue_ca"]
    expect_error_report(bpy.ops.springblend.check_server, "the TLS handshake failed")

    # The right CA: health needs no token; an upload does, and the report says how to give one.
    preferences.tls_ca = config["ca"]
    check(bpy.ops.springblend.check_server() == {"FINISHED"}, "check_server over TLS failed")
    expect_error_report(bpy.ops.springblend.upload, "UNAUTHENTICATED")
    expect_error_report(bpy.ops.springblend.upload, "$SPRINGBLEND_TOKEN")
    preferences.token = "not-the-token"
    expect_error_report(bpy.ops.springblend.upload, "check token= or $SPRINGBLEND_TOKEN")

    # With the token: upload, bake and a live preview.
    preferences.token = config["token"]
    scene.springblend.timeout = 120
    check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload over TLS with the token failed")
    check(len(obj.springblend_character) == 64, "upload stored no character id")
    scene.springblend.bake_mode = "SHAPE_KEYS"
    check(bpy.ops.springblend.bake() == {"FINISHED"}, "bake over TLS with the token failed")
    baked = [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith("springblend_frame_")]
    check(len(baked) == len(config["frames"]), f"unexpected baked keys {baked}")
    from springblend_blender import live
    scene.frame_set(config["frames"][0])
    check(bpy.ops.springblend.live_preview() == {"FINISHED"}, "the live preview did not start")
    shown = wait_for_live_answer(live)
    print(f"secure_in_blender: live answer over TLS: converged {shown.converged}, {shown.latency_ms:.0f} ms")
    live.stop("test over")

    # An empty server field and the token field: $SPRINGBLEND_SERVER and $SPRINGBLEND_TOKEN, as for the CLI.
    scene.springblend.server = ""
    preferences.token = ""
    os.environ["SPRINGBLEND_SERVER"] = config["server"]
    os.environ["SPRINGBLEND_TOKEN"] = config["token"]
    check(bpy.ops.springblend.upload() == {"FINISHED"}, "upload through the environment variables failed")
    print("secure_in_blender: OK")


main()
