"""Ignore masks: what part of a scan registration should not fit (a floor, a wall, a prop).

A mask is given per scan vertex, as the add-on's *Ignore Group* gives it: a weight in [0, 1], 1 =
ignore; registration takes per-face weights (``registration.register(scan_face_weights=)``), a face
weighing 1 - the mean of its vertices' ignore weights.

Files (``bareesa register --ignore``, the pair verbs' ``--ignore-a/-b``, ``register-batch``'s
``SCAN.ignore.*`` next to a scan): ``.npy`` of M numbers, or text with M numbers separated by
spaces, commas or new lines (``#`` starts a comment), one per scan vertex in the mesh file's order.
"""

from pathlib import Path

import numpy as np

from .errors import InputError


def face_weights_from_ignore(ignore, faces):
    """Per-vertex ignore weights (M,) in [0, 1], faces (G, 3) -> face weights (G,) = 1 - mean over the
    face's vertices, clipped to [0, 1]."""
    ignore = np.asarray(ignore, dtype=np.float64)
    return np.clip(1.0 - ignore[np.asarray(faces)].mean(1), 0.0, 1.0)


def read_ignore_weights(path, n_verts):
    """A mask file (see the module docstring) of a scan with n_verts vertices -> ignore weights (M,) float64.
    Raises InputError naming the file: missing, unreadable, not n_verts numbers, outside [0, 1]."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"mask file {path} does not exist")
    try:
        if path.suffix.lower() == ".npy":
            values = np.load(path, allow_pickle=False)
        else:
            lines = [line.split("#", 1)[0] for line in path.read_text().splitlines()]
            tokens = " ".join(lines).replace(",", " ").replace(";", " ").split()
            values = np.array([float(t) for t in tokens])
    except (OSError, ValueError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read the mask {path}: {str(err).splitlines()[0]}") from None
    values = np.asarray(values)
    if values.dtype == bool:  # e.g. np.save(path, verts[:, 2] < 0.02)
        values = values.astype(np.float64)
    if values.ndim != 1 or len(values) != n_verts or not np.issubdtype(values.dtype, np.number):
        raise InputError(f"mask {path}: expected {n_verts} numbers, one ignore weight per scan vertex, "
                         f"got {values.size if values.ndim else 1}" + (f" in shape {values.shape}" if values.ndim > 1
                                                                         else ""))
    values = values.astype(np.float64)
    if not np.isfinite(values).all() or (values < 0).any() or (values > 1).any():
        raise InputError(f"mask {path}: ignore weights must be between 0 (keep) and 1 (ignore)")
    return values


def read_face_weights(path, faces, n_verts):
    """A mask file of a scan (n_verts vertices, faces (G, 3)) -> its face weights (G,)
    (``face_weights_from_ignore``); InputError when it ignores every face."""
    weights = face_weights_from_ignore(read_ignore_weights(path, n_verts), faces)
    if not (weights > 0).any():
        raise InputError(f"mask {path} ignores every face of the scan: nothing is left to register")
    return weights
