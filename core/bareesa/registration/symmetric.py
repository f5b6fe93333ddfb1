"""Symmetric matching of two raw scans: both codes and the geodesic between them in one solve."""

import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from ..errors import InputError
from ..geodesics import decode_path, geodesic, straight_path
from ..h2_metric import H2Weights, path_energy
from ..latent import decode
from ..optimize import minimize_lbfgs
from ..progress import Monitor
from ..transforms import Similarity
from ..varifold import VarifoldLoss, is_oriented
from .multiscale import level_kernels, register
from .problem import orient_like

@dataclass
class Matching:
    """Symmetric matching of two scans: the latent path (T, P) between their codes, its
    distance, each scan's similarity into the template frame, and the final varifold residuals."""

    path: np.ndarray
    energy: float
    distance: float
    transforms: tuple
    varifold: tuple
    seconds: float

    def frame_transform(self, t):
        """The similarity at time t in [0, 1], interpolated between the two scans' (slerp, log-scale)."""
        a, b = self.transforms
        rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a.rotation, b.rotation])))([t]).as_matrix()[0]
        return Similarity(rot, a.scale ** (1 - t) * b.scale ** t, (1 - t) * a.translation + t * b.translation)

    def vertices(self, template, fields, codes, times=None):
        """Frames of codes (K, P) in the scans' frame (K, N, 3); times default to evenly spaced."""
        times = np.linspace(0.0, 1.0, len(codes)) if times is None else times
        frames = decode_path(template, fields, codes)
        return np.stack([self.frame_transform(float(t)).invert(v) for t, v in zip(times, frames)])


def symmetric_match(basis, scan0, scan1, steps=10, schedule=None, weights=None, prealign=True, kernel="auto",
                    callback=None, cancel=None, dtype=torch.float64, device="cpu"):
    """Codes of two raw scans and the geodesic between them in one optimisation (paper eq. sym. match).

    scan0, scan1: (verts (M, 3), faces (G, 3)). Each scan is first registered (warm start,
    its own pre-alignment unless prealign is False); then weight * [Gamma(F(alpha_0), q0) +
    Gamma(F(alpha_1), q1)] + E(alpha) is minimised jointly over the whole path at the finest level
    of the schedule, with the finest kernel each scan's registration used (``register``'s ``kernel``;
    an oriented one on the scan's faces turned like its registration). weights: the H2 weights of E
    and of the registrations (default the basis'); dtype, device: of the objective.
    """
    start = time.perf_counter()
    if steps < 2:
        raise InputError(f"a path needs at least 2 time points, got {steps}")
    monitor = Monitor("symmetric matching", callback, cancel)
    levels = tuple(basis.schedule if schedule is None else schedule)
    weights = H2Weights.parse(basis.weights if weights is None else weights)
    level_kernels(kernel, len(levels))  # checked before any solve
    options = dict(schedule=levels, prealign=prealign, metric=weights, kernel=kernel, cancel=cancel, dtype=dtype,
                   device=device)
    r0 = register(basis, *scan0, callback=monitor.scaled(0.0, 0.4), **options)
    r1 = register(basis, *scan1, callback=monitor.scaled(0.4, 0.8), **options)
    template, faces, fields = basis.tensors(dtype=dtype, device=device)
    last = levels[-1]
    sigma = last.sigma * basis.scale
    losses = []
    for r, (v, f) in ((r0, scan0), (r1, scan1)):
        v = r.transform.apply(np.asarray(v, dtype=np.float64))
        names = r.levels[-1]["kernel"].split("+")  # each scan's finest kernel, as its registration chose
        if any(is_oriented(name) for name in names):
            f = orient_like(v, f, r.transform.apply(r.vertices), basis.faces)[0]
        losses.append([VarifoldLoss(torch.as_tensor(v, dtype=dtype, device=device),
                                    torch.as_tensor(np.asarray(f), dtype=torch.long, device=device), sigma, name)
                       for name in names])
    p = fields.shape[0]
    ramp = torch.linspace(0, 1, steps, dtype=dtype, device=device)[1:-1, None]
    terms = {}

    def objective(x):
        # variables: both end codes, then the interior's deviation from the straight line (conditioning)
        x = x.to(dtype=dtype, device=device)
        a0, a1, dev = x[:p], x[p:2 * p], x[2 * p:].reshape(steps - 2, p)
        path = torch.cat([a0[None], (1 - ramp) * a0 + ramp * a1 + dev, a1[None]])
        meshes = decode(template, fields, path)
        energy = path_energy(meshes, faces, weights)
        gammas = [sum(loss(mesh, faces) for loss in losses[k]) for k, mesh in ((0, meshes[0]), (1, meshes[-1]))]
        terms.update(energy=energy, gammas=gammas)
        return last.weight * (gammas[0] + gammas[1]) + energy

    init = geodesic(template, faces, fields, r0.code, r1.code, weights, steps=steps, cancel=cancel,
                    metric=basis.template_metric(weights), max_iter=100)
    straight = straight_path(r0.code, r1.code, steps)
    x0 = np.concatenate([r0.code, r1.code, (init.path - straight)[1:-1].ravel()])
    x, value, _ = minimize_lbfgs(objective, x0, monitor, max_iter=last.max_iter, progress=(0.8, 1.0),
                                 message="symmetric matching")
    with torch.no_grad():
        objective(torch.from_numpy(x))
    a0, a1 = x[:p], x[p:2 * p]
    path = straight_path(a0, a1, steps)
    path[1:-1] += x[2 * p:].reshape(steps - 2, p)
    energy = float(terms["energy"])
    monitor.report(1.0, "symmetric matching done", value)
    return Matching(path=path, energy=energy, distance=float(np.sqrt(max(energy, 0.0))),
                    transforms=(r0.transform, r1.transform),
                    varifold=tuple(float(g) for g in terms["gammas"]), seconds=time.perf_counter() - start)
