"""Stores a bake in the character: as a PC2 point cache played by a Mesh Cache modifier (the default), or as
one corrective shape key per frame, driven by the timeline. A bake of either kind replaces an earlier one of
both kinds.

Point cache: the file holds the solved positions of every baked frame (sample i = frame first + i); the
modifier "springblend_cache", first in the stack, overwrites the mesh with them (frames before the range show
the first baked frame, frames after it the last).

Shape keys: the key of frame f holds rest + (solved_f - linear_f), where linear_f is the linear blend of the targets at
f's animated values. Its value is keyed 1 on f and 0 on f - 1 and f + 1 (linear interpolation), so at frame f
Blender shows linear_f + (solved_f - linear_f) = solved_f while the artist's target keys keep animating as
they were; between frames the corrections cross-fade. Changing the target animation afterwards needs a rebake.
"""

import bpy
import numpy as np

from .scene_data import BAKE_PREFIX, baked_key_name

CACHE_MODIFIER = "springblend_cache"


def remove_bake(obj):
    """Deletes the shape keys (and their animation curves) of an earlier bake; returns how many."""
    keys = obj.data.shape_keys
    if keys is None:
        return 0
    baked = [kb for kb in keys.key_blocks if kb.name.startswith(BAKE_PREFIX)]
    action = keys.animation_data.action if keys.animation_data else None
    for kb in baked:
        if action is not None:
            curve = action.fcurves.find(f'key_blocks["{kb.name}"].value')
            if curve is not None:
                action.fcurves.remove(curve)
        obj.shape_key_remove(kb)
    return len(baked)


def store_frame(obj, frame, rest, linear, solved):
    """Adds the corrective shape key of one frame (see the module's docstring)."""
    kb = obj.shape_key_add(name=baked_key_name(frame), from_mix=False)
    kb.relative_key = obj.data.shape_keys.reference_key
    kb.slider_min, kb.slider_max = 0.0, 1.0
    corrected = rest + (np.asarray(solved, dtype=np.float64) - linear)
    kb.data.foreach_set("co", corrected.astype(np.float32).ravel())
    for key_frame, value in ((frame - 1, 0.0), (frame, 1.0), (frame + 1, 0.0)):
        kb.value = value
        kb.keyframe_insert("value", frame=key_frame)
    curve = obj.data.shape_keys.animation_data.action.fcurves.find(f'key_blocks["{kb.name}"].value')
    for point in curve.keyframe_points:
        point.interpolation = "LINEAR"
    kb.value = 0.0
    return kb


def cache_modifier(obj):
    """The Mesh Cache modifier of a point-cache bake, or None."""
    modifier = obj.modifiers.get(CACHE_MODIFIER)
    return modifier if modifier is not None and modifier.type == "MESH_CACHE" else None


def remove_cache(obj):
    """Removes the Mesh Cache modifier of an earlier point-cache bake (the file stays); True if there was one."""
    modifier = cache_modifier(obj)
    if modifier is None:
        return False
    obj.modifiers.remove(modifier)
    return True


def install_cache(obj, filepath, first_frame):
    """Plays a PC2 file on the object through the springblend Mesh Cache modifier, sample 0 on first_frame,
    creating the modifier first in the stack (before anything that changes the topology) or updating it."""
    modifier = cache_modifier(obj)
    if modifier is None:
        modifier = obj.modifiers.new(CACHE_MODIFIER, "MESH_CACHE")
        if obj.modifiers[0] != modifier:
            with bpy.context.temp_override(object=obj):
                bpy.ops.object.modifier_move_to_index(modifier=modifier.name, index=0)
    modifier.cache_format = "PC2"
    modifier.filepath = filepath
    modifier.time_mode = "FRAME"
    modifier.play_mode = "SCENE"
    modifier.frame_start = float(first_frame)  # scene frame first_frame plays sample 0
    modifier.frame_scale = 1.0
    modifier.deform_mode = "OVERWRITE"
    modifier.interpolation = "LINEAR"
    modifier.forward_axis, modifier.up_axis = "POS_Y", "POS_Z"  # the file is in the object's own axes
    modifier.flip_axis = set()
    modifier.factor = 1.0
    modifier.vertex_group = ""
    modifier.show_viewport = modifier.show_render = True
    return modifier
