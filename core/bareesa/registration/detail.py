r"""``fit_detail``: the scan's own detail on the registered template, after the basis fit.

A basis fit q = F(alpha) reproduces the body the basis can make. The detail step adds free per-vertex
displacements d (N, 3) of the registered template (template frame), the paper's unrestricted H2 matching
started from the basis fit, over the levels of ``DetailFit`` (sigmas, weights, iterations):

    minimise_d   weight * [ Gamma_sigma(q + d, scan) + landmark term ]  +  E(q -> q + d)  +  slide * |d_t|^2,

Gamma the squared varifold distance (kernel ``DetailFit.kernel``, the scan's pieces turned to face like
the basis fit when it is oriented; the registration's backend and scan face weights), E the H2 energy
(the basis' shape metric) of the deformation q -> q + d as a path of ``steps`` straight steps, and
|d_t|^2 the area-weighted squared part of d along the surface (``tangential_matrix``): the varifold cannot
see a vertex slide along the surface, and without it vertices leave their places. The last level's data
term sees each face as its four midpoint sub-faces (a finer quadrature than one point per face, which
biases the fit at a sigma under the template's edge length). Template faces farther than ``reach`` x the
first sigma from the scan (over a hole, a cropped or masked part) are left out of the data term: the energy
carries them along with their neighbours. No sigma is finer than ``spacing`` x the scan's sampling.

The solve is L-BFGS preconditioned by the energy's Hessian at d = 0 (``h2_metric.sparse_metric``), the data
term's curvature (``data_stiffness``) and the sliding penalty (``optimize.minimize_preconditioned``): plain
L-BFGS needs hundreds of iterations on N x 3 free variables under a second-order energy, this a few tens.

A detail layer never adds broken faces: a fit that flips or collapses faces of the basis fit
(``bad_faces``) is fitted again with a stiffer energy (``stiffen`` times the last, ``retries`` times); where
the last fit still flips a face or makes the surface cross itself where the basis fit did not, the detail is
faded out around those faces (``fade``), wider each round, and left out (d = 0) when that does not end it. The result is a ``Detail``, in the
template frame: F(alpha) + d is the detailed mesh. Why each choice: docs/decisions/022-detail-layer.md.
"""

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import torch
from scipy.spatial import cKDTree

from .. import h2_metric, optimize
from ..geometry import vertex_areas
from ..mesh import edge_split, face_geometry, self_intersections, vertex_adjacency
from ..varifold import VarifoldLoss, default_cutoff, is_oriented
from .problem import orient_like


@dataclass
class Detail:
    """The detail layer of a registration: displacement (N, 3) in the template frame (None when left
    out), one report per level {sigma, weight, subdivided, stiffness, iterations, evaluations, energy,
    varifold, seconds}, how many times the energy was stiffened, how many vertices were faded out to keep
    the surface whole, why the layer was left out (None: kept), seconds, and the scan's estimated noise
    (``scan_noise``, a length in the template frame; None where not estimated)."""

    displacement: np.ndarray | None
    levels: list
    stiffened: int = 0
    faded: int = 0
    skipped: str | None = None
    seconds: float = 0.0
    noise: float | None = None

    def to_json(self):
        """JSON-ready summary (no arrays): kept, skipped, stiffened, faded, rms and max displacement, levels,
        seconds, noise."""
        size = None if self.displacement is None else np.linalg.norm(self.displacement, axis=1)
        return {"kept": self.displacement is not None, "skipped": self.skipped, "stiffened": self.stiffened,
                "faded": self.faded, "rms": None if size is None else float(np.sqrt((size ** 2).mean())),
                "max": None if size is None else float(size.max()), "levels": self.levels,
                "seconds": float(self.seconds), "noise": None if self.noise is None else float(self.noise)}


def bad_faces(verts, faces, reference, flip_cos=0.0, collapse=0.1):
    """Faces of ``verts`` flipped against ``reference`` (their normals' cosine below flip_cos) or collapsed
    (area below collapse x the reference's): (N, 3), (F, 3), (N, 3) -> bool (F,)."""
    vec, area, _ = face_geometry(verts, faces)
    ref_vec, ref_area, _ = face_geometry(reference, faces)
    cos = (vec * ref_vec).sum(1) / np.maximum(area * ref_area, 1e-300)
    return (cos < flip_cos) | (area < collapse * ref_area)


def scan_spacing(verts, faces):
    """The scan's sampling: the side of a right isosceles triangle of its median face area (a length)."""
    return math.sqrt(2.0 * float(np.median(face_geometry(verts, faces)[1])))


def scan_noise(verts, neighbours=10, centres=50000):
    """A robust estimate of the std of a scan's vertex noise across its surface: each vertex's height over
    the quadric least-squares fitted to its ``neighbours`` nearest vertices (itself among them), standardised
    by its leverage, 1.4826 x the median of their sizes (the quadric takes the surface's curvature; a clean
    mesh still shows its sampling's share, a fraction of a millimetre on a body); at most ``centres``
    vertices (a fixed random choice) are measured: verts (M, 3) -> a length."""
    points = np.asarray(verts, dtype=np.float64)
    chosen = points
    if len(points) > centres:
        chosen = points[np.random.default_rng(0).choice(len(points), centres, replace=False)]
    near = points[cKDTree(points).query(chosen, k=min(neighbours, len(points)))[1]]   # (C, k, 3), itself first
    centred = near - near.mean(1, keepdims=True)
    frame = np.linalg.eigh(np.einsum("mki,mkj->mij", centred, centred))[1]          # columns: normal first
    local = np.einsum("mki,mij->mkj", near - near[:, :1], frame)                     # (height, u, t)
    height, u, t = local[..., 0], local[..., 1], local[..., 2]
    spread = np.sqrt((u ** 2 + t ** 2).mean(1, keepdims=True)) + 1e-300
    u, t = u / spread, t / spread
    design = np.stack([np.ones_like(u), u, t, u * u, u * t, t * t], -1)              # (C, k, 6)
    normal = np.einsum("mki,mkj->mij", design, design) + 1e-9 * np.eye(6)
    coef = np.linalg.solve(normal, np.einsum("mki,mk->mi", design, height)[..., None])[..., 0]
    residual = height[:, 0] - np.einsum("mi,mi->m", design[:, 0], coef)
    leverage = np.einsum("mi,mi->m", design[:, 0], np.linalg.solve(normal, design[:, 0][..., None])[..., 0])
    return 1.4826 * float(np.median(np.abs(residual) / np.sqrt(np.clip(1 - leverage, 1e-3, None))))


def reached_faces(fit, faces, target, target_faces, target_weights, distance):
    """Template faces whose centre lies within ``distance`` of the scan's counted surface (its vertices and
    face centres): fit (N, 3), faces (F, 3), target (M, 3), target_faces (G, 3), target_weights (G,) or None
    -> bool (F,)."""
    tf = target_faces if target_weights is None else target_faces[np.asarray(target_weights) > 0]
    points = np.concatenate([target[np.unique(tf)], face_geometry(target, tf)[2]])
    return cKDTree(points).query(face_geometry(fit, faces)[2], k=1, distance_upper_bound=distance)[0] <= distance


def data_stiffness(objective, x, stiff_matrix, stiffness, mass, probe=1e-4):
    """The data term's curvature per unit area along its own gradient: a finite difference of the objective's
    gradient at x (3N,) along it, less the energy's part (2 x stiffness x stiff_matrix), over the mass
    matrix's norm of the direction (>= 0) -> (float, (the objective's value at x, its gradient (3N,)))."""
    def evaluate(z):
        zt = torch.from_numpy(z).requires_grad_(True)
        value = objective(zt)
        return float(value.detach()), torch.autograd.grad(value, zt)[0].numpy()

    value, g = evaluate(x)
    direction = g / max(math.sqrt(float(g @ (mass @ g))), 1e-300)
    length = probe * max(float(np.abs(x).max()), 1.0)
    curvature = direction @ (evaluate(x + length * direction)[1] - g) / length
    curvature -= 2 * stiffness * direction @ (stiff_matrix @ direction)
    return max(float(curvature), 0.0), (value, g)


def vertex_normals(verts, faces):
    """Area-weighted unit vertex normals of a consistently wound mesh: (N, 3), (F, 3) -> (N, 3)."""
    vectors = face_geometry(verts, faces)[0]
    normals = np.zeros_like(np.asarray(verts, dtype=np.float64))
    for k in range(3):
        np.add.at(normals, faces[:, k], vectors)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)


def tangential_matrix(verts, faces):
    """sum_v A_v |d_v - (d_v . n_v) n_v|^2 as d^T T d on vertex fields flattened vertex-major: (N, 3), (F, 3)
    -> scipy.sparse csr (3N, 3N) (3 x 3 blocks A_v (I - n_v n_v^T))."""
    normals = vertex_normals(verts, faces)
    area = vertex_areas(torch.as_tensor(verts), torch.as_tensor(faces)).numpy()
    blocks = area[:, None, None] * (np.eye(3)[None] - normals[:, :, None] * normals[:, None, :])
    return scipy.sparse.block_diag(list(blocks), format="csr")


def fade(displacement, faces, vertices, rings):
    """The displacement (N, 3) faded to 0 at ``vertices`` and over ``rings`` rings of edges around them
    (linearly in the ring): -> (N, 3)."""
    n = displacement.shape[0]
    adjacency = vertex_adjacency(n, faces)
    reached = np.zeros(n, dtype=bool)
    reached[vertices] = True
    keep = np.where(reached, 0.0, 1.0)
    for ring in range(1, rings + 1):
        grown = (adjacency @ reached.astype(np.float64)) > 0
        keep[grown & ~reached] = ring / (rings + 1)
        reached |= grown
    return displacement * keep[:, None]


def _crossing_vertices(verts, faces, reference, near=None):
    """Vertices of the faces of ``verts`` that cross another face where those two faces of ``reference``
    (N, 3) do not; near (K,) vertex indices: only faces about those are tested (where the surface changed
    since the last test; every face within twice a face's size of them) -> (K',) int."""
    tested = np.arange(len(faces))
    if near is not None and not len(near):
        return np.zeros(0, dtype=np.int64)
    if near is not None:
        centres = face_geometry(verts, faces)[2]
        reach = 2 * float(np.linalg.norm(verts[faces] - centres[:, None], axis=2).max())
        close = cKDTree(verts[near]).query(centres, k=1, distance_upper_bound=reach)[0] <= reach
        tested = np.flatnonzero(close)
    pairs = tested[self_intersections(verts, faces[tested])]
    if len(pairs):  # those that crossed already (tested among the few faces involved)
        involved = np.unique(pairs)
        old = {tuple(p) for p in involved[self_intersections(reference, faces[involved])].tolist()}
        pairs = np.array([p for p in pairs.tolist() if tuple(p) not in old], dtype=np.int64).reshape(-1, 2)
    return np.unique(faces[pairs.ravel()])


def fit_detail(fit, faces, target, target_faces, settings, metric, scale, *, backend="auto", device="cpu",
               target_weights=None, landmarks=None, monitor=None, progress=(0.0, 1.0)):
    """Detail displacements of a basis fit: fit (N, 3) F(alpha) and target (M, 3) the scan in the template
    frame, faces (F, 3), target_faces (G, 3), settings a ``DetailFit``, metric the H2 weights, scale the
    basis' (sigmas are relative to it); backend and device (torch) of the objective, float64 (the
    preconditioned solve runs on the CPU); target_weights (G,) numpy or None; landmarks (pull, points) as
    ``RegistrationProblem`` holds them, or None; monitor a ``progress.Monitor`` (cancellable) -> Detail."""
    t0 = time.perf_counter()
    fit, faces = np.asarray(fit, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    target, target_faces = np.asarray(target, dtype=np.float64), np.asarray(target_faces, dtype=np.int64)
    if is_oriented(settings.kernel):  # the scan's pieces turned to face like the basis fit
        target_faces = orient_like(target, target_faces, fit, faces, target_weights)[0]
    on = {"dtype": torch.float64, "device": device}
    q, f = torch.as_tensor(fit, **on), torch.as_tensor(faces, device=device)
    tv, tf = torch.as_tensor(target, **on), torch.as_tensor(target_faces, device=device)
    tw = None if target_weights is None else torch.as_tensor(np.asarray(target_weights, dtype=np.float64), **on)
    counted = target_faces if target_weights is None else target_faces[np.asarray(target_weights) > 0]
    floor = settings.spacing * scan_spacing(target, counted)
    # a noisier scan is a less likely surface: the data term weighs as the inverse of the noise's variance
    # (the estimate less the floor a clean mesh's sampling makes), whole up to the floor's; the layer takes
    # the scan's detail, not its noise
    noise = scan_noise(target[np.unique(counted)]) if settings.noise_floor is not None else None
    noise = noise if noise is not None and math.isfinite(noise) else None  # (a degenerate scan: not lowered)
    quiet = 1.0
    if noise is not None:
        floor2 = (settings.noise_floor * scale) ** 2
        quiet = min(1.0, floor2 / max(noise ** 2 - floor2, 1e-300))
    plan = []  # (sigma, weight, iterations, subdivided) per level; a level the floor makes a repeat is dropped
    for k, s in enumerate(settings.sigmas):
        level = (max(s * scale, floor), quiet * settings.weights[min(k, len(settings.weights) - 1)],
                 settings.max_iter[min(k, len(settings.max_iter) - 1)],
                 bool(settings.subdivided[min(k, len(settings.subdivided) - 1)]))
        if not plan or level[0] < plan[-1][0] * 0.999 or level[3] != plan[-1][3]:
            plan.append(level)
    reached = reached_faces(fit, faces, target, target_faces, target_weights, settings.reach * plan[0][0])
    # a subdivided level's data term sees each face as its four midpoint sub-faces: one point per face is
    # too coarse a quadrature at a sigma under the template's edge length (it biases the fit by a fraction
    # of a millimetre; three Strang-Fix points measured a little less close for a little less time)
    edges, fine_faces = edge_split(faces, len(fit))  # (sub-face k + jF from face k)
    edges, fine_faces = torch.as_tensor(edges, device=device), torch.as_tensor(fine_faces, device=device)
    weights_of = {False: torch.as_tensor(reached, **on), True: torch.as_tensor(np.tile(reached, 4), **on)}
    ramp = torch.linspace(0, 1, settings.steps + 1, **on)[:, None, None]
    stiff_matrix = h2_metric.sparse_metric(q.cpu(), f.cpu(), metric)  # the energy's Hessian at d = 0 is 2 x this
    areas = vertex_areas(q, f)
    mass = scipy.sparse.kron(scipy.sparse.diags(areas.cpu().numpy()), scipy.sparse.identity(3), format="csr")
    sliding = tangential_matrix(fit, faces)
    normals = torch.as_tensor(vertex_normals(fit, faces), **on)
    lo, hi = progress
    stiffness, stiffened = 1.0, 0
    for attempt in range(settings.retries + 1):
        x, levels = np.zeros(q.numel()), []
        for k, (sigma, weight, iterations, subdivided) in enumerate(plan):
            t1 = time.perf_counter()
            loss = VarifoldLoss(tv, tf, sigma, kernel=settings.kernel, backend=backend, target_weights=tw,
                                cutoff=default_cutoff(sigma, settings.tol), target_cell=settings.scan_cell * sigma,
                                ranges_margin=settings.ranges_margin)
            terms, slide, source_weights = {}, [0.0], weights_of[subdivided]

            def objective(xt):
                d = xt.to(device).reshape(q.shape)
                moved = q + d
                energy = stiffness * h2_metric.path_energy(q + ramp * d, f, metric)
                if subdivided:
                    fine = torch.cat([moved, (moved[edges[:, 0]] + moved[edges[:, 1]]) / 2])
                    gamma = loss(fine, fine_faces, source_weights)
                else:
                    gamma = loss(moved, f, source_weights)
                data = gamma if landmarks is None else gamma + landmarks[0](moved, landmarks[1])
                terms[xt.detach().cpu().numpy().tobytes()] = (float(energy.detach()), float(gamma.detach()))
                out = weight * data + energy
                if slide[0]:  # d^T T d of ``tangential_matrix``
                    along = d - (d * normals).sum(1, keepdim=True) * normals
                    out = out + slide[0] * (areas * (along ** 2).sum(1)).sum()
                return out

            share = (lo + (hi - lo) * k / len(plan), lo + (hi - lo) * (k + 1) / len(plan))
            start = None
            if k == 0 or weight != plan[k - 1][1]:  # (a finer level keeps the preconditioner: L-BFGS rescales it)
                curvature, first = data_stiffness(objective, x, stiff_matrix, stiffness, mass)
                start = None if x.any() else first  # the solve's first evaluation (at d = 0 sliding adds nothing)
                solve = optimize.sparse_solver(2 * stiffness * stiff_matrix + curvature * mass
                                               + 2 * settings.tangential * curvature * sliding)
            slide[0] = settings.tangential * curvature  # sliding along the surface costs like a normal misfit
            x, _, nit = optimize.minimize_preconditioned(objective, x, solve, monitor, max_iter=iterations,
                                                         progress=share, message=f"registration: detail "
                                                         f"(sigma {sigma:.3g})", ftol=settings.ftol,
                                                         plateau=(settings.plateau_window, settings.plateau),
                                                         memory=settings.memory, start=start)
            energy, gamma = terms.get(x.tobytes(), (float("nan"), float("nan")))
            levels.append({"sigma": float(sigma), "weight": float(weight), "subdivided": subdivided,
                           "stiffness": float(stiffness),
                           "iterations": int(nit), "evaluations": len(terms), "energy": energy, "varifold": gamma,
                           "seconds": time.perf_counter() - t1})
        d = x.reshape(q.shape)
        if attempt == settings.retries or not bad_faces(fit + d, faces, fit, settings.flip_cos, settings.collapse).any():
            break
        stiffness *= settings.stiffen
        stiffened += 1
    # the kept layer adds no crossing of the surface and no bad face (those the stiffest fit still has): faded
    # out around them, wider each round
    faded = np.zeros(len(fit), dtype=bool)
    changed = None  # (after the first test, only about the vertices a fade changed)
    for rings in range(settings.fade_rings, settings.fade_rings + settings.fade_rounds + 1):
        broken = np.unique(faces[bad_faces(fit + d, faces, fit, settings.flip_cos, settings.collapse)])
        broken = np.union1d(broken, _crossing_vertices(fit + d, faces, fit, changed))
        if not len(broken):
            return Detail(d, levels, stiffened, int(faded.sum()), None, time.perf_counter() - t0, noise)
        faded[broken] = True
        faded_before = d
        d = fade(d, faces, np.flatnonzero(faded), rings)
        changed = np.flatnonzero(np.any(d != faded_before, axis=1))
    return Detail(None, levels, stiffened, int(faded.sum()), "it flipped faces or made the surface cross itself",
                  time.perf_counter() - t0, noise)


def detail_of(basis, code, transform, scan_verts, scan_faces, config, scan_face_weights=None, landmarks=None,
              monitor=None, progress=(0.0, 1.0)):
    """The detail layer of a basis fit: code (P,), transform (scan -> template frame), the scan (M, 3), (G, 3) in
    its frame, a ``RegistrationConfig`` (its ``detail`` settings, shape metric and backend); scan_face_weights
    (G,) or None; landmarks (pull, points in the template frame) or None -> Detail."""
    return fit_detail(basis.template + np.tensordot(code, basis.fields, axes=1), basis.faces,
                      transform.apply(np.asarray(scan_verts, dtype=np.float64)), scan_faces, config.detail,
                      config.shape_metric(basis), basis.scale, backend=config.backend, device=config.device,
                      target_weights=scan_face_weights, landmarks=landmarks, monitor=monitor, progress=progress)
