"""Imports a rig file (a baked one from `springblend bake-rig`, or any rig file) as a mesh with shape keys that play
without the server: one slider per target (a custom property on the object, named after the target), and every
shape key driven by the sliders with the rig-file semantics, so Blender shows what
springblend.rigfile.linear_blend computes: a target's in-betweens (keys TARGET@W) blend piecewise linearly, a
combination (key A*B) is on by the product of its drivers' sliders and taken off its drivers' full keys, a mask is
the key's vertex group. The keys follow the add-on's conventions, so the imported rig exports and uploads again.

Drivers are Blender's simple expressions (min, max, arithmetic): they run without trusting the file's scripts."""

import bpy
import numpy as np

from . import connection
from .scene_data import UserError

# Blender clamps a key's value to its slider range; blended weights leave [0, 1] (extrapolated sliders, a
# combination taken off its drivers).
_KEY_RANGE = 10.0


def _hat(var, knots, i):
    """A simple driver expression of knot i's weight (1 <= i < len(knots)) on the piecewise-linear path through
    knots (ascending, knots[0] == 0 is the rest shape, knots[-1] == 1 the full shape), extrapolated linearly with
    the first and last segment's slope."""
    b = knots[i]
    a = knots[i - 1]
    rise = f"({var} - {a!r}) / {b - a!r}"
    last = i == len(knots) - 1
    if last:
        return var if len(knots) == 2 else f"max({rise}, 0.0)"
    c = knots[i + 1]
    fall = f"({c!r} - {var}) / {c - b!r}"
    lower = rise if i == 1 else f"max({rise}, 0.0)"
    upper = fall if i + 1 == len(knots) - 1 else f"max({fall}, 0.0)"
    return f"min({lower}, {upper})"


def _driver(obj, key_block, expression, variables):
    """Drives key_block.value by expression over the object's custom properties {variable: property name}."""
    fcurve = key_block.driver_add("value")
    driver = fcurve.driver
    driver.type = "SCRIPTED"
    for name, prop in variables.items():
        var = driver.variables.new()
        var.name = name
        var.type = "SINGLE_PROP"
        var.targets[0].id_type = "OBJECT"
        var.targets[0].id = obj
        var.targets[0].data_path = f'["{prop}"]'
    driver.expression = expression
    if not driver.is_simple_expression:
        raise UserError(f"internal: the driver of '{key_block.name}' is not a simple expression: {expression}")


def import_rig(context, path):
    """A new mesh object of the rig file at path, with its keys, sliders and drivers; returns it."""
    springblend = connection.client_module()
    try:
        rig = springblend.rigfile.load_rig(path)
    except springblend.SpringblendError as error:  # the file's fault, not a server's
        raise UserError(error.message) from None
    names = rig.weight_names
    for name in names:
        if '"' in name or "\\" in name:
            raise UserError(f"{path}: target '{name}': a slider's name cannot hold quotes or backslashes")
    mesh = bpy.data.meshes.new(bpy.path.display_name_from_filepath(path))
    mesh.from_pydata(rig.rest.tolist(), [], rig.faces.tolist())
    mesh.update()
    obj = bpy.data.objects.new(mesh.name, mesh)
    context.collection.objects.link(obj)
    obj.shape_key_add(name="Basis", from_mix=False)
    variables = {name: f"w{i}" for i, name in enumerate(names)}
    for name in names:
        obj[name] = 0.0
        ui = obj.id_properties_ui(name)
        ui.update(min=-_KEY_RANGE, max=_KEY_RANGE, soft_min=0.0, soft_max=1.0,
                  description=f"springblend target '{name}' (drives its shape keys)")

    def key(name, positions):
        kb = obj.shape_key_add(name=name, from_mix=False)
        kb.data.foreach_set("co", np.asarray(positions, dtype=np.float32).ravel())
        kb.slider_min, kb.slider_max = -_KEY_RANGE, _KEY_RANGE
        return kb

    ordinary = [t for t in rig.targets if not t.combination]
    combinations = [t for t in rig.targets if t.combination]
    for target in ordinary:
        var = variables[target.name]
        inbetweens = sorted(target.inbetweens, key=lambda k: k[0])
        knots = [0.0] + [float(w) for w, _ in inbetweens] + [1.0]
        group = None
        if target.mask is not None:
            group = obj.vertex_groups.new(name=f"{target.name}_mask")
            for vertex, weight in enumerate(np.asarray(target.mask, dtype=np.float64)):
                if weight != 0.0:
                    group.add([vertex], float(weight), "REPLACE")
        shapes = [(f"{target.name}@{w:g}", p) for w, p in inbetweens] + [(target.name, target.positions)]
        for i, (key_name, positions) in enumerate(shapes, 1):
            kb = key(key_name, positions)
            if group is not None:
                kb.vertex_group = group.name
            expression = _hat(var, knots, i)
            used = {var: target.name}
            if i == len(shapes):
                # The combinations this target drives are taken off its full shape.
                for c in combinations:
                    if target.name in c.combination:
                        expression += " - " + " * ".join(variables[d] for d in c.combination)
                        used.update({variables[d]: d for d in c.combination})
            _driver(obj, kb, expression, used)
    for c in combinations:
        kb = key("*".join(c.combination), c.positions)
        _driver(obj, kb, " * ".join(variables[d] for d in c.combination),
                {variables[d]: d for d in c.combination})
    return obj
