"""Imports a captured take (a Live Link Face CSV, docs/takes.md) onto a character's sliders as keyframes, so it
plays with the live preview and bakes like any animation.

The sliders are the object's target shape keys (what Upload Character sends), or, for a rig brought in with Import
Rig File, the custom properties of the same names that drive its keys. The take is read and matched to those
names by springblend.performance (the CLI's rules: names, symmetric shapes, a map, lost rows) on a worker thread;
the keys are written on the main thread, one F-curve per slider, one key per frame from the chosen start frame,
linear between frames. The scene's frame rate and range become the take's. Keyframes hold float32 values: the
file's weights rounded to float32. A shape key's slider range is widened to the take's weights (Blender clamps a
key's value to it).
"""

import numpy as np

from . import connection, jobs, scene_data
from .scene_data import UserError

# The group of the F-curves an import writes (an earlier import's curves of the same sliders are replaced).
ACTION_GROUP = "springblend take"
# Blender's range for a shape key's slider.
_SLIDER_LIMIT = 10.0


def sliders(obj):
    """[(name, kind)] of the object's sliders, kind "property" (an imported rig's custom property) or "key" (a
    target shape key), in shape-key order."""
    keys = scene_data.shape_keys(obj)
    found = []
    for kb in scene_data.target_blocks(keys):
        if scene_data.key_role(kb.name)[0] != "target":
            continue
        found.append((kb.name, "property" if kb.name in obj.keys() else "key"))
    return found


def prepare(obj, filepath, map_path, lost):
    """The Job that reads and matches the take on a worker thread: it delivers one (name, kind, values) per slider
    and returns the Performance."""
    springblend = connection.client_module()
    names = sliders(obj)
    if not names:
        raise UserError(f"'{obj.name}' has no target shape keys to key")
    target_names = [n for n, _ in names]
    kinds = dict(names)

    def work(job):
        job.progress(0.0, f"reading the take {filepath}")
        try:
            take = springblend.performance.read_take(filepath)
            job.progress(0.3, f"matching {len(take.shapes)} shapes to {len(target_names)} sliders")
            performance = springblend.performance.match(take, target_names, map=map_path or None, lost=lost.lower(),
                                                        warn=False)
        except springblend.SpringblendError as error:  # the file's fault, not a server's
            raise UserError(error.message) from None
        for i, name in enumerate(target_names):
            job.deliver((name, kinds[name], performance.weights[:, i]))
            job.progress(0.3 + 0.7 * (i + 1) / len(target_names),
                         f"keying {name} ({i + 1} of {len(target_names)} sliders, {len(performance.weights)} frames)")
        return performance

    return jobs.Job(work, "take")


def write_keys(obj, name, kind, values, start_frame):
    """One F-curve of keys start_frame, start_frame + 1, ... on a slider, replacing the curve an earlier import
    wrote; linear between frames."""
    if kind == "property":
        owner, data_path = obj, f'["{name}"]'
    else:
        owner, data_path = obj.data.shape_keys, f'key_blocks["{name}"].value'
        kb = owner.key_blocks[name]
        low, high = float(np.min(values)), float(np.max(values))
        if low < -_SLIDER_LIMIT or high > _SLIDER_LIMIT:
            raise UserError(f"shape key '{name}': the take's weights reach {low:g} to {high:g}, beyond Blender's "
                            f"slider range of +-{_SLIDER_LIMIT:g}")
        kb.slider_min, kb.slider_max = min(kb.slider_min, low), max(kb.slider_max, high)
    if owner.animation_data is None:
        owner.animation_data_create()
    if owner.animation_data.action is None:
        owner.animation_data.action = _new_action(owner)
    curves = owner.animation_data.action.fcurves
    old = curves.find(data_path)
    if old is not None:
        curves.remove(old)
    curve = curves.new(data_path, action_group=ACTION_GROUP)
    count = len(values)
    curve.keyframe_points.add(count)
    co = np.empty(2 * count, dtype=np.float32)
    co[0::2] = start_frame + np.arange(count, dtype=np.float64)
    co[1::2] = values
    curve.keyframe_points.foreach_set("co", co)
    curve.keyframe_points.foreach_set("interpolation", np.full(count, _LINEAR, dtype=np.int32))
    curve.update()


def _new_action(owner):
    import bpy
    return bpy.data.actions.new(f"{owner.name} take")


# The index of 'LINEAR' in Blender's keyframe interpolation enum (CONSTANT, LINEAR, BEZIER, ...).
_LINEAR = 1


def set_timing(scene, performance, start_frame):
    """The scene's frame range over the take, and its frame rate the take's when the timecode gives one."""
    scene.frame_start = start_frame
    scene.frame_end = start_frame + len(performance.weights) - 1
    rate = performance.frame_rate
    if rate:
        fps = max(1, int(round(rate)))
        scene.render.fps, scene.render.fps_base = fps, fps / rate
