"""A character's id computed before its upload, so that the upload carries the routing header its solves
carry and a balancer that hashes the header builds the character on the replica its solves reach
(docs/server.md#routing). The id is the hex SHA-256 of the canonical bytes the server hashes
(server/character_store.cc), little-endian, field by field from the upload's header and arrays, with the
server's defaults for zero options; the C++ client's CharacterId computes the same bytes.
"""

import hashlib
import struct

import numpy as np

# After the shapes of a production rig; plain characters end before it. Then, when target paths are off, the
# options' marker and a zero byte.
_RIG_MARKER = b"SBRIG001"
_OPTIONS_MARKER = b"SBOPT001"
# RigOptions' defaults, which a zero BuildOptions field means.
_DEFAULT_STATIC_TOLERANCE = 1e-6
_DEFAULT_BENDING_STIFFNESS = 1.0
_DEFAULT_PATH_INTERVALS = 16
_DEFAULT_PATH_MAX_SAMPLES = 64


def _string(text):
    data = text.encode("utf-8")
    return struct.pack("<I", len(data)) + data


def character_id(header, faces, shapes, masks):
    """The id the server will give this upload: header an UploadHeader, faces #F by 3 int32, shapes the
    POSITIONS arrays in the proto's order (rest, targets, then each target's in-betweens), masks
    {target index: float64 bytes}."""
    options = header.options
    digest = hashlib.sha256()
    digest.update(_string(""))  # the name is a label, not part of the id
    digest.update(struct.pack("<I", len(options.fixed_vertices)))
    digest.update(struct.pack(f"<{len(options.fixed_vertices)}i", *options.fixed_vertices))
    digest.update(struct.pack("<d", options.static_tolerance or _DEFAULT_STATIC_TOLERANCE))
    digest.update(struct.pack("<BB", 0 if options.no_interior else 1, 0 if options.no_anchor else 1))
    digest.update(struct.pack("<d", options.bending_stiffness or _DEFAULT_BENDING_STIFFNESS))
    digest.update(struct.pack("<I", len(header.target_names)))
    for name in header.target_names:
        digest.update(_string(name))
    digest.update(struct.pack("<I", len(faces)))
    digest.update(np.ascontiguousarray(faces, dtype="<i4").tobytes())
    digest.update(struct.pack("<I", header.vertex_count))
    targets = len(header.target_names)
    for points in shapes[:1 + targets]:
        digest.update(np.ascontiguousarray(points, dtype="<f8").tobytes())
    if any(t.inbetween_weights or t.has_mask or t.combination for t in header.targets):
        digest.update(_RIG_MARKER)
        inbetweens = iter(shapes[1 + targets:])
        for index, spec in enumerate(header.targets):
            digest.update(struct.pack("<I", len(spec.inbetween_weights)))
            for weight in spec.inbetween_weights:
                digest.update(struct.pack("<d", weight))
                digest.update(np.ascontiguousarray(next(inbetweens), dtype="<f8").tobytes())
            digest.update(struct.pack("<B", 1 if spec.has_mask else 0))
            if spec.has_mask:
                digest.update(masks[index])
            digest.update(struct.pack("<I", len(spec.combination)))
            for driver in spec.combination:
                digest.update(_string(driver))
    # The options tail, only where an option differs from the default.
    intervals = options.path_intervals or _DEFAULT_PATH_INTERVALS
    samples = options.path_max_samples or _DEFAULT_PATH_MAX_SAMPLES
    density = intervals != _DEFAULT_PATH_INTERVALS or samples != _DEFAULT_PATH_MAX_SAMPLES
    if options.no_target_paths or options.hold_outer_rim or density:
        digest.update(_OPTIONS_MARKER + (b"\0" if options.no_target_paths else b"\1"))
        if options.hold_outer_rim or density:
            digest.update(b"\1" if options.hold_outer_rim else b"\0")
        if density:
            digest.update(struct.pack("<II", intervals, samples))
    return digest.hexdigest()
