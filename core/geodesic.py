"""Geodesics and distances in the latent space (paper section 4.2).

The boundary value problem: minimise the discrete path energy
sum_k dalpha_k^T G-bar(mid_k) dalpha_k / dt over the interior points of a
latent path with fixed endpoints; the distance is sqrt of the optimal energy.
"""

from dataclasses import dataclass

import numpy as np
import torch

from .errors import InputError
from .latent import decode, latent_path_energy
from .optimize import minimize_lbfgs
from .progress import Monitor


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


def geodesic(template, faces, fields, alpha0, alpha1, weights, steps=10, max_iter=500, init=None,
             callback=None, cancel=None):
    """Solve the latent boundary value problem between two codes.

    template (N, 3), faces (F, 3), fields (P, N, 3) torch tensors; alpha0, alpha1 (P,);
    steps T >= 2 time points including both ends; init (T, P) optional initial path.
    """
    if steps < 2:
        raise InputError(f"a geodesic needs at least 2 time points, got {steps}")
    _check_codes(fields, alpha0, alpha1)
    monitor = Monitor("geodesic", callback, cancel)
    path0 = straight_path(alpha0, alpha1, steps) if init is None else np.array(init, dtype=np.float64)
    if path0.shape != (steps, fields.shape[0]):
        raise InputError(f"initial path must have shape {(steps, fields.shape[0])}, got {path0.shape}")
    path0[0], path0[-1] = alpha0, alpha1
    ends = torch.as_tensor(path0[[0, -1]], dtype=template.dtype, device=template.device)
    p = fields.shape[0]

    def energy(x):
        interior = x.to(template.dtype).reshape(steps - 2, p)
        path = torch.cat([ends[:1], interior, ends[1:]])
        return latent_path_energy(template, faces, fields, path, weights)

    monitor.report(0.0, "geodesic")
    x, value, nit = minimize_lbfgs(energy, path0[1:-1].ravel(), monitor, max_iter=max_iter, message="geodesic")
    path0[1:-1] = x.reshape(steps - 2, p)
    monitor.report(1.0, "geodesic done", value)
    return Geodesic(path=path0, energy=value, distance=float(np.sqrt(max(value, 0.0))), iterations=nit)


def step_lengths(template, faces, fields, path, weights):
    """Riemannian length of each step of a latent path: (T, P) -> (T - 1,) numpy.

    length_k = sqrt(G-bar_{mid_k}(dalpha_k, dalpha_k)) * (T - 1): the speed on
    the unit time interval (on a geodesic all are equal; their mean is the length).
    """
    path_t = torch.as_tensor(np.asarray(path), dtype=template.dtype, device=template.device)
    steps = latent_path_energy(template, faces, fields, path_t, weights, per_step=True)
    dt = 1.0 / (path_t.shape[0] - 1)
    return np.sqrt(np.clip(steps.detach().cpu().numpy() / dt, 0, None))


def resample_path(template, faces, fields, path, weights, n_frames, refine=16):
    """Resample a latent path to n_frames at constant metric speed: (T, P) -> (n_frames, P).

    Each step is first split into ``refine`` linear sub-steps so that the arc
    length (measured with the latent metric) is accurate also where the metric
    varies along a step; frames are then placed at equal arc length, so
    keyframes come out evenly paced.
    """
    path = np.asarray(path, dtype=np.float64)
    if n_frames < 2:
        raise InputError(f"need at least 2 frames, got {n_frames}")
    u = np.linspace(0.0, 1.0, refine + 1)[:-1, None, None]
    dense = (path[:-1] + u * (path[1:] - path[:-1])).transpose(1, 0, 2).reshape(-1, path.shape[1])
    dense = np.concatenate([dense, path[-1:]])
    lengths = step_lengths(template, faces, fields, dense, weights) / (dense.shape[0] - 1)
    s = np.concatenate([[0.0], np.cumsum(lengths)])
    if s[-1] <= 0:
        return np.repeat(path[:1], n_frames, axis=0)
    targets = np.linspace(0.0, s[-1], n_frames)
    k = np.clip(np.searchsorted(s, targets, side="right") - 1, 0, len(lengths) - 1)
    frac = np.where(lengths[k] > 0, (targets - s[k]) / np.where(lengths[k] > 0, lengths[k], 1), 0.0)
    out = dense[k] + np.clip(frac, 0, 1)[:, None] * (dense[k + 1] - dense[k])
    out[0], out[-1] = path[0], path[-1]
    return out


def decode_path(template, fields, path):
    """Vertices of every frame of a latent path: (T, P) -> (T, N, 3) numpy."""
    path_t = torch.as_tensor(np.asarray(path), dtype=template.dtype, device=template.device)
    return decode(template, fields, path_t).detach().cpu().numpy()
