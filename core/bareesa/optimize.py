"""L-BFGS on float64 with torch autograd gradients (the paper's optimiser), cancellable."""

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
