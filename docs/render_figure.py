"""Renders the README's picture, docs/springblend.png, from the real solver's output:

  1. the cylinder half way to a 180-degree twist (tests/data/cylinder/poses-1_cylinder-4 at weight 0.5) as a
     linear blendshape, which shrinks to a candy wrapper, beside
  2. springblend's solve of the same weight, which keeps its volume;
  3. the ICT face opening its jaw (jawOpen 0.7), solved;
  4. a ball pushing into the cylinder as it bends (poses-2_cylinder-1 at 0.6), solved with the ball a collider.

One command, from the repository root after a build (the springblend CLI solves locally, no server needed;
the face's rig build takes about a minute on 2 cores):

  blender --background --factory-startup --python docs/render_figure.py -- \
      [--cli build/release/client/springblend] [--out docs/springblend.png] [--samples 32]

Cycles renders on the CPU; a few minutes on 2 cores. Not part of CI: the PNG is committed.
"""

import argparse
import math
import os
import pathlib
import subprocess
import sys
import tempfile

import bpy
import mathutils
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
sys.path.insert(0, str(ROOT / "tests" / "python"))
from springblend_testing import load_obj  # noqa: E402

BALL = ((-1.5, 1.0, 0.3), 0.55)  # centre and radius of the collider, in the cylinder's space


def arguments():
    parser = argparse.ArgumentParser(prog="render_figure.py")
    parser.add_argument("--cli", default=str(ROOT / "build" / "release" / "client" / "springblend"))
    parser.add_argument("--out", default=str(ROOT / "docs" / "springblend.png"))
    parser.add_argument("--samples", type=int, default=32)
    return parser.parse_args(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else [])


def solve(cli, directory, name, rest, target, weight, *extra):
    """Runs `springblend blend` and returns the solved vertices and the rest faces."""
    out = os.path.join(directory, f"{name}.obj")
    command = [cli, "blend", "--rest", str(rest), "--target", str(target), "--weights", str(weight),
               "--out", out, *extra]
    print("render_figure:", " ".join(command), flush=True)
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return load_obj(out)


def material(name, color, roughness=0.45, alpha=1.0):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    shader = mat.node_tree.nodes["Principled BSDF"]
    shader.inputs["Base Color"].default_value = (*color, 1.0)
    shader.inputs["Roughness"].default_value = roughness
    shader.inputs["Alpha"].default_value = alpha
    return mat


def add_mesh(name, vertices, faces, mat, rotation, slot, height):
    """A smooth-shaded object, rotated, scaled to `height` and centred on x = slot (z from 0)."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices.tolist(), [], faces.tolist())
    mesh.update()
    for polygon in mesh.polygons:
        polygon.use_smooth = True
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.data.materials.append(mat)
    obj.rotation_euler = rotation
    bpy.context.view_layer.update()
    corners = np.array([obj.matrix_world @ v.co for v in mesh.vertices])
    low, high = corners.min(axis=0), corners.max(axis=0)
    scale = height / (high[2] - low[2])
    obj.scale = (scale,) * 3
    centre = (low + high) / 2
    obj.location = (slot - centre[0] * scale, -centre[1] * scale, -low[2] * scale)
    return obj, scale, centre, low


def add_label(text, slot):
    curve = bpy.data.curves.new(f"label {text}", "FONT")
    curve.body = text
    curve.align_x = "CENTER"
    curve.size = 0.32
    label = bpy.data.objects.new(f"label {text}", curve)
    bpy.context.scene.collection.objects.link(label)
    label.location = (slot, 0, 4.3)
    label.rotation_euler = (math.radians(90), 0, 0)
    label.data.materials.append(material(f"ink {text}", (0.02, 0.02, 0.02), roughness=1.0))


def stage(samples):
    scene = bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.render.resolution_x, scene.render.resolution_y = 1000, 400
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.compression = 100
    scene.view_settings.view_transform = "Standard"
    world = bpy.data.worlds.new("white")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (1, 1, 1, 1)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.55
    scene.world = world
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 2.2
    sun.rotation_euler = (math.radians(50), math.radians(10), math.radians(-35))
    scene.collection.objects.link(sun)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.data.type = "ORTHO"
    camera.data.ortho_scale = 15.0
    camera.location = (6.6, -30, 2.45 + 30 * math.tan(math.radians(8)))
    camera.rotation_euler = (math.radians(82), 0, 0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    floor = bpy.data.meshes.new("floor")
    floor.from_pydata([(-20, -20, 0), (40, -20, 0), (40, 40, 0), (-20, 40, 0)], [], [(0, 1, 2, 3)])
    floor_obj = bpy.data.objects.new("floor", floor)
    floor_obj.is_shadow_catcher = True
    scene.collection.objects.link(floor_obj)
    scene.render.film_transparent = False


def main():
    args = arguments()
    cylinder = DATA / "cylinder"
    with tempfile.TemporaryDirectory(prefix="springblend-figure-") as directory:
        twist = cylinder / "poses-1_cylinder-4.obj"
        linear = solve(args.cli, directory, "linear", cylinder / "cylinder.obj", twist, 0.5, "--linear")
        physical = solve(args.cli, directory, "physical", cylinder / "cylinder.obj", twist, 0.5)
        face = solve(args.cli, directory, "face", DATA / "face" / "generic_neutral_mesh.obj",
                     DATA / "face" / "jawOpen.obj", 0.7)
        (cx, cy, cz), radius = BALL
        pushed = solve(args.cli, directory, "pushed", cylinder / "cylinder.obj", cylinder / "poses-2_cylinder-1.obj",
                       0.6, "--collider", f"sphere:{cx},{cy},{cz},{radius}")

    stage(args.samples)
    upright = (0, math.radians(-90), 0)  # the cylinder's axis (x) up
    blue, orange = material("linear", (0.55, 0.62, 0.72)), material("springblend", (0.85, 0.45, 0.18))
    add_mesh("linear", *linear, blue, upright, 0.0, 4.0)
    add_mesh("springblend", *physical, orange, upright, 3.2, 4.0)
    add_mesh("face", *face, material("skin", (0.8, 0.6, 0.5)), (math.radians(90), 0, 0), 7.6, 4.0)
    # Upright and turned a quarter about the vertical, so the ball sits beside the cylinder, not behind it.
    pushed_obj, scale, _, _ = add_mesh("pushed", *pushed, orange, (0, math.radians(-90), math.radians(90)),
                                       12.4, 4.0)
    # The ball in the same space as the cylinder it pushes: through the cylinder object's transform.
    bpy.ops.mesh.primitive_uv_sphere_add(segments=48, ring_count=24, radius=radius)
    ball = bpy.context.active_object
    ball.location = pushed_obj.matrix_world @ mathutils.Vector(BALL[0])
    ball.scale = (scale,) * 3
    bpy.ops.object.shade_smooth()
    ball.data.materials.append(material("ball", (0.35, 0.7, 0.45), roughness=0.3))
    for text, slot in (("linear blend", 0.0), ("springblend", 3.2), ("face: jawOpen 0.7", 7.6),
                       ("a ball collider", 12.4)):
        add_label(text, slot)

    bpy.context.scene.render.filepath = args.out
    bpy.ops.render.render(write_still=True)
    print(f"render_figure: wrote {args.out} ({os.path.getsize(args.out) // 1024} KB)")


if __name__ == "__main__":  # docs/render_bake_figure.py imports the staging helpers
    main()
