"""The initial value problem: discrete geodesic calculus (paper section 4.3).

With the one-step energy W(a, b) = (b - a)^T G-bar((a + b)/2) (b - a) (the same
midpoint rule as the boundary value problem, so shooting reproduces its
geodesics), alpha^2 continues alpha^0, alpha^1 when alpha^1 is the discrete
geodesic midpoint of alpha^0 and alpha^2, i.e. when

    Phi(alpha^2) = d/dalpha^1 [ W(alpha^0, alpha^1) + W(alpha^1, alpha^2) ] = 0.

Phi costs one energy gradient (two meshes); its Jacobian is -2 G-bar(m) (m the
midpoint) up to terms of the order of the step. The Jacobian is therefore
approximated from a latent metric matrix that is computed rarely: once per
extrapolation and again only when the iteration stops contracting (the metric
varies slowly along the path), refined between refreshes by Broyden updates.
A step has converged when the remaining correction is below ``tol`` times the
step length, both measured in the metric. Strongly curved steps, where that
iteration does not contract, are finished by a damped Newton method with the
exact Jacobian (double backpropagation; P energy gradients per iteration).
"""

import numpy as np
import torch

from .errors import InputError, ShootingFailed
from .geodesics import anchor_path, geodesic
from .h2_metric import H2Weights, path_energy
from .h2_metric import assembled_metric_matrix as jacobian_metric
from .latent import decode
from .progress import Monitor

#: A step is accepted when the quasi-Newton correction, in the metric norm, is below
#: STEP_TOL x the step length in the same norm (rounding noise sits near 1e-11).
STEP_TOL = 1e-8
#: The metric matrix is recomputed when one iteration shrinks the correction by less than this.
REFRESH_RATIO = 0.3
#: Metric eigenvalues below NULL_RTOL x the largest are null directions (dependent fields).
NULL_RTOL = 1e-12


def _check_codes(p, **codes):
    """Raise InputError unless every code is a finite (p,) vector; -> dict of float64 arrays."""
    out = {}
    for name, code in codes.items():
        try:
            c = np.asarray(code, dtype=np.float64)
        except (TypeError, ValueError):
            c = None
        if c is None or c.shape != (p,):
            raise InputError(f"{name} must be a latent code of {p} coefficients, got shape {np.shape(code)}")
        if not np.isfinite(c).all():
            raise InputError(f"{name} contains {int((~np.isfinite(c)).sum())} NaN or infinite coefficients")
        out[name] = c
    return out


class _Stepper:
    """Consecutive geodesic steps of one problem sharing an approximate inverse Jacobian."""

    def __init__(self, template, faces, fields, weights, tol=STEP_TOL, max_iter=40, refresh=REFRESH_RATIO):
        for what, x in (("template", template), ("fields", fields)):
            if not torch.isfinite(x).all():
                raise InputError(f"NaN or infinite values in the basis {what}; check the basis file")
        self.template, self.faces, self.fields = template, faces, fields
        self.weights = H2Weights.parse(weights)
        self.p = fields.shape[0]
        floor = 1e3 * torch.finfo(template.dtype).eps  # reachable in the tensors' precision
        self.tol, self.max_iter, self.refresh = max(float(tol), floor), int(max_iter), float(refresh)
        self.metric = None  # G (P, P) numpy, the norm of the convergence test
        self.inv_jac = None  # H ~ (dPhi/dalpha^2)^-1 = -(2 G)^-1, Broyden-updated
        self.n_grad = self.n_metric = 0

    def grads(self, a, b):
        """(dW/da, dW/db) at codes a, b (P,) -> two (P,) float64 arrays; ShootingFailed if not finite."""
        ends = torch.as_tensor(np.stack([a, b]), dtype=self.template.dtype, device=self.template.device)
        ends.requires_grad_(True)
        with torch.enable_grad():
            e = path_energy(decode(self.template, self.fields, ends), self.faces, self.weights)
            (g,) = torch.autograd.grad(e, ends)
        self.n_grad += 1
        g = g.detach().double().cpu().numpy()
        if not (np.isfinite(g).all() and torch.isfinite(e)):
            raise ShootingFailed("the H2 energy of a step is not finite: the decoded meshes degenerate "
                                 "(coefficients too large for the basis); use a smaller velocity or fewer steps")
        return g[0], g[1]

    def refresh_jacobian(self, mid):
        """Metric matrix at the latent midpoint mid (P,) and the chord inverse Jacobian -(2 G)^-1."""
        m = torch.as_tensor(mid, dtype=self.template.dtype, device=self.template.device)
        with torch.no_grad():
            gram = jacobian_metric(decode(self.template, self.fields, m), self.faces, self.fields,
                                   self.weights).double().cpu().numpy()
        self.n_metric += 1
        if not np.isfinite(gram).all():
            raise ShootingFailed("the latent metric is not finite along the path: the decoded mesh degenerates; "
                                 "use a smaller velocity or fewer steps")
        evals, evecs = np.linalg.eigh(gram)
        if not evals[-1] > 0:
            raise ShootingFailed("the latent metric matrix is zero: the basis fields do not deform the mesh")
        # pseudo-inverse: directions the metric does not see (linearly dependent fields) are not moved
        keep = evals > NULL_RTOL * evals[-1]
        self.metric = gram
        self.inv_jac = -(evecs[:, keep] / (2 * evals[keep])) @ evecs[:, keep].T

    def norm(self, v):
        """sqrt(v^T G v), the metric length of a latent vector."""
        return float(np.sqrt(abs(v @ self.metric @ v)))

    def jacobian(self, a1, a2):
        """Exact dPhi/dalpha^2 = d2 W / da db at (a1, a2) by double backpropagation: -> (P, P)."""
        as_t = lambda a: torch.as_tensor(a, dtype=self.template.dtype, device=self.template.device)  # noqa: E731
        start = as_t(a1)

        def dw_da(end):
            ends = torch.stack([start, end])
            e = path_energy(decode(self.template, self.fields, ends), self.faces, self.weights)
            return torch.autograd.grad(e, ends, create_graph=True)[0][0]

        with torch.enable_grad():
            jac = torch.autograd.functional.jacobian(dw_da, as_t(a2)).double().cpu().numpy()
        self.n_grad += self.p
        if not np.isfinite(jac).all():
            raise ShootingFailed("the Jacobian of a geodesic step is not finite: the decoded meshes degenerate; "
                                 "use a smaller velocity or fewer steps")
        return jac

    def step(self, a0, a1, guess=None, c=None):
        """alpha^2 continuing a0, a1 (P,) -> (alpha^2, dW/da at (alpha^1, alpha^2) for the next step).

        guess: initial alpha^2 (default 2 a1 - a0); c: dW/db at (a0, a1) if already known.
        """
        if c is None:
            c = self.grads(a0, a1)[1]
        x = 2 * a1 - a0 if guess is None else np.asarray(guess, dtype=np.float64)
        try:
            return self._quasi_newton(a0, a1, x, c)
        except _Diverged as div:
            return self._newton(a0, a1, div.best, c)

    def _quasi_newton(self, a0, a1, x, c):
        """Broyden iteration from the metric's chord Jacobian; raises _Diverged(best x) when it fails."""
        fresh = self.inv_jac is None
        if fresh:
            self.refresh_jacobian((a1 + x) / 2)
        length = self.norm(a1 - a0)
        g_a, g_b = self.grads(a1, x)
        r, prev, best = c + g_a, None, (np.inf, x)
        for _ in range(self.max_iter):
            d = -self.inv_jac @ r
            err = self.norm(d)
            if not (np.isfinite(err) and np.isfinite(d).all()):
                raise _Diverged(best[1])
            best = min(best, (err, x), key=lambda b: b[0])
            if err <= self.tol * length:
                return x, g_b
            if prev is not None and err > self.refresh * prev:
                if fresh and err > prev:  # diverging although the metric is current: far from linear
                    raise _Diverged(best[1])
                if not fresh:
                    self.refresh_jacobian((a1 + x) / 2)  # the metric moved: recompute it here
                    fresh, prev = True, None
                    continue
            prev = err
            try:
                g_a, g_b = self.grads(a1, x + d)
            except ShootingFailed:
                raise _Diverged(best[1]) from None
            x, y, r = x + d, c + g_a - r, c + g_a
            hy = self.inv_jac @ y
            gd = self.metric @ d  # Broyden in the metric inner product: invariant to the scale of the fields
            denom = gd @ hy
            if abs(denom) > 1e-14 * np.linalg.norm(gd) * np.linalg.norm(hy):
                self.inv_jac += np.outer(d - hy, gd @ self.inv_jac) / denom
        raise _Diverged(best[1])

    def _newton(self, a0, a1, x, c, max_iter=8):
        """Damped Newton with the exact Jacobian (the fallback for strongly curved steps) -> (alpha^2, next c)."""
        self.refresh_jacobian((a1 + x) / 2)
        chord = self.inv_jac
        length = self.norm(a1 - a0)
        merit = lambda r: self.norm(chord @ r)  # noqa: E731  the residual in the metric's dual norm
        r = c + self.grads(a1, x)[0]
        for _ in range(max_iter):
            jac = self.jacobian(a1, x)
            d = -np.linalg.lstsq(jac, r, rcond=None)[0]
            if self.norm(d) <= self.tol * length:
                x = x + d
                g_a, g_b = self.grads(a1, x)
                self.inv_jac = np.linalg.pinv(jac)  # the exact Jacobian starts the next step's Broyden model
                return x, g_b
            t, m0 = 1.0, merit(r)
            while t >= 1 / 64:  # backtracking on the metric-dual residual
                try:
                    r_new = c + self.grads(a1, x + t * d)[0]
                    if merit(r_new) < (1 - 1e-4 * t) * m0:
                        break
                except ShootingFailed:
                    pass
                t /= 2
            else:
                break
            x, r = x + t * d, r_new
        raise ShootingFailed(f"a geodesic step did not converge (remaining correction {self.norm(d) / length:.1e} "
                             "of the step length in the metric norm): the motion bends too fast for this step "
                             "size; use smaller steps (more substeps when extrapolating, more steps when shooting)")


class _Diverged(Exception):
    """Internal: quasi-Newton failed; carries the best iterate for the Newton fallback."""

    def __init__(self, best):
        super().__init__("quasi-Newton diverged")
        self.best = best


def geodesic_step(template, faces, fields, alpha0, alpha1, weights, tol=STEP_TOL, max_iter=40):
    """alpha^2 such that alpha^1 is the discrete geodesic midpoint of alpha^0 and alpha^2: (P,) -> (P,).

    W is normalised by the step (duration 1 per step, so Phi is homogeneous of
    degree one in the step size); tol bounds the remaining correction relative to
    the step length |alpha^1 - alpha^0|, both in the metric norm. Raises
    InputError for non-finite codes, ShootingFailed if the step cannot be solved.
    """
    codes = _check_codes(fields.shape[0], alpha0=alpha0, alpha1=alpha1)
    stepper = _Stepper(template, faces, fields, weights, tol, max_iter)
    return stepper.step(codes["alpha0"], codes["alpha1"])[0]


def extrapolate(template, faces, fields, alpha0, alpha1, weights, n_new, callback=None, cancel=None,
                tol=STEP_TOL, substeps=1, anchor=False):
    """Continue the discrete geodesic through alpha^0, alpha^1 by n_new steps: -> (n_new + 2, P).

    template (N, 3), faces (F, 3), fields (P, N, 3) torch tensors; codes (P,). The
    steps share one quasi-Newton Jacobian (the metric matrix is recomputed only
    when the iteration stops contracting) and start from a quadratic predictor.
    substeps > 1 refines time: the boundary value geodesic alpha^0 -> alpha^1 with
    substeps intervals is continued by n_new * substeps steps, and every substeps-th
    point is returned (strongly curved motions need it: a step that does not
    converge raises ShootingFailed). anchor: keep the body's unmoving part where the
    straight latent line alpha^0 + k (alpha^1 - alpha^0) puts it (``geodesics.anchor_path``;
    the predicted frames only).
    """
    p = fields.shape[0]
    try:
        codes = _check_codes(p, alpha0=alpha0, alpha1=alpha1)
    except InputError as err:
        raise InputError(f"extrapolation needs two finite codes of {p} coefficients: {err}") from None
    if n_new < 0:
        raise InputError(f"number of new steps must be >= 0, got {n_new}")
    if int(substeps) != substeps or substeps < 1:
        raise InputError(f"substeps must be a positive integer, got {substeps}")
    substeps = int(substeps)
    monitor = Monitor("extrapolate", callback, cancel)
    path = [codes["alpha0"], codes["alpha1"]]
    if substeps > 1 and n_new > 0:
        monitor.report(0.0, "geodesic through the two given codes")
        path = list(geodesic(template, faces, fields, path[0], path[1], weights, steps=substeps + 1,
                             cancel=cancel).path[-2:])
        path[-1] = codes["alpha1"]
    stepper = _Stepper(template, faces, fields, weights, tol)
    c = None
    total = n_new * substeps
    for k in range(total):
        monitor.check()
        monitor.report(k / max(total, 1), f"step {k + 1}/{total}")
        guess = 3 * path[-1] - 3 * path[-2] + path[-3] if len(path) >= 3 else None
        x, c = stepper.step(path[-2], path[-1], guess, c)
        path.append(x)
    monitor.report(1.0, "done")
    out = np.stack([codes["alpha0"], codes["alpha1"]] + path[1 + substeps::substeps])
    return anchor_extrapolation(template, fields, out) if anchor else out


def anchor_extrapolation(template, fields, path):
    """An extrapolated path (T, P) with its predicted frames anchored (``geodesics.anchor_path``)
    to the straight latent line alpha^0 + k (alpha^1 - alpha^0) through its two given frames."""
    path = np.asarray(path, dtype=np.float64)
    line = path[0] + np.arange(len(path))[:, None] * (path[1] - path[0])
    return anchor_path(template, fields, path, line, fixed=(0, 1))


def shoot(template, faces, fields, alpha0, velocity, weights, steps=10, callback=None, cancel=None):
    """exp map: geodesic from alpha0 with initial velocity over unit time, steps >= 1: -> (steps + 1, P)."""
    if steps < 1:
        raise InputError(f"shooting needs at least one step, got {steps}")
    codes = _check_codes(fields.shape[0], alpha0=alpha0, velocity=velocity)
    alpha1 = codes["alpha0"] + codes["velocity"] / steps
    return extrapolate(template, faces, fields, codes["alpha0"], alpha1, weights, steps - 1, callback, cancel)


def initial_velocity(path):
    """Initial velocity of a discrete latent path on unit time: (T, P) -> (P,) (the log map of a BVP path)."""
    path = np.asarray(path)
    return (path[1] - path[0]) * (path.shape[0] - 1)
