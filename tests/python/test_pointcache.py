"""The Python client's PC2 writer and reader, without a server: the header byte for byte, samples read back,
Solution.write_pc2, a failed write leaving the earlier file, and the refusals."""

import os
import struct
import tempfile
import unittest

import numpy as np

import springblend
from springblend import pointcache


def samples(count, points):
    grid = np.arange(count * points * 3, dtype=np.float64).reshape(count, points, 3)
    return grid * 0.1 - 2.0


class PointCacheTest(unittest.TestCase):
    def setUp(self):
        self._directory = tempfile.TemporaryDirectory()
        self.directory = self._directory.name

    def tearDown(self):
        self._directory.cleanup()

    def path(self, name):
        return os.path.join(self.directory, name)

    def test_header_is_the_formats_layout_byte_for_byte(self):
        pointcache.write_pc2(self.path("a.pc2"), samples(3, 4))
        with open(self.path("a.pc2"), "rb") as cache:
            data = cache.read()
        self.assertEqual(len(data), 32 + 3 * 4 * 12)
        self.assertEqual(data[:12], b"POINTCACHE2\0")
        self.assertEqual(struct.unpack_from("<iiffi", data, 12), (1, 4, 1.0, 1.0, 3))
        # Sample 1, point 2: float32 x y z right after sample 0.
        np.testing.assert_array_equal(struct.unpack_from("<3f", data, 32 + (4 + 2) * 12),
                                      samples(3, 4)[1, 2].astype(np.float32))

    def test_reads_back_what_was_written_at_float_precision(self):
        positions = samples(7, 5)
        pointcache.write_pc2(self.path("b.pc2"), positions, start_frame=10, sample_rate=0.5)
        cache = pointcache.read_pc2(self.path("b.pc2"))
        self.assertEqual((cache.start_frame, cache.sample_rate), (10.0, 0.5))
        self.assertEqual(cache.positions.dtype, np.float32)
        np.testing.assert_array_equal(cache.positions, positions.astype(np.float32))

    def test_solution_writes_its_frames(self):
        positions = samples(2, 3).astype(np.float32)
        solution = springblend.Solution(positions=positions, normals=None, summaries=[])
        solution.write_pc2(self.path("c.pc2"))
        cache = pointcache.read_pc2(self.path("c.pc2"))
        self.assertEqual(cache.start_frame, 1.0)  # frame = index + 1
        np.testing.assert_array_equal(cache.positions, positions)

    def test_a_failed_write_leaves_the_earlier_cache(self):
        pointcache.write_pc2(self.path("d.pc2"), samples(2, 3))
        with self.assertRaises(RuntimeError):
            with pointcache.PointCacheWriter(self.path("d.pc2"), 3) as cache:
                cache.add(samples(1, 3)[0])
                raise RuntimeError("the solve failed")
        self.assertEqual(sorted(os.listdir(self.directory)), ["d.pc2"])
        np.testing.assert_array_equal(pointcache.read_pc2(self.path("d.pc2")).positions,
                                      samples(2, 3).astype(np.float32))

    def test_refusals(self):
        with pointcache.PointCacheWriter(self.path("e.pc2"), 4) as cache:
            with self.assertRaisesRegex(ValueError, "shape"):
                cache.add(np.zeros((3, 3)))
            cache.add(np.zeros((4, 3)))
        with self.assertRaises(ValueError):
            cache.add(np.zeros((4, 3)))  # closed
        with self.assertRaises(ValueError):
            pointcache.write_pc2(self.path("f.pc2"), np.zeros((4, 3)))  # not #frames by #points by 3
        with open(self.path("g.pc2"), "w") as text:
            text.write("not a cache at all, just some text")
        with self.assertRaisesRegex(ValueError, "POINTCACHE2"):
            pointcache.read_pc2(self.path("g.pc2"))
        with open(self.path("e.pc2"), "r+b") as cut:
            cut.truncate(40)
        with self.assertRaisesRegex(ValueError, "bytes"):
            pointcache.read_pc2(self.path("e.pc2"))
        with self.assertRaises(OSError):
            pointcache.PointCacheWriter(self.path("missing/dir/h.pc2"), 4)

    def test_a_planted_partial_link_is_refused_and_its_target_left_alone(self):
        # Hardening IV, item 12: the writer opened NAME.pc2.partial following links and overwrote the victim.
        victim = self.path("victim.txt")
        with open(victim, "w") as text:
            text.write("precious")
        os.symlink(victim, self.path("shot.pc2.partial"))
        with self.assertRaisesRegex(OSError, "shot.pc2.partial.*not a regular file"):
            pointcache.write_pc2(self.path("shot.pc2"), samples(2, 3))
        with open(victim) as text:
            self.assertEqual(text.read(), "precious")
        self.assertTrue(os.path.islink(self.path("shot.pc2.partial")))
        self.assertFalse(os.path.exists(self.path("shot.pc2")))
        # A stale regular partial (a run killed mid-write) is replaced.
        os.remove(self.path("shot.pc2.partial"))
        with open(self.path("shot.pc2.partial"), "w") as stale:
            stale.write("half a cache")
        pointcache.write_pc2(self.path("shot.pc2"), samples(2, 3))
        np.testing.assert_array_equal(pointcache.read_pc2(self.path("shot.pc2")).positions,
                                      samples(2, 3).astype(np.float32))
        self.assertFalse(os.path.exists(self.path("shot.pc2.partial")))

    def test_a_sample_not_finite_as_float32_is_refused(self):
        bad = samples(2, 3)
        bad[1, 2, 0] = 1e39  # finite as a double, inf as float32
        with self.assertRaisesRegex(ValueError, "sample 1 .*not finite"):
            pointcache.write_pc2(self.path("i.pc2"), bad)
        self.assertEqual(os.listdir(self.directory), [])


if __name__ == "__main__":
    unittest.main()
