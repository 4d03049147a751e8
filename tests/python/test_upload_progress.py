"""Upload progress: upload(..., on_progress=) reports the build about twice a second, against a real server.

The bundled face (tests/data/face: the ICT neutral mesh and jawOpen, a build of over a minute) is uploaded
with an 8 s timeout: the callbacks must carry the character's id (the CLI's, which names the same content) and
a stage, come about every half second, and the upload must then fail with DEADLINE_EXCEEDED saying so. A
callback that raises cancels the upload and its exception reaches the caller. Bounded: about 20 s in all.
"""

import os
import re
import subprocess
import time
import unittest

import grpc
import numpy as np

import springblend
import springblend_testing as testing

FACE = testing.DATA / "face"
STAGES = {"queued", "springs", "interior", "analysis", "placement", "paths", "done"}


# The bundled face's five expressions, uploaded with the densest paths (PATH_INTERVALS): a build of minutes, which
# outlasts the tests' deadlines however fast paths become.
EXPRESSIONS = ["jawOpen", "mouthClose", "mouthFunnel", "mouthSmile_L", "mouthStretch_L"]
PATH_INTERVALS = 128


def face():
    """(rest, faces, {name: positions}), rounded to float32 as the CLI's OBJ reader does (same id)."""
    rest, faces = testing.load_obj(FACE / "generic_neutral_mesh.obj")
    targets = {name: testing.load_obj(FACE / f"{name}.obj")[0].astype(np.float32).astype(np.float64)
               for name in EXPRESSIONS}
    return rest.astype(np.float32).astype(np.float64), faces, targets


class UploadProgressTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.server = testing.Server()
        cls.rest, cls.faces, cls.targets = face()

    @classmethod
    def tearDownClass(cls):
        cls.server.stop()

    def test_progress_arrives_while_the_face_builds_then_the_deadline_ends_the_upload(self):
        calls = []
        start = time.monotonic()
        with springblend.Client(self.server.address, timeout=8) as client:
            with self.assertRaises(springblend.SpringblendError) as raised:
                client.upload(self.rest, self.faces, self.targets, name="face", path_intervals=PATH_INTERVALS,
                              on_progress=lambda i, p: calls.append((time.monotonic() - start, i, p)))
        took = time.monotonic() - start
        self.assertEqual(raised.exception.code, grpc.StatusCode.DEADLINE_EXCEEDED)
        self.assertIn("timeout of 8 s", raised.exception.message)
        self.assertLess(took, 12)
        # About twice a second for most of the 8 s (the pieces take a moment to send and check).
        self.assertGreaterEqual(len(calls), 8, calls)
        self.assertLessEqual(len(calls), 17, calls)
        ids = {character_id for _, character_id, _ in calls}
        self.assertEqual(len(ids), 1, ids)
        (character_id,) = ids
        self.assertRegex(character_id, "^[0-9a-f]{64}$")
        for _, _, progress in calls:
            self.assertIn(progress.stage, STAGES)
        self.assertEqual(calls[-1][2].targets, len(EXPRESSIONS))  # their paths are being built by then
        gaps = np.diff([t for t, _, _ in calls])
        self.assertTrue(np.all((gaps > 0.3) & (gaps < 1.5)), gaps)

        # The same content through the CLI names the same character in its progress lines.
        if os.environ.get("SPRINGBLEND_CLI"):
            result = subprocess.run(
                [testing.required_path("SPRINGBLEND_CLI"), "upload", "--server", self.server.address, "--timeout",
                 "3", "--path-intervals", str(PATH_INTERVALS), "--rest", str(FACE / "generic_neutral_mesh.obj"),
                 "--target", *[str(FACE / f"{name}.obj") for name in EXPRESSIONS]],
                capture_output=True, text=True, timeout=30)
            self.assertNotEqual(result.returncode, 0)
            shown = re.findall(r"building ([0-9a-f]{12})", result.stderr)
            self.assertTrue(shown, result.stderr)
            self.assertTrue(character_id.startswith(shown[0]), (character_id, result.stderr))

    def test_a_callback_that_raises_cancels_the_upload(self):
        class Stop(Exception):
            pass

        seen = []

        def stop(character_id, progress):
            seen.append(character_id)
            raise Stop

        start = time.monotonic()
        with springblend.Client(self.server.address, timeout=60) as client:
            with self.assertRaises(Stop):
                client.upload(self.rest, self.faces, self.targets, name="face", path_intervals=PATH_INTERVALS,
                              on_progress=stop)
            self.assertLess(time.monotonic() - start, 5)
            # The server learns of the cancel: the build stops and nothing is kept (within about a second).
            deadline = time.monotonic() + 5
            while True:
                try:
                    state = client.get(seen[0], no_wait=True).state
                except springblend.SpringblendError as error:
                    self.assertEqual(error.code, grpc.StatusCode.NOT_FOUND)
                    break
                self.assertLess(time.monotonic(), deadline, f"the cancelled build is still there: {state}")
                time.sleep(0.2)

    def test_a_small_upload_with_progress_returns_the_character(self):
        rest, faces, targets = testing.cylinder()
        with springblend.Client(self.server.address, timeout=60) as client:
            calls = []
            character = client.upload(rest, faces, targets, name="cylinder",
                                      on_progress=lambda i, p: calls.append(i))
            self.assertEqual(character.id, client.upload(rest, faces, targets, name="cylinder").id)
            self.assertTrue(all(i == character.id for i in calls), calls)


if __name__ == "__main__":
    unittest.main()
