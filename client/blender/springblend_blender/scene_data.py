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


# Production rigs (README: Blender conventions). A shape key named TARGET@W (W in (0, 1), e.g. jawOpen@0.5) is
# an in-between of the key TARGET; one named A*B[*C...] (e.g. jawOpen*mouthSmile_L) is a combination corrective
# of the keys A, B, ... (its shape is the sculpt with every driver at 1); a key's vertex group is its mask.
INBETWEEN_MARK = "@"
COMBINATION_MARK = "*"


def key_role(name):
    """("target", None), ("inbetween", (target name, weight)) or ("combination", [driver names]) of a key's name."""
    if COMBINATION_MARK in name:
        return "combination", [part.strip() for part in name.split(COMBINATION_MARK)]
    target, mark, weight = name.rpartition(INBETWEEN_MARK)
    if mark and target:
        try:
            return "inbetween", (target, float(weight))
        except ValueError:
            raise UserError(f"shape key '{name}': '{weight}' after '{INBETWEEN_MARK}' is not a weight; an "
                            f"in-between is named TARGET{INBETWEEN_MARK}W with W in (0, 1), e.g. jawOpen@0.5") \
                from None
    return "target", None


def vertex_group_mask(obj, group_name, vertex_count):
    """One weight per vertex of a vertex group (0 for vertices not in it)."""
    group = obj.vertex_groups.get(group_name)
    if group is None:
        raise UserError(f"vertex group '{group_name}' is gone from '{obj.name}'")
    mask = np.zeros(vertex_count, dtype=np.float64)
    for vertex in obj.data.vertices:
        for element in vertex.groups:
            if element.group == group.index:
                mask[vertex.index] = element.weight
    return mask


FIXED_GROUP = "springblend_fixed"


def fixed_vertices(obj):
    """The vertices of the vertex group 'springblend_fixed' (weight 0.5 or more), held as the character's fixed
    vertices (as Vellum's pin groups and Ziva's attachments hold theirs); none without the group."""
    group = obj.vertex_groups.get(FIXED_GROUP)
    if group is None:
        return []
    return [v.index for v in obj.data.vertices
            if any(e.group == group.index and e.weight >= 0.5 for e in v.groups)]


def character_rig(obj):
    """(rest #V by 3, faces #F by 3 int32, targets) of a mesh object with shape keys, in the object's local space.
    targets: a list of dicts (name, positions, inbetweens [(weight, positions)], mask or None, combination) in
    shape-key order, the fields of springblend.rigfile.Target. Polygons are triangulated the way Blender draws
    them; vertex order is Blender's."""
    keys = shape_keys(obj)
    vertex_count = len(obj.data.vertices)
    targets, inbetweens = {}, []
    for kb in target_blocks(keys):
        if kb.relative_key != keys.reference_key:
            raise UserError(f"shape key '{kb.name}' is relative to '{kb.relative_key.name}'; springblend needs "
                            f"every target relative to '{keys.reference_key.name}'")
        role, detail = key_role(kb.name)
        if role == "inbetween":
            if kb.vertex_group:
                raise UserError(f"in-between key '{kb.name}' has vertex group '{kb.vertex_group}': an in-between "
                                f"takes the mask of its target '{detail[0]}'")
            inbetweens.append((kb.name, detail, key_positions(kb)))
            continue
        target = {"name": kb.name, "positions": key_positions(kb), "inbetweens": [], "mask": None,
                  "combination": detail if role == "combination" else []}
        if kb.vertex_group:
            if role == "combination":
                raise UserError(f"combination key '{kb.name}' has vertex group '{kb.vertex_group}': a combination "
                                "takes no mask")
            target["mask"] = vertex_group_mask(obj, kb.vertex_group, vertex_count)
        targets[kb.name] = target
    for name, (target_name, weight), positions in inbetweens:
        if target_name not in targets:
            raise UserError(f"in-between key '{name}': there is no shape key '{target_name}' it belongs to")
        targets[target_name]["inbetweens"].append((weight, positions))
    mesh = obj.data
    mesh.calc_loop_triangles()
    if len(mesh.loop_triangles) == 0:
        raise UserError(f"'{obj.name}' has no faces")
    faces = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", faces)
    return key_positions(keys.reference_key), faces.reshape(-1, 3), list(targets.values())


def is_production_rig(targets):
    """Whether any target of character_rig has in-betweens, a mask or drivers (else a plain upload)."""
    return any(t["inbetweens"] or t["mask"] is not None or t["combination"] for t in targets)


def key_values(obj):
    """{key name: the value Blender applies now} of every target, in-between and combination key (a muted key
    counts 0)."""
    return {kb.name: 0.0 if kb.mute else float(kb.value) for kb in target_blocks(obj.data.shape_keys)}


def shown_blend(obj, rest, values):
    """What Blender shows from the keys at these values (key_values), without the bake's or the live preview's
    keys: rest + sum over keys of value * vertex-group weight * (key - rest), Blender's relative shape keys."""
    keys = obj.data.shape_keys
    blend = rest.copy()
    for kb in target_blocks(keys):
        value = values.get(kb.name, 0.0)
        if value == 0.0:
            continue
        change = key_positions(kb) - rest
        if kb.vertex_group:
            change *= vertex_group_mask(obj, kb.vertex_group, len(rest))[:, None]
        blend += value * change
    return blend


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

