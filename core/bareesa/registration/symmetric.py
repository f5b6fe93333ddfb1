"""Symmetric matching of two raw scans: both codes and the geodesic between them in one solve."""

import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from ..errors import InputError
from ..geodesics import FRAMES_PLATEAU, decode_path, geodesic, midpoint_metric, straight_path
from ..h2_metric import H2Weights, path_energy
from ..latent import decode, interior_whitening, whitening
from ..optimize import minimize_lbfgs
from ..progress import Monitor
from ..threads import with_one_blas_thread
from ..transforms import Similarity
from ..varifold import VarifoldLoss, is_oriented
from .checks import check_face_weights, check_landmarks, level_kernels
from .config import RegistrationConfig
from .multiscale import SETTING_ALIASES, register
from .prealign import surface_moments
from .problem import end_whitening, landmark_pull, orient_like


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


@with_one_blas_thread
def symmetric_match(basis, scan0, scan1, steps=10, config=None, *, weights=None, face_weights=(None, None),
                    landmarks=(None, None), callback=None, cancel=None, **settings):
    """Codes of two raw scans and the geodesic between them in one optimisation (paper eq. sym. match).

    scan0, scan1: (verts (M, 3), faces (G, 3)). Each scan is first registered (warm start,
    its own pre-alignment unless prealign is False); then weight * [Gamma(F(alpha_0), q0) +
    Gamma(F(alpha_1), q1)] + E(alpha) is minimised jointly over the whole path at the finest level
    of the schedule, with the finest kernel each scan's registration used (an oriented one on the scan's
    faces turned like its registration). config: a ``RegistrationConfig`` (None: the basis'), keyword
    ``settings`` override it as ``register``'s do; weights: the H2 weights of E and of the registrations
    (default the basis': ``weights`` for E, ``shape_metric`` for the registrations); face_weights,
    landmarks: one per scan, as ``register`` takes them (an ignored face stays ignored and a landmark
    keeps pulling in the joint solve too).
    """
    start = time.perf_counter()
    if steps < 2:
        raise InputError(f"a path needs at least 2 time points, got {steps}")
    monitor = Monitor("symmetric matching", callback, cancel)
    config = RegistrationConfig.from_basis(basis) if config is None else config
    config = config.with_overrides({SETTING_ALIASES.get(k, k): v for k, v in settings.items()})
    if config.schedule is None:
        config = config.with_overrides(schedule=basis.schedule)
    if weights is not None:  # the ends' registrations use the basis' shape metric unless weights are given
        config = config.with_overrides(metric=weights)
    weights = H2Weights.parse(basis.weights if weights is None else weights)
    level_kernels(config.kernel, len(config.schedule))  # checked before any solve
    face_weights, landmarks = tuple(face_weights), tuple(landmarks)
    if len(face_weights) != 2 or len(landmarks) != 2:
        raise InputError("face_weights and landmarks: one entry (or None) per scan, two in all")
    for scan, w, marks in zip((scan0, scan1), face_weights, landmarks):  # both checked before any solve
        check_face_weights(w, len(scan[1]))
        check_landmarks(marks, basis.template.shape[0])
    starts = config.with_overrides({"detail.enabled": False})  # the joint solve moves the ends: no detail yet
    r0 = register(basis, *scan0, starts, scan_face_weights=face_weights[0], landmarks=landmarks[0],
                  callback=monitor.scaled(0.0, 0.4), cancel=cancel)
    r1 = register(basis, *scan1, starts, scan_face_weights=face_weights[1], landmarks=landmarks[1],
                  callback=monitor.scaled(0.4, 0.8), cancel=cancel)
    path, energy, gammas = match_registered(basis, (scan0, scan1), (r0, r1), steps, config.schedule[-1], weights,
                                            monitor, config, face_weights, landmarks)
    monitor.report(1.0, "symmetric matching done", energy + config.schedule[-1].weight * sum(gammas))
    return Matching(path=path, energy=energy, distance=float(np.sqrt(max(energy, 0.0))),
                    transforms=(r0.transform, r1.transform), varifold=gammas, seconds=time.perf_counter() - start)


def _end_terms(basis, scan, reg, level, gram, face_weights, landmarks, landmark_weight, dtype, device):
    """One end of the joint solve -> (gamma, pull, whitening). gamma(F(code) (N, 3), faces): the varifold
    losses of its scan at ``level``'s sigma with the kernels its registration's finest level used (an
    oriented one on the scan's faces turned like the fit), exact: no cells, no truncation (on `human` scans
    0.1 mm closer to the truth than the registration's cell sums), the scan's face weights (G,) applied;
    pull(F(code)): the landmark term as ``register`` adds it (0 without landmarks), the landmarks moved into
    the template frame by the registration's similarity; the whitening (P, P) of its code
    (``problem.end_whitening`` at the registered code)."""
    verts = reg.transform.apply(np.asarray(scan[0], dtype=np.float64))
    faces = np.asarray(scan[1])
    face_w = check_face_weights(face_weights, len(faces))
    names = reg.levels[-1]["kernel"].split("+")
    if any(is_oriented(name) for name in names):
        faces = orient_like(verts, faces, reg.transform.apply(reg.vertices), basis.faces, face_w)[0]
    as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    verts_t, faces_t = as_t(verts), torch.as_tensor(faces, dtype=torch.long, device=device)
    losses = [VarifoldLoss(verts_t, faces_t, level.sigma * basis.scale, name,
                           target_weights=None if face_w is None else as_t(face_w)) for name in names]
    gamma = lambda mesh, faces: sum(loss(mesh, faces) for loss in losses)  # noqa: E731
    marks = check_landmarks(landmarks, basis.template.shape[0])
    pull = lambda mesh: 0.0  # noqa: E731
    if marks is not None:
        points = as_t(reg.transform.apply(marks[1]))
        term = landmark_pull(marks, landmark_weight, surface_moments(basis.template, basis.faces)[0], dtype, device)
        pull = lambda mesh: term(mesh, points)  # noqa: E731
    return gamma, pull, end_whitening(gram, basis.template, basis.faces, basis.fields, level.weight, reg.code)


def match_registered(basis, scans, regs, steps, level, weights, monitor, config=None, face_weights=(None, None),
                     landmarks=(None, None)):
    """The joint solve of symmetric matching from two registrations: minimise level.weight * [Gamma(F(alpha_0),
    q0) + Gamma(F(alpha_1), q1)] + E(alpha) over the path (steps, P), both ends free, each scan fixed in the
    template frame by its registration's similarity (Gamma with each scan's face weights and landmark term,
    as its registration had them), settings from ``config`` (dtype, device, landmark_weight, ``matching``;
    None: the defaults). -> (path (steps, P), energy, (Gamma_0, Gamma_1)).

    Preconditioned like a registration level (``problem.PathVariables``): each end code whitened by its
    level Hessian estimate, the interior's deviation from the straight line by the time whitening and the
    metric at the mean of the registered codes (``geodesics.midpoint_metric``), so that L-BFGS meets a
    nearly isotropic problem; stopped at ``solve.ftol`` or ``matching``'s plateau. Starts from the geodesic
    between the registered codes (in ``matching.start_dtype``)."""
    config = RegistrationConfig() if config is None else config
    dtype, device, landmark_weight, settings = config.dtype, config.device, config.landmark_weight, config.matching
    template, faces, fields = basis.tensors(dtype=dtype, device=device)
    p = fields.shape[0]
    gram = basis.template_metric(weights)
    ends = [_end_terms(basis, scan, reg, level, gram, w, marks, landmark_weight, dtype, device)
            for scan, reg, w, marks in zip(scans, regs, face_weights, landmarks)]
    codes = [reg.code for reg in regs]
    start_tensors = basis.tensors(dtype=settings.start_dtype, device=device)
    middle = midpoint_metric(*start_tensors, *codes, weights)
    b_path = whitening(middle)
    r_inv = interior_whitening(steps - 2)
    as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    b0, b1, b_t, r_t = as_t(ends[0][2]), as_t(ends[1][2]), as_t(b_path), as_t(r_inv)
    ramp = torch.linspace(0, 1, steps, dtype=dtype, device=device)[1:-1, None]
    terms = {}

    def path_of(x):
        x = x.to(dtype=dtype, device=device)
        a0, a1 = x[:p] @ b0, x[p:2 * p] @ b1
        inner = (1 - ramp) * a0 + ramp * a1 + r_t @ x[2 * p:].reshape(steps - 2, p) @ b_t
        return torch.cat([a0[None], inner, a1[None]])

    def objective(x):
        meshes = decode(template, fields, path_of(x))
        energy = path_energy(meshes, faces, weights, compute_dtype=config.solve.energy_dtype)
        ends_mesh = meshes[[0, -1]]
        gammas = [gamma(mesh, faces) for (gamma, _, _), mesh in zip(ends, ends_mesh)]
        pulls = [pull(mesh) for (_, pull, _), mesh in zip(ends, ends_mesh)]
        terms.update(energy=energy, gammas=gammas)
        return level.weight * (gammas[0] + gammas[1] + pulls[0] + pulls[1]) + energy

    # start: the geodesic between the two registrations' codes
    init = geodesic(*start_tensors, *codes, weights, steps=steps, cancel=monitor.cancel, max_iter=100,
                    metric=middle, plateau=FRAMES_PLATEAU)
    deviation = (init.path - straight_path(*codes, steps))[1:-1]
    inner = np.linalg.solve(r_inv, deviation) @ np.linalg.inv(b_path) if steps > 2 else deviation
    x0 = np.concatenate([np.linalg.solve(ends[0][2].T, codes[0]), np.linalg.solve(ends[1][2].T, codes[1]),
                         inner.ravel()])
    x, _, _ = minimize_lbfgs(objective, x0, monitor, max_iter=level.max_iter, progress=(0.8, 1.0),
                             message="symmetric matching", ftol=config.solve.ftol,
                             plateau=(settings.plateau_window, settings.plateau))
    with torch.no_grad():
        path = path_of(torch.from_numpy(x)).double().cpu().numpy()
        objective(torch.from_numpy(x))
    return path, float(terms["energy"]), tuple(float(g) for g in terms["gammas"])
