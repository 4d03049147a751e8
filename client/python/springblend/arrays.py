"""Conversions between numpy arrays and the proto's packed little-endian buffers."""

import numpy as np

from springblend.errors import invalid_argument


def as_array(values, what, dtype=None):
    """np.asarray, with a ragged or non-numeric input reported as an INVALID_ARGUMENT naming `what`."""
    try:
        return np.asarray(values, dtype=dtype)
    except (TypeError, ValueError) as error:
        raise invalid_argument(f"{what}: not a rectangular array of numbers ({error})") from None


def as_points(values, what):
    """Returns values as a C-contiguous #V by 3 float64 array, or raises naming `what`."""
    array = as_array(values, what, np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise invalid_argument(f"{what}: expected a #V by 3 array of positions, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        row = int(np.argwhere(~np.isfinite(array))[0][0])
        raise invalid_argument(f"{what}: vertex {row} has a non-finite coordinate")
    return np.ascontiguousarray(array)


def as_faces(values, vertex_count):
    """Returns values as a C-contiguous #F by 3 int32 array of 0-based vertex indices, or raises."""
    array = as_array(values, "faces")
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] == 0:
        raise invalid_argument(f"faces: expected a non-empty #F by 3 array of triangles, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.integer):
        raise invalid_argument(f"faces: expected integer vertex indices, got {array.dtype}")
    if array.min() < 0 or array.max() >= vertex_count:
        raise invalid_argument(
            f"faces: indices must lie in [0, {vertex_count}) (0-based), found {array.min()}..{array.max()}")
    return np.ascontiguousarray(array, dtype="<i4")


def pack_float64(points):
    """#V by 3 float64 -> bytes, x y z per vertex, little-endian (MeshPiece POSITIONS)."""
    return np.ascontiguousarray(points, dtype="<f8").tobytes()


def unpack_float32(data):
    """SolvedFrame positions or normals (float32 little-endian x y z) -> #V by 3 float32 array."""
    if len(data) % 12:
        raise ValueError(f"a packed vertex buffer of {len(data)} bytes is not a whole number of float32 triples")
    return np.frombuffer(data, dtype="<f4").reshape(-1, 3)
