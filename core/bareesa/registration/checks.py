"""Checks of a registration's inputs, and how a fit is judged (its residual against the basis' own)."""

import math

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from ..mesh import face_geometry
from ..varifold import KERNELS
from .config import RegistrationConfig
from .prealign import surface_moments


def level_kernels(kernel, n_levels, noisy=False):
    """The varifold kernel of each level: "auto" binet on every level, except that the finest is linear
    when the scan is ``noisy`` (see ``register``; a one-level schedule stays binet: no fit to orient
    the scan by); a name of ``KERNELS`` (or a sum, "binet+linear") on every level; or a sequence of
    names, one per level."""
    if isinstance(kernel, str):
        auto = ["binet"] * (n_levels - 1) + ["linear" if noisy and n_levels > 1 else "binet"]
        names = auto if kernel == "auto" else [kernel] * n_levels
    else:
        names = list(kernel)
        if len(names) != n_levels:
            raise InputError(f"kernel: {len(names)} kernels given for a schedule of {n_levels} levels")
    for name in names:
        if not (isinstance(name, str) and all(part in KERNELS for part in name.split("+"))):
            raise InputError(f"unknown varifold kernel {name!r}; choose 'auto', one of {sorted(KERNELS)} "
                             "or a sum of them such as 'binet+linear'")
    return names


def check_face_weights(weights, n_faces):
    """Scan face weights (G,) >= 0, not all zero, or None -> float64 (G,) or None (InputError otherwise)."""
    if weights is None:
        return None
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n_faces,):
        raise InputError(f"scan face weights must have shape ({n_faces},), one per scan face, got {w.shape}")
    if not np.isfinite(w).all() or (w < 0).any():
        raise InputError("scan face weights must be finite and >= 0")
    if not (w > 0).any():
        raise InputError("every scan face weight is zero: nothing to register")
    return w


def check_landmarks(landmarks, n_verts):
    """[(template vertex, scan xyz[, weight]), ...] -> indices (L,), points (L, 3), weights (L,)."""
    if landmarks is None or len(landmarks) == 0:
        return None
    idx, pts, wts = [], [], []
    for k, lm in enumerate(landmarks):
        if len(lm) not in (2, 3):
            raise InputError(f"landmark {k}: expected (template vertex index, (x, y, z)[, weight]), got {lm!r}")
        i = lm[0]
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < n_verts:
            raise InputError(f"landmark {k}: template vertex index {i!r} is not an integer in 0..{n_verts - 1}")
        p = np.asarray(lm[1], dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise InputError(f"landmark {k}: scan point must be 3 finite coordinates, got {lm[1]!r}")
        w = float(lm[2]) if len(lm) == 3 else 1.0
        if not (math.isfinite(w) and w >= 0):
            raise InputError(f"landmark {k}: weight must be finite and >= 0, got {w}")
        idx.append(int(i))
        pts.append(p)
        wts.append(w)
    if sum(wts) <= 0:
        return None
    return np.array(idx), np.stack(pts), np.array(wts)



def check_plausible_scan(basis, verts, faces, face_weights=None, config=None):
    """Refuse a scan that cannot be registered onto ``basis`` (InputError naming why): fewer faces than
    ``config.min_scan_faces`` (capped at an eighth of the template's), or flat against the template's
    extent (``config.min_flatness_ratio``; a one-triangle "scan" would otherwise register for minutes and
    come back as a full body). verts (M, 3), faces (G, 3), face_weights (G,) or None."""
    config = RegistrationConfig() if config is None else config
    used = int(np.count_nonzero(face_geometry(verts, faces)[1] * (1.0 if face_weights is None else face_weights)))
    need = min(config.min_scan_faces, basis.faces.shape[0] // 8)
    if used < need:
        raise InputError(f"the scan has {used} face{'s' * (used != 1)} with area: too few to register onto basis "
                         f"'{basis.name}' (at least {need}); give the whole scanned mesh, not a piece of it")
    extent = lambda v, f, w: np.linalg.eigvalsh(surface_moments(v, f, w)[2])  # noqa: E731
    scan, template = extent(verts, faces, face_weights), extent(basis.template, basis.faces, None)
    flat, reference = scan[0] / scan[-1], template[0] / template[-1]
    if flat < config.min_flatness_ratio * reference:
        raise InputError(f"the scan is flat (its thinnest extent is {math.sqrt(flat):.2g} of its longest; the "
                         f"template's {math.sqrt(reference):.2g}): it cannot be a shape of basis '{basis.name}'; check "
                         "that the right object is selected and that floors or walls are masked out")


def fit_residual(basis, vertices, scan_points, transform):
    """Mean distance from scan points (M, 3) to the registered surface (vertices (N, 3), both in the
    scan's frame) over the basis' size, in the template frame (units and scale of the scan cancel): the
    surface is sampled at its vertices and face barycentres -> float."""
    surface = np.concatenate([vertices, face_geometry(vertices, basis.faces)[2]])
    return float(cKDTree(surface).query(scan_points, k=1)[0].mean() * transform.scale / basis.scale)


def is_poor_fit(basis, residual):
    """Whether a residual (``fit_residual``) is far above what the basis reaches on its own held-out scans
    (``basis.fit_check["poor_fit_above"]``); None when the basis is not calibrated."""
    threshold = basis.fit_check.get("poor_fit_above")
    return None if threshold is None else bool(residual > threshold)
