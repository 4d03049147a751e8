"""Captured facial performances ("takes", docs/takes.md): a Live Link Face CSV (Epic's iOS app, ARKit's 52 shapes
per frame; other capture tools write the same names) read into per-frame weights of a character's targets.

    take = springblend.performance.read_take("take.csv")            # columns, rows, timing; no rig needed
    performance = springblend.performance.match(take, client.target_names(character), map="map.json")
    performance.weights        # #frames by #targets float64, in target_names order
    performance.report         # what was left out or changed (also given as one warning)
    for frame in client.solve_take(character, performance): ...    # streamed, as solve_frames
    solution.write_pc2("shot.pc2", performance.start_frame)         # on the take's timecode

The rules are the CLI's (client/cli/take.cc), to the bit: names match case-insensitively ignoring '_', '.', '-'
and spaces, a side suffix (Left/Right, _L/_R, .L/.R, L/R after a lower-case letter) matches any other side
convention, an exact name wins, and a shape without a side drives both halves of a target the rig splits; a map
{"Shape": "target" | ["target", ...] | {"target": factor} | None} overrides names for the shapes it lists, and
columns driving one target add up in column order. Rows where tracking was lost (BlendShapeCount 0) are held at
the last tracked row (leading ones at the first) or skipped. Errors (SpringblendError, INVALID_ARGUMENT) name the
file, line and column.
"""

import dataclasses
import json
import math
import re
import string
import warnings

import numpy as np

from springblend.errors import invalid_argument

ARKIT_SHAPES = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawRight", "JawLeft", "JawOpen", "MouthClose", "MouthFunnel",
    "MouthPucker", "MouthRight", "MouthLeft", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft",
    "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft", "MouthPressRight",
    "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft", "MouthUpperUpRight", "BrowDownLeft",
    "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft",
    "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut")
_ARKIT_LOWER = {s.lower() for s in ARKIT_SHAPES}
# Timecode frame rates in use, for a take too short to show where its timecode's frames wrap.
_TIMECODE_RATES = (24, 25, 30, 48, 50, 60, 72, 96, 100, 120)
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_TIMECODE = re.compile(r"([0-9]{1,6}):([0-9]{1,6}):([0-9]{1,6})[:;.]([0-9]{1,6})(?:\.[0-9]+)?")
_SEPARATORS = "_.- "
_SPACE = " \t\n\v\f\r"  # what the CLI trims (C's isspace)
_ASCII_LOWER = str.maketrans(string.ascii_uppercase, string.ascii_lowercase)


def _lower(name):
    """ASCII lower case, as the CLI compares names."""
    return name.translate(_ASCII_LOWER)


def _count(n, noun):
    """"1 row", "8 rows"."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


class TakeWarning(UserWarning):
    """The report of a take matched to a character, when it has something to say."""


@dataclasses.dataclass
class Row:
    line: int             # in the file, 1-based (the header is line 1)
    timecode: str         # as written ("" without a Timecode column)
    tracked: bool         # False: BlendShapeCount 0, tracking was lost
    values: tuple         # one per shape column when tracked


@dataclasses.dataclass
class Timing:
    """When the rows were captured, from the Timecode column (HH:MM:SS:FF[.sss]): the timecode counts
    timecode_rate frames per second and steps by `step` per row; start_frame is the first row's timecode counted
    in take frames ((seconds of the day * timecode_rate + FF) / step)."""
    known: bool = False
    timecode_rate: int = 0
    step: int = 0
    frame_rate: float = 0.0
    start_frame: float = 0.0
    rate_assumed: bool = False  # the take spans no second boundary: the smallest usual rate above its frames


@dataclasses.dataclass
class Take:
    """A take as read: the weight columns' names, the columns that are not weights, the rows and the timing."""
    source: str
    shapes: list
    shape_columns: list
    other_columns: list
    rows: list
    timing: Timing

    @property
    def lost_rows(self):
        return sum(1 for r in self.rows if not r.tracked)


@dataclasses.dataclass
class OutOfRange:
    target: str
    frames: int      # frames with the target's weight outside [0, 1]
    low: float
    high: float
    line: int        # where the first such frame is


@dataclasses.dataclass
class Report:
    """What matching a take to a character left out or changed (the CLI prints the same on stderr)."""
    source: str
    rows: int = 0
    frames: int = 0
    timing: Timing = dataclasses.field(default_factory=Timing)
    other_columns: list = dataclasses.field(default_factory=list)
    unmatched_shapes: list = dataclasses.field(default_factory=list)
    ambiguous_shapes: list = dataclasses.field(default_factory=list)
    unused_map_entries: list = dataclasses.field(default_factory=list)
    undriven_targets: list = dataclasses.field(default_factory=list)
    summed_targets: list = dataclasses.field(default_factory=list)
    out_of_range: list = dataclasses.field(default_factory=list)
    lost: str = "hold"
    lost_rows: int = 0
    leading_lost_rows: int = 0
    longest_lost: int = 0
    longest_lost_line: int = 0

    def lines(self):
        """One line per finding, as the CLI words them."""
        t = self.timing
        when = "frame rate unknown (no Timecode column, or too few rows): a point cache starts at frame 1"
        if t.known:
            assumed = "; the take spans no second boundary, so the rate is assumed" if t.rate_assumed else ""
            when = (f"{t.frame_rate:g} frames per second (timecode at {t.timecode_rate} per second, step {t.step}"
                    f"{assumed}), first frame {t.start_frame:.15g}")
        lines = [f"{_count(self.rows, 'row')}, {_count(self.frames, 'frame')}; {when}"]
        for items, what in ((self.other_columns, "not weights, left out"),
                            (self.unmatched_shapes, "shapes that drive no target"),
                            (self.ambiguous_shapes, "shapes that fit several targets, left out (name them in --map)"),
                            (self.unused_map_entries, "map entries for shapes the take lacks"),
                            (self.undriven_targets, "targets no column drives (0 in every frame)"),
                            (self.summed_targets, "targets several columns drive (their sum)")):
            if items:
                lines.append(f"{what}: {', '.join(items)}")
        if self.out_of_range:
            lines.append("weights outside [0, 1]: " + ", ".join(
                f"{o.target} in {_count(o.frames, 'frame')} ({o.low:g} to {o.high:g}, first at line {o.line})"
                for o in self.out_of_range))
        if self.lost_rows:
            line = (f"tracking lost in {_count(self.lost_rows, 'row')} (the longest stretch "
                    f"{_count(self.longest_lost, 'row')}, from line {self.longest_lost_line})")
            if self.lost == "skip":
                line += ", skipped"
                if t.known:
                    line += ": the frames after the first lost row no longer keep the take's timing"
            else:
                line += ", held at the last tracked weights"
                if self.leading_lost_rows:
                    line += f" ({_count(self.leading_lost_rows, 'row')} before the first tracked one at its weights)"
            lines.append(line)
        return lines

    @property
    def noteworthy(self):
        """Whether anything beyond the counts is said."""
        return len(self.lines()) > 1

    def __str__(self):
        return "\n".join(f"{self.source}: {line}" for line in self.lines())


@dataclasses.dataclass
class Performance:
    """A take matched to a character: weights[i] is frame i's weights in target_names order; lines[i] the file
    line it came from; start_frame and frame_rate the take's timing (None when unknown)."""
    take: Take
    target_names: list
    weights: np.ndarray
    lines: list
    report: Report

    @property
    def frame_rate(self):
        return self.take.timing.frame_rate if self.take.timing.known else None

    @property
    def start_frame(self):
        """The PC2 start frame on the take's timecode (1.0 when the timing is unknown), as the CLI writes it."""
        return self.take.timing.start_frame if self.take.timing.known else 1.0

    def by_name(self, frame):
        """{target name: weight} of one frame."""
        return dict(zip(self.target_names, self.weights[frame].tolist()))


def looks_like_take(path):
    """Whether the file's first line is a take's header (Timecode, BlendShapeCount or an ARKit shape column)."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as text:
            first = text.readline()
    except OSError:
        return False
    fields = [_lower(f.strip(_SPACE)) for f in first.rstrip("\r\n").split(",")]
    return any(f in ("timecode", "blendshapecount") or f in _ARKIT_LOWER for f in fields)


def read_take(path):
    """Reads a take file (see parse_take)."""
    try:
        with open(path, "rb") as data:
            raw = data.read()
    except FileNotFoundError:
        raise invalid_argument(f"take file not found: {path}") from None
    return parse_take(raw.decode("utf-8", errors="replace"), str(path))


def _number(text):
    if not _NUMBER.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None


def _is_rotation(lower):
    return lower.endswith(("yaw", "pitch", "roll")) and (lower.startswith("head") or "eye" in lower)


def parse_take(text, source="take"):
    """A take from its text; raises SpringblendError naming source, line and column for a bad take."""
    def invalid(line, column, what):
        return invalid_argument(f"{source}: line {line}, column {column}: {what}")

    if text.startswith("\ufeff"):
        text = text[1:]
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    lines = [line[:-1] if line.endswith("\r") else line for line in lines]
    if not lines or not lines[0].strip(_SPACE):
        raise invalid_argument(f"{source}: line 1: empty, not a take's header (Timecode,BlendShapeCount,"
                               "EyeBlinkLeft,...)")
    header = [f.strip(_SPACE) for f in lines[0].split(",")]
    timecode_column = count_column = -1
    known = False
    shapes, shape_columns, others = [], [], []
    for c, name in enumerate(header):
        lower = _lower(name)
        if not name:
            raise invalid(1, c + 1, "a column without a name")
        if lower == "timecode":
            timecode_column, known = c, True
        elif lower == "blendshapecount":
            count_column, known = c, True
        elif _is_rotation(lower):
            others.append(name)
        else:
            known = known or lower in _ARKIT_LOWER
            shapes.append(name)
            shape_columns.append(c)
    if not known:
        raise invalid(1, 1, "not a take's header: no Timecode, BlendShapeCount or ARKit shape column (EyeBlinkLeft "
                            "... JawOpen ... TongueOut)")
    if not shapes:
        raise invalid(1, 1, "the header names no shape column (only timecode and rotations)")
    rows, codes = [], []
    for number, line in enumerate(lines[1:], 2):
        if not line.strip(_SPACE):
            continue
        fields = [f.strip(_SPACE) for f in line.split(",")]
        if len(fields) > len(header):
            raise invalid(number, len(header) + 1, f"{len(fields)} fields, but the header has {len(header)} columns")
        tracked = True
        if 0 <= count_column < len(fields):
            count = _number(fields[count_column])
            if count is None:
                raise invalid(number, count_column + 1,
                              f"({header[count_column]}) '{fields[count_column]}' is not a number")
            tracked = count != 0.0
        if tracked and len(fields) < len(header):
            raise invalid(number, len(fields) + 1,
                          f"the row ends after {len(fields)} of the header's {len(header)} columns (a row where "
                          "tracking was lost has BlendShapeCount 0)")
        timecode = ""
        if timecode_column >= 0:
            if timecode_column >= len(fields):
                raise invalid(number, timecode_column + 1, "the row has no timecode")
            timecode = fields[timecode_column]
            match = _TIMECODE.fullmatch(timecode)
            if match is None or int(match[2]) > 59 or int(match[3]) > 59:
                raise invalid(number, timecode_column + 1,
                              f"({header[timecode_column]}) '{timecode}' is not a timecode HH:MM:SS:FF[.sss]")
            codes.append((int(match[1]) * 3600 + int(match[2]) * 60 + int(match[3]), int(match[4])))
        values = ()
        if tracked:
            parsed = []
            for c in shape_columns:
                value = _number(fields[c])
                if value is None:
                    raise invalid(number, c + 1, f"({header[c]}) '{fields[c]}' is not a number")
                parsed.append(value)
            for c, field in enumerate(fields):
                if c != timecode_column and _number(field) is None:
                    raise invalid(number, c + 1, f"({header[c]}) '{field}' is not a number")
            values = tuple(parsed)
        rows.append(Row(line=number, timecode=timecode, tracked=tracked, values=values))
    if not rows:
        raise invalid_argument(f"{source}: the take has a header but no rows")
    return Take(source=source, shapes=shapes, shape_columns=shape_columns, other_columns=others, rows=rows,
                timing=_timing(codes))


def _mode(values):
    """The most frequent value (the smallest of equally frequent ones), or None."""
    if not values:
        return None
    counts = {}
    for v in values:
        counts[v] = counts.get(v, 0) + 1
    return min(counts, key=lambda v: (-counts[v], v))


def _timing(codes):
    timing = Timing()
    if len(codes) < 2:
        return timing
    max_frame = max(frame for _, frame in codes)
    step = _mode([b[1] - a[1] for a, b in zip(codes, codes[1:]) if a[0] == b[0] and b[1] > a[1]])
    if step is None:
        return timing
    wraps = [a[1] + step - b[1] for a, b in zip(codes, codes[1:]) if (b[0] - a[0] + 86400) % 86400 == 1]
    rate = _mode(wraps)
    if rate is None or rate <= max_frame:
        rate = next((r for r in _TIMECODE_RATES if r > max_frame), max_frame + 1)
        timing.rate_assumed = not wraps
    timing.known, timing.timecode_rate, timing.step = True, rate, step
    timing.frame_rate = rate / step
    timing.start_frame = (float(codes[0][0]) * rate + codes[0][1]) / float(step)
    return timing


def _side_key(name):
    """(base, side) of a name: lower case without '_', '.', '-' or spaces, and 'l', 'r' or '' for a side suffix."""
    lower, rest, side = _lower(name), name, ""
    if len(lower) > 4 and lower.endswith("left"):
        side, rest = "l", name[:-4]
    elif len(lower) > 5 and lower.endswith("right"):
        side, rest = "r", name[:-5]
    elif len(lower) >= 3 and name[-2] in _SEPARATORS and lower[-1] in "lr":
        side, rest = lower[-1], name[:-2]
    elif len(name) >= 2 and name[-1] in "LR" and (name[-2] in "abcdefghijklmnopqrstuvwxyz0123456789"):
        side, rest = name[-1].lower(), name[:-1]
    return "".join(c for c in _lower(rest) if c not in _SEPARATORS), side


def _find_exact(names, name):
    if name in names:
        return [names.index(name)]
    return [i for i, n in enumerate(names) if _lower(n) == _lower(name)]


def load_map(path_or_map):
    """A user's map as a list of (shape, [(target, factor), ...]): from a JSON file's path, or a dict
    {"Shape": "target" | ["target", ...] | {"target": factor} | None}."""
    source = "map"
    if not isinstance(path_or_map, dict):
        source = str(path_or_map)
        try:
            with open(path_or_map) as text:
                path_or_map = json.load(text)
        except FileNotFoundError:
            raise invalid_argument(f"map file not found: {source}") from None
        except json.JSONDecodeError as error:
            raise invalid_argument(f"{source}: not valid JSON: {error}") from None
        if not isinstance(path_or_map, dict):
            raise invalid_argument(f"{source}: must be an object of shape names to a target, a list of targets, or "
                                   "{target: factor}")
    entries = []
    for shape, value in path_or_map.items():
        if isinstance(value, str):
            targets = [(value, 1.0)]
        elif isinstance(value, (list, tuple)):
            if not all(isinstance(t, str) for t in value):
                raise invalid_argument(f'{source}: "{shape}": a list must hold target names')
            targets = [(t, 1.0) for t in value]
        elif isinstance(value, dict):
            targets = []
            for target, factor in value.items():
                if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not np.isfinite(factor):
                    raise invalid_argument(f"{source}: \"{shape}\": the factor of '{target}' must be a number")
                targets.append((target, float(factor)))
        elif value is None:
            targets = []
        else:
            raise invalid_argument(f'{source}: "{shape}": must be a target name, a list of them, {{target: factor}} '
                                   f"or null, not {type(value).__name__}")
        entries.append((shape, targets))
    return source, entries


def match(take, target_names, map=None, lost="hold", warn=True):  # noqa: A002 - the CLI's --map
    """The take's rows as weights of the character's targets (target_names, in weight order): a Performance.
    map: None, a JSON map file's path or a dict (see load_map). lost: "hold" or "skip". warn: give the report as
    one TakeWarning when it says more than the counts."""
    if lost not in ("hold", "skip"):
        raise invalid_argument(f"lost must be 'hold' or 'skip', got {lost!r}")
    if isinstance(take, str) or hasattr(take, "__fspath__"):
        take = read_take(take)
    targets = [str(t) for t in target_names]
    report = Report(source=take.source, rows=len(take.rows), timing=take.timing,
                    other_columns=list(take.other_columns), lost=lost)
    drives = [[] for _ in take.shapes]
    mapped = [False] * len(take.shapes)
    if map is not None:
        map_source, entries = load_map(map)
        for shape, entry in entries:
            columns = _find_exact(take.shapes, shape)
            if not columns:
                report.unused_map_entries.append(shape)
                continue
            for c in columns:
                mapped[c] = True
                for target, factor in entry:
                    found = _find_exact(targets, target)
                    if len(found) != 1:
                        why = "is not a target of the rig" if not found else "names several targets (give its case)"
                        raise invalid_argument(f"{map_source}: \"{shape}\": '{target}' {why} (targets: "
                                               f"{', '.join(targets)})")
                    drives[c].append((found[0], factor))
    keys = [_side_key(t) for t in targets]

    def with_key(key):
        return [i for i, k in enumerate(keys) if k == key]

    for c, shape in enumerate(take.shapes):
        if mapped[c]:
            continue
        found = _find_exact(targets, shape)
        key = _side_key(shape)
        if not found:
            found = with_key(key)
        if len(found) > 1:
            report.ambiguous_shapes.append(f"{shape} ({', '.join(targets[t] for t in found)})")
            continue
        if not found and not key[1]:
            left, right = with_key((key[0], "l")), with_key((key[0], "r"))
            if len(left) > 1 or len(right) > 1:
                report.ambiguous_shapes.append(f"{shape} ({', '.join(targets[t] for t in left + right)})")
                continue
            found = left + right
        if not found:
            report.unmatched_shapes.append(shape)
            continue
        drives[c] = [(t, 1.0) for t in found]
    report.unmatched_shapes += [f"{take.shapes[c]} (null in the map)" for c in range(len(take.shapes))
                                if mapped[c] and not drives[c]]
    drivers = [0] * len(targets)
    for entry in drives:
        for t, _ in entry:
            drivers[t] += 1
    report.undriven_targets = [targets[t] for t in range(len(targets)) if drivers[t] == 0]
    report.summed_targets = [targets[t] for t in range(len(targets)) if drivers[t] > 1]
    if not any(drivers):
        raise invalid_argument(f"{take.source}: line 1: no column of the header is a shape of this rig (its targets: "
                               f"{', '.join(targets)}; the take's shapes: {', '.join(take.shapes)}); a map names the "
                               "others")
    tracked = [r for r in take.rows if r.tracked]
    if not tracked:
        raise invalid_argument(f"{take.source}: tracking was lost in every row (BlendShapeCount 0): nothing to solve")

    def weights_of(row):
        w = [0.0] * len(targets)
        for c, entry in enumerate(drives):
            for t, factor in entry:
                w[t] += factor * row.values[c]
        return w

    held = weights_of(tracked[0])
    frames, lines, stretch, seen_tracked = [], [], 0, False
    for row in take.rows:
        if row.tracked:
            held, stretch, seen_tracked = weights_of(row), 0, True
        else:
            report.lost_rows += 1
            stretch += 1
            if stretch > report.longest_lost:
                report.longest_lost, report.longest_lost_line = stretch, row.line - stretch + 1
            if not seen_tracked:
                report.leading_lost_rows += 1
            if lost == "skip":
                continue
        frames.append(held)
        lines.append(row.line)
    report.frames = len(frames)
    weights = np.array(frames, dtype=np.float64).reshape(len(frames), len(targets))
    for t, name in enumerate(targets):
        column = weights[:, t]
        outside = np.flatnonzero((column < 0.0) | (column > 1.0))
        if len(outside):
            report.out_of_range.append(OutOfRange(target=name, frames=len(outside), low=float(column[outside].min()),
                                                  high=float(column[outside].max()), line=lines[outside[0]]))
    if warn and report.noteworthy:
        warnings.warn(str(report), TakeWarning, stacklevel=2)
    return Performance(take=take, target_names=targets, weights=weights, lines=lines, report=report)


def read(path, target_names, map=None, lost="hold", warn=True):  # noqa: A002
    """read_take and match in one: the take at path (or a Take already read) as weights of target_names."""
    return match(path, target_names, map=map, lost=lost, warn=warn)

