"""Builders for the proto's collider shapes, their rigid motions and pins.

Shapes are given once per solve in the character's units and space; each frame may then move every collider
rigidly with a transform p -> R p + t (R from a unit quaternion w, x, y, z).
"""

import numpy as np

from springblend._generated import pb
from springblend.errors import invalid_argument


def vec3(values, what="vector"):
    """A proto Vec3 from three numbers."""
    x, y, z = _three(values, what)
    return pb.Vec3(x=x, y=y, z=z)


def sphere(center, radius):
    """A ball of the given radius (> 0) around center."""
    return pb.Collider(sphere=pb.Sphere(center=vec3(center, "sphere center"), radius=float(radius)))


def box(center, half_extents):
    """An axis-aligned box (rotate it with a transform); every half extent > 0."""
    return pb.Collider(box=pb.Box(center=vec3(center, "box center"),
                                  half_extents=vec3(half_extents, "box half_extents")))


def capsule(a, b, radius):
    """The points within radius of the segment a-b."""
    return pb.Collider(capsule=pb.Capsule(a=vec3(a, "capsule a"), b=vec3(b, "capsule b"), radius=float(radius)))


def plane(point, normal):
    """A half-space: solid behind the plane through point with the given (non-zero) normal."""
    return pb.Collider(plane=pb.Plane(point=vec3(point, "plane point"), normal=vec3(normal, "plane normal")))


def mesh(vertices, faces, as_obj_text=False):
    """A closed, outward-oriented triangle mesh collider: #V by 3 positions, #F by 3 0-based triangles.

    Sent as packed arrays (float64 positions, int32 triangles), which the server reads without parsing;
    as_obj_text=True sends OBJ text instead, for servers older than the arrays (the text's coordinates are read
    as float32)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise invalid_argument("mesh collider: expected #V by 3 vertices and #F by 3 faces")
    if not np.issubdtype(faces.dtype, np.integer):
        raise invalid_argument("mesh collider: faces must be integer vertex indices")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise invalid_argument(f"mesh collider: faces refer to vertices outside 0..{len(vertices) - 1}")
    if as_obj_text:
        lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
        return pb.Collider(mesh_obj="\n".join(lines) + "\n")
    return pb.Collider(mesh=pb.MeshArrays(positions=vertices.astype("<f8").tobytes(),
                                          triangles=faces.astype("<i4").tobytes()))


def transform(translation=(0.0, 0.0, 0.0), rotation=(1.0, 0.0, 0.0, 0.0)):
    """A rigid motion p -> R p + translation, R the unit quaternion rotation = (w, x, y, z)."""
    if isinstance(translation, pb.Transform):
        return translation
    w, x, y, z = (float(v) for v in _sequence(rotation, 4, "rotation quaternion (w, x, y, z)"))
    return pb.Transform(translation=vec3(translation, "translation"), qw=w, qx=x, qy=y, qz=z)


def pin(vertex, position):
    """Holds vertex (0-based, rest mesh order) at position in this frame."""
    return pb.Pin(vertex=int(vertex), position=vec3(position, "pin position"))


def _three(values, what):
    return [float(v) for v in _sequence(values, 3, what)]


def _sequence(values, count, what):
    values = list(np.asarray(values, dtype=np.float64).reshape(-1))
    if len(values) != count:
        raise invalid_argument(f"{what}: expected {count} numbers, got {len(values)}")
    return values
