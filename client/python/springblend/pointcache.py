"""PC2 point caches: every frame's vertex positions in one binary file, which Blender's Mesh Cache modifier,
3ds Max, Maya and Houdini play back.

Layout, little-endian: the 12-byte signature b"POINTCACHE2\\0", int32 version (1), int32 number of points,
float32 start frame, float32 sample rate (frames per sample), int32 number of samples, then float32 x y z per
point per sample. Frame i (0-based) of a solve is sample i; the start frame is 1 unless told otherwise.
"""

import dataclasses
import os
import stat
import struct

import numpy as np

SIGNATURE = b"POINTCACHE2\0"
_HEADER = struct.Struct("<12siiffi")
_COUNT_OFFSET = 28  # where the number of samples sits in the header


@dataclasses.dataclass
class PointCache:
    """A read PC2 file: positions is #samples by #points by 3 float32."""
    positions: np.ndarray
    start_frame: float
    sample_rate: float


class PointCacheWriter:
    """Writes samples as they come, e.g. frames streamed by Client.solve_frames:

        with PointCacheWriter("shot.pc2", len(rest)) as cache:
            for frame in client.solve_frames(character_id, weights):
                cache.add(frame.positions)

    The cache is written under a temporary name beside the path and renamed onto it when the writer closes
    without an error, so the path holds a whole cache or what it held before (a failed bake leaves the earlier
    one playing); an exception inside the with block discards the new samples.
    """

    def __init__(self, path, num_points, start_frame=1.0, sample_rate=1.0):
        if int(num_points) <= 0:
            raise ValueError(f"{path}: a point cache needs points, got {num_points}")
        self.path = os.fspath(path)
        self.num_points = int(num_points)
        self.samples = 0
        self._partial = self.path + ".partial"
        self._file = os.fdopen(_create_partial(self.path, self._partial), "wb")
        self._file.write(_HEADER.pack(SIGNATURE, 1, self.num_points, float(start_frame), float(sample_rate), 0))

    def add(self, positions):
        """Appends one sample: #points by 3 positions (rounded to float32)."""
        if self._file is None:
            raise ValueError(f"{self.path}: the point cache is closed")
        sample = np.asarray(positions, dtype="<f4")
        if sample.shape != (self.num_points, 3):
            raise ValueError(f"{self.path}: sample {self.samples} has shape {sample.shape}, the cache needs "
                             f"({self.num_points}, 3)")
        if not np.all(np.isfinite(sample)):
            raise ValueError(f"{self.path}: sample {self.samples} has positions that are not finite as float32")
        self._file.write(np.ascontiguousarray(sample).tobytes())
        self.samples += 1

    def close(self):
        """Writes the sample count into the header and puts the file in place."""
        if self._file is None:
            return
        self._file.seek(_COUNT_OFFSET)
        self._file.write(struct.pack("<i", self.samples))
        self._file.close()
        self._file = None
        os.replace(self._partial, self.path)

    def discard(self):
        """Abandons the write: the path keeps what it held before."""
        if self._file is None:
            return
        self._file.close()
        self._file = None
        try:
            os.remove(self._partial)
        except OSError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        if exc_type is None:
            self.close()
        else:
            self.discard()


def _create_partial(path, partial):
    """The temporary, created afresh and never through a link (as the C++ writer does): a planted
    NAME.pc2.partial -> victim must not get the victim overwritten. A stale regular partial (an earlier run killed
    mid-write) is removed first; anything else there (a link, a directory, a FIFO) is refused with OSError."""
    try:
        if stat.S_ISREG(os.lstat(partial).st_mode):
            os.unlink(partial)
    except FileNotFoundError:
        pass
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        return os.open(partial, flags, 0o644)
    except OSError as error:
        hint = "; it is not a regular file (a link?): remove it" if isinstance(error, FileExistsError) else ""
        raise OSError(error.errno, f"{path}: cannot write the point cache: {partial} ({error.strerror}){hint}") \
            from error


def write_pc2(path, positions, start_frame=1.0, sample_rate=1.0):
    """Writes #frames by #points by 3 positions as a PC2 file (frame i is sample i, at start_frame + i *
    sample_rate)."""
    positions = np.asarray(positions)
    if positions.ndim != 3 or positions.shape[0] == 0 or positions.shape[2] != 3:
        raise ValueError(f"{path}: expected #frames by #points by 3 positions, got shape {positions.shape}")
    with PointCacheWriter(path, positions.shape[1], start_frame, sample_rate) as cache:
        for sample in positions:
            cache.add(sample)


def read_pc2(path):
    """Reads a whole PC2 file into a PointCache; raises ValueError naming the path when it is not one."""
    with open(path, "rb") as cache:
        data = cache.read()
    if len(data) < _HEADER.size or not data.startswith(SIGNATURE):
        raise ValueError(f"{path}: not a PC2 point cache (no POINTCACHE2 signature)")
    _, version, points, start, rate, samples = _HEADER.unpack_from(data)
    if version != 1 or points <= 0 or samples < 0:
        raise ValueError(f"{path}: unsupported PC2 header (version {version}, {points} points, {samples} samples)")
    expected = _HEADER.size + 12 * points * samples
    if len(data) != expected:
        raise ValueError(f"{path}: {len(data)} bytes, but {samples} samples of {points} points take {expected}")
    positions = np.frombuffer(data, dtype="<f4", offset=_HEADER.size).reshape(samples, points, 3)
    return PointCache(positions=positions, start_frame=start, sample_rate=rate)
