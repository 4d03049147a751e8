"""The Python client does not trust a server's answers (Hardening IV, item 13): frames missing, extra, repeated or
out of order, positions of the wrong shape and positions that are not finite raise the package's own
SpringblendError (DATA_LOSS) naming the frame, never a bare ValueError nor a silently accepted solution.

The server here is a stand-in speaking the real protocol (grpc on loopback), scripted to answer wrongly; the
client under test is the real one."""

import concurrent.futures
import struct
import unittest

import grpc
import numpy as np

import springblend
from springblend._generated import pb, pb_grpc

VERTICES = 4


def positions(value=0.5, count=VERTICES):
    return struct.pack(f"<{3 * count}f", *([value] * (3 * count)))


def frame(index, packed=None, normals=b""):
    return pb.SolvedFrame(index=index, positions=positions() if packed is None else packed, normals=normals,
                          summary=pb.FrameSummary(converged=True))


class ScriptedSolves(pb_grpc.SolveServiceServicer):
    """Answers every Solve (and every Interactive session) with the frames of `script`."""

    def __init__(self):
        self.script = []

    def Solve(self, request, context):
        yield from self.script

    def Interactive(self, requests, context):
        next(requests, None)  # the start
        yield from self.script


class AnswersTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.solves = ScriptedSolves()
        cls.server = grpc.server(concurrent.futures.ThreadPoolExecutor(max_workers=4))
        pb_grpc.add_SolveServiceServicer_to_server(cls.solves, cls.server)
        port = cls.server.add_insecure_port("127.0.0.1:0")
        cls.server.start()
        cls.client = springblend.Client(f"127.0.0.1:{port}", timeout=10)

    @classmethod
    def tearDownClass(cls):
        cls.client.close()
        cls.server.stop(None)

    def solve(self, script, frames=3):
        self.solves.script = script
        return self.client.solve("0" * 64, np.zeros((frames, 2)))

    def assert_refused(self, script, message, frames=3):
        with self.assertRaises(springblend.SpringblendError) as raised:
            self.solve(script, frames)
        self.assertEqual(raised.exception.code, grpc.StatusCode.DATA_LOSS)
        self.assertRegex(raised.exception.message, message)

    def test_a_whole_answer_is_accepted(self):
        solution = self.solve([frame(0), frame(1), frame(2)])
        self.assertEqual(solution.positions.shape, (3, VERTICES, 3))
        self.assertTrue(solution.converged)

    def test_missing_extra_repeated_and_reordered_frames_are_refused(self):
        self.assert_refused([frame(0), frame(1)], "ended after 2 of 3 frames")
        self.assert_refused([frame(0), frame(1), frame(2), frame(3)], "frame 3 came, but the request has 3 frames")
        self.assert_refused([frame(0), frame(0), frame(1)], "frame 0 came where frame 1 of 3 was due")
        self.assert_refused([frame(0), frame(2), frame(1)], "frame 2 came where frame 1 of 3 was due")
        self.assert_refused([], "ended after 0 of 3 frames")

    def test_positions_of_the_wrong_shape_are_refused(self):
        self.assert_refused([frame(0), frame(1, positions(count=VERTICES + 1)), frame(2)],
                            "frame 1 has 5 vertices, the frames before it 4")
        self.assert_refused([frame(0, b"\0" * 13)], "frame 0: .*13 bytes")
        self.assert_refused([frame(0, b"")], "frame 0 has no vertices")
        self.assert_refused([frame(0, normals=positions(count=2))], "frame 0 has 2 normals for 4 vertices")

    def test_positions_that_are_not_finite_are_refused(self):
        bad = bytearray(positions())
        bad[12 * 2:12 * 2 + 4] = struct.pack("<f", float("nan"))
        self.assert_refused([frame(0), frame(1, bytes(bad)), frame(2)], "frame 1: positions of vertex 2 are not finite")
        self.assert_refused([frame(0, positions(float("inf")))], "frame 0: positions of vertex 0 are not finite")

    def test_an_interactive_sessions_answers_are_checked(self):
        bad = bytearray(positions())
        bad[0:4] = struct.pack("<f", float("nan"))
        self.solves.script = [frame(0), frame(1, bytes(bad))]
        with self.client.interactive("0" * 64) as session:
            session.send([0.1, 0.2])
            session.send([0.3, 0.4])
            self.assertEqual(session.next_frame().positions.shape, (VERTICES, 3))
            with self.assertRaises(springblend.SpringblendError) as raised:
                session.next_frame()
        self.assertEqual(raised.exception.code, grpc.StatusCode.DATA_LOSS)
        self.assertIn("frame 1: positions of vertex 0 are not finite", raised.exception.message)
        # An answer to a frame never sent.
        self.solves.script = [frame(0), frame(5)]
        with self.client.interactive("0" * 64) as session:
            session.send([0.1, 0.2])
            session.send([0.3, 0.4])
            session.next_frame()
            with self.assertRaises(springblend.SpringblendError) as raised:
                session.next_frame()
        self.assertIn("frame 5 came, but the session has sent 2 frames", raised.exception.message)


if __name__ == "__main__":
    unittest.main()
