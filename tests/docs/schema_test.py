"""The JSON Schemas of rig and scene files (docs/schemas/) agree with the readers: every document the CLI reads
validates, and every document the CLI refuses for a fault a schema can express (an unknown key, a missing or
mistyped field, an in-between weight out of range, a combination with a mask) fails validation. So an editor
that checks a file against the schema tells the truth about it.

Run by CTest (schema_test) with /usr/bin/python3 and Debian's python3-jsonschema; needs $SPRINGBLEND_CLI and
$SPRINGBLEND_TEST_DATA.
"""

import copy
import json
import os
import pathlib
import subprocess
import sys
import tempfile

import jsonschema

ROOT = pathlib.Path(__file__).resolve().parents[2]
DATA = pathlib.Path(os.environ["SPRINGBLEND_TEST_DATA"])
CLI = os.environ["SPRINGBLEND_CLI"]
CYLINDER = DATA / "cylinder"


def schema(name):
    document = json.loads((ROOT / "docs" / "schemas" / f"{name}.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(document)
    return jsonschema.Draft202012Validator(document)


def valid(validator, document):
    return not list(validator.iter_errors(document))


def cli_accepts(arguments):
    result = subprocess.run([CLI, *arguments], capture_output=True, text=True, timeout=120)
    if result.returncode not in (0, 2):
        raise SystemExit(f"schema_test: springblend {' '.join(arguments)} exited {result.returncode}:\n{result.stderr}")
    return result.returncode == 0


def main():
    failures = []
    rig_schema, scene_schema = schema("rig"), schema("scene")
    bundled = json.loads((CYLINDER / "rig.json").read_text())
    # Absolute paths, so the documents can live in a temporary directory.
    good = copy.deepcopy(bundled)
    good["rest"] = str(CYLINDER / good["rest"])
    for target in good["targets"]:
        target["mesh"] = str(CYLINDER / target["mesh"])
        for inbetween in target.get("inbetweens", []):
            inbetween["mesh"] = str(CYLINDER / inbetween["mesh"])
        if isinstance(target.get("mask"), str):
            target["mask"] = str(CYLINDER / target["mask"])

    def changed(edit):
        document = copy.deepcopy(good)
        edit(document)
        return document

    rigs = {
        "the bundled rig": (good, True),
        "with $schema": (changed(lambda d: d.update({"$schema": "../docs/schemas/rig.schema.json"})), True),
        "fixed vertices": (changed(lambda d: d.update({"fixed_vertices": [0, 5]})), True),
        "an unknown key": (changed(lambda d: d["targets"][1].update({"maks": "x.txt"})), False),
        "no rest": (changed(lambda d: d.pop("rest")), False),
        "a target without a mesh": (changed(lambda d: d["targets"][0].pop("mesh")), False),
        "an in-between at 1.5": (changed(lambda d: d["targets"][0]["inbetweens"][0].update({"weight": 1.5})), False),
        "a weight as a string": (changed(lambda d: d["targets"][0]["inbetweens"][0].update({"weight": "0.5"})), False),
        "a combination with a mask": (changed(lambda d: d["targets"][2].update({"mask": [1.0] * 420})), False),
        "targets as an object": (changed(lambda d: d.update({"targets": {"bend": "x.obj"}})), False),
    }
    scenes = {
        "weights in order": ({"frames": [{"weights": [0.5]}]}, True),
        "weights by name, collider motions and pins": ({
            "colliders": ["sphere:-1.7,0.75,0.75,0.35"],
            "frames": [{"weights": {"poses-2_cylinder-1": 0.8}, "colliders": [{"translation": [0, 0, 0.1]}],
                        "pins": [{"vertex": 5, "position": [2, 0, 0]}]}]}, True),
        "no frames": ({"frames": []}, False),
        "a weight as a string": ({"frames": [{"weights": {"poses-2_cylinder-1": "0.5"}}]}, False),
        "a pin without a position": ({"frames": [{"weights": [0.5], "pins": [{"vertex": 5}]}]}, False),
        "a rotation of three numbers": ({"frames": [{"weights": [0.5], "colliders": [{"rotation": [1, 0, 0]}]}],
                                         "colliders": ["sphere:-1.7,0.75,0.75,0.35"]}, False),
    }
    with tempfile.TemporaryDirectory(prefix="springblend-schema-") as directory:
        for what, (document, expected) in rigs.items():
            path = os.path.join(directory, "rig.json")
            pathlib.Path(path).write_text(json.dumps(document))
            by_schema = valid(rig_schema, document)
            by_cli = cli_accepts(["blend", "--rig", path, "--no-target-paths", "--linear", "--weights", "0.5,0.5",
                                  "--out", os.path.join(directory, "rig.obj")])
            if by_schema != expected or by_cli != expected:
                failures.append(f"rig, {what}: schema {'accepts' if by_schema else 'refuses'}, CLI "
                                f"{'accepts' if by_cli else 'refuses'}, expected both to "
                                f"{'accept' if expected else 'refuse'}")
        for what, (document, expected) in scenes.items():
            path = os.path.join(directory, "scene.json")
            pathlib.Path(path).write_text(json.dumps(document))
            by_schema = valid(scene_schema, document)
            by_cli = cli_accepts(["blend", "--rest", str(CYLINDER / "cylinder.obj"), "--target",
                                  str(CYLINDER / "poses-2_cylinder-1.obj"), "--no-target-paths", "--linear",
                                  "--frames", path, "--out", os.path.join(directory, "scene")])
            if by_schema != expected or by_cli != expected:
                failures.append(f"scene, {what}: schema {'accepts' if by_schema else 'refuses'}, CLI "
                                f"{'accepts' if by_cli else 'refuses'}, expected both to "
                                f"{'accept' if expected else 'refuse'}")
    for failure in failures:
        print("schema_test: FAILED:", failure, file=sys.stderr)
    if failures:
        raise SystemExit(1)
    print(f"schema_test: OK ({len(rigs)} rig files, {len(scenes)} scene files)")


if __name__ == "__main__":
    main()
