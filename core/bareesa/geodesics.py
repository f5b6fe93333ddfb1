"""Geodesics and distances in the latent space (paper section 4.2).

The boundary value problem: minimise the discrete path energy
sum_k dalpha_k^T G-bar(mid_k) dalpha_k / dt over the interior points of a
latent path with fixed endpoints; the distance is sqrt of the optimal energy.
"""

from dataclasses import dataclass

import numpy as np
import torch

from . import h2_metric
from .errors import InputError
from .geometry import face_areas
from .latent import decode, interior_whitening, latent_path_energy, whitening
from .optimize import minimize_lbfgs
from .progress import Monitor
from .threads import with_one_blas_thread


@dataclass
class Geodesic:
    """A solved latent path: path (T, P), its energy, distance = sqrt(energy), iterations."""

    path: np.ndarray
    energy: float
    distance: float
    iterations: int = 0


def straight_path(alpha0, alpha1, steps):
    """Straight line in latent space: (P,), (P,) -> (steps, P)."""
    t = np.linspace(0.0, 1.0, steps)[:, None]
    return (1 - t) * np.asarray(alpha0, dtype=np.float64) + t * np.asarray(alpha1, dtype=np.float64)


def _check_codes(fields, *codes):
    p = fields.shape[0]
    for c in codes:
        c = np.asarray(c)
        if c.shape != (p,):
            raise InputError(f"a latent code must have {p} coefficients, got shape {c.shape}")
        if not np.isfinite(c).all():
            raise InputError("a latent code contains NaN or infinite values")


#: L-BFGS relative decrease below which a geodesic solve stops (in whitened coordinates the
#: energy converges in a few tens of iterations; later digits move the path by ~1e-5)
GEODESIC_FTOL = 1e-10
#: (window k, rtol r) for a geodesic between two known codes that frames are made from: stop once the
#: energy fell by less than r of itself over the last k iterations: about half the iterations of a solve
#: to GEODESIC_FTOL, its frames well within the time discretisation's own error
#: (docs/decisions/019-geodesics-between-known-codes.md).
FRAMES_PLATEAU = (5, 1e-5)
#: ... and once this many times the plateau's window of evaluations in a row did not lower the energy by
#: its rtol (``optimize.minimize_lbfgs``'s stall: line searches lost in float32 rounding noise)
STALL_PER_WINDOW = 2
#: ``midpoint_metric`` falls back to the template's metric where a face of the mean code's surface has
#: less than this share of its template area
DEGENERATE_AREA = 1e-3


def midpoint_metric(template, faces, fields, alpha0, alpha1, weights):
    """G-bar at the mean of two codes (P,), (P,) -> (P, P) float64 numpy (``h2_metric.assembled_metric_matrix``,
    formed face by face): what ``geodesic`` preconditions with by default. The metric along a path between
    two bodies is closer to it than to the template's, so the geodesic converges in fewer iterations and
    closer to the exact path (docs/decisions/019-geodesics-between-known-codes.md).
    Where the mean code's surface has a face collapsed below DEGENERATE_AREA of its template area (its
    H2 terms divide by the area) or the matrix is not finite, the template's G-bar instead."""
    mean = torch.as_tensor((np.asarray(alpha0, np.float64) + alpha1) / 2, dtype=template.dtype, device=template.device)
    surface = decode(template, fields, mean)
    gram = None
    if face_areas(surface, faces).div(face_areas(template, faces).clamp_min(1e-300)).min() >= DEGENERATE_AREA:
        gram = h2_metric.assembled_metric_matrix(surface, faces, fields, weights)
    if gram is None or not torch.isfinite(gram).all():
        gram = h2_metric.assembled_metric_matrix(template, faces, fields, weights)
    return gram.double().cpu().numpy()


@with_one_blas_thread
def geodesic(template, faces, fields, alpha0, alpha1, weights, steps=10, max_iter=500, init=None,
             metric=None, callback=None, cancel=None, plateau=None):
    """Solve the latent boundary value problem between two codes.

    template (N, 3), faces (F, 3), fields (P, N, 3) torch tensors; alpha0, alpha1 (P,);
    steps T >= 2 time points including both ends; init (T, P) optional initial path;
    metric (P, P) a latent metric to precondition with (default G-bar at the mean of the end codes,
    ``midpoint_metric``; ``Basis.template_metric()`` costs nothing but converges slower); plateau: (k, r)
    also stop once the energy fell by less than r of itself over k iterations (e.g. FRAMES_PLATEAU), and
    once 2 k evaluations in a row did not lower it by r (STALL_PER_WINDOW). The interior is optimised in
    coordinates z with path = straight line + sqrt(dt) R^-1 z B (``time_whitening``, ``whitening``), in
    which the energy is close to |z|^2 + const, so L-BFGS converges in tens of iterations.
    """
    if steps < 2:
        raise InputError(f"a geodesic needs at least 2 time points, got {steps}")
    _check_codes(fields, alpha0, alpha1)
    monitor = Monitor("geodesic", callback, cancel)
    line = straight_path(alpha0, alpha1, steps)
    path0 = line.copy() if init is None else np.array(init, dtype=np.float64)
    p = fields.shape[0]
    if path0.shape != (steps, p):
        raise InputError(f"initial path must have shape {(steps, p)}, got {path0.shape}")
    path0[0], path0[-1] = alpha0, alpha1
    if steps == 2:
        with torch.no_grad():
            e = float(latent_path_energy(template, faces, fields, torch.as_tensor(path0, dtype=template.dtype,
                                                                                  device=template.device), weights))
        return Geodesic(path=path0, energy=e, distance=float(np.sqrt(max(e, 0.0))), iterations=0)
    if metric is None:
        metric = midpoint_metric(template, faces, fields, alpha0, alpha1, weights)
    b = whitening(metric)
    r_inv = interior_whitening(steps - 2)
    # z0 from the initial path: deviation = r_inv z b  <=>  z = r_inv^-1 deviation b^-1
    z0 = np.linalg.solve(r_inv, path0[1:-1] - line[1:-1]) @ np.linalg.inv(b)
    as_t = lambda a: torch.as_tensor(a, dtype=template.dtype, device=template.device)  # noqa: E731
    ends, inner, r_inv_t, b_t = as_t(line[[0, -1]]), as_t(line[1:-1]), as_t(r_inv), as_t(b)

    def path_of(z):
        return torch.cat([ends[:1], inner + r_inv_t @ z.reshape(steps - 2, p) @ b_t, ends[1:]])

    def energy(z):
        return latent_path_energy(template, faces, fields, path_of(z.to(template)), weights)

    monitor.report(0.0, "geodesic")
    z, value, nit = minimize_lbfgs(energy, z0.ravel(), monitor, max_iter=max_iter, message="geodesic",
                                   ftol=GEODESIC_FTOL, plateau=plateau,
                                   stall=None if plateau is None else STALL_PER_WINDOW * plateau[0])
    with torch.no_grad():
        path = path_of(torch.from_numpy(z).to(template)).double().cpu().numpy()
    path[0], path[-1] = alpha0, alpha1
    monitor.report(1.0, "geodesic done", value)
    return Geodesic(path=path, energy=value, distance=float(np.sqrt(max(value, 0.0))), iterations=nit)


def step_lengths(template, faces, fields, path, weights):
    """Riemannian length of each step of a latent path: (T, P) -> (T - 1,) numpy.

    length_k = sqrt(G-bar_{mid_k}(dalpha_k, dalpha_k)) * (T - 1): the speed on
    the unit time interval (on a geodesic all are equal; their mean is the length).
    """
    path_t = torch.as_tensor(np.asarray(path), dtype=template.dtype, device=template.device)
    steps = latent_path_energy(template, faces, fields, path_t, weights, per_step=True)
    dt = 1.0 / (path_t.shape[0] - 1)
    return np.sqrt(np.clip(steps.detach().cpu().numpy() / dt, 0, None))


#: Linear sub-steps per step when measuring a path's arc length for resampling: 4 place the frames as 16
#: do, to a negligible distance, for a quarter of the meshes evaluated
#: (docs/decisions/019-geodesics-between-known-codes.md).
RESAMPLE_REFINE = 4


#: How keyframes are paced along a path: "shape" places them at equal mean vertex displacement of the
#: decoded meshes (what an artist sees), "metric" at equal Riemannian arc length. The two differ where
#: the metric barely sees a motion that moves vertices far (a limb swinging nearly rigidly about a
#: joint, a translation: only the a0 term sees it), and there metric pacing stalls, then snaps.
PACES = ("shape", "metric")


def resample_path(template, faces, fields, path, weights, n_frames, refine=RESAMPLE_REFINE, pace="shape"):
    """Resample a latent path to n_frames evenly paced frames: (T, P) -> (n_frames, P).

    Each step is first split into ``refine`` linear sub-steps; frames are then placed at equal arc
    length of the refined path, measured by ``pace``: "shape" (default) the mean vertex displacement
    of the decoded meshes (exact on each linear sub-step, since the decoder is affine), "metric" the
    latent metric (accurate also where the metric varies along a step).
    """
    path = np.asarray(path, dtype=np.float64)
    if n_frames < 2:
        raise InputError(f"need at least 2 frames, got {n_frames}")
    if pace not in PACES:
        raise InputError(f"pace must be one of {', '.join(PACES)}, got {pace!r}")
    u = np.linspace(0.0, 1.0, refine + 1)[:-1, None, None]
    dense = (path[:-1] + u * (path[1:] - path[:-1])).transpose(1, 0, 2).reshape(-1, path.shape[1])
    dense = np.concatenate([dense, path[-1:]])
    if pace == "metric":
        lengths = step_lengths(template, faces, fields, dense, weights) / (dense.shape[0] - 1)
    else:
        lengths = vertex_step_lengths(template, fields, dense)
    s = np.concatenate([[0.0], np.cumsum(lengths)])
    if s[-1] <= 0:
        return np.repeat(path[:1], n_frames, axis=0)
    targets = np.linspace(0.0, s[-1], n_frames)
    k = np.clip(np.searchsorted(s, targets, side="right") - 1, 0, len(lengths) - 1)
    frac = np.where(lengths[k] > 0, (targets - s[k]) / np.where(lengths[k] > 0, lengths[k], 1), 0.0)
    out = dense[k] + np.clip(frac, 0, 1)[:, None] * (dense[k + 1] - dense[k])
    out[0], out[-1] = path[0], path[-1]
    return out


def vertex_step_lengths(template, fields, path):
    """Mean vertex displacement of each step of a latent path: (T, P) -> (T - 1,) numpy, in the
    template's units (the decoder is affine, so a linear step moves every vertex in a straight line)."""
    verts = decode_path(template, fields, path)
    return np.linalg.norm(np.diff(verts, axis=0), axis=2).mean(axis=1)


#: an axis counts as spanned by a basis when the least-squares fit of a unit translation along
#: it leaves less than this relative residual (the humanoid basis: z 0.12 %, x and y ~30 %)
TRANSLATION_SPAN_TOL = 0.01


def translation_codes(fields, tol=TRANSLATION_SPAN_TOL):
    """Codes of the unit translations a basis spans: fields (P, N, 3) -> axes (K,), codes (K, P), K <= 3."""
    h = torch.as_tensor(fields).detach().double().cpu().numpy().reshape(fields.shape[0], -1)
    axes, codes = [], []
    for axis in range(3):
        unit = np.zeros((fields.shape[1], 3))
        unit[:, axis] = 1.0
        beta = np.linalg.lstsq(h.T, unit.ravel(), rcond=None)[0]
        if np.linalg.norm(h.T @ beta - unit.ravel()) < tol * np.linalg.norm(unit):
            axes.append(axis)
            codes.append(beta)
    return np.array(axes, dtype=int), np.array(codes).reshape(len(codes), h.shape[0])


def anchor_path(template, fields, path, reference, fixed=(0, -1)):
    """Translate each frame of a latent path so that the body's unmoving part stays where a
    reference path (the straight line) puts it: (T, P), (T, P) -> (T, P).

    The L2 (a0) term of the metric prefers velocity fields of zero mean, so a geodesic
    keeps the body's centroid still: when an arm rises, the rest of the body sinks mid-path
    (the feet go through the floor; centimetres in the paper's body weights, millimetres in the
    ``human`` basis' motion weights). Each frame is shifted, along the
    translations the basis spans (``translation_codes``), by the coordinate-wise median
    of reference minus frame over the vertices: the median follows the majority of the
    body, which does not move in the reference, and ignores the limbs that do. The
    frames ``fixed`` are left as they are: the ends of an interpolation, the two given
    frames of an extrapolation (0, 1).
    """
    path, reference = np.asarray(path, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if path.shape != reference.shape:
        raise InputError(f"a path {path.shape} and its reference {reference.shape} must have the same shape")
    free = np.setdiff1d(np.arange(len(path)), np.arange(len(path))[list(fixed)])
    axes, codes = translation_codes(fields)
    if len(axes) == 0 or len(free) == 0:
        return path.copy()
    gap = decode_path(template, fields, reference[free]) - decode_path(template, fields, path[free])
    shift = np.median(gap[:, :, axes], axis=1)  # (T_free, K)
    out = path.copy()
    out[free] += shift @ codes
    return out


def keyframe_path(template, faces, fields, path, weights, n_frames, anchor=True, pace="shape"):
    """A solved latent path (T, P) as n_frames evenly paced keyframes (n_frames, P): anchored
    to the straight line between its ends (``anchor_path``, unless anchor is False), then
    resampled at constant speed (``resample_path``; ``pace`` "shape" or "metric")."""
    path = np.asarray(path, dtype=np.float64)
    if anchor:
        path = anchor_path(template, fields, path, straight_path(path[0], path[-1], len(path)))
    return resample_path(template, faces, fields, path, weights, n_frames, pace=pace)


def decode_path(template, fields, path):
    """Vertices of every frame of a latent path: (T, P) -> (T, N, 3) numpy."""
    path_t = torch.as_tensor(np.asarray(path), dtype=template.dtype, device=template.device)
    return decode(template, fields, path_t).detach().cpu().numpy()
