"""Rig files (README: rig files): a production rig in JSON with its meshes beside it, read and written the way
the C++ command line reads them, so `springblend upload --rig`, Client.upload_rig and the Blender add-on
upload the very same character (the same content id).

    {"rest": "neutral.obj", "fixed_vertices": [12, 13],
     "targets": [
       {"name": "jawOpen", "mesh": "jawOpen.obj", "inbetweens": [{"weight": 0.5, "mesh": "jawOpen_half.obj"}]},
       {"name": "mouthSmile_L", "mesh": "smile_L.obj", "mask": "smile_L_mask.txt"},
       {"name": "jawOpen_mouthSmile_L", "mesh": "jaw_smile.obj", "combination": ["jawOpen", "mouthSmile_L"]}]}

Paths are relative to the rig file. Meshes are OBJ here (the C++ command line also reads PLY, OFF and STL);
coordinates are rounded to float32 as the C++ loader rounds them. A mask is a list of one weight per vertex or
a text file with one number per line. Every error names the file, the target and the field.
"""

import dataclasses
import json
import math
import os
import typing

import numpy as np

from springblend.errors import invalid_argument


@dataclasses.dataclass
class Target:
    """One target: its shape at weight 1 (a combination's: with every driver at 1), in-betweens as
    (weight, #V by 3) pairs, an optional mask (one weight per vertex) and, for a combination, its drivers."""
    name: str
    positions: np.ndarray
    inbetweens: list = dataclasses.field(default_factory=list)
    mask: typing.Optional[np.ndarray] = None
    combination: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Rig:
    """A production rig: rest #V by 3, faces #F by 3 int32, targets in file order, fixed vertices."""
    rest: np.ndarray
    faces: np.ndarray
    targets: list
    fixed_vertices: list = dataclasses.field(default_factory=list)
    path: str = "rig"

    @property
    def weight_names(self):
        """The weight order of frames: the targets that are not combinations, in file order."""
        return [t.name for t in self.targets if not t.combination]


def _fail(where, what):
    raise invalid_argument(f"{where}: {what}")


def read_obj(path, where):
    """(#V by 3 float64 rounded to float32, #F by 3 int32) of an OBJ file; polygons split into fans, vertex
    order kept (as the C++ loader does)."""
    if not os.path.isfile(path):
        _fail(where, f"file not found: {path}")
    if not path.lower().endswith(".obj"):
        _fail(where, f"{path}: the Python client reads OBJ meshes only (the springblend CLI reads PLY, OFF, STL)")
    vertices, faces = [], []
    with open(path) as obj:
        for number, line in enumerate(obj, 1):
            fields = line.split()
            if not fields:
                continue
            try:
                if fields[0] == "v":
                    vertices.append([float(v) for v in fields[1:4]])
                elif fields[0] == "f":
                    corners = [int(f.split("/")[0]) for f in fields[1:]]
                    corners = [c - 1 if c > 0 else len(vertices) + c for c in corners]
                    faces += [[corners[0], corners[k], corners[k + 1]] for k in range(1, len(corners) - 1)]
            except ValueError:
                _fail(where, f"{path}: line {number}: cannot read '{line.strip()[:40]}'")
    positions = np.array(vertices, dtype=np.float64).reshape(-1, 3).astype(np.float32).astype(np.float64)
    triangles = np.array(faces, dtype=np.int32).reshape(-1, 3)
    if len(positions) == 0 or len(triangles) == 0:
        _fail(where, f"{path}: no vertices or no faces")
    if triangles.min() < 0 or triangles.max() >= len(positions):
        _fail(where, f"{path}: a face refers to a vertex the file does not have")
    return positions, triangles


def write_obj(path, positions, faces):
    """v and f lines; 9 significant digits, so float32 coordinates read back exactly."""
    with open(path, "w") as obj:
        obj.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in np.asarray(positions, dtype=np.float64))
        obj.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in np.asarray(faces))


def parse_mask_text(text, source):
    """One number per line (blank lines and lines starting with # are skipped)."""
    values = []
    for number, line in enumerate(text.splitlines(), 1):
        item = line.strip()
        if not item or item.startswith("#"):
            continue
        try:
            value = float(item)
        except ValueError:
            _fail(source, f"line {number}: '{item[:40]}' is not a number (one weight per line)")
        if not math.isfinite(value):
            _fail(source, f"line {number}: {item} is not finite")
        values.append(value)
    return values


def _check_keys(value, where, allowed, required):
    if not isinstance(value, dict):
        _fail(where, f"expected an object, got {_type(value)}")
    for key in value:
        if key not in allowed:
            _fail(where, f"unknown key '{key}' (expected {', '.join(sorted(allowed))})")
    for key in required:
        if key not in value:
            _fail(where, f"'{key}' is missing")


def _type(value):
    return {dict: "object", list: "array", str: "string", bool: "boolean", type(None): "null"}.get(
        type(value), "number")


def _string(value, where):
    if not isinstance(value, str):
        _fail(where, f"expected a string, got {_type(value)}")
    return value


def _number(value, where):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _fail(where, f"expected a number, got {_type(value)}")
    if not math.isfinite(value):
        _fail(where, f"{value} is not finite")
    return float(value)


def _list(value, where):
    if not isinstance(value, list):
        _fail(where, f"expected a list, got {_type(value)}")
    return value


def load_rig(path):
    """Reads a rig file and its meshes and masks; raises SpringblendError(INVALID_ARGUMENT) naming the file, the
    target and the field. The rig's own rules (in-between weights, combination drivers) are the server's to
    check; Client.upload_rig puts the rig file's path in front of its refusals."""
    base = os.path.dirname(path)
    try:
        with open(path) as text:
            doc = json.load(text)
    except OSError as error:
        _fail(path, f"cannot open: {error.strerror}")
    except ValueError as error:
        _fail(path, f"not valid JSON: {error}")
    _check_keys(doc, path, {"$schema", "rest", "fixed_vertices", "targets"}, ("rest", "targets"))  # $schema: editors
    rest, faces = read_obj(os.path.join(base, _string(doc["rest"], f"{path}: rest")), f"{path}: rest")

    def mesh(value, where):
        positions, triangles = read_obj(os.path.join(base, _string(value, where)), where)
        if positions.shape != rest.shape:
            _fail(where, f"{len(positions)} vertices, but the rest mesh has {len(rest)}")
        if triangles.shape != faces.shape or not np.array_equal(triangles, faces):
            _fail(where, "its faces differ from the rest mesh's; every shape must have the rest mesh's faces")
        return positions

    fixed = []
    for i, v in enumerate(_list(doc.get("fixed_vertices", []), f"{path}: fixed_vertices")):
        if isinstance(v, bool) or not isinstance(v, int):
            _fail(f"{path}: fixed_vertices[{i}]", f"expected a vertex index, got {json.dumps(v)}")
        if not 0 <= v < len(rest):
            _fail(f"{path}: fixed_vertices[{i}]", f"{v} is not a vertex of the rest mesh (it has {len(rest)})")
        fixed.append(v)
    entries = _list(doc["targets"], f"{path}: targets")
    if not entries:
        _fail(path, "targets is empty: a rig needs at least one target")
    targets = []
    combinations = {}  # sorted drivers -> the first target with them
    for t, entry in enumerate(entries):
        where = f"{path}: targets[{t}]"
        _check_keys(entry, where, {"name", "mesh", "inbetweens", "mask", "combination"}, ("name", "mesh"))
        name = _string(entry["name"], f"{where}.name")
        if not name:
            _fail(f"{where}.name", "is empty")
        for character in "=,":
            # Weights are given by name as NAME=WEIGHT,NAME=WEIGHT: such a name could not be addressed.
            if character in name:
                _fail(f"{where}.name '{name}'",
                      f"contains '{character}': weights given by name (NAME=WEIGHT,...) could not address it")
        where = f"{path}: target '{name}'"
        target = Target(name, mesh(entry["mesh"], f"{where}: mesh"))
        for i, inbetween in enumerate(_list(entry.get("inbetweens", []), f"{where}: inbetweens")):
            at = f"{where}: inbetweens[{i}]"
            _check_keys(inbetween, at, {"weight", "mesh"}, ("weight", "mesh"))
            target.inbetweens.append((_number(inbetween["weight"], f"{at}.weight"), mesh(inbetween["mesh"], f"{at}.mesh")))
        if "mask" in entry:
            target.mask = _mask(entry["mask"], base, f"{where}: mask", len(rest))
        if "combination" in entry:
            drivers = _list(entry["combination"], f"{where}: combination")
            target.combination = [_string(d, f"{where}: combination[{i}]") for i, d in enumerate(drivers)]
            if not target.combination:
                _fail(f"{where}: combination", "is empty (name at least two targets)")
            # a*b and b*a are one product of weights: two correctives on it would both switch on together.
            first = combinations.setdefault(tuple(sorted(target.combination)), name)
            if first != name:
                _fail(f"{where}: combination", f"has the drivers of target '{first}' (in any order, the same product "
                      "of weights): one combination per set of drivers")
        targets.append(target)
    return Rig(rest, faces, targets, fixed, path)


def _mask(value, base, where, vertices):
    source = ""
    if isinstance(value, str):
        mask_path = os.path.join(base, value)
        if not os.path.isfile(mask_path):
            _fail(where, f"file not found: {mask_path}")
        with open(mask_path) as text:
            values = parse_mask_text(text.read(), f"{where}: {mask_path}")
        source = f" in {mask_path}"
    elif isinstance(value, list):
        values = [_number(v, f"{where}[{i}]") for i, v in enumerate(value)]
    else:
        _fail(where, f"expected a list of weights (one per vertex) or the path of a text file, got {_type(value)}")
    if len(values) != vertices:
        _fail(where, f"{len(values)} values{source}, but the rest mesh has {vertices} vertices")
    return np.array(values, dtype=np.float64)


def write_rig(path, rig):
    """Writes a rig file at path with its meshes (OBJ) and masks (text files) beside it, named after the rig
    file and the targets. Returns the path. Float32 coordinates and mask values read back exactly."""
    directory = os.path.dirname(os.path.abspath(path))
    stem = os.path.splitext(os.path.basename(path))[0]
    os.makedirs(directory, exist_ok=True)

    def file_name(*parts):
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in "_".join(parts))
        return safe

    def write_mesh(positions, *parts):
        name = file_name(stem, *parts) + ".obj"
        write_obj(os.path.join(directory, name), positions, rig.faces)
        return name

    doc = {"rest": write_mesh(rig.rest, "rest")}
    if rig.fixed_vertices:
        doc["fixed_vertices"] = [int(v) for v in rig.fixed_vertices]
    doc["targets"] = []
    for index, target in enumerate(rig.targets):
        key = f"{index:03d}"
        entry = {"name": target.name, "mesh": write_mesh(target.positions, key, target.name)}
        if target.inbetweens:
            entry["inbetweens"] = [{"weight": float(w), "mesh": write_mesh(p, key, target.name, f"{w:g}")}
                                   for w, p in target.inbetweens]
        if target.mask is not None:
            mask_name = file_name(stem, key, target.name, "mask") + ".txt"
            with open(os.path.join(directory, mask_name), "w") as text:
                text.writelines(f"{float(v)!r}\n" for v in np.asarray(target.mask, dtype=np.float64))
            entry["mask"] = mask_name
        if target.combination:
            entry["combination"] = list(target.combination)
        doc["targets"].append(entry)
    with open(path, "w") as out:
        json.dump(doc, out, indent=1)
    return path


def linear_blend(rig, weights):
    """The plain linear blendshape of a rig (#V by 3), as any blendshape evaluator with in-betweens and
    combinations plays it, and as `springblend blend --rig RIG.json --linear` computes it: one weight per target
    that is not a combination (rig.weight_names order), or a dict by name (the others 0). A target blends
    piecewise linearly through its in-betweens (extrapolated with the first or last segment's slope outside
    [0, 1]), its offsets scaled per vertex by its mask; a combination is on by the product of its drivers'
    weights, less that product on each driver's full shape. A baked rig (`springblend bake-rig`) played this way
    gives the solved frames at its in-betweens' weights and its combinations' driver settings."""
    names = rig.weight_names
    if isinstance(weights, dict):
        unknown = [n for n in weights if n not in names]
        if unknown:
            raise invalid_argument(f"weights: '{unknown[0]}' is not a target of this rig (targets: {', '.join(names)})")
        weights = [float(weights.get(n, 0.0)) for n in names]
    weights = [float(w) for w in weights]
    if len(weights) != len(names):
        raise invalid_argument(f"weights: {len(weights)} given for a rig of {len(names)} targets")
    if not all(math.isfinite(w) for w in weights):
        raise invalid_argument("weights: every weight must be finite")
    by_name = dict(zip(names, weights))
    ordinary = {t.name: t for t in rig.targets if not t.combination}
    rest = np.asarray(rig.rest, dtype=np.float64)
    out = rest.copy()

    def offset(target, positions):
        delta = np.asarray(positions, dtype=np.float64) - rest
        return delta if target.mask is None else delta * np.asarray(target.mask, dtype=np.float64)[:, None]

    for target in ordinary.values():
        w = by_name[target.name]
        if w == 0.0:
            continue
        knots = sorted(target.inbetweens, key=lambda k: k[0]) + [(1.0, target.positions)]
        i = 0
        while i + 1 < len(knots) and w > knots[i][0]:
            i += 1
        a = 0.0 if i == 0 else knots[i - 1][0]
        b = knots[i][0]
        u = (w - a) / (b - a)
        out += u * offset(target, knots[i][1])
        if i > 0:
            out += (1.0 - u) * offset(target, knots[i - 1][1])
    for target in rig.targets:
        if not target.combination:
            continue
        product = math.prod(by_name[d] for d in target.combination)
        if product == 0.0:
            continue
        out += product * (np.asarray(target.positions, dtype=np.float64) - rest)
        for d in target.combination:
            out -= product * offset(ordinary[d], ordinary[d].positions)
    return out
