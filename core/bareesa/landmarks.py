"""Landmarks: named points of a basis' template and their positions on a scan.

A basis may carry named anatomical landmarks, ``Basis.landmarks`` = {name: template vertex index}
(in its card). A scan's landmarks say where some of them are on the scan; registration takes them
as [(template vertex, (x, y, z), weight)] (``registration.register``).

Files
    template landmarks (``build-basis --landmarks``): JSON {name: vertex} or CSV lines ``name, vertex``.
    scan landmarks (``register --landmarks``): JSON {name: [x, y, z]} or {name: {"point": [x, y, z],
    "weight": w}}, JSON [[vertex, [x, y, z](, weight)], ...], or CSV lines ``name or vertex, x, y, z[,
    weight]``; names are the basis' landmark names, vertices template vertex indices.
"""

import json
import math
from pathlib import Path

import numpy as np

from .errors import InputError


def _read_text(path, what):
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file {path} does not exist")
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read {what} from {path}: {err}") from None


def _csv_rows(text):
    return [[c.strip() for c in line.replace(";", ",").split(",")]
            for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def read_template_landmarks(path, n_verts):
    """A template landmark file -> {name: template vertex index}, checked against n_verts vertices."""
    path = Path(path)
    text = _read_text(path, "landmarks")
    if path.suffix.lower() == ".json":
        try:
            table = json.loads(text)
        except ValueError as err:
            raise InputError(f"cannot read landmarks from {path}: {err}") from None
    else:
        table = {}
        for row in _csv_rows(text):
            if len(row) != 2:
                raise InputError(f"{path}: line '{', '.join(row)}' must be 'name, vertex'")
            table[row[0]] = row[1]
    if not isinstance(table, dict) or not table:
        raise InputError(f"{path}: expected landmark names with template vertex indices ({{name: vertex}})")
    out = {}
    for name, vertex in table.items():
        try:
            index = int(vertex)
        except (TypeError, ValueError):
            index = None
        if index is None or str(vertex).strip() != str(index) or not 0 <= index < n_verts:
            raise InputError(f"{path}: landmark '{name}' must be a template vertex index in 0..{n_verts - 1}, "
                             f"got {vertex!r}")
        out[str(name).strip()] = index
    return out


def _point(value, where):
    try:
        xyz = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        xyz = ()
    if len(xyz) != 3 or not all(math.isfinite(x) for x in xyz):
        raise InputError(f"{where}: the point must be 3 finite coordinates, got {value!r}")
    return xyz


def _weight(value, where):
    try:
        w = float(value)
    except (TypeError, ValueError):
        w = math.nan
    if not (math.isfinite(w) and w >= 0):
        raise InputError(f"{where}: the weight must be a finite number >= 0, got {value!r}")
    return w


def template_vertex(basis, key, where):
    """A landmark name of the basis or a template vertex index -> template vertex index."""
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        index = int(key)
    elif isinstance(key, str) and key.strip().lstrip("-").isdigit():
        index = int(key)
    elif isinstance(key, str) and key.strip() in basis.landmarks:
        return basis.landmarks[key.strip()]
    else:
        known = ", ".join(sorted(basis.landmarks)) or "none: give template vertex indices"
        raise InputError(f"{where}: basis '{basis.name}' has no landmark '{key}' (its landmarks: {known})")
    if not 0 <= index < basis.template.shape[0]:
        raise InputError(f"{where}: template vertex {index} is not in 0..{basis.template.shape[0] - 1}")
    return index


def _landmark(basis, key, xyz, weight, where):
    """One scan landmark checked: -> (template vertex, (x, y, z), weight)."""
    return template_vertex(basis, key, where), _point(xyz, where), _weight(weight, where)


def scan_landmarks(basis, points):
    """Named scan points {name or vertex: (x, y, z) or ((x, y, z), weight)} -> [(vertex, (x, y, z), weight)]."""
    out = []
    for key, value in points.items():
        where = f"landmark '{key}'"
        if isinstance(value, (tuple, list)) and len(value) == 2 and not np.isscalar(value[0]):
            xyz, w = value
        else:
            xyz, w = value, 1.0
        out.append(_landmark(basis, key, xyz, w, where))
    return out


def read_scan_landmarks(path, basis):
    """A scan landmark file (see the module docstring) -> [(template vertex, (x, y, z), weight)]."""
    path = Path(path)
    text = _read_text(path, "landmarks")
    rows = []
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except ValueError as err:
            raise InputError(f"cannot read landmarks from {path}: {err}") from None
        if isinstance(data, dict):
            for key, value in data.items():
                if isinstance(value, dict):
                    if "point" not in value:
                        raise InputError(f"{path}: landmark '{key}' needs a \"point\": [x, y, z]")
                    rows.append((key, value["point"], value.get("weight", 1.0)))
                else:
                    rows.append((key, value, 1.0))
        elif isinstance(data, list):
            for k, row in enumerate(data):
                if not isinstance(row, (list, tuple)) or len(row) < 2:
                    raise InputError(f"{path}: landmark {k + 1} must be [vertex or name, [x, y, z](, weight)], "
                                     f"got {row!r}")
                flat = [row[0], *row[1], *row[2:]] if isinstance(row[1], (list, tuple)) else list(row)
                rows.append((flat[0], flat[1:4], flat[4] if len(flat) > 4 else 1.0))
        else:
            raise InputError(f"{path}: expected a JSON object {{name: [x, y, z]}} or a list")
    else:
        for k, row in enumerate(_csv_rows(text)):
            if len(row) not in (4, 5):
                raise InputError(f"{path}: landmark {k + 1} ('{', '.join(row)}') must be 'name or vertex, x, y, "
                                 "z[, weight]'")
            rows.append((row[0], row[1:4], row[4] if len(row) == 5 else 1.0))
    return [_landmark(basis, key, xyz, w, f"{path}: landmark {k + 1} ('{key}')")
            for k, (key, xyz, w) in enumerate(rows)]

