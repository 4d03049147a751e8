"""Stores a bake in the mesh as one corrective shape key per frame, driven by the timeline.

The key of frame f holds rest + (solved_f - linear_f), where linear_f is the linear blend of the targets at
f's animated values. Its value is keyed 1 on f and 0 on f - 1 and f + 1 (linear interpolation), so at frame f
Blender shows linear_f + (solved_f - linear_f) = solved_f while the artist's target keys keep animating as
they were; between frames the corrections cross-fade. Changing the target animation afterwards needs a rebake.
"""

import numpy as np

from .scene_data import BAKE_PREFIX, baked_key_name


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
