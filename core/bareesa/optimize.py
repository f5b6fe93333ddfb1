"""L-BFGS on float64 with torch autograd gradients (the paper's optimiser), cancellable."""

import warnings

import numpy as np
import scipy.optimize
import torch

from .errors import SolveDiverged
from .threads import with_one_blas_thread

#: Past steps L-BFGS keeps by default (scipy's ``maxcor``)
LBFGS_MEMORY = 20


class _Stalled(Exception):
    """Raised inside the objective to end a solve whose line searches no longer lower it."""


@with_one_blas_thread
def minimize_lbfgs(objective, x0, monitor=None, max_iter=200, progress=(0.0, 1.0), message="",
                   gtol=1e-10, ftol=1e-12, plateau=None, preview=None, stall=None, memory=LBFGS_MEMORY):
    """Minimise ``objective(x: torch float64 tensor) -> scalar tensor`` from x0 (n,) numpy.

    Returns (x (n,) numpy, final value, number of iterations). The monitor's
    cancel token is checked at every evaluation; progress is reported as
    iterations advance within the ``progress`` fraction range. plateau (window k, rtol r):
    also stop once the objective fell by less than r * |objective| over the last k iterations.
    stall (n, with plateau): also stop once n evaluations in a row have not lowered the best value by
    r * |best|, and return the best point evaluated: near its minimum a float32 objective's rounding
    noise sends line searches round for up to 20 evaluations each (a `human` geodesic: 9 evaluations
    to converge, 65 more spent so). preview (every k, x -> dict): every k iterations the progress
    report carries preview(x). memory: the number of past steps L-BFGS keeps (its ``maxcor``).
    """
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    state = {"it": 0, "value": None, "best": (np.inf, x0), "ref": np.inf, "since": 0}

    def fun(x):
        if monitor is not None:
            monitor.check()
        xt = torch.from_numpy(x).requires_grad_(True)
        value = objective(xt)
        (grad,) = torch.autograd.grad(value, xt)
        v, g = float(value.detach()), grad.numpy().astype(np.float64)
        if not np.isfinite(v) or not np.isfinite(g).all():
            raise SolveDiverged(f"{message or 'the solve'} diverged (non-finite energy); "
                                "try a coarser schedule or check the input mesh")
        state["value"] = v
        if stall is not None and plateau is not None:
            if v < state["best"][0]:
                state["best"] = (v, x.copy())
            if state["ref"] - v > plateau[1] * abs(v):  # lowered by r since the count began: count again
                state["ref"], state["since"] = v, 0
            else:
                state["since"] += 1
                if state["since"] >= stall:
                    raise _Stalled
        return v, g

    history = []

    def callback(intermediate_result):
        state["it"] += 1
        if monitor is not None:
            monitor.check()
            lo, hi = progress
            shown = None
            if preview is not None and state["it"] % preview[0] == 0:
                shown = preview[1](np.asarray(intermediate_result.x))
            monitor.report(lo + (hi - lo) * state["it"] / max_iter, f"{message} it {state['it']}", state["value"],
                           shown)
        if plateau is not None:
            window, rtol = plateau
            history.append(float(intermediate_result.fun))
            if len(history) > window and history[-1 - window] - history[-1] < rtol * abs(history[-1]):
                raise StopIteration

    if x0.size == 0:
        return x0, float(objective(torch.from_numpy(x0))), 0
    try:
        res = scipy.optimize.minimize(fun, x0, jac=True, method="L-BFGS-B", callback=callback,
                                      options={"maxiter": max_iter, "gtol": gtol, "ftol": ftol, "maxcor": memory})
    except _Stalled:
        value, x = state["best"]
        return x, value, state["it"]
    return res.x, float(res.fun), int(res.nit)


def sparse_solver(matrix):
    """A solve y -> A^-1 y with a symmetric positive definite scipy sparse A (N, N), factored once (SuperLU in
    its symmetric mode): -> callable on (N,) float64 arrays."""
    import scipy.sparse.linalg

    lu = scipy.sparse.linalg.splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                  options={"SymmetricMode": True})
    return lu.solve


@with_one_blas_thread
def minimize_preconditioned(objective, x0, precondition, monitor=None, max_iter=100, progress=(0.0, 1.0), message="",
                            ftol=1e-9, plateau=None, memory=10, probe=1e-3, start=None):
    """Minimise ``objective(x: torch float64 tensor) -> scalar tensor`` from x0 (n,) by L-BFGS whose initial
    inverse Hessian is ``precondition`` (y -> P^-1 y, P symmetric positive definite, e.g. ``sparse_solver``),
    scaled at each iteration by s^T y / y^T P^-1 y, with scipy's strong Wolfe line search.

    For many variables coupled by a stiff regulariser (free vertex displacements under an H2 energy) whose
    Hessian P is known: plain L-BFGS needs hundreds of iterations there, this a few tens. The first pair (s, y)
    is a finite difference along P^-1 g of length ``probe`` x |x0| (or ``probe``), so the first step is already
    scaled. start: (value, gradient (n,)) at x0 where the caller has them (not evaluated again). Returns
    (x (n,), value, iterations); stops after max_iter iterations, when a step lowers the
    objective by less than ftol (relative), on plateau (window k, rtol r) like ``minimize_lbfgs``, or when the
    line search fails twice in a row. Cancellable through the monitor; SolveDiverged on a non-finite value.
    """
    from collections import deque

    cache = {}

    def fun(x):
        key = x.tobytes()
        if key not in cache:
            if monitor is not None:
                monitor.check()
            xt = torch.from_numpy(np.array(x, dtype=np.float64)).requires_grad_(True)
            value = objective(xt)
            (grad,) = torch.autograd.grad(value, xt)
            v, g = float(value.detach()), grad.numpy().astype(np.float64)
            if not np.isfinite(v) or not np.isfinite(g).all():
                raise SolveDiverged(f"{message or 'the solve'} diverged (non-finite energy)")
            if len(cache) > 8:
                cache.clear()
            cache[key] = (v, g)
        return cache[key]

    x = np.array(x0, dtype=np.float64)
    if start is not None:
        cache[x.tobytes()] = (float(start[0]), np.asarray(start[1], dtype=np.float64))
    value, grad = fun(x)
    pairs = deque(maxlen=memory)  # (s, y, 1 / s^T y, P^-1 y)
    direction = precondition(grad)
    length = probe * max(np.linalg.norm(x), 1.0) / max(np.linalg.norm(direction), 1e-300)
    s = -length * direction
    y = fun(x + s)[1] - grad
    if s @ y > 0:
        pairs.append((s, y, 1.0 / (s @ y), precondition(y)))
    history, failures, it = [value], 0, 0
    lo, hi = progress
    while it < max_iter:
        q = grad.copy()
        alphas = []
        for s, y, rho, _ in reversed(pairs):
            a = rho * (s @ q)
            q -= a * y
            alphas.append(a)
        r = precondition(q)
        if pairs:
            s, y, _, py = pairs[-1]
            r *= (s @ y) / (y @ py)
        for (s, y, rho, _), a in zip(pairs, reversed(alphas)):
            r += s * (a - rho * (y @ r))
        step = -r
        if step @ grad >= 0:  # not a descent direction: start the memory again
            pairs.clear()
            step = -precondition(grad)
        with warnings.catch_warnings():  # a failed search is handled below (memory cleared, then stop)
            warnings.filterwarnings("ignore", message="The line search algorithm did not converge")
            alpha, *_ = scipy.optimize.line_search(lambda z: fun(z)[0], lambda z: fun(z)[1], x, step, grad, value,
                                                   maxiter=20)
        if alpha is None:
            failures += 1
            pairs.clear()
            if failures > 1:
                break
            continue
        failures = 0
        x_new = x + alpha * step
        new_value, new_grad = fun(x_new)
        s, y = x_new - x, new_grad - grad
        if s @ y > 1e-300:
            pairs.append((s, y, 1.0 / (s @ y), precondition(y)))
        fell = value - new_value
        x, value, grad = x_new, new_value, new_grad
        it += 1
        history.append(value)
        if monitor is not None:
            monitor.report(lo + (hi - lo) * it / max_iter, f"{message} it {it}", value)
        if fell <= ftol * max(abs(value), 1.0):
            break
        if plateau is not None:
            window, rtol = plateau
            if len(history) > window and history[-1 - window] - history[-1] < rtol * abs(history[-1]):
                break
    return x, value, it
