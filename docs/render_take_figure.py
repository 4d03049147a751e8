"""Renders docs/take.png from springblend-take-bench's output: one frame of the shared take on the shared face (the
frame where the first model measured lands farthest from the linear blend), side by side as the linear blend and
each mix model's answer, each answer coloured by its distance from the linear blend (white 0, red at --scale
percent of the face's bounding-box diagonal or more).

  build/release/bench/springblend-take-bench --hold-outer-rim --out bench-results/take ... \\
      --models superposed,rest-lengths
  blender --background --factory-startup --python docs/render_take_figure.py -- \\
      --dir bench-results/take --frame 1530 [--out docs/take.png] [--scale 3]

Workbench renders in seconds on the CPU. Not part of CI: the PNG is committed.
"""

import argparse
import math
import pathlib
import sys

import bpy
import numpy as np


def read_obj(path):
    vertices, faces = [], []
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                faces.append([int(x.split("/")[0]) - 1 for x in line.split()[1:4]])
    return np.array(vertices), faces


def add_mesh(name, vertices, faces, offset, colours):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v + offset) for v in vertices], [], faces)
    attribute = mesh.color_attributes.new(name="distance", type="FLOAT_COLOR", domain="POINT")
    for i, c in enumerate(colours):
        attribute.data[i].color = (c[0], c[1], c[2], 1.0)
    for polygon in mesh.polygons:
        polygon.use_smooth = True
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def main():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    parser = argparse.ArgumentParser()
    parser.add_argument("--dir", required=True)
    parser.add_argument("--frame", required=True)
    parser.add_argument("--models", default="superposed,rest-lengths")
    parser.add_argument("--out", default=str(pathlib.Path(__file__).resolve().parent / "take.png"))
    parser.add_argument("--scale", type=float, default=3.0, help="percent of the diagonal shown fully red")
    args = parser.parse_args(argv)
    folder = pathlib.Path(args.dir)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    linear, faces = read_obj(folder / f"take-linear-at-{args.frame}.obj")
    diagonal = float(np.linalg.norm(linear.max(0) - linear.min(0)))
    width = float(linear[:, 0].max() - linear[:, 0].min()) * 1.15
    panels = [("linear blend", linear)]
    for model in args.models.split(","):
        vertices, _ = read_obj(folder / f"take-{model}-at-{args.frame}.obj")
        panels.append((model, vertices))
    for k, (name, vertices) in enumerate(panels):
        d = np.linalg.norm(vertices - linear, axis=1) / diagonal * 100.0 / args.scale
        d = np.clip(d, 0.0, 1.0)
        colours = np.stack([np.ones_like(d), 1.0 - d, 1.0 - d], axis=1)
        add_mesh(name, vertices, faces, np.array([k * width, 0.0, 0.0]), colours)
    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "VERTEX"
    scene.render.resolution_x = 360 * len(panels)
    scene.render.resolution_y = 480
    scene.render.film_transparent = False
    scene.world = bpy.data.worlds.new("world")
    centre = linear.mean(0)
    camera_data = bpy.data.cameras.new("camera")
    camera_data.type = "ORTHO"
    camera_data.ortho_scale = width * len(panels)
    camera = bpy.data.objects.new("camera", camera_data)
    scene.collection.objects.link(camera)
    # The face looks along +z (the ICT face's front); the camera in front of it, looking back along -z.
    camera.location = (centre[0] + width * (len(panels) - 1) / 2.0, centre[1], centre[2] + 3.0 * diagonal)
    camera.rotation_euler = (0.0, 0.0, 0.0)
    scene.camera = camera
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.compression = 100
    scene.render.filepath = args.out
    bpy.ops.render.render(write_still=True)
    print(f"wrote {args.out}: {', '.join(name for name, _ in panels)}")


main()
