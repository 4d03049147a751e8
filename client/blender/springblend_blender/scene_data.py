"""Reads what a solve needs out of a Blender scene: the mesh's rest shape, triangles and shape-key targets,
the animated shape-key values of a frame, and the colliders with their motion. Plain numpy out; nothing here
talks to the server."""

import numpy as np

# Shape keys the bake writes (one per frame); never uploaded as targets.
BAKE_PREFIX = "springblend_frame_"
# The shape key the live preview writes (solved minus linear); never uploaded as a target.
LIVE_KEY = "springblend_live"


class UserError(Exception):
    """Something the artist can fix; its message is shown as a Blender report."""


def baked_key_name(frame):
    """The name of the shape key that holds a frame's bake."""
    return f"{BAKE_PREFIX}{frame:04d}"


def shape_keys(obj):
    """The mesh's Key datablock, checked to hold a basis and at least one target."""
    if obj is None or obj.type != "MESH":
        raise UserError("select a mesh object (the character) first")
    keys = obj.data.shape_keys
    if keys is None or len(target_blocks(keys)) == 0:
        raise UserError(f"'{obj.name}' needs shape keys: a Basis and at least one target")
    if not keys.use_relative:
        raise UserError(f"'{obj.name}': springblend needs relative shape keys (Shape Keys panel, Relative)")
    return keys


def target_blocks(keys):
    """The key blocks that are targets: all but the reference (Basis), earlier bakes and the live preview."""
    return [kb for kb in keys.key_blocks
            if kb != keys.reference_key and not kb.name.startswith(BAKE_PREFIX) and kb.name != LIVE_KEY]


def key_positions(key_block):
    """A key block's positions as a #V by 3 float64 array."""
    flat = np.empty(len(key_block.data) * 3, dtype=np.float32)
    key_block.data.foreach_get("co", flat)
    return flat.reshape(-1, 3).astype(np.float64)


def character_arrays(obj):
    """(rest #V by 3, faces #F by 3 int32, {target name: #V by 3}) of a mesh object with shape keys, in the
    object's local space. Polygons are triangulated the way Blender draws them; vertex order is Blender's."""
    keys = shape_keys(obj)
    targets = {}
    for kb in target_blocks(keys):
        if kb.relative_key != keys.reference_key:
            raise UserError(f"shape key '{kb.name}' is relative to '{kb.relative_key.name}'; springblend needs "
                            f"every target relative to '{keys.reference_key.name}'")
        if kb.vertex_group:
            raise UserError(f"shape key '{kb.name}' is limited to vertex group '{kb.vertex_group}', which "
                            "springblend cannot send; apply it into the key first")
        targets[kb.name] = key_positions(kb)
    mesh = obj.data
    mesh.calc_loop_triangles()
    if len(mesh.loop_triangles) == 0:
        raise UserError(f"'{obj.name}' has no faces")
    faces = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", faces)
    return key_positions(keys.reference_key), faces.reshape(-1, 3), targets


def frame_weights(obj, target_names):
    """The current (animated) values of the named shape keys; a muted key counts as 0."""
    blocks = obj.data.shape_keys.key_blocks
    weights = []
    for name in target_names:
        kb = blocks.get(name)
        if kb is None:
            raise UserError(f"shape key '{name}' of the uploaded character is gone from '{obj.name}'; upload again")
        weights.append(0.0 if kb.mute else float(kb.value))
    return weights


# ---------------------------------------------------------------------------------------------------------
# Colliders. Each is described once in its own (scaled) object space, and every frame sends the rigid motion
# of that space relative to the character's object space, so moving, rotating colliders work. Scale is taken
# at the bake's first frame (the proto moves colliders rigidly).

def collider_objects(collection):
    """The objects of the colliders collection (and its children) that are colliders, in a stable order."""
    if collection is None:
        return []
    objects = [o for o in collection.all_objects if collider_shape(o) != "NONE"]
    return sorted(objects, key=lambda o: o.name)


def collider_shape(obj):
    """SPHERE, BOX, MESH or NONE: the object's springblend shape with AUTO resolved."""
    shape = obj.springblend_collider
    if shape != "AUTO":
        return shape
    if obj.type == "EMPTY":
        return {"SPHERE": "SPHERE", "CUBE": "BOX"}.get(obj.empty_display_type, "NONE")
    if obj.type == "MESH" and len(obj.data.vertices) > 0:
        return "SPHERE" if _vertices_on_a_sphere(obj.data) else "BOX"
    return "NONE"


def collider_geometry(character, obj):
    """("sphere", center, radius), ("box", center, half_extents) or ("mesh", vertices, faces), in the
    collider's own space scaled by its scale relative to the character."""
    _, _, scale = _relative(character, obj).decompose()
    scale = np.abs(np.array(scale, dtype=np.float64))
    shape = collider_shape(obj)
    if shape == "MESH":
        if obj.type != "MESH":
            raise UserError(f"collider '{obj.name}' is set to Mesh but is a {obj.type.lower()}")
        mesh = obj.data
        mesh.calc_loop_triangles()
        faces = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
        mesh.loop_triangles.foreach_get("vertices", faces)
        flat = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
        mesh.vertices.foreach_get("co", flat)
        return ("mesh", flat.reshape(-1, 3) * scale, faces.reshape(-1, 3))
    if obj.type == "EMPTY":
        low, high = -np.full(3, obj.empty_display_size), np.full(3, obj.empty_display_size)
    else:
        corners = np.array([tuple(c) for c in obj.bound_box], dtype=np.float64)
        low, high = corners.min(axis=0), corners.max(axis=0)
    center, half = (low + high) / 2 * scale, (high - low) / 2 * scale
    if shape == "SPHERE":
        return ("sphere", center, float(half.max()))
    if np.any(half <= 0):
        raise UserError(f"collider '{obj.name}' is flat (a box needs a positive size on every axis)")
    return ("box", center, half)


def collider_message(springblend, geometry):
    """The springblend client's Collider message of what collider_geometry returned."""
    kind, a, b = geometry
    return {"sphere": springblend.colliders.sphere, "box": springblend.colliders.box,
            "mesh": springblend.colliders.mesh}[kind](a, b)


def collider_motion(character, obj):
    """((x, y, z), (w, x, y, z)): the collider's current rigid motion in the character's space."""
    location, rotation, _ = _relative(character, obj).decompose()
    return tuple(location), tuple(rotation)


def _relative(character, obj):
    return character.matrix_world.inverted() @ obj.matrix_world


def _vertices_on_a_sphere(mesh, tolerance=0.02):
    flat = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", flat)
    points = flat.reshape(-1, 3).astype(np.float64)
    center = (points.min(axis=0) + points.max(axis=0)) / 2
    distances = np.linalg.norm(points - center, axis=1)
    return distances.max() > 0 and (distances.max() - distances.min()) <= tolerance * distances.max()


def linear_blend(rest, targets, weights):
    """The plain linear blendshape rest + sum_t w_t (target_t - rest), what Blender shows from the keys."""
    blend = rest.copy()
    for target, weight in zip(targets, weights):
        if weight != 0.0:
            blend += weight * (target - rest)
    return blend

