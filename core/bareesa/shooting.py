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
step length, both measured in the metric (or below ``accept_tol`` when the
iteration stalls there). Where a step does not converge, or changes the metric
speed (which a geodesic keeps), ``extrapolate`` and ``shoot`` refine time: the step
is halved, from the discrete geodesic midpoint of the last two points, and
re-solved, down to 1/MAX_SUBSTEPS of a frame (``ShootingReport`` says where); a step solved there
is kept even when its speed still changes (near a creased, almost degenerate body the metric
varies that fast: ``ShootingReport.speed_relaxed`` names those frames). A
single step (``geodesic_step``) that quasi-Newton cannot solve is finished by a
damped Newton method with the exact Jacobian (double backpropagation; P energy
gradients per iteration), which is also the last resort at the finest refinement.
"""

from dataclasses import dataclass, field

import numpy as np
import torch

from .errors import FrameRejected, InputError, ShootingFailed
from .geodesics import anchor_path, geodesic
from .h2_metric import H2Weights, path_energy
from .h2_metric import assembled_metric_matrix as jacobian_metric
from .latent import decode
from .progress import Monitor
from .threads import with_one_blas_thread

#: A step is accepted when the quasi-Newton correction, in the metric norm, is below
#: STEP_TOL x the step length in the same norm (rounding noise sits near 1e-11).
STEP_TOL = 1e-8
#: A step whose iteration stalls before STEP_TOL is accepted when its remaining correction is below
#: ACCEPT_TOL x the step length: the error it leaves is below the time discretisation's own
#: (``python -m bench.shooting_tolerance``; docs/decisions/013-shooting-tolerance-and-step-refinement.md).
ACCEPT_TOL = 1e-4
#: A step that does not converge is halved, down to 1/MAX_SUBSTEPS of a frame ...
MAX_SUBSTEPS = 64
#: ... and so is a step whose metric speed differs from the previous step's by more than this share.
#: A discrete geodesic keeps its speed up to O(h^3), so a larger change means a step too long for the
#: curvature (docs/decisions/013-shooting-tolerance-and-step-refinement.md).
SPEED_TOL = 0.01
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

    def __init__(self, template, faces, fields, weights, tol=STEP_TOL, max_iter=40, refresh=REFRESH_RATIO,
                 accept_tol=None):
        for what, x in (("template", template), ("fields", fields)):
            if not torch.isfinite(x).all():
                raise InputError(f"NaN or infinite values in the basis {what}; check the basis file")
        self.template, self.faces, self.fields = template, faces, fields
        self.weights = H2Weights.parse(weights)
        self.p = fields.shape[0]
        floor = 1e3 * torch.finfo(template.dtype).eps  # reachable in the tensors' precision
        self.tol, self.max_iter, self.refresh = max(float(tol), floor), int(max_iter), float(refresh)
        self.accept_tol = self.tol if accept_tol is None else max(float(accept_tol), self.tol)
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

    def speed_change(self, a0, a1, a2):
        """|speed(a1 -> a2) / speed(a0 -> a1) - 1| of two consecutive steps (P,), speeds in the metric at
        each step's midpoint (a discrete geodesic keeps its speed up to the discretisation)."""
        path = torch.as_tensor(np.stack([a0, a1, a2]), dtype=self.template.dtype, device=self.template.device)
        with torch.no_grad():
            w = path_energy(decode(self.template, self.fields, path), self.faces, self.weights, per_step=True)
        w = w.double().cpu().numpy()
        if not np.isfinite(w).all():
            raise StepNotConverged(np.inf, nonfinite=True)
        return abs(float(np.sqrt(w[1] / w[0])) - 1.0) if w[0] > 0 else (0.0 if w[1] == 0 else np.inf)

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

    def step(self, a0, a1, guess=None, c=None, newton=True):
        """alpha^2 continuing a0, a1 (P,) -> (alpha^2, dW/da at (alpha^1, alpha^2) for the next step,
        remaining correction relative to the step length).

        guess: initial alpha^2 (default 2 a1 - a0); c: dW/db at (a0, a1) if already known; newton: try
        the exact-Jacobian Newton fallback when quasi-Newton fails (P gradients per iteration: a caller
        that can halve the step instead does not). A step is accepted at ``tol``, or at ``accept_tol``
        when the iterations get no further; otherwise StepNotConverged (a ShootingFailed) carries the
        smallest correction reached.
        """
        if c is None:
            c = self.grads(a0, a1)[1]
        x = 2 * a1 - a0 if guess is None else np.asarray(guess, dtype=np.float64)
        fresh = self.inv_jac is None
        if fresh:
            self.refresh_jacobian((a1 + x) / 2)
        length = self.norm(a1 - a0)
        try:
            return self._quasi_newton(a1, x, c, length, fresh)
        except _Diverged as div:
            best = div
        if best.correction <= self.accept_tol:
            return self._accept(a1, best.x, best.correction)
        if not newton:
            raise StepNotConverged(best.correction, best.nonfinite)
        try:
            return self._newton(a1, best.x, c, length)
        except ShootingFailed:  # a non-finite energy or Jacobian on the way
            best.nonfinite = True
        except _Diverged as div:
            if div.correction < best.correction:
                best = div
        if best.correction <= self.accept_tol:
            return self._accept(a1, best.x, best.correction)
        raise StepNotConverged(best.correction, best.nonfinite)

    def _accept(self, a1, x, correction):
        """The best iterate of a step that stalled within ``accept_tol``: -> as ``step``."""
        return x, self.grads(a1, x)[1], correction

    def _quasi_newton(self, a1, x, c, length, fresh):
        """Broyden iteration from the metric's chord Jacobian (``fresh``: just computed at this step);
        raises _Diverged(best) when it fails."""
        g_a, g_b = self.grads(a1, x)
        r, prev, best = c + g_a, None, _Diverged(np.inf, x)
        for _ in range(self.max_iter):
            d = -self.inv_jac @ r
            err = self.norm(d)
            if not (np.isfinite(err) and np.isfinite(d).all()):
                raise best.flag_nonfinite()
            if err / length < best.correction:
                best = _Diverged(err / length, x)
            if err <= self.tol * length:
                return x, g_b, err / length
            if prev is not None and err > self.refresh * prev:
                if fresh and err > prev:  # diverging although the metric is current: far from linear
                    raise best
                if not fresh:
                    self.refresh_jacobian((a1 + x) / 2)  # the metric moved: recompute it here
                    fresh, prev = True, None
                    continue
            prev = err
            try:
                g_a, g_b = self.grads(a1, x + d)
            except ShootingFailed:
                raise best.flag_nonfinite() from None
            x, y, r = x + d, c + g_a - r, c + g_a
            hy = self.inv_jac @ y
            gd = self.metric @ d  # Broyden in the metric inner product: invariant to the scale of the fields
            denom = gd @ hy
            if abs(denom) > 1e-14 * np.linalg.norm(gd) * np.linalg.norm(hy):
                self.inv_jac += np.outer(d - hy, gd @ self.inv_jac) / denom
        raise best

    def _newton(self, a1, x, c, length, max_iter=8):
        """Damped Newton with the exact Jacobian (the fallback for strongly curved steps) -> as ``step``;
        raises _Diverged(best) when it does not reach ``tol``."""
        self.refresh_jacobian((a1 + x) / 2)
        chord = self.inv_jac
        merit = lambda r: self.norm(chord @ r)  # noqa: E731  the residual in the metric's dual norm
        r = c + self.grads(a1, x)[0]
        best = _Diverged(np.inf, x)
        for _ in range(max_iter):
            jac = self.jacobian(a1, x)
            d = -np.linalg.lstsq(jac, r, rcond=None)[0]
            err = self.norm(d) / length
            if not np.isfinite(err):
                raise best.flag_nonfinite()
            if err < best.correction:
                best = _Diverged(err, x)
            if err <= self.tol:
                x = x + d
                g_a, g_b = self.grads(a1, x)
                self.inv_jac = np.linalg.pinv(jac)  # the exact Jacobian starts the next step's Broyden model
                return x, g_b, err
            t, m0 = 1.0, merit(r)
            while t >= 1 / 64:  # backtracking on the metric-dual residual
                try:
                    r_new = c + self.grads(a1, x + t * d)[0]
                    if merit(r_new) < (1 - 1e-4 * t) * m0:
                        break
                except ShootingFailed:
                    best.nonfinite = True
                t /= 2
            else:
                break
            x, r = x + t * d, r_new
        raise best


class _Diverged(Exception):
    """Internal: an iteration of a step failed; carries its best iterate and that iterate's remaining
    correction (relative to the step length), and whether it met non-finite energies."""

    def __init__(self, correction, x, nonfinite=False):
        super().__init__("the iteration of a geodesic step diverged")
        self.correction, self.x, self.nonfinite = float(correction), x, nonfinite

    def flag_nonfinite(self):
        self.nonfinite = True
        return self


class StepNotConverged(ShootingFailed):
    """A geodesic step that no iteration could solve to ``accept_tol``: the smallest remaining
    correction reached (relative to the step length), whether non-finite energies were met, and
    ``reason``, the message without advice (callers that refine the step add their own)."""

    def __init__(self, correction, nonfinite=False):
        if nonfinite:
            self.reason = (f"a geodesic step met energies that are not finite (best remaining correction "
                           f"{correction:.1e}): the decoded meshes degenerate")
            advice = "the coefficients are too large for the basis; use a smaller velocity or fewer steps"
        else:
            self.reason = (f"a geodesic step did not converge (remaining correction {correction:.1e} of the step "
                           "length in the metric norm)")
            advice = "the motion bends too fast for this step size; use smaller steps"
        super().__init__(f"{self.reason}: {advice}")
        self.correction, self.nonfinite = correction, nonfinite


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


@dataclass
class ShootingReport:
    """How an initial value problem was solved: for each new frame the number of steps it was split
    into (1 = one discrete step per frame; the time refinement), how many times a step was halved,
    the largest remaining correction accepted (relative to its step length, metric norm), the largest
    relative change of metric speed between two consecutive steps, and the energy gradients and metric
    matrices it took; speed_relaxed the frames where a step solved at the finest refinement was kept
    although it changed the metric speed by more than ``SPEED_TOL``; frozen the frames finished in the
    metric frozen at their last point, where no step converged even at the finest refinement."""

    substeps: list
    refinements: int
    max_correction: float
    max_speed_change: float
    n_grad: int
    n_metric: int
    speed_relaxed: list = field(default_factory=list)
    frozen: list = field(default_factory=list)

    def to_json(self):
        """JSON-ready dict of the report."""
        return {"substeps": [int(k) for k in self.substeps], "refinements": int(self.refinements),
                "max_correction": float(self.max_correction),
                "max_speed_change": float(self.max_speed_change), "energy_gradients": int(self.n_grad),
                "metric_matrices": int(self.n_metric), "speed_relaxed": [int(k) for k in self.speed_relaxed],
                "frozen": [int(k) for k in self.frozen]}


def _march(stepper, start, n_frames, substeps, midpoint, monitor, max_substeps, speed_tol, frame_check=None,
           frozen=False):
    """Continue the discrete geodesic through start = (prev, cur), 1/substeps of a frame apart, by n_frames
    frames: -> (frames (n_frames, P), ShootingReport). frame_check, frozen: see ``extrapolate``.

    A step is refused when it does not converge or when it changes the metric speed by more than
    ``speed_tol`` (a geodesic keeps its speed: a jump means the step is too long for the curvature,
    even where its equation was solved). A refused step is halved (the new previous point is the
    discrete geodesic midpoint of the last two, ``midpoint``) and re-solved from that last good state,
    down to 1/max_substeps of a frame; the finer spacing is kept for the rest of the path. There, a step
    whose equation was solved is kept even when it changes the speed (recorded in ``speed_relaxed``):
    near a joint creased almost flat the speed change at the finest refinement is noise from step to step,
    not a step too long (docs/decisions/013-shooting-tolerance-and-step-refinement.md);
    only a step that does not converge there fails, or, with ``frozen``, finishes its frame as the
    geodesic of the metric frozen at the last point does (a straight latent step at the last velocity),
    after which the next frame is shot again from the frame spacing (``ShootingReport.frozen``).
    """
    history, level, c = list(start), substeps, None
    frames, per_frame, refinements, worst, fastest, relaxed, held = [], [], 0, 0.0, 0.0, [], []
    for k in range(n_frames):
        remaining = level
        while remaining:
            monitor.check()
            guess = 3 * history[-1] - 3 * history[-2] + history[-3] if len(history) >= 3 else None
            try:
                x, c, correction = stepper.step(history[-2], history[-1], guess, c, newton=2 * level > max_substeps)
                change = stepper.speed_change(history[-2], history[-1], x)
                problem = None if change <= speed_tol else (
                    f"a step changes the metric speed of the geodesic by {change:.0%} (a geodesic keeps its speed)")
                if problem is not None and 2 * level > max_substeps:  # solved at the finest step: kept
                    problem = None
                    relaxed += [k + 1] if k + 1 not in relaxed else []
            except StepNotConverged as err:
                problem = err.reason
            if problem is None:
                worst, fastest = max(worst, correction), max(fastest, change)
                history.append(x)
                remaining -= 1
                continue
            if 2 * level > max_substeps and frozen:
                velocity = history[-1] - history[-2]
                end = history[-1] + remaining * velocity
                history, c, remaining = [end - velocity * (level / substeps), end], None, 0
                level = substeps
                held.append(k + 1)
                monitor.report(k / n_frames, f"frame {k + 1}/{n_frames}: continued in the metric frozen there")
                continue
            if 2 * level > max_substeps:
                fewer = f"ask for at most {k} frame{'s' if k > 1 else ''} or " if k else ""
                raise ShootingFailed(f"frame {k + 1} of {n_frames}: {problem} even at 1/{level} of the frame step; "
                                     "the motion leaves the part of the latent space where the basis deforms "
                                     f"smoothly: {fewer}start from closer codes (a smaller velocity)",
                                     frames=np.array(frames).reshape(k, stepper.p))
            history, c = [midpoint(history[-2], history[-1]), history[-1]], None
            level, remaining, refinements = 2 * level, 2 * remaining, refinements + 1
            monitor.report(k / n_frames, f"frame {k + 1}/{n_frames}: step refined to 1/{level}")
        history = history[-3:]
        reason = None if frame_check is None else frame_check(history[-1])
        if reason:
            raise FrameRejected(f"frame {k + 1} of {n_frames}: {reason}", frames=np.array(frames).reshape(k, stepper.p))
        frames.append(history[-1])
        per_frame.append(level)
        monitor.report((k + 1) / n_frames, f"frame {k + 1}/{n_frames}" + (f" (1/{level} steps)" if level > 1 else ""))
    report = ShootingReport(per_frame, refinements, worst, fastest, stepper.n_grad, stepper.n_metric, relaxed, held)
    return np.array(frames).reshape(n_frames, -1), report


@with_one_blas_thread
def extrapolate(template, faces, fields, alpha0, alpha1, weights, n_new, callback=None, cancel=None,
                tol=STEP_TOL, substeps=1, anchor=False, accept_tol=ACCEPT_TOL, max_substeps=MAX_SUBSTEPS,
                speed_tol=SPEED_TOL, with_report=False, frame_check=None, frozen=False):
    """Continue the discrete geodesic through alpha^0, alpha^1 by n_new steps: -> (n_new + 2, P)
    (and a ShootingReport when ``with_report``).

    template (N, 3), faces (F, 3), fields (P, N, 3) torch tensors; codes (P,). The
    steps share one quasi-Newton Jacobian (the metric matrix is recomputed only
    when the iteration stops contracting) and start from a quadratic predictor.
    substeps > 1 refines time from the start: the boundary value geodesic alpha^0 -> alpha^1
    with substeps intervals is continued by n_new * substeps steps, and every substeps-th
    point is returned. Where a step does not converge (a strongly curved motion) it is halved
    automatically, down to 1/max_substeps of a frame (``ShootingReport.substeps`` says where),
    and so is a step that changes the metric speed by more than ``speed_tol``; a step is accepted
    at ``tol`` or, when the iteration stalls, at ``accept_tol`` (see ACCEPT_TOL).
    ShootingFailed names the frame that could not be reached. anchor: keep the body's unmoving part
    where the straight latent line alpha^0 + k (alpha^1 - alpha^0) puts it (``geodesics.anchor_path``;
    the predicted frames only). frame_check: code (P,) -> None, or why a new frame is refused: the shot
    stops there with FrameRejected (naming the frame), so that a caller that would discard the whole
    path does not pay for the rest of it (``workflows.sample_bodies``: a joint creased flat). frozen: where no
    step converges even at the finest refinement, finish that frame in the metric frozen at its last point
    (the geodesic of a constant metric: a straight latent step at the last velocity) and shoot on from the
    frame after it (``ShootingReport.frozen`` names those frames) instead of failing.
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
    stepper = _Stepper(template, faces, fields, weights, tol, accept_tol=accept_tol)

    def midpoint(a, b):
        """The discrete geodesic midpoint of two codes (a three-point boundary value problem)."""
        return geodesic(template, faces, fields, a, b, weights, steps=3, metric=stepper.metric,
                        cancel=cancel).path[1]

    start = (codes["alpha0"], codes["alpha1"])
    if substeps > 1 and n_new > 0:
        monitor.report(0.0, "geodesic through the two given codes")
        start = tuple(geodesic(template, faces, fields, *start, weights, steps=substeps + 1, cancel=cancel).path[-2:])
        start = (start[0], codes["alpha1"])
    new, report = _march(stepper, start, n_new, substeps, midpoint, monitor, max(max_substeps, substeps), speed_tol,
                         frame_check, frozen)
    monitor.report(1.0, "done")
    out = np.concatenate([np.stack([codes["alpha0"], codes["alpha1"]]), new])
    if anchor:
        out = anchor_extrapolation(template, fields, out)
    return (out, report) if with_report else out


def anchor_extrapolation(template, fields, path):
    """An extrapolated path (T, P) with its predicted frames anchored (``geodesics.anchor_path``)
    to the straight latent line alpha^0 + k (alpha^1 - alpha^0) through its two given frames."""
    path = np.asarray(path, dtype=np.float64)
    line = path[0] + np.arange(len(path))[:, None] * (path[1] - path[0])
    return anchor_path(template, fields, path, line, fixed=(0, 1))


@with_one_blas_thread
def shoot(template, faces, fields, alpha0, velocity, weights, steps=10, callback=None, cancel=None,
          with_report=False, frame_check=None):
    """exp map: geodesic from alpha0 with initial velocity over unit time, steps >= 1: -> (steps + 1, P)
    (and a ShootingReport when ``with_report``; steps that do not converge are refined, and frame_check
    refuses frames after the first, as in ``extrapolate``)."""
    if steps < 1:
        raise InputError(f"shooting needs at least one step, got {steps}")
    codes = _check_codes(fields.shape[0], alpha0=alpha0, velocity=velocity)
    alpha1 = codes["alpha0"] + codes["velocity"] / steps
    return extrapolate(template, faces, fields, codes["alpha0"], alpha1, weights, steps - 1, callback, cancel,
                       with_report=with_report, frame_check=frame_check)


def initial_velocity(path):
    """Initial velocity of a discrete latent path on unit time: (T, P) -> (P,) (the log map of a BVP path)."""
    path = np.asarray(path)
    return (path[1] - path[0]) * (path.shape[0] - 1)
