r"""One level of the multiscale registration problem (paper section 4.1).

The objective of a level is weight * [Gamma(S(F(alpha(1))), T(q)) + landmark term] + E(alpha) over
a discrete latent path from 0 (``PathVariables``, preconditioned) and a small similarity S
optimised jointly with it; ``RegistrationProblem`` holds what is constant across levels (template
tensors, scan, landmarks, preconditioners) and solves, re-aligns and scores.
"""

import math
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

from .. import h2_metric
from ..latent import decode, interior_whitening, whitening
from ..mesh import face_geometry, smoothed_normals, winding_parity
from ..optimize import minimize_lbfgs
from ..transforms import Similarity, axis_angle_rotation
from ..varifold import BinnedMeasureLoss, BinnedVarifoldLoss, VarifoldLoss, default_cutoff, is_oriented
from .config import RegistrationConfig
from .prealign import CoarseVarifold, coarse_measure, surface_centroid, surface_moments

def log_scale(l, limit):
    """A level's log-scale change (tensor), bounded smoothly to +-limit (the objective and
    ``delta_similarity`` share it)."""
    return limit * torch.tanh(l / limit)


def delta_similarity(params, center, units, limit):
    """Similarity x -> c + e^l R(w) (x - c) + tau of params (w, tau, l) / units (7,) numpy, l bounded to
    +-limit."""
    p = np.asarray(params) * units
    r = axis_angle_rotation(p[:3])
    s = float(torch.exp(log_scale(torch.tensor(float(p[6]), dtype=torch.float64), limit)))
    return Similarity(r, s, center - s * r @ center + p[3:6])


def resample_in_time(path, steps):
    """Linear resampling in time of a latent path from 0: (T+1, P) -> (steps+1, P)."""
    path = np.asarray(path, dtype=np.float64)
    t_old = np.linspace(0.0, 1.0, path.shape[0])
    t_new = np.linspace(0.0, 1.0, steps + 1)
    return np.stack([np.interp(t_new, t_old, path[:, i]) for i in range(path.shape[1])], 1)


class PathVariables:
    """The latent path (T+1, P) from 0 as optimisation variables v (T, P): the end code
    alpha(1) = v_0 B and the deviations of alpha(k/T) from the straight line k/T alpha(1),
    d = sqrt(1/T) R^-1 v_1.. B (k = 1..T-1), with B, R^-1 the metric and time whitenings
    (``latent.whitening``, ``latent.time_whitening``).

    The end code carries the stiff varifold term, the deviations only the path energy, so the
    blocks decouple; in whitened coordinates the path energy is close to |v|^2 and L-BFGS
    converges in far fewer iterations than on the raw path.
    """

    def __init__(self, steps, whiten_end, whiten_path):
        self.steps = steps
        self.b_end, self.b = np.asarray(whiten_end, np.float64), np.asarray(whiten_path, np.float64)
        self.r_inv = interior_whitening(steps - 1)
        self.ramp = np.linspace(0.0, 1.0, steps + 1)[:, None]
        self._t = {}

    def _tensors(self, like):
        key = (like.dtype, like.device)
        if key not in self._t:
            self._t[key] = tuple(torch.as_tensor(a, dtype=like.dtype, device=like.device)
                                 for a in (self.b_end, self.b, self.r_inv, self.ramp))
        return self._t[key]

    def path(self, v):
        """Variables (T, P) tensor -> path (T+1, P) tensor."""
        b_end, b, r_inv, ramp = self._tensors(v)
        zero = v.new_zeros(1, v.shape[1])
        return ramp * (v[:1] @ b_end) + torch.cat([zero, r_inv @ v[1:] @ b, zero])

    def variables(self, path):
        """Inverse of ``path``: path (T+1, P) numpy from 0 -> variables (T, P) numpy."""
        dev = (path - self.ramp * path[-1])[1:-1]
        inner = np.linalg.solve(self.r_inv, dev) @ np.linalg.inv(self.b) if len(dev) else dev
        return np.concatenate([path[-1:] @ np.linalg.inv(self.b_end), inner])


def orient_like(verts, faces, ref_verts, ref_faces, weights=None):
    """Faces (G, 3) of a mesh (verts (M, 3)) wound consistently (``mesh.winding_parity``), each connected
    piece turned to face like a reference surface (N, 3), (F, 3) in the same frame: the area-weighted
    vote of its faces' normals (times face weights (G,), e.g. an ignore mask's) against the normal of
    the nearest reference face (by barycentre) -> (faces (G, 3) int64 numpy, number of faces turned).

    A scan with flipped or inconsistently wound faces, registered at a coarse level, can then be
    matched with an oriented kernel. Winding, not each face's own normal, decides: on a noisy scan
    some small faces really point backwards, and the oriented kernel's insensitivity to noise (a
    patch's sum of a n depends only on its boundary) needs them kept as they are.
    """
    faces = np.array(faces, dtype=np.int64)
    parity, pieces = winding_parity(faces)
    vectors, _, centres = face_geometry(verts, faces)
    ref_vectors, ref_areas, ref_centres = face_geometry(ref_verts, ref_faces)
    nearest = cKDTree(ref_centres).query(centres, k=1)[1]
    ref_normals = ref_vectors[nearest] / np.maximum(ref_areas[nearest], 1e-300)[:, None]
    agreement = parity * np.einsum("gk,gk->g", vectors, ref_normals)
    if weights is not None:
        agreement = agreement * np.asarray(weights, dtype=np.float64)
    vote = np.bincount(pieces, weights=agreement, minlength=int(pieces.max()) + 1)
    turn = parity * np.where(vote[pieces] < 0, -1, 1) < 0
    faces[turn] = faces[turn][:, [0, 2, 1]]
    return faces, int(turn.sum())


def normal_spread(verts, faces, weights=None):
    """How much a scan's normals are spread by noise: 1 - (projected area / area) of its faces against
    their normals denoised over 2 rings of neighbours (``mesh.smoothed_normals``):
    (M, 3), (G, 3), face weights (G,) or None -> float in [0, 1] (~0.005 on a clean body mesh, 0.08
    with 2 mm noise on 5 mm faces). Invariant under similarities."""
    _, projected = smoothed_normals(verts, faces, 2)
    areas = face_geometry(verts, faces)[1]
    w = np.ones(len(areas)) if weights is None else np.asarray(weights, dtype=np.float64)
    return float(1.0 - (w * projected).sum() / max((w * areas).sum(), 1e-300))


def _normal_gram(verts, faces, fields):
    """N_ij = sum_v A_v (h_i . n_v)(h_j . n_v): the L2 metric of the fields' normal components at the
    template: (N, 3), (F, 3), (P, N, 3) -> (P, P) numpy."""
    vectors = face_geometry(verts, faces)[0]  # a_f n_f
    normals = np.zeros_like(verts)
    for k in range(3):
        np.add.at(normals, faces[:, k], vectors)
    area = np.linalg.norm(normals, axis=1) / 3  # |sum of adjacent a_f n_f| / 3
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    hn = np.einsum("pvk,vk->pv", fields, normals)
    return (hn * area) @ hn.T


def landmark_pull(marks, landmark_weight, area, dtype, device):
    """The landmark term of ``register``: marks = (template vertex indices (L,), scan points (L, 3), weights
    (L,)) as ``multiscale.check_landmarks`` returns them, area the template's -> pull(final (N, 3), points
    (L, 3) tensors) = sum_i w_i |final_i - p_i|^2 with w = marks' weights / their sum * landmark_weight * area."""
    idx = torch.as_tensor(marks[0], device=device)
    w = torch.as_tensor(marks[2] / marks[2].sum() * landmark_weight * area, dtype=dtype, device=device)
    return lambda final, points: (w * ((final[idx] - points) ** 2).sum(1)).sum()


def end_whitening(gram, template, faces, fields, weight, code):
    """Whitening (P, P) of an end code fitted with weight * Gamma, about code (P,): of G-bar + 4 pi weight N.

    gram (P, P) the latent metric G-bar; template (N, 3), faces (F, 3), fields (P, N, 3) numpy. The
    varifold of a surface offset by d along its normals is ~ 2 pi int d^2 (any sigma), so weight * Gamma
    has Hessian ~ 4 pi weight N in the code (N = ``_normal_gram``) next to G-bar; N is taken at F(code),
    where the solve starts, not at the template: a body in a pose the pose stage found has its limbs'
    normals elsewhere (a random body's finest level: 97 -> 62 iterations)."""
    start = template + np.tensordot(code, fields, axes=1)
    return whitening(gram + 4 * math.pi * weight * _normal_gram(start, faces, fields))


class RegistrationProblem:
    """The constant parts of a registration (template tensors, scan, landmarks, settings) and one level's
    solve: basis, scan (M, 3), (G, 3), a RegistrationConfig, a progress Monitor; face_w (G,) or None;
    marks as ``multiscale.check_landmarks`` gives them, or None."""

    def __init__(self, basis, sv, sf, config=None, monitor=None, face_w=None, marks=None):
        from ..progress import Monitor

        self.config = config = RegistrationConfig.from_basis(basis) if config is None else config
        self.monitor = monitor or Monitor("register")
        dtype, device = config.dtype, config.device
        self.template, self.faces, self.fields = basis.tensors(dtype=dtype, device=device)
        area, self.center, _ = surface_moments(basis.template, basis.faces)
        self.center_t = torch.as_tensor(self.center, dtype=dtype, device=device)
        # preconditioning (see PathVariables): the path's interior is whitened by the latent
        # metric at the template, the end code by an estimate of the level's Hessian
        metric = config.shape_metric(basis)
        self.gram = basis.template_metric(metric)
        self.whiten = whitening(self.gram)
        self.radius = math.sqrt(((basis.template - self.center) ** 2).sum(-1).mean())
        self.scan, self.scan_faces_np, self.scan_weights_np = sv, sf, face_w
        self.scan_faces = torch.as_tensor(sf, dtype=torch.long, device=device)
        self.scan_weights = None if face_w is None else torch.as_tensor(face_w, dtype=dtype, device=device)
        self.marks = marks
        if marks is not None:
            self.pull = landmark_pull(marks, config.landmark_weight, area, dtype, device)
        self.metric, self.backend, self.binning = metric, config.backend, config.binning
        self.n_extra = 7 if config.refines_transform else 0
        self.dtype, self.device = dtype, device
        self.scale, self.n_fields = basis.scale, basis.n_fields
        self.template_np, self.faces_np, self.fields_np = basis.template, basis.faces, basis.fields

    def realign(self, level, codes, transform, max_iter=None, energies=None):
        """The alignment refined for each surface F(code) at ``level``'s sigma (binned binet varifold,
        rotation, translation and a bounded log-scale about the template's centre), starting from the
        translation that matches F(code)'s area centroid with the scan's (a raised arm moves the centroid
        by several cm): codes (K, P) -> [(Similarity, weight * Gamma + energy of the straight path
        0 -> code)], Gamma on the coarse cells. max_iter (None: ``poses.align_iterations``) 0 scores the
        centroid-matched starts alone; energies: those straight paths' energies (``straight_energies``)
        when known, else computed."""
        max_iter = self.config.poses.align_iterations if max_iter is None else max_iter
        limit = self.config.solve.scale_log_limit
        sigma = level.sigma * self.scale
        cell = self.config.prealignment.cell * sigma
        moved = transform.apply(self.scan)
        scan_center = surface_centroid(moved, self.scan_faces_np, self.scan_weights_np)[1]
        # one loss against the scan for every code: the scan's self term is summed once
        scan = BinnedMeasureLoss(*coarse_measure(moved - self.center, self.scan_faces, self.scan_weights_np, cell),
                                 sigma)
        eye = torch.eye(3, dtype=torch.float64)
        energies = self.straight_energies(level, codes) if energies is None else energies
        out = []
        for code, energy in zip(codes, energies):
            self.monitor.check()
            with torch.no_grad():
                verts = decode(self.template, self.fields, torch.as_tensor(code, dtype=self.dtype, device=self.device))
            verts = verts.detach().cpu().numpy().astype(np.float64)
            x0 = np.zeros(7)
            x0[3:6] = scan_center - surface_centroid(verts, self.faces_np)[1]
            coarse = CoarseVarifold(scan, coarse_measure(verts - self.center, self.faces, None, cell), sigma)
            fun = lambda p: coarse(torch.cat([p[:6], log_scale(p[6:], limit)]), eye)  # noqa: E731
            if max_iter:
                x, gamma, _ = minimize_lbfgs(fun, x0, max_iter=max_iter, gtol=1e-9, ftol=1e-10)
            else:
                with torch.no_grad():
                    x, gamma = x0, float(fun(torch.from_numpy(x0)))
            # F(code) moved by S: x -> e^l R (x - c) + tau + c; the scan moves by the inverse instead
            scale = math.exp(float(log_scale(torch.as_tensor(x[6]), limit)))
            rot = axis_angle_rotation(x[:3])
            move = Similarity(rot, scale, x[3:6] + self.center - scale * rot @ self.center)
            out.append((move.inverse().compose(transform), level.weight * gamma + energy))
        return out

    def straight_energies(self, level, codes):
        """Energies of the straight paths 0 -> code in ``level.steps`` steps: codes (K, P) -> [float] * K,
        ``solve.straight_batch`` paths at a time (one path energy call instead of one a code)."""
        batch, energy_dtype = self.config.solve.straight_batch, self.config.solve.energy_dtype
        codes = torch.as_tensor(np.asarray(codes, dtype=np.float64), dtype=self.dtype, device=self.device)
        ramp = torch.linspace(0, 1, level.steps + 1, dtype=self.dtype, device=self.device)[:, None]
        out = []
        with torch.no_grad():
            for s in range(0, codes.shape[0], batch):
                paths = decode(self.template, self.fields, ramp * codes[s:s + batch, None, :])
                out += h2_metric.path_energy(paths, self.faces, self.metric, compute_dtype=energy_dtype).tolist()
        return out

    def screen_score(self, level, code, transform, energy):
        """weight * (Gamma + landmark term) + energy of a solved path at ``level``'s sigma and weight,
        Gamma (kernel ``screening.kernel``) on a binning of both surfaces with cells of ``screening.cell``
        x sigma.

        A level's objective bins with coarser cells; its error (a difference of large
        kernel sums) depends on how each alignment falls on the cells, enough to rank a wrong
        alignment first: finer cells make the objective comparable across alignments.
        code (P,), transform: the end of a ``solve_level`` result; energy: its path energy -> float.
        """
        sigma = level.sigma * self.scale
        target = torch.as_tensor(transform.apply(self.scan), dtype=self.dtype, device=self.device)
        code = torch.as_tensor(code, dtype=self.dtype, device=self.device)
        with torch.no_grad():
            final = decode(self.template, self.fields, code)
            screening = self.config.screening
            loss = BinnedVarifoldLoss(final, self.faces, target, self.scan_faces, sigma, screening.kernel,
                                      self.scan_weights, cell=screening.cell * sigma, backend=self.backend)
            fit = loss(final, self.faces)
            if self.marks is not None:
                fit = fit + self.landmark_term(final, self.landmark_points(transform))
            return level.weight * float(fit) + energy

    def landmark_points(self, transform):
        """The scan's landmark points mapped into the template frame by ``transform``: -> (L, 3) tensor."""
        return torch.as_tensor(transform.apply(self.marks[1]), dtype=self.dtype, device=self.device)

    def landmark_term(self, final, points):
        """sum_i w_i |F_i - p_i|^2 of the landmark vertices of ``final`` (N, 3) against ``points`` (L, 3)."""
        return self.pull(final, points)

    def oriented_scan_faces(self, code, transform):
        """The scan's faces turned like the nearest faces of F(code) (``orient_like``, template frame):
        code (P,), transform scan -> template -> (faces (G, 3) tensor, number turned)."""
        with torch.no_grad():
            fit = decode(self.template, self.fields, torch.as_tensor(code, dtype=self.dtype, device=self.device))
        faces, turned = orient_like(transform.apply(self.scan), self.scan_faces_np, fit.cpu().numpy(), self.faces_np,
                                    self.scan_weights_np)
        return torch.as_tensor(faces, dtype=torch.long, device=self.device), turned

    def level_loss(self, kernel, sigma, target, scan_faces, code, bin_cell, binned=None):
        """The varifold loss of one level against the scan (target (M, 3) in the template frame):
        binned (``BinnedVarifoldLoss`` about F(code), cells of bin_cell x sigma) as ``self.binning`` says
        (when "auto", as the level's own ``binned`` says unless it is None, then ``solve.bin_gain``'s
        pair-count rule), else truncated at ``solve.fine_tol`` with the scan summed over cells of
        ``solve.scan_cell`` (``oriented_scan_cell`` for an oriented kernel) x sigma -> (loss, binned)."""
        settings = self.config.solve
        binning = binned if self.binning == "auto" and binned is not None else self.binning
        if binning:
            start = decode(self.template, self.fields, torch.as_tensor(code, dtype=self.dtype, device=self.device))
            loss = BinnedVarifoldLoss(start, self.faces, target, scan_faces, sigma, kernel, self.scan_weights,
                                      cell=bin_cell * sigma, backend=self.backend)
            n_s, n_t = self.faces.shape[0], scan_faces.shape[0]
            pairs = loss.n_groups * (loss.n_groups + loss.n_target)
            if binning is True or pairs <= settings.bin_gain * n_s * (n_s + n_t):
                return loss, True
        cell = settings.oriented_scan_cell if is_oriented(kernel) else settings.scan_cell
        return VarifoldLoss(target, scan_faces, sigma, kernel=kernel, backend=self.backend,
                            target_weights=self.scan_weights, cutoff=default_cutoff(sigma, settings.fine_tol),
                            target_cell=None if cell is None else cell * sigma), False

    def solve_level(self, level, path, transform, progress, message, kernel="binet", orient=False,
                    bin_cell=None):
        """Minimise one level from path (T0+1, P) and the alignment -> (path (T+1, P), alignment, report).

        kernel: the varifold's (a name of ``bareesa.varifold.KERNELS``, or names joined by "+": the sum
        of their varifolds); orient: with an oriented kernel, first turn the scan's faces like the fit
        so far (``oriented_scan_faces``), else use them as given; bin_cell: the cells of a binned level,
        in units of sigma (``level_loss``; None: the level's own ``bin_cell``, else ``solve.bin_cell``)."""
        t0 = time.perf_counter()
        settings = self.config.solve
        limit = settings.scale_log_limit
        bin_cell = next(c for c in (bin_cell, level.bin_cell, settings.bin_cell) if c is not None)
        self.monitor.check()
        dtype, device, p_dim, steps = self.dtype, self.device, self.n_fields, level.steps
        sigma = level.sigma * self.scale
        target = torch.as_tensor(transform.apply(self.scan), dtype=dtype, device=device)
        names = kernel.split("+")
        scan_faces, turned = self.scan_faces, None
        if orient and any(is_oriented(name) for name in names):
            scan_faces, turned = self.oriented_scan_faces(path[-1], transform)
        losses = [self.level_loss(name, sigma, target, scan_faces, path[-1], bin_cell, level.binned) for name in names]
        binned = losses[0][1]
        losses = [loss for loss, _ in losses]
        if self.marks is not None:
            lm_pts = self.landmark_points(transform)
        terms = {}  # the energy and varifold of every point evaluated, by the point's bytes

        def objective(x):
            key = x.detach().cpu().numpy().tobytes()
            x = x.to(dtype=dtype, device=device)
            alpha = variables.path(x[:steps * p_dim].reshape(steps, p_dim))
            meshes = decode(self.template, self.fields, alpha)
            energy = h2_metric.path_energy(meshes, self.faces, self.metric, compute_dtype=settings.energy_dtype)
            final = meshes[-1]
            if self.n_extra:
                p = x[steps * p_dim:] * units_t
                rotation = axis_angle_rotation(p[:3])
                final = (self.center_t + torch.exp(log_scale(p[6], limit)) * (final - self.center_t) @ rotation.T
                         + p[3:6])
            gamma = sum(loss(final, self.faces) for loss in losses)
            fit = gamma
            if self.marks is not None:
                fit = fit + self.landmark_term(final, lm_pts)
            terms[key] = (float(energy.detach()), float(gamma.detach()))
            return level.weight * fit + energy

        whiten_end = end_whitening(self.gram, self.template_np, self.faces_np, self.fields_np, level.weight, path[-1])
        variables = PathVariables(steps, whiten_end, self.whiten)
        # similarity variables scaled so that a unit step moves the surface about as much as a
        # unit step of the (whitened) end code: a well-conditioned joint problem
        move = math.sqrt((np.tensordot(whiten_end, self.fields_np, axes=1) ** 2).sum(-1).mean())
        units = np.array([move / self.radius] * 3 + [move] * 3 + [move / self.radius])
        units_t = torch.as_tensor(units, dtype=dtype, device=device)
        x0 = np.concatenate([variables.variables(resample_in_time(path, steps)).ravel(), np.zeros(self.n_extra)])

        def unpack(x):
            """The path (steps + 1, P) and the alignment the variables x stand for."""
            path = variables.path(torch.from_numpy(x[:steps * p_dim].reshape(steps, p_dim))).numpy()
            if not self.n_extra:
                return path, transform
            return path, delta_similarity(x[steps * p_dim:], self.center, units, limit).inverse().compose(transform)

        def result_so_far(x):
            path, moved = unpack(x)
            return {"code": path[-1], "transform": moved}

        x, value, nit = minimize_lbfgs(objective, x0, self.monitor, max_iter=level.max_iter,
                                       progress=progress, message=message, ftol=settings.ftol,
                                       plateau=(settings.plateau_window, level.plateau or settings.plateau),
                                       memory=settings.memory,
                                       preview=((settings.preview_every, result_so_far) if self.monitor.wants_preview
                                                else None))
        if x.tobytes() not in terms:  # the optimiser returns a point it evaluated: this is only a safeguard
            with torch.no_grad():
                objective(torch.from_numpy(x))
        energy, gamma = terms[x.tobytes()]
        path, transform = unpack(x)
        return path, transform, {"sigma": float(sigma), "weight": float(level.weight), "steps": int(steps),
                                 "iterations": int(nit), "energy": energy,
                                 "varifold": gamma, "objective": float(value),
                                 "binned": binned, "kernel": kernel, "turned_faces": turned,
                                 "seconds": time.perf_counter() - t0}
