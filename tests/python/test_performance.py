"""Captured takes (issue 59) in Python: springblend.performance reads a take into the very weights the CLI reads
(to the bit) with the very report the CLI prints, refuses bad takes naming the line and column as the CLI does, and
the client solves a take as a stream (the CLI's `solve --take` gives the same point cache).

tests/data/take/edge_take.csv (ours): lost-tracking rows (the first, a stretch of six, one more), a weight above 1,
one below 0, symmetric shapes (BrowInnerUp, CheekPuff), columns no target takes (TongueOut, rotations) and one only
a map names (LipCornerPull, edge_map.json); read against a rig whose targets split BrowInnerUp but not CheekPuff."""

import json
import os
import pathlib
import shutil
import struct
import tempfile
import unittest
import warnings

import numpy as np

import springblend
from springblend import performance
import springblend_testing as testing

TAKES = testing.DATA / "take"
EDGE = TAKES / "edge_take.csv"
EDGE_MAP = TAKES / "edge_map.json"
EXCERPT = TAKES / "alex_rom_4_excerpt.csv"
# The rig the edge take drives: the cylinder's poses under these names (the names matter, not the shapes).
EDGE_TARGETS = ["eyeBlink_L", "EyeBlink.R", "browInnerUp_L", "browInnerUp_R", "cheekPuff", "jawOpen",
                "eyeLookOut_L", "smile_L", "smile_R", "sneer_L", "neckTense"]
POSES = ["poses-1_cylinder-1", "poses-1_cylinder-2", "poses-1_cylinder-3", "poses-1_cylinder-4",
         "poses-2_cylinder-1", "poses-2_cylinder-2", "poses-2_cylinder-3", "poses-2_cylinder-4"]


def cli_take(directory, take, *options):
    """The CLI's linear blend of a take on the cylinder with EDGE_TARGETS: (weights per frame, report lines)."""
    import subprocess
    arguments = [testing.required_path("SPRINGBLEND_CLI"), "blend", "--linear",
                 "--rest", str(testing.CYLINDER / "cylinder.obj")]
    for name in EDGE_TARGETS:
        arguments += ["--target", os.path.join(directory, f"{name}.obj")]
    arguments += [*options, "--out", os.path.join(directory, "out.pc2")]
    arguments += ["--take", str(take)] if "--frames" not in options else []
    result = subprocess.run(arguments, capture_output=True, text=True, timeout=120)
    if result.returncode != 0:
        raise AssertionError(f"springblend blend exited {result.returncode}: {result.stderr}")
    weights = np.array([json.loads(line)["weights"] for line in result.stdout.splitlines()], dtype=np.float64)
    prefix = f"springblend: take {take}: "
    report = [line[len(prefix):] for line in result.stderr.splitlines() if line.startswith(prefix)]
    return weights, report


class PerformanceTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.directory = tempfile.mkdtemp(prefix="springblend-take-")
        for i, name in enumerate(EDGE_TARGETS):
            shutil.copy(testing.CYLINDER / f"{POSES[i % len(POSES)]}.obj", os.path.join(cls.directory, f"{name}.obj"))

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.directory, ignore_errors=True)

    def read(self, *args, **kwargs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", performance.TakeWarning)
            return performance.read(*args, **kwargs)

    def test_the_cli_and_python_read_the_same_weights_and_report(self):
        for lost in ("hold", "skip"):
            with self.subTest(lost=lost):
                weights, report = cli_take(self.directory, EDGE, "--map", str(EDGE_MAP), "--lost", lost)
                mine = self.read(EDGE, EDGE_TARGETS, map=str(EDGE_MAP), lost=lost)
                self.assertEqual(weights.shape, mine.weights.shape)
                self.assertTrue(np.array_equal(weights, mine.weights), "the CLI's and Python's weights differ")
                self.assertEqual(report, mine.report.lines())
        # Without the map: LipCornerPull drives nothing, and --frames recognises the take by its header.
        weights, report = cli_take(self.directory, EDGE, "--frames", str(EDGE))
        mine = self.read(str(EDGE), EDGE_TARGETS)
        self.assertTrue(np.array_equal(weights, mine.weights))
        self.assertEqual(report, mine.report.lines())

    def test_the_edge_take(self):
        p = self.read(EDGE, EDGE_TARGETS, map=str(EDGE_MAP))
        take, r = p.take, p.report
        self.assertEqual(p.weights.shape, (24, len(EDGE_TARGETS)))
        self.assertEqual((take.timing.timecode_rate, take.timing.step, take.timing.frame_rate), (60, 2, 30.0))
        self.assertEqual(p.start_frame, ((10 * 3600 + 20 * 60 + 30) * 60 + 52) / 2)
        self.assertEqual((r.lost_rows, r.leading_lost_rows, r.longest_lost, r.longest_lost_line), (8, 1, 6, 11))
        names = {n: i for i, n in enumerate(EDGE_TARGETS)}
        row = take.rows[3]  # line 5, tracked
        col = {s: row.values[i] for i, s in enumerate(take.shapes)}
        w = p.weights[3]
        self.assertEqual(w[names["eyeBlink_L"]], col["EyeBlinkLeft"])
        self.assertEqual(w[names["EyeBlink.R"]], col["EyeBlinkRight"])
        self.assertEqual(w[names["browInnerUp_L"]], col["BrowInnerUp"])  # a symmetric shape drives both halves
        self.assertEqual(w[names["browInnerUp_R"]], col["BrowInnerUp"])
        self.assertEqual(w[names["cheekPuff"]], col["CheekPuff"])
        self.assertEqual(w[names["jawOpen"]], col["JawOpen"])
        self.assertEqual(w[names["smile_L"]], 0.0 + 0.25 * col["JawOpen"] + 0.5 * col["LipCornerPull"])
        self.assertEqual(w[names["smile_R"]], 0.5 * col["LipCornerPull"])
        # Lost rows held: the first at the first tracked row, the stretch at the row before it.
        self.assertTrue(np.array_equal(p.weights[0], p.weights[1]))
        self.assertTrue(all(np.array_equal(p.weights[i], p.weights[8]) for i in range(9, 15)))
        self.assertEqual(p.lines[:3], [2, 3, 4])
        self.assertEqual(r.undriven_targets, ["sneer_L", "neckTense"])
        self.assertEqual(r.summed_targets, ["smile_L"])
        self.assertEqual(r.unused_map_entries, ["NoseSneerLeft"])
        self.assertEqual(r.unmatched_shapes, ["TongueOut (null in the map)"])
        self.assertEqual(r.other_columns, ["HeadYaw", "HeadPitch", "LeftEyeYaw"])
        above = {o.target: o for o in r.out_of_range}
        self.assertEqual(above["eyeLookOut_L"].high, 1.0423118472)
        self.assertEqual(above["eyeLookOut_L"].line, 7)
        self.assertEqual(above["jawOpen"].low, -0.0000123)
        skipped = self.read(EDGE, EDGE_TARGETS, map=str(EDGE_MAP), lost="skip")
        self.assertEqual(len(skipped.weights), 16)
        self.assertEqual(skipped.lines[0], 3)

    def test_the_report_is_one_warning(self):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            performance.read(EDGE, EDGE_TARGETS)
        self.assertEqual(len(caught), 1)
        self.assertTrue(issubclass(caught[0].category, performance.TakeWarning))
        self.assertIn("tracking lost in 8 rows", str(caught[0].message))

    def test_the_excerpt_on_the_ict_names(self):
        names = ["browInnerUp_L", "browInnerUp_R", "cheekRaiser_L", "eyeLookIn_L", "jawLeft", "jawOpen", "mouthLeft"]
        p = self.read(EXCERPT, names)
        self.assertEqual((p.take.timing.frame_rate, p.weights.shape), (30.0, (40, len(names))))
        self.assertEqual(p.start_frame, ((16 * 3600 + 56 * 60 + 29) * 60 + 40) / 2)
        self.assertEqual(p.report.undriven_targets, ["cheekRaiser_L"])
        self.assertIn("TongueOut", p.report.unmatched_shapes)
        self.assertEqual(p.by_name(0)["jawLeft"], p.take.rows[0].values[p.take.shapes.index("JawLeft")])

    def test_other_rates_lengths_and_long_lost_stretches(self):
        for rate, step, rows, lost_from, lost_to in ((24, 1, 500, 10, 400), (25, 1, 30, 0, 29), (60, 1, 121, 60, 61),
                                                     (50, 2, 40, 3, 37)):
            lines = ["Timecode,BlendShapeCount,JawOpen,CheekPuff"]
            frame = 3600 * rate
            for r in range(rows):
                sec, ff = divmod(frame + r * step, rate)
                code = f"{sec // 3600:02d}:{sec // 60 % 60:02d}:{sec % 60:02d}:{ff:02d}"
                lines.append(f"{code},0" if lost_from <= r < lost_to else f"{code},2,{r / rows!r},0.5")
            take = performance.parse_take("\n".join(lines) + "\n", "generated.csv")
            with self.subTest(rate=rate, step=step, rows=rows):
                self.assertEqual((take.timing.timecode_rate, take.timing.step), (rate, step))
                self.assertEqual(take.timing.start_frame, 3600 * rate / step)
                p = self.read(take, ["jawOpen", "cheekPuff_L", "cheekPuff_R"])
                self.assertEqual(len(p.weights), rows)
                self.assertEqual(p.report.longest_lost, lost_to - lost_from)
                held = lost_from - 1 if lost_from > 0 else lost_to
                self.assertTrue(np.array_equal(p.weights[lost_from], p.weights[held]))

    def test_bad_takes_name_the_line_and_column(self):
        header = "Timecode,BlendShapeCount,JawOpen,MouthClose,HeadYaw\n"
        cases = [
            (header + "00:00:00:00,3,0.1,0.2,0\n00:00:00:01,3,0.1\n",
             "bad.csv: line 3, column 4: the row ends after 3 of the header's 5 columns (a row where tracking was "
             "lost has BlendShapeCount 0)"),
            (header + "00:00:00:00,3,0.1,abc,0\n", "bad.csv: line 2, column 4: (MouthClose) 'abc' is not a number"),
            (header + "00:00:00:00,3,0.1,nan,0\n", "bad.csv: line 2, column 4: (MouthClose) 'nan' is not a number"),
            (header + "00:00:00:00,3,0.1,1e999,0\n", "bad.csv: line 2, column 4: (MouthClose) '1e999' is not a number"),
            (header + "\n00:00:00:00,3,0.1,0.2,0,9\n", "bad.csv: line 3, column 6: 6 fields, but the header has 5 columns"),
            (header + "0:00:61:00,3,0.1,0.2,0\n",
             "bad.csv: line 2, column 1: (Timecode) '0:00:61:00' is not a timecode HH:MM:SS:FF[.sss]"),
            ("Frame,Alpha,Beta\n1,2,3\n",
             "bad.csv: line 1, column 1: not a take's header: no Timecode, BlendShapeCount or ARKit shape column "
             "(EyeBlinkLeft ... JawOpen ... TongueOut)"),
            (header, "bad.csv: the take has a header but no rows"),
        ]
        for text, message in cases:
            with self.subTest(message=message):
                with self.assertRaises(springblend.SpringblendError) as caught:
                    performance.parse_take(text, "bad.csv")
                self.assertEqual(caught.exception.message, message)

    def test_the_cli_refuses_bad_takes_and_writes_nothing(self):
        import subprocess
        path = os.path.join(self.directory, "short.csv")
        with open(EDGE) as take:
            lines = take.read().splitlines()
        lines[4] = ",".join(lines[4].split(",")[:5])
        with open(path, "w") as out:
            out.write("\n".join(lines) + "\n")
        with self.assertRaises(springblend.SpringblendError) as caught:
            performance.read_take(path)
        out = os.path.join(self.directory, "never.pc2")
        result = subprocess.run([testing.required_path("SPRINGBLEND_CLI"), "blend", "--linear", "--rest",
                                 str(testing.CYLINDER / "cylinder.obj"), "--target",
                                 os.path.join(self.directory, "jawOpen.obj"), "--take", path, "--out", out],
                                capture_output=True, text=True, timeout=60)
        self.assertEqual(result.returncode, 2)
        self.assertEqual(result.stderr.strip(), f"springblend: error: {caught.exception.message}")
        self.assertIn("line 5, column 6", result.stderr)
        self.assertFalse(os.path.exists(out) or os.path.exists(out + ".partial"))


class SolveTakeTest(unittest.TestCase):
    """The client streams a take's solve; the CLI's `solve --take` of the same take is the same point cache."""

    @classmethod
    def setUpClass(cls):
        cls.server = testing.Server()
        cls.client = springblend.Client(cls.server.address, timeout=120)
        rest, faces, _ = testing.cylinder()
        targets = {name: testing.load_obj(testing.CYLINDER / f"{POSES[i % len(POSES)]}.obj")[0]
                   .astype(np.float32).astype(np.float64) for i, name in enumerate(EDGE_TARGETS)}
        cls.character = cls.client.upload(rest, faces, targets, name="edge")

    @classmethod
    def tearDownClass(cls):
        cls.client.close()
        cls.server.stop()

    def test_solve_take_streams_what_the_cli_solves(self):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", performance.TakeWarning)
            take = self.client.read_take(self.character.id, str(EDGE), map=str(EDGE_MAP))
            frames = list(self.client.solve_take(self.character.id, str(EDGE), map=str(EDGE_MAP), linear=True))
        self.assertEqual([f.index for f in frames], list(range(24)))
        solution = self.client.solve(self.character.id, take.weights, linear=True)
        self.assertTrue(np.array_equal(np.stack([f.positions for f in frames]), solution.positions))
        with tempfile.TemporaryDirectory() as directory:
            mine, theirs = os.path.join(directory, "python.pc2"), os.path.join(directory, "cli.pc2")
            solution.write_pc2(mine, take.start_frame)
            testing.cli("solve", "--server", self.server.address, "--character", self.character.id, "--linear",
                        "--take", str(EDGE), "--map", str(EDGE_MAP), "--out", theirs)
            self.assertEqual(pathlib.Path(mine).read_bytes(), pathlib.Path(theirs).read_bytes())
            start = struct.unpack_from("<f", pathlib.Path(theirs).read_bytes(), 20)[0]
            self.assertEqual(start, np.float32(take.start_frame))
        with self.assertRaises(springblend.SpringblendError):
            self.client.solve_take(self.character.id, performance.read(EDGE, ["jawOpen"], warn=False))


if __name__ == "__main__":
    unittest.main()
