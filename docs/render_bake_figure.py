"""Renders docs/bake.png, a baked plain rig beside the linear blendshape and the solve, from the real tools:

  the bundled cylinder rig's bend at weight 0.4 and the bundled face's jawOpen at 0.6, each as
  1. the plain linear blendshape of the rig's sculpts,
  2. the rig baked by `springblend bake-rig` (3 in-betweens per target) played as a linear blendshape
     (`springblend blend --linear` of the baked rig file: what any blendshape evaluator shows), and
  3. springblend's solve of the same weight.

One command, from the repository root after a build (the CLI bakes and solves locally; the face's rig takes
about a minute on 2 cores):

  blender --background --factory-startup --python docs/render_bake_figure.py -- \
      [--cli build/release/client/springblend] [--out docs/bake.png] [--samples 32]

Not part of CI: the PNG is committed.
"""

import argparse
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile

import bpy

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import render_figure as figure  # noqa: E402  (its staging helpers; its main() does not run on import)

ROOT = figure.ROOT
DATA = figure.DATA


def arguments():
    parser = argparse.ArgumentParser(prog="render_bake_figure.py")
    parser.add_argument("--cli", default=str(ROOT / "build" / "release" / "client" / "springblend"))
    parser.add_argument("--out", default=str(ROOT / "docs" / "bake.png"))
    parser.add_argument("--samples", type=int, default=32)
    return parser.parse_args(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else [])


def run(cli, *arguments):
    command = [cli, *map(str, arguments)]
    print("render_bake_figure:", " ".join(command), flush=True)
    return subprocess.run(command, check=True, stdout=subprocess.PIPE, text=True).stdout


def three(cli, directory, name, rig, weights):
    """(linear, baked, solved) surfaces and the faces of a rig file at these weights."""
    baked = os.path.join(directory, f"{name}-baked")
    summary = json.loads(run(cli, "bake-rig", "--rig", rig, "--inbetweens", 3, "--pairs", "none", "--out", baked))
    out = []
    for kind, extra in (("linear", ["--rig", rig, "--linear"]), ("baked", ["--rig", summary["rig"], "--linear"]),
                        ("solved", ["--rig", rig])):
        path = os.path.join(directory, f"{name}-{kind}.obj")
        run(cli, "blend", *extra, "--weights", weights, "--out", path)
        out.append(figure.load_obj(path))
    return out


def main():
    args = arguments()
    with tempfile.TemporaryDirectory(prefix="springblend-bake-figure-") as directory:
        face_rig = os.path.join(directory, "face.json")
        with open(face_rig, "w") as text:
            json.dump({"rest": str(DATA / "face" / "generic_neutral_mesh.obj"),
                       "targets": [{"name": "jawOpen", "mesh": str(DATA / "face" / "jawOpen.obj")}]}, text)
        cylinder = three(args.cli, directory, "cylinder", DATA / "cylinder" / "rig.json", "bend=0.4")
        face = three(args.cli, directory, "face", face_rig, "jawOpen=0.6")

    figure.stage(args.samples)
    camera = bpy.context.scene.camera
    camera.data.ortho_scale = 17.5
    camera.location.x = 7.0
    upright = (0, math.radians(-90), 0)
    colours = [figure.material("linear", (0.55, 0.62, 0.72)), figure.material("baked", (0.45, 0.65, 0.45)),
               figure.material("springblend", (0.85, 0.45, 0.18))]
    names = ["linear blend", "baked rig", "springblend"]
    for i, (mesh, colour, name) in enumerate(zip(cylinder, colours, names)):
        figure.add_mesh(f"cylinder {name}", *mesh, colour, upright, 2.4 * i, 4.0)
        figure.add_label(name, 2.4 * i)
    for i, (mesh, colour, name) in enumerate(zip(face, colours, names)):
        slot = 7.6 + 2.9 * i
        figure.add_mesh(f"face {name}", *mesh, colour, (math.radians(90), 0, 0), slot, 3.6)
        figure.add_label(name, slot)
    bpy.context.scene.render.resolution_x = 1200
    bpy.context.scene.render.filepath = args.out
    bpy.ops.render.render(write_still=True)
    print(f"render_bake_figure: wrote {args.out} ({os.path.getsize(args.out) // 1024} KB)")


if __name__ == "__main__":
    main()
