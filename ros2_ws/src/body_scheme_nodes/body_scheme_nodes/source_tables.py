"""Tables of other stacks' sessions as samples (:func:`~body_scheme_nodes.sources.translate`'s ``.csv`` and ``.jsonl``):
one pose per row, already still. CSV columns: an optional ``stamp`` (s), the joint names, and per body ``<id>.x <id>.y
<id>.z <id>.qx <id>.qy <id>.qz <id>.qw`` (a pose) or ``<id>.<point>.x <id>.<point>.y <id>.<point>.z`` (the points of the
map's ``points`` by label); an empty cell is not observed. JSON lines: ``{"stamp": s, "joints": {name: value}, "poses":
{"<id>": [x, y, z, qx, qy, qz, qw]}, "points": {"<id>": {"<point>": [x, y, z]}}}``. Without stamps, row ``k`` is
commanded at ``k`` s; stamps must increase. A row's observation follows its command by 0.1 s, or half the time to the
next row if that is shorter: a row's poses are its own, whatever the spacing.
"""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict

import numpy as np

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import transform_from_pose

__all__ = ["TABLE_SUFFIXES", "TABLE_DELAY", "TABLE_PERIOD", "table_samples", "append_sample"]

TABLE_SUFFIXES = (".csv", ".jsonl")
#: Seconds between a row's command and its observation, and between rows without stamps.
TABLE_DELAY, TABLE_PERIOD = 0.1, 1.0
_POSE_FIELDS = ("x", "y", "z", "qx", "qy", "qz", "qw")


def append_sample(seen, counts, key, stamp, value):
    """Append ``(stamp, value())`` to ``seen[key]``; a value that cannot be read is counted as ``invalid_pose``."""
    try:
        seen[key].append((stamp, value()))
    except (InvalidInputError, IndexError, TypeError, ValueError):
        counts["invalid_pose"] += 1


def table_samples(path, source_map, counts):
    """The table's rows as samples ``[(stamp, values, {(id, label): (stamp, pose or point)})]`` (each row one pose;
    its stamps must increase); what is dropped is counted in ``counts``."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise InvalidInputError(f"cannot read the table {path}: {error}") from error
    rows = _csv_rows(path, text, source_map, counts) if path.suffix == ".csv" else _jsonl_rows(path, text)
    points_of = {body.marker_id: body for body in source_map.bodies if body.points}
    samples, last = [], -math.inf
    for k, row in enumerate(rows):
        try:
            stamp = float(row["stamp"]) if row.get("stamp") not in (None, "") else k * TABLE_PERIOD
            values = np.array([float(row["joints"][name]) for name in source_map.joint_names])
            if not (math.isfinite(stamp) and np.all(np.isfinite(values)) and stamp > last):
                raise ValueError("not finite, or not after the row before")
            poses, points = row.get("poses") or {}, row.get("points") or {}
            if not (isinstance(poses, dict) and isinstance(points, dict)):
                raise TypeError("poses and points must be objects keyed by marker id")
        except (KeyError, TypeError, ValueError, AttributeError):
            counts["invalid_row"] += 1
            continue
        last = stamp
        found = defaultdict(list)
        for marker_id, numbers in poses.items():
            append_sample(found, counts, _marker_id(marker_id), stamp + TABLE_DELAY,
                    lambda n=numbers: transform_from_pose(_floats(n[:3]), _floats(n[3:7])))
        for marker_id, labelled in points.items():
            body = points_of.get(_marker_id(marker_id))
            if body is None or not isinstance(labelled, dict):
                counts["invalid_pose"] += 1
                continue
            for label, xyz in labelled.items():
                if label in body.points:
                    append_sample(found, counts, (body.marker_id, label), stamp + TABLE_DELAY, lambda v=xyz: _floats(v))
                else:
                    counts["invalid_pose"] += 1
        samples.append((stamp, values, {key: items[0] for key, items in found.items() if items and key[0] is not None}))
        if found.get((None, "")):
            counts["invalid_pose"] += len(found[(None, "")])
    if not samples and not counts["invalid_row"]:
        raise InvalidInputError(f"table {path}: no row with values of the joints {list(source_map.joint_names)}")
    # A row's observation follows its command by TABLE_DELAY, or half the time to the next row if that is shorter:
    # always before the next row's command, so the pairing cannot give a row another row's poses.
    for k, (stamp, values, found) in enumerate(samples):
        gap = samples[k + 1][0] - stamp if k + 1 < len(samples) else math.inf
        delay = min(TABLE_DELAY, gap / 2)
        samples[k] = (stamp, values, {key: (stamp + delay, item) for key, (_, item) in found.items()})
    return samples


def _marker_id(key):
    """``(id, "")`` of a table's marker key ("7" or 7); ``(None, "")`` for anything else."""
    try:
        marker_id = int(key)
    except (TypeError, ValueError):
        return (None, "")
    return (marker_id, "") if str(marker_id) == str(key).strip() and marker_id >= 0 else (None, "")


def _floats(values):
    array = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(array)):
        raise InvalidInputError("not finite")
    return array


def _csv_rows(path, text, source_map, counts):
    reader = csv.DictReader(text.splitlines())
    header = reader.fieldnames or []
    missing = [name for name in source_map.joint_names if name not in header]
    if missing:
        raise InvalidInputError(f"table {path}: no column for the joints {missing} (header: {header})")
    known = {"stamp", *source_map.joint_names}
    ignored = [c for c in header if c not in known and not _body_column(c)]
    if ignored:
        counts["ignored_columns"] += len(ignored)
    rows = []
    for line in reader:
        row = {"joints": {name: line[name] for name in source_map.joint_names}, "poses": {}, "points": {}}
        if line.get("stamp"):
            row["stamp"] = line["stamp"]
        for column, cell in line.items():
            if column is None or "." not in column or cell in (None, ""):
                continue
            marker, _, rest = column.partition(".")
            if not marker.isdigit():
                continue
            label, _, axis = rest.rpartition(".")
            if not label and axis in _POSE_FIELDS:
                row["poses"].setdefault(marker, [math.nan] * 7)[_POSE_FIELDS.index(axis)] = _number(cell)
            elif label and axis in ("x", "y", "z"):
                row["points"].setdefault(marker, {}).setdefault(label, [math.nan] * 3)["xyz".index(axis)] = \
                    _number(cell)
        rows.append(row)
    return rows


def _body_column(column):
    """Whether a CSV column is ``<id>.<field>`` of a pose or ``<id>.<point>.<axis>`` of a point."""
    marker, _, rest = column.partition(".")
    label, _, axis = rest.rpartition(".")
    return marker.isdigit() and ((not label and axis in _POSE_FIELDS) or (bool(label) and axis in ("x", "y", "z")))


def _number(cell):
    try:
        return float(cell)
    except ValueError:
        return math.nan


def _jsonl_rows(path, text):
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as error:
            raise InvalidInputError(f"table {path}, line {number}: not JSON: {error}") from error
        if not isinstance(row, dict):
            raise InvalidInputError(f"table {path}, line {number}: expected an object with joints and poses")
        rows.append(row)
    return rows
