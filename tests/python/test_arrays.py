"""The Python client's checks and conversions that need no server: bad arrays are refused before anything
is sent, with an INVALID_ARGUMENT that names the argument; packed buffers round-trip."""

import unittest

import grpc
import numpy as np

import springblend
from springblend import arrays, colliders
from springblend.client import _frame_requests


class ArraysTest(unittest.TestCase):
    def assertRefused(self, call, fragment):
        with self.assertRaises(springblend.SpringblendError) as caught:
            call()
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn(fragment, caught.exception.message)

    def test_points_must_be_v_by_3_and_finite(self):
        self.assertRefused(lambda: arrays.as_points(np.zeros((4, 2)), "rest"), "rest")
        self.assertRefused(lambda: arrays.as_points([[0, 0, 0], [0, 0]], "rest"), "rectangular")
        self.assertRefused(lambda: arrays.as_points([[0, 0, 0], [0, np.nan, 0]], "target 'a'"), "vertex 1")

    def test_faces_must_be_integer_triangles_in_range(self):
        self.assertRefused(lambda: arrays.as_faces(np.zeros((2, 3)), 3), "integer")
        self.assertRefused(lambda: arrays.as_faces([[0, 1, 3]], 3), "[0, 3)")
        self.assertEqual(arrays.as_faces([[0, 1, 2]], 3).dtype, np.dtype("<i4"))

    def test_float32_buffers_round_trip(self):
        points = np.arange(12, dtype=np.float32).reshape(4, 3)
        np.testing.assert_array_equal(arrays.unpack_float32(points.astype("<f4").tobytes()), points)
        with self.assertRaises(ValueError):
            arrays.unpack_float32(b"12345")

    def test_frames_take_one_row_per_frame_and_one_entry_per_frame(self):
        frames = _frame_requests([[0.5, 0.25]], [[((1, 2, 3), (1, 0, 0, 0))]], [{3: (0, 0, 1)}])
        self.assertEqual(list(frames[0].weights), [0.5, 0.25])
        self.assertEqual(frames[0].collider_transforms[0].translation.z, 3.0)
        self.assertEqual(frames[0].pins[0].vertex, 3)
        self.assertRefused(lambda: _frame_requests([[0.5], [0.5, 0.2]], None, None), "weights")
        self.assertRefused(lambda: _frame_requests([[0.5], [0.2]], [[]], None), "collider_transforms")

    def test_collider_builders(self):
        self.assertEqual(colliders.sphere((1, 2, 3), 0.5).sphere.radius, 0.5)
        self.assertEqual(colliders.box((0, 0, 0), (1, 2, 3)).box.half_extents.y, 2.0)
        triangle = [[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], [[0, 1, 2]]
        self.assertIn("f 1 2 3", colliders.mesh(*triangle, as_obj_text=True).mesh_obj)
        arrays = colliders.mesh(*triangle).mesh
        np.testing.assert_array_equal(np.frombuffer(arrays.positions, "<f8").reshape(-1, 3), triangle[0])
        np.testing.assert_array_equal(np.frombuffer(arrays.triangles, "<i4").reshape(-1, 3), triangle[1])
        self.assertRefused(lambda: colliders.mesh(triangle[0], [[0, 1, 3]]), "faces refer to vertices")
        self.assertRefused(lambda: colliders.sphere((1, 2), 0.5), "sphere center")


if __name__ == "__main__":
    unittest.main()
