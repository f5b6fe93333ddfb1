"""What the command line's files and flags become: meshes as workflow inputs, 4D sequences, a path of
same-topology meshes, registration settings (``--config`` / ``--set``)."""

import json
from pathlib import Path

import numpy as np

from .errors import InputError
from .landmarks import read_scan_landmarks
from .masks import read_face_weights
from .mesh import load_mesh, validate_mesh
from .registration.config import parse_settings
from .workflows import Scan, TemplateMesh, mesh_input


def registration_overrides(args):
    """The registration settings of --config FILE and --set KEY=VALUE (in that order): -> dict (InputError on a
    missing file, bad JSON or a malformed --set; unknown keys are refused when the configuration is built)."""
    out = {}
    if getattr(args, "config", None) is not None:
        try:
            given = json.loads(Path(args.config).read_text())
        except OSError as err:
            raise InputError(f"--config {args.config}: cannot read it ({err.strerror or err})") from None
        except ValueError as err:
            raise InputError(f"--config {args.config}: not JSON ({err})") from None
        if not isinstance(given, dict):
            raise InputError(f"--config {args.config}: expected a JSON object of settings")
        out.update(given)
    for item in getattr(args, "settings", None) or []:
        out.update(parse_settings(item))
    return out


def load_path(paths):
    """Load same-topology meshes as a path: -> verts (T, N, 3) float64 array, faces (F, 3)."""
    frames, faces = [], None
    for p in paths:
        v, f = load_mesh(p)
        validate_mesh(v, f, name=str(p))
        if faces is None:
            faces, first = f, p
        elif v.shape[0] != frames[0].shape[0]:
            raise InputError(f"{p} has {v.shape[0]} vertices but {first} has {frames[0].shape[0]}: "
                             "a path needs meshes in one topology (register scans first)")
        elif f.shape != faces.shape or not np.array_equal(f, faces):
            raise InputError(f"{p} has different faces from {first}: a path needs meshes in one topology")
        frames.append(v)
    return np.stack(frames), faces


def parse_sequences(specs):
    """['pose:a.ply,b.ply', 'pose:DIR', ...] -> {group: [list of paths]} (several sequences per group allowed);
    a single DIR (or summary.json/.csv) is a register-batch output: its registered meshes in order."""
    from .batch import registered_meshes  # (Dask is not needed to read a batch's output)

    groups = {}
    for spec in specs:
        group, sep, files = spec.partition(":")
        paths = [Path(p) for p in files.split(",") if p]
        if len(paths) == 1 and (paths[0].is_dir() or paths[0].name.startswith("summary.")):
            paths = registered_meshes(paths[0])
        if not sep or not group or len(paths) < 2:
            raise InputError(f"--sequence '{spec}' must look like GROUP:F1,F2[,...] or GROUP:BATCH_DIR with at "
                             "least two frames")
        groups.setdefault(group, []).append(paths)
    return groups


def parse_components(specs, groups):
    """['GROUP=K', ...] -> {group: K} for the groups of the sequences (InputError otherwise)."""
    out = {}
    for spec in specs or []:
        group, sep, k = spec.partition("=")
        if not sep or group not in groups or not k.isdigit() or int(k) < 1:
            raise InputError(f"--components '{spec}' must look like GROUP=K with K >= 1 and GROUP one of "
                             f"{', '.join(groups)}")
        out[group] = int(k)
    return out


def load_input(basis, path, landmarks=None, ignore=None, options=("--landmarks", "--ignore")):
    """A mesh file as a workflow input (validated): a TemplateMesh in the basis' template topology, else a Scan
    with the landmarks and ignore mask of the given files (``landmarks``, ``masks``; options: their flags, for
    the message when the mesh is not a raw scan)."""
    v, f = load_mesh(path)
    validate_mesh(v, f, name=str(path))
    found = mesh_input(basis, v, f)
    given = [flag for flag, file in zip(options, (landmarks, ignore)) if file is not None]
    if not given:
        return found
    if isinstance(found, TemplateMesh):
        raise InputError(f"{path} is in the basis' template topology (its code is a projection, not a registration): "
                         f"{' and '.join(given)} {'apply' if len(given) > 1 else 'applies'} to raw scans only")
    return Scan(v, f, face_weights=None if ignore is None else read_face_weights(ignore, f, len(v)),
                landmarks=None if landmarks is None else read_scan_landmarks(landmarks, basis))
