"""The initial value problem: discrete geodesic calculus (paper section 4.3).

With the one-step energy W(a, b) = (b - a)^T G-bar((a + b)/2) (b - a) (the same
midpoint rule as the boundary value problem, so shooting reproduces its
geodesics), alpha^2 continues alpha^0, alpha^1 when alpha^1 is the discrete
geodesic midpoint of alpha^0 and alpha^2, i.e. when

    Phi(alpha^2) = d/dalpha^1 [ W(alpha^0, alpha^1) + W(alpha^1, alpha^2) ] = 0.

Phi is solved by a chord-Newton iteration whose Jacobian is the dominant term
-2 G-bar(m) (m the predicted midpoint), starting from the straight continuation
2 alpha^1 - alpha^0 (exact when the metric is constant); if that stalls, the
paper's nonlinear least squares (scipy) finishes the step.
"""

import numpy as np
import scipy.linalg
import scipy.optimize
import torch

from .errors import BareEsaError, InputError
from .latent import decode, latent_metric
from .h2_metric import path_energy
from .progress import Monitor


class ShootingFailed(BareEsaError):
    """A step of the initial value problem did not converge."""


def _step_energy_grad(template, faces, fields, a, b, weights, wrt):
    """Gradient of W(a, b) w.r.t. a (wrt=0) or b (wrt=1): (P,), (P,) -> (P,) numpy."""
    ends = [torch.as_tensor(x, dtype=template.dtype, device=template.device).clone() for x in (a, b)]
    ends[wrt].requires_grad_(True)
    e = path_energy(decode(template, fields, torch.stack(ends)), faces, weights)
    (g,) = torch.autograd.grad(e, ends[wrt])
    return g.detach().cpu().numpy().astype(np.float64)


def geodesic_step(template, faces, fields, alpha0, alpha1, weights, tol=1e-10, max_iter=30):
    """alpha^2 such that alpha^1 is the discrete geodesic midpoint of alpha^0 and alpha^2: (P,) -> (P,).

    W is normalised by the step (duration 1 per step, so Phi is homogeneous of
    degree one in the step size); tol is relative to |2 G-bar beta|.
    """
    a0, a1 = np.asarray(alpha0, dtype=np.float64), np.asarray(alpha1, dtype=np.float64)
    c = _step_energy_grad(template, faces, fields, a0, a1, weights, wrt=1)  # d2 W(a0, a1)

    def phi(a2):
        return c + _step_energy_grad(template, faces, fields, a1, a2, weights, wrt=0)

    a2 = 2 * a1 - a0
    scale = np.linalg.norm(c) + 1e-300
    mid = torch.as_tensor((a1 + a2) / 2, dtype=template.dtype, device=template.device)
    gram = latent_metric(template, faces, fields, mid, weights).detach().cpu().numpy().astype(np.float64)
    chol = scipy.linalg.cho_factor(2 * gram)
    r = phi(a2)
    for _ in range(max_iter):
        if np.linalg.norm(r) <= tol * scale:
            return a2
        a2 = a2 + scipy.linalg.cho_solve(chol, r)  # J ~ -2 G-bar(m)
        r = phi(a2)
    if np.linalg.norm(r) <= 1e-6 * scale:
        return a2
    res = scipy.optimize.least_squares(phi, a2, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    if np.linalg.norm(res.fun) > 1e-6 * scale:
        raise ShootingFailed(f"a geodesic step did not converge (|Phi|/scale = {np.linalg.norm(res.fun) / scale:.2e});"
                             " use more steps or a smaller velocity")
    return res.x


def extrapolate(template, faces, fields, alpha0, alpha1, weights, n_new, callback=None, cancel=None):
    """Continue the discrete geodesic through alpha^0, alpha^1 by n_new steps: -> (n_new + 2, P).

    template (N, 3), faces (F, 3), fields (P, N, 3) torch tensors; codes (P,).
    """
    p = fields.shape[0]
    for code in (alpha0, alpha1):
        code = np.asarray(code)
        if code.shape != (p,) or not np.isfinite(code).all():
            raise InputError(f"extrapolation needs two finite codes of {p} coefficients, got shape {code.shape}")
    if n_new < 0:
        raise InputError(f"number of new steps must be >= 0, got {n_new}")
    monitor = Monitor("extrapolate", callback, cancel)
    path = [np.asarray(alpha0, dtype=np.float64), np.asarray(alpha1, dtype=np.float64)]
    for k in range(n_new):
        monitor.check()
        monitor.report(k / max(n_new, 1), f"step {k + 1}/{n_new}")
        path.append(geodesic_step(template, faces, fields, path[-2], path[-1], weights))
    monitor.report(1.0, "done")
    return np.stack(path)


def shoot(template, faces, fields, alpha0, velocity, weights, steps=10, callback=None, cancel=None):
    """exp map: geodesic from alpha0 with initial velocity over unit time, steps >= 1: -> (steps + 1, P)."""
    if steps < 1:
        raise InputError(f"shooting needs at least one step, got {steps}")
    alpha0 = np.asarray(alpha0, dtype=np.float64)
    alpha1 = alpha0 + np.asarray(velocity, dtype=np.float64) / steps
    return extrapolate(template, faces, fields, alpha0, alpha1, weights, steps - 1, callback, cancel)


def initial_velocity(path):
    """Initial velocity of a discrete latent path on unit time: (T, P) -> (P,) (the log map of a BVP path)."""
    path = np.asarray(path)
    return (path[1] - path[0]) * (path.shape[0] - 1)
