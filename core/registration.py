r"""Latent code retrieval of an unregistered scan (paper section 4.1), with rigid pre-alignment.

Given a basis (template q-bar, fields h_i, metric weights, schedule) and a scan q with any
vertices and faces, ``register`` minimises over discrete latent paths
alpha = (alpha(0) = 0, alpha(1/T), ..., alpha(1))  (P*T free variables)

    weight * [ Gamma(S(F(alpha(1))), T(q)) + landmark term ]  +  E(alpha),

where Gamma is the squared varifold distance at scale sigma (``core.varifold``), E the discrete
H2 path energy of the decoded path (``h2_metric.path_energy``; this is the paper's energy
Gamma + (1/lambda) E multiplied by lambda = ``weight``), T the similarity that maps the scan
into the template frame (the pre-alignment) and S a small similarity (rotation, translation,
log-scale; 7 variables) optimised jointly with the path, so that the pre-alignment is refined
at every level (``refine_transform``). The schedule is multiscale (sigma decreasing, weight
and steps increasing); each level is warm-started from the last, its latent path resampled
linearly in time to the new number of steps.

Pre-alignment (``align_to_template``): both surfaces are normalised (area-weighted centroid, RMS radius);
candidate rotations map the principal axes of the scan's area-weighted second moments onto the
template's (the 24 proper signed permutations, so near-equal moments and any axis order are
covered) plus the identity; each is scored by a coarse binet varifold (faces binned into cubic
cells, each cell keeping its area-weighted centroid and orientation tensor sum a n n^T, which is
exact for the binet kernel up to the binning of positions); the best few are refined by
L-BFGS over (axis-angle, translation, log-scale) at a coarse then a finer sigma. A deformed
scan of a nearly symmetric template can match a flipped template better than the right one,
so ``register`` runs a short first level from each distinct candidate whose varifold is within
PREALIGN_RATIO of the best, ranks them by ``screen_score`` and, when the best two are within
SCREEN_TIE, runs a short second level from both and keeps the one that fits better at the second
level's sigma (at the first level's sigma a body is nearly front/back symmetric). The binet
kernel ignores normal orientation, so inconsistently oriented scans align as well.

Pose candidates (``_try_poses``): the first level cannot find a pose far from the template (at
coarse sigma raising an arm overhead costs more energy than it gains in data term, so an elbow
bends instead, and the finer levels keep that local minimum). A basis may store typical poses
(``extras["pose_prototypes"]``, k-means centres of its training codes); before the second level
each one's pose group, with the other groups of the code so far, is re-aligned to the scan and
scored at the second level's sigma; the best few get a short second level next to the current
path, and the one that fits best at the next level's sigma goes on.

Frames: registration happens in the template frame; ``RegistrationResult.vertices`` are mapped
back with the inverse similarity, so they overlay the scan in the scan's units.
"""

import math
import time
from dataclasses import dataclass, field, replace
from itertools import permutations, product

import numpy as np
import torch

from . import h2_metric
from .errors import InputError, MeshError
from .evaluation import chamfer
from .h2_metric import H2Weights
from .latent import Level, decode, time_whitening, whitening
from .mesh import validate_mesh
from .optimize import minimize_lbfgs
from .progress import Monitor
from .varifold import VarifoldLoss, default_cutoff

#: Pre-alignment sigmas (scoring/refinement, final refinement), in units of the RMS radius.
PREALIGN_SIGMAS = (0.5, 0.25)
PREALIGN_CELL = 0.5         # bin size of the binned measure, in units of its sigma
PREALIGN_REFINE = 8         # candidates refined at the coarse sigma
PREALIGN_KEEP = 6           # distinct ones refined at the finer sigma and tried by the first level
PREALIGN_DISTINCT = 20.0    # degrees between two distinct candidates
PREALIGN_RATIO = 4.0        # candidates whose varifold is within this factor of the best's are tried
PREALIGN_MAX_ITER = 40
SCREEN_DIVISOR = 8          # candidate alignments are screened with 1/8 of the first level's iterations
#                             and a one-step path (the end code decides between alignments)
SCREEN_CELL = 0.25          # screened alignments are compared on cells of this x sigma (both surfaces):
#                             the level's own coarse binning (BIN_CELL) errs differently per alignment
SCREEN_FINALISTS = 2        # the best screened alignments get a short second level, which decides: at the
SCREEN_SECOND_ITER = 5      # first level's sigma a body is nearly front/back symmetric...
SCREEN_TIE = 1.5            # ... when the second best scored within this factor of the best
PREALIGN_FRACTION = 0.1     # share of the progress bar given to the pre-alignment
#: Pose candidates (a basis' stored ``pose_prototypes``, see ``_try_poses``): before the second level each
#: prototype's pose coefficients, with the code's other groups, are re-aligned to the scan (at most
#: POSE_ALIGN_ITER L-BFGS steps) and scored at the second level's sigma with POSE_WEIGHT_GAIN x its
#: weight (the level's own weight prefers a bent elbow to an arm raised overhead: less energy); the best
#: POSE_FINALISTS within POSE_TIE x the current code's score get a short solve at that weight (POSE_ITER
#: iterations) next to the current path; the one that fits best at the next level's sigma goes on at
#: the level's own weight.
POSE_FINALISTS = 2
POSE_TIE = 2.0
POSE_ITER = 40
POSE_WEIGHT_GAIN = 10.0
POSE_ALIGN_ITER = 15
#: L-BFGS stops a level when an iteration lowers the objective by less than this relative amount
#: (the objective is dominated by weight x varifold; later digits only polish the path's interior)
LEVEL_FTOL = 1e-9
#: ... and when it fell by less than LEVEL_PLATEAU[1] (relative) over the last LEVEL_PLATEAU[0]
#: iterations: easy problems plateau within ~15 iterations, a body in a new pose needs ~100
LEVEL_PLATEAU = (5, 1e-3)
BIN_CELL = 0.4              # cell size of the binned varifold, in units of sigma
BIN_GAIN = 0.05             # "auto" bins a level when that leaves at most this share of face pairs
#: Unbinned levels: truncation tolerance of the varifold kernel (cutoff sigma sqrt(log(1/tol)),
#: relative error of d^2 ~1e-6 at paper scale) and cell size, in units of sigma, of the scan's
#: ``binned_measure`` (None: the scan's faces are used as they are)
FINE_TOL = 1e-4
SCAN_CELL = 0.5
#: a level changes the similarity's scale by at most this factor (log): pre-alignment matched the
#: surface areas, and a free scale let wrong alignments grow the template over the scan (x1.9)
SCALE_LOG_LIMIT = math.log(1.15)


# --------------------------------------------------------------------------- similarity


def _rotation_np(w):
    """Rotation matrix of an axis-angle vector: (3,) -> (3, 3) numpy."""
    return _rotation(torch.as_tensor(np.asarray(w, dtype=np.float64))).numpy()


def _rotation(w):
    """Rotation matrix of an axis-angle vector (differentiable, exact at 0): (3,) -> (3, 3)."""
    z = torch.zeros((), dtype=w.dtype, device=w.device)
    skew = torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])
    return torch.linalg.matrix_exp(skew)


@dataclass(frozen=True, eq=False)
class Similarity:
    """The map x -> scale * rotation @ x + translation (scan frame -> template frame).

    rotation (3, 3) proper orthogonal, scale > 0, translation (3,).
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    scale: float = 1.0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        r = np.array(self.rotation, dtype=np.float64).reshape(3, 3)
        t = np.array(self.translation, dtype=np.float64).reshape(3)
        s = float(self.scale)
        if not (np.isfinite(r).all() and np.isfinite(t).all() and math.isfinite(s) and s > 0):
            raise InputError(f"invalid similarity: scale {s}, rotation/translation finite: "
                             f"{bool(np.isfinite(r).all())}/{bool(np.isfinite(t).all())}")
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
            raise InputError("similarity rotation must be a proper rotation matrix (R R^T = I, det +1)")
        for a in (r, t):
            a.flags.writeable = False
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "scale", s)

    def _like(self, points):
        if isinstance(points, torch.Tensor):
            as_t = lambda a: torch.tensor(a.tolist(), dtype=points.dtype, device=points.device)  # noqa: E731
            return as_t(self.rotation), as_t(self.translation)
        return self.rotation, self.translation

    def apply(self, points):
        """Scan frame -> template frame: (..., 3) ndarray or tensor -> same type."""
        r, t = self._like(points)
        return self.scale * points @ r.T + t

    def invert(self, points):
        """Template frame -> scan frame: (..., 3) ndarray or tensor -> same type."""
        r, t = self._like(points)
        return ((points - t) / self.scale) @ r

    def compose(self, other):
        """The similarity ``self o other`` (apply ``other`` first)."""
        return Similarity(self.rotation @ other.rotation, self.scale * other.scale,
                          self.scale * self.rotation @ other.translation + self.translation)

    def inverse(self):
        """The inverse similarity."""
        return Similarity(self.rotation.T, 1.0 / self.scale, -(self.rotation.T @ self.translation) / self.scale)

    def to_dict(self):
        """JSON-ready {"rotation": 3x3 list, "scale": s, "translation": [x, y, z]}."""
        return {"rotation": self.rotation.tolist(), "scale": self.scale,
                "translation": self.translation.tolist()}

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(d["rotation"], d["scale"], d["translation"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"not a similarity record: {d!r}") from exc


def _log_scale(l):
    """A level's log-scale change (tensor), bounded smoothly to +-SCALE_LOG_LIMIT (the objective and
    ``_delta_similarity`` share it)."""
    return SCALE_LOG_LIMIT * torch.tanh(l / SCALE_LOG_LIMIT)


def _delta_similarity(params, center, units):
    """Similarity x -> c + e^l R(w) (x - c) + tau of params (w, tau, l) / units (7,) numpy."""
    p = np.asarray(params) * units
    r = _rotation_np(p[:3])
    s = float(torch.exp(_log_scale(torch.tensor(float(p[6]), dtype=torch.float64))))
    return Similarity(r, s, center - s * r @ center + p[3:6])


# --------------------------------------------------------------------------- pre-alignment


def surface_moments(verts, faces, face_weights=None):
    """Weighted area, centroid (3,) and second moment about it (3, 3) of a surface: exact integrals.

    verts (N, 3), faces (F, 3), face_weights (F,) or None; the second moment is
    int (x - c)(x - c)^T dA / A, so sqrt of its trace is the RMS radius.
    """
    p = np.asarray(verts, dtype=np.float64)[np.asarray(faces)]
    a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    if face_weights is not None:
        a = a * face_weights
    total = a.sum()
    if not total > 0:
        raise MeshError("the scan has zero (weighted) surface area; nothing to register")
    center = (a[:, None] * p.mean(1)).sum(0) / total
    q = p - center
    s = q.sum(1)
    # int over a triangle of x x^T = A/12 (sum_i q_i q_i^T + s s^T), s = sum_i q_i
    second = np.einsum("f,fik,fil->kl", a, q, q) + np.einsum("f,fk,fl->kl", a, s, s)
    return float(total), center, second / (12.0 * total)


def _coarse_measure(points, faces, face_weights, cell):
    """Faces binned into cubic cells -> centroids (C, 3), orientation tensors sum a n n^T (C, 9)."""
    p = points[faces]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    a = 0.5 * norm * (1.0 if face_weights is None else face_weights)
    keep = a > 0
    a, n, c = a[keep], cross[keep] / norm[keep, None], p[keep].mean(1)
    _, inv = np.unique(np.floor(c / cell).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    area = np.bincount(inv, a)
    x = np.stack([np.bincount(inv, a * c[:, k]) for k in range(3)], 1) / area[:, None]
    nn = a[:, None] * (n[:, :, None] * n[:, None, :]).reshape(-1, 9)
    tensors = np.stack([np.bincount(inv, nn[:, k]) for k in range(9)], 1)
    return torch.from_numpy(x), torch.from_numpy(tensors)


class _CoarseVarifold:
    """Binet varifold of binned measures against a fixed target; the source moves by a similarity."""

    def __init__(self, target, source, sigma):
        self.g = 1.0 / sigma**2
        self.xt, self.st = target
        self.xs, self.ss = source
        self.self_t = float(self._inner(self.xt, self.st, self.xt, self.st))

    def _inner(self, x, s, y, t):
        d2 = ((x * x).sum(1)[:, None] + (y * y).sum(1)[None, :] - 2 * x @ y.T).clamp_min(0)
        return (torch.exp(-self.g * d2) * (s @ t.T)).sum()

    def __call__(self, params, base):
        """Squared distance after x -> e^l R(w) base x + tau; params (w, tau, l) (7,) tensor."""
        r = _rotation(params[:3]) @ base
        scale = torch.exp(params[6])
        x = scale * self.xs @ r.T + params[3:6]
        s = (scale**2 * (r @ self.ss.reshape(-1, 3, 3) @ r.T)).reshape(-1, 9)
        return self.self_t - 2 * self._inner(x, s, self.xt, self.st) + self._inner(x, s, x, s)


def _candidate_rotations(axes_t, axes_s):
    """Rotations mapping the scan's principal axes onto the template's (24) plus the identity."""
    out = []
    for perm in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            q = np.zeros((3, 3))
            q[list(perm), range(3)] = signs
            r = axes_t @ q @ axes_s.T
            if np.linalg.det(r) > 0:
                out.append(r)
    out.append(np.eye(3))
    return out


def _rotation_angle(a, b):
    """Angle in degrees between two rotation matrices."""
    return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(a @ b.T) - 1) / 2))))


def prealign_candidates(template_verts, template_faces, scan_verts, scan_faces, scan_face_weights=None,
                        keep=PREALIGN_KEEP, monitor=None, progress=(0.0, 1.0)):
    """Distinct candidate alignments of a scan to a template, best first: -> [(varifold, Similarity)].

    template (N, 3), (F, 3); scan (M, 3), (G, 3); scan_face_weights (G,) or None (zero-weight
    faces are ignored). Each Similarity maps scan coordinates into the template frame; the
    varifold is the (binned, binet) squared distance at the finer pre-alignment sigma between
    the normalised template and the mapped scan. At most ``keep`` candidates, pairwise more
    than PREALIGN_DISTINCT degrees apart.
    """
    monitor = monitor or Monitor("prealign")
    lo, hi = progress
    tv, tf = np.asarray(template_verts, np.float64), np.asarray(template_faces, np.int64)
    sv, sf = np.asarray(scan_verts, np.float64), np.asarray(scan_faces, np.int64)
    _, ct, mt = surface_moments(tv, tf)
    _, cs, ms = surface_moments(sv, sf, scan_face_weights)
    rho_t, rho_s = math.sqrt(np.trace(mt)), math.sqrt(np.trace(ms))
    yt, zs = (tv - ct) / rho_t, (sv - cs) / rho_s
    candidates = _candidate_rotations(np.linalg.eigh(mt)[1], np.linalg.eigh(ms)[1])

    def measures(sigma):
        cell = PREALIGN_CELL * sigma
        return (_coarse_measure(yt, tf, None, cell), _coarse_measure(zs, sf, scan_face_weights, cell))

    coarse = _CoarseVarifold(*measures(PREALIGN_SIGMAS[0]), PREALIGN_SIGMAS[0])
    zero = torch.zeros(7, dtype=torch.float64)
    scores = []
    for r in candidates:
        monitor.check()
        with torch.no_grad():
            scores.append(float(coarse(zero, torch.from_numpy(r))))
    span = (hi - lo) / (PREALIGN_REFINE + keep + 1)
    monitor.report(lo + span, "pre-alignment: candidates scored", min(scores))

    def refine(obj, r, x0, k):
        x, value, _ = minimize_lbfgs(lambda p: obj(p, torch.from_numpy(r)), x0, monitor,
                                     max_iter=PREALIGN_MAX_ITER, progress=(lo + k * span, lo + (k + 1) * span),
                                     message="pre-alignment", gtol=1e-9, ftol=1e-10)
        return _rotation_np(x[:3]) @ r, x, value

    stage = []
    for k, i in enumerate(np.argsort(scores)[:PREALIGN_REFINE]):
        r, x, value = refine(coarse, candidates[i], np.zeros(7), k + 1)
        stage.append((value, r, x))
    stage.sort(key=lambda s: s[0])
    distinct = []
    for value, r, x in stage:
        if all(_rotation_angle(r, d[1]) > PREALIGN_DISTINCT for d in distinct):
            distinct.append((value, r, x))
    fine = _CoarseVarifold(*measures(PREALIGN_SIGMAS[1]), PREALIGN_SIGMAS[1])
    out = []
    for k, (_, r0, x0) in enumerate(distinct[:keep]):
        x0 = np.concatenate([np.zeros(3), x0[3:]])
        r, x, value = refine(fine, r0, x0, PREALIGN_REFINE + 1 + k)
        scale = rho_t * math.exp(x[6]) / rho_s
        out.append((value / fine.self_t, Similarity(r, scale, ct + rho_t * x[3:6] - scale * r @ cs)))
    out.sort(key=lambda c: c[0])
    monitor.report(hi, "pre-alignment done", out[0][0])
    return out


def align_to_template(template_verts, template_faces, scan_verts, scan_faces, scan_face_weights=None,
                      monitor=None, progress=(0.0, 1.0)):
    """Rigid + uniform-scale alignment of a scan to a template from any initial orientation.

    template (N, 3), (F, 3); scan (M, 3), (G, 3); scan_face_weights (G,) or None -> the
    Similarity mapping scan coordinates into the template frame (best of ``prealign_candidates``).
    """
    return prealign_candidates(template_verts, template_faces, scan_verts, scan_faces, scan_face_weights,
                               keep=1, monitor=monitor, progress=progress)[0][1]


# --------------------------------------------------------------------------- binned varifold


def _cell_groups(points, cell):
    """Index of the cubic cell of each point: (F, 3) numpy -> groups (F,) int64, number of cells."""
    _, inv = np.unique(np.floor(points / cell).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    return inv, int(inv.max()) + 1


def _binned_measure(centers, normals, areas, groups, n_groups, kernel):
    """Sums of a face measure over groups -> centroids (C, 3), kernel features (C, K).

    The features make the orientation kernel a dot product, so a group of faces is exact for it:
    binet (n.n')^2 = <n n^T, n' n'^T>: sum a n n^T (9); linear: sum a n (3); constant: sum a (1).
    """
    total = areas.new_zeros(n_groups).index_add(0, groups, areas)
    moment = centers.new_zeros(n_groups, 3).index_add(0, groups, areas[:, None] * centers)
    x = moment / total.clamp_min(torch.finfo(total.dtype).tiny)[:, None]
    if kernel == "binet":
        per_face = (normals[:, :, None] * normals[:, None, :]).reshape(-1, 9)
    elif kernel == "linear":
        per_face = normals
    else:
        per_face = torch.ones_like(areas)[:, None]
    feat = areas.new_zeros(n_groups, per_face.shape[1]).index_add(0, groups, areas[:, None] * per_face)
    return x, feat


class BinnedVarifoldLoss:
    """Squared varifold distance with both measures summed over cubic cells of size BIN_CELL x sigma.

    For sigma much larger than the faces (the coarse levels of a schedule) this replaces
    F x (F + G) face pairs by C x (C + D) cell pairs. The target (scan) is binned once; the
    source's faces are grouped once (by their cells at construction) and each call sums the
    moving faces over these fixed groups (differentiable). Orientation is exact; positions are
    approximated by each group's centroid (relative kernel error ~ (cell / sigma)^2 / 4).
    """

    def __init__(self, source_verts, faces, target_verts, target_faces, sigma, kernel="binet",
                 target_weights=None, cell=None):
        from .varifold import KERNELS, varifold_measure

        if kernel not in KERNELS:
            raise InputError(f"unknown varifold kernel {kernel!r}; choose one of {sorted(KERNELS)}")
        self.g, self.kernel = 1.0 / sigma**2, kernel
        cell = BIN_CELL * sigma if cell is None else cell
        centers = varifold_measure(source_verts.detach(), faces)[0]
        groups, self.n_groups = _cell_groups(centers.cpu().numpy(), cell)
        self.groups = torch.as_tensor(groups, device=source_verts.device)
        c, n, a = varifold_measure(target_verts, target_faces, target_weights)
        t_groups, n_t = _cell_groups(c.cpu().numpy(), cell)
        x, feat = _binned_measure(c, n, a, torch.as_tensor(t_groups, device=c.device), n_t, kernel)
        keep = feat.abs().sum(1) > 0
        self.target = (x[keep], feat[keep])
        self.n_target = int(keep.sum())
        self._self_t = None

    @property
    def self_t(self):
        """|target|^2 (computed on first use: callers may first only look at the sizes)."""
        if self._self_t is None:
            with torch.no_grad():
                self._self_t = self._inner(*self.target, *self.target)
        return self._self_t

    def _inner(self, x, f, y, h, chunk=2**22):
        out = x.new_zeros(())
        rows = max(1, chunk // max(1, y.shape[0]))
        y2 = (y * y).sum(1)[None, :]
        for s in range(0, x.shape[0], rows):
            xs = x[s:s + rows]
            d2 = ((xs * xs).sum(1)[:, None] + y2 - 2 * xs @ y.T).clamp_min(0)
            out = out + (torch.exp(-self.g * d2) * (f[s:s + rows] @ h.T)).sum()
        return out

    def __call__(self, verts, faces):
        """Squared binned distance of the mesh (verts (N, 3), faces (F, 3)) to the target -> scalar."""
        from .varifold import varifold_measure

        x, f = _binned_measure(*varifold_measure(verts, faces), self.groups, self.n_groups, self.kernel)
        return self._inner(x, f, x, f) - 2 * self._inner(x, f, *self.target) + self.self_t


# --------------------------------------------------------------------------- registration


@dataclass
class RegistrationResult:
    """Latent code of a scan and the registered template.

    code (P,); vertices (N, 3) registered template in the scan's frame and units; path (T+1, P)
    the final latent path from 0 to code; transform the similarity scan -> template frame
    (pre-alignment refined by the registration: vertices = transform.invert(F(code)));
    levels one dict per schedule level {sigma, weight, steps, iterations, energy, varifold,
    objective, binned, seconds}; varifold the squared varifold residual at the finest sigma (template
    frame); chamfer between vertices and the scan (scan frame); seconds of wall time;
    prealignment the candidate alignment the registration started from.
    """

    code: np.ndarray
    vertices: np.ndarray
    path: np.ndarray
    transform: Similarity
    levels: list
    varifold: float
    chamfer: float
    seconds: float
    prealignment: Similarity = None

    def to_json(self):
        """JSON-ready summary {code, varifold, chamfer, seconds, levels, transform}."""
        return {"code": [float(c) for c in self.code], "varifold": float(self.varifold),
                "chamfer": float(self.chamfer), "seconds": float(self.seconds),
                "levels": [{k: (float(v) if isinstance(v, float) else v) for k, v in lv.items()}
                           for lv in self.levels],
                "transform": self.transform.to_dict()}


def resample_in_time(path, steps):
    """Linear resampling in time of a latent path from 0: (T+1, P) -> (steps+1, P)."""
    path = np.asarray(path, dtype=np.float64)
    t_old = np.linspace(0.0, 1.0, path.shape[0])
    t_new = np.linspace(0.0, 1.0, steps + 1)
    return np.stack([np.interp(t_new, t_old, path[:, i]) for i in range(path.shape[1])], 1)


class _PathVariables:
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
        self.r_inv = time_whitening(steps - 1) * math.sqrt(1.0 / steps) if steps > 1 else np.zeros((0, 0))
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


def _check_schedule(schedule):
    try:
        levels = tuple(lv if isinstance(lv, Level) else Level(**lv) for lv in schedule)
    except TypeError as err:
        raise InputError(f"a schedule is a sequence of Level(sigma, weight, steps, max_iter): {err}") from None
    if not levels:
        raise InputError("the registration schedule is empty")
    return levels


def _check_face_weights(weights, n_faces):
    if weights is None:
        return None
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n_faces,):
        raise InputError(f"scan face weights must have shape ({n_faces},), one per scan face, got {w.shape}")
    if not np.isfinite(w).all() or (w < 0).any():
        raise InputError("scan face weights must be finite and >= 0")
    if not (w > 0).any():
        raise InputError("every scan face weight is zero: nothing to register")
    return w


def _check_landmarks(landmarks, n_verts):
    """[(template vertex, scan xyz[, weight]), ...] -> indices (L,), points (L, 3), weights (L,)."""
    if landmarks is None or len(landmarks) == 0:
        return None
    idx, pts, wts = [], [], []
    for k, lm in enumerate(landmarks):
        if len(lm) not in (2, 3):
            raise InputError(f"landmark {k}: expected (template vertex index, (x, y, z)[, weight]), got {lm!r}")
        i = lm[0]
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < n_verts:
            raise InputError(f"landmark {k}: template vertex index {i!r} is not an integer in 0..{n_verts - 1}")
        p = np.asarray(lm[1], dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise InputError(f"landmark {k}: scan point must be 3 finite coordinates, got {lm[1]!r}")
        w = float(lm[2]) if len(lm) == 3 else 1.0
        if not (math.isfinite(w) and w >= 0):
            raise InputError(f"landmark {k}: weight must be finite and >= 0, got {w}")
        idx.append(int(i))
        pts.append(p)
        wts.append(w)
    if sum(wts) <= 0:
        return None
    return np.array(idx), np.stack(pts), np.array(wts)


def _check_pose_candidates(basis, candidates):
    """Pose candidates (K, P) float64 from ``register``'s argument, or None."""
    if isinstance(candidates, str):
        if candidates != "auto":
            raise InputError(f"pose_candidates must be 'auto', None or an array of codes, got {candidates!r}")
        candidates = basis.extras.get("pose_prototypes")
    if candidates is None:
        return None
    codes = np.asarray(candidates, dtype=np.float64)
    if codes.ndim != 2 or codes.shape[1] != basis.n_fields or not np.isfinite(codes).all():
        raise InputError(f"pose candidates must be finite codes of shape (K, {basis.n_fields}), got {codes.shape}")
    return codes if len(codes) else None


def pose_starts(basis, candidates, code):
    """Start codes from pose candidates: each candidate's "pose" group with ``code``'s other groups
    (the candidates themselves when the basis has no "pose" group or nothing else): (K, P), (P,) -> (K, P)."""
    starts = np.array(candidates, dtype=np.float64)
    if "pose" in basis.groups and len(basis.groups) > 1:
        keep = np.ones(basis.n_fields, dtype=bool)
        keep[basis.group_slice("pose")] = False
        starts[:, keep] = code[keep]
    return starts


def register(basis, scan_verts, scan_faces, *, schedule=None, prealign=True, landmarks=None,
             landmark_weight=1.0, scan_face_weights=None, metric=None, kernel="binet", backend="auto",
             binning="auto", refine_transform=None, init_code=None, pose_candidates="auto", callback=None, cancel=None,
             dtype=torch.float64, device="cpu"):
    """Latent code of an unregistered scan: basis, scan (M, 3), (G, 3) -> RegistrationResult.

    schedule: Levels (default basis.schedule); prealign: align the scan to the template first
    (else it must be in the template frame already); landmarks: [(template vertex, scan xyz
    [, weight])], adding weight * landmark_weight * A * sum_i w_i |S F(alpha)_i - T p_i|^2 / sum w
    (A the template area: comparable to the varifold of a surface offset by the same distance);
    scan_face_weights (G,) >= 0 (0 ignores a face, e.g. a floor); metric: H2 weights (default
    the basis'); kernel, backend: of the varifold (``core.varifold``); binning: "auto" evaluates
    a level's varifold on cell sums (``BinnedVarifoldLoss``) when sigma is so large that this
    cuts the face pairs 20-fold, True always, False never (an unbinned level still sums the scan
    alone over cells of SCAN_CELL x sigma when that leaves fewer points, ``VarifoldLoss(target_cell=)``,
    and truncates the kernel at FINE_TOL); refine_transform: optimise the
    similarity jointly with the path (default: as prealign); init_code (P,) starts from the
    straight path 0 -> init_code; pose_candidates (K, P): codes whose pose group (the whole code
    when the basis has no other group) is tried as a start of the second level (see POSE_FINALISTS),
    "auto" the basis' ``extras["pose_prototypes"]`` if it has them, None none; dtype: precision of
    the objective (the optimiser is float64).
    Raises MeshError/InputError on bad input, SolveCancelled when cancelled (no partial result).
    """
    start_time = time.perf_counter()
    monitor = Monitor("register", callback, cancel)
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise InputError(f"dtype must be a torch floating point dtype, got {dtype!r}")
    validate_mesh(scan_verts, scan_faces, "scan")
    sv, sf = np.asarray(scan_verts, np.float64), np.asarray(scan_faces, np.int64)
    face_w = _check_face_weights(scan_face_weights, sf.shape[0])
    marks = _check_landmarks(landmarks, basis.template.shape[0])
    if not (math.isfinite(landmark_weight) and landmark_weight >= 0):
        raise InputError(f"landmark_weight must be finite and >= 0, got {landmark_weight}")
    levels = _check_schedule(basis.schedule if schedule is None else schedule)
    if binning not in ("auto", True, False):
        raise InputError(f"binning must be 'auto', True or False, got {binning!r}")
    metric = H2Weights.parse(basis.weights if metric is None else metric)
    refine_transform = prealign if refine_transform is None else bool(refine_transform)
    path = np.zeros((2, basis.n_fields))
    if init_code is not None:
        init = np.asarray(init_code, dtype=np.float64)
        if init.shape != (basis.n_fields,) or not np.isfinite(init).all():
            raise InputError(f"init_code must be {basis.n_fields} finite coefficients, got shape {init.shape}")
        path[1] = init
    poses = _check_pose_candidates(basis, pose_candidates)

    monitor.report(0.0, "registration: pre-aligning" if prealign else "registration: starting")
    monitor.check()
    if prealign:
        candidates = prealign_candidates(basis.template, basis.faces, sv, sf, face_w, monitor=monitor,
                                         progress=(0.0, PREALIGN_FRACTION))
        candidates = [c for c in candidates if c[0] <= PREALIGN_RATIO * candidates[0][0] + 1e-12]
    else:
        candidates = [(0.0, Similarity())]
    problem = _Problem(basis, sv, sf, face_w, marks, landmark_weight, metric, kernel, backend, binning,
                       refine_transform, dtype, device, monitor)

    # progress: the first level is tried from every candidate alignment
    budget = np.array([lv.steps * lv.max_iter for lv in levels], dtype=np.float64)
    budget[0] *= 1 + (len(candidates) / SCREEN_DIVISOR if len(candidates) > 1 else 0)
    tries_poses = poses is not None and len(levels) > 1
    if tries_poses:
        budget[1] += (POSE_FINALISTS + 1) * levels[1].steps * POSE_ITER
    lo = PREALIGN_FRACTION if prealign else 0.0
    bounds = lo + (1 - lo) * np.concatenate([[0.0], np.cumsum(budget) / budget.sum()])
    name = lambda k: f"registration level {k + 1}/{len(levels)}"  # noqa: E731
    # screen every candidate alignment with a short first level; only the best one gets the full level
    screen = levels[0] if len(candidates) == 1 else replace(levels[0], steps=1,
                                                            max_iter=max(10, levels[0].max_iter // SCREEN_DIVISOR))
    share = len(candidates) / SCREEN_DIVISOR
    mid = bounds[1] if screen is levels[0] else bounds[0] + (bounds[1] - bounds[0]) * share / (1 + share)
    tries = []
    for j, (_, transform) in enumerate(candidates):
        span = (mid - bounds[0]) / len(candidates)
        tries.append(problem.solve_level(screen, path, transform, (bounds[0] + j * span, bounds[0] + (j + 1) * span),
                                         name(0) + (f" (alignment {j + 1}/{len(candidates)})" if j else "")))
    best, resume = 0, None
    if len(tries) > 1:
        # the screened objectives ranked on fine cells; the finer second level decides between the best
        scores = [problem.screen_score(levels[0], p[-1], t, r["energy"]) for p, t, r in tries]
        order = np.argsort(scores)
        best = int(order[0])
        finalists = [int(j) for j in order[:SCREEN_FINALISTS] if scores[j] <= SCREEN_TIE * scores[best]]
        if len(levels) > 1 and len(finalists) > 1:
            short = replace(levels[1], max_iter=SCREEN_SECOND_ITER)
            second = [problem.solve_level(short, tries[j][0], tries[j][1], (mid, mid), name(1) + " (screening)")
                      for j in finalists]
            k = int(np.argmin([problem.screen_score(levels[1], p[-1], t, r["energy"]) for p, t, r in second]))
            best, resume = finalists[k], second[k]  # the second level goes on from the winner's short one
    (path, transform, first), initial = tries[best], candidates[best][1]
    if resume is not None:
        path, transform = resume[0], resume[1]
    elif screen is not levels[0]:
        path, transform, first = problem.solve_level(levels[0], path, transform, (mid, bounds[1]), name(0))
    report = [first]
    monitor.report(bounds[1], f"{name(0)} done", first["objective"])
    for k in range(1, len(levels)):
        span = (bounds[k], bounds[k + 1])
        if k == 1 and tries_poses:
            path, transform, share = _try_poses(problem, basis, levels[1], levels[min(2, len(levels) - 1)], path,
                                                transform, poses, span, name(1))
            span = (span[0] + share * (span[1] - span[0]), span[1])
        path, transform, lv_report = problem.solve_level(levels[k], path, transform, span, name(k))
        report.append(lv_report)
        monitor.report(bounds[k + 1], f"{name(k)} done", lv_report["objective"])

    code = path[-1]
    decoded = basis.template + np.tensordot(code, basis.fields, axes=1)
    vertices = transform.invert(decoded)
    used = sv if face_w is None else sv[np.unique(sf[face_w > 0])]
    return RegistrationResult(code=code, vertices=vertices, path=path, transform=transform, levels=report,
                              varifold=report[-1]["varifold"], chamfer=chamfer(vertices, used),
                              seconds=time.perf_counter() - start_time, prealignment=initial)


def _try_poses(problem, basis, level, judge, path, transform, candidates, progress, message):
    """The pose-candidate stage before ``level`` (see POSE_FINALISTS): -> (path, transform, share of
    ``progress`` used). The path returned is the best short solve, or ``path`` when no candidate is close.

    Every start (the current end code and each candidate) is first re-aligned to the scan on its own
    (``_CoarseVarifold`` at the level's sigma, from the current alignment): the pre-alignment matched
    the scan's centroid and RMS radius to the template's, which a raised arm shifts by several cm.
    """
    code = path[-1]
    level = replace(level, weight=level.weight * POSE_WEIGHT_GAIN)
    starts = pose_starts(basis, candidates, code)
    aligned, scores = zip(*problem.realign(level, [code, *starts], transform))
    scores = np.array(scores)
    pick = [int(j) for j in np.argsort(scores[1:])[:POSE_FINALISTS] if scores[1 + j] <= POSE_TIE * scores[0]]
    total = (POSE_FINALISTS + 1) * level.steps * POSE_ITER
    full = level.steps * level.max_iter + total
    if not pick:
        return path, transform, 0.0
    short = replace(level, max_iter=POSE_ITER)
    lo, hi = progress
    step = (hi - lo) * total / full / (len(pick) + 1)
    firsts = [(path, aligned[0])] + [(np.stack([np.zeros_like(code), starts[j]]), aligned[1 + j]) for j in pick]
    tries = [problem.solve_level(short, p, t, (lo + i * step, lo + (i + 1) * step),
                                 f"{message} (pose {i + 1}/{len(pick) + 1})") for i, (p, t) in enumerate(firsts)]
    best = int(np.argmin([problem.screen_score(judge, p[-1], t, r["energy"]) for p, t, r in tries]))
    return tries[best][0], tries[best][1], total / full


def _normal_gram(verts, faces, fields):
    """N_ij = sum_v A_v (h_i . n_v)(h_j . n_v): the L2 metric of the fields' normal components at the
    template: (N, 3), (F, 3), (P, N, 3) -> (P, P) numpy."""
    p = verts[faces]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normals = np.zeros_like(verts)
    for k in range(3):
        np.add.at(normals, faces[:, k], cross)
    area = np.linalg.norm(normals, axis=1) / 6  # |sum of adjacent a_f n_f| / 3, a_f = |cross| / 2
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    hn = np.einsum("pvk,vk->pv", fields, normals)
    return (hn * area) @ hn.T


class _Problem:
    """The constant parts of a registration (template tensors, scan, landmarks) and one level's solve."""

    def __init__(self, basis, sv, sf, face_w, marks, landmark_weight, metric, kernel, backend, binning,
                 refine_transform, dtype, device, monitor):
        self.binning = binning
        self.template, self.faces, self.fields = basis.tensors(dtype=dtype, device=device)
        area, self.center, _ = surface_moments(basis.template, basis.faces)
        self.center_t = torch.as_tensor(self.center, dtype=dtype, device=device)
        # preconditioning (see _PathVariables): the path's interior is whitened by the latent
        # metric at the template, the end code by an estimate of the level's Hessian
        self.gram = basis.template_metric(metric)
        self.whiten = whitening(self.gram)
        self.normal_gram = _normal_gram(basis.template, basis.faces, basis.fields)
        self.radius = math.sqrt(((basis.template - self.center) ** 2).sum(-1).mean())
        self.scan, self.scan_faces = sv, torch.as_tensor(sf, dtype=torch.long, device=device)
        self.scan_weights = None if face_w is None else torch.as_tensor(face_w, dtype=dtype, device=device)
        self.marks = marks
        if marks is not None:
            self.lm_idx = torch.as_tensor(marks[0], device=device)
            self.lm_w = torch.as_tensor(marks[2] / marks[2].sum() * landmark_weight * area, dtype=dtype,
                                        device=device)
        self.metric, self.kernel, self.backend = metric, kernel, backend
        self.n_extra = 7 if refine_transform else 0
        self.dtype, self.device, self.monitor = dtype, device, monitor
        self.scale, self.n_fields = basis.scale, basis.n_fields
        self.fields_np = basis.fields

    def realign(self, level, codes, transform):
        """The alignment refined for each surface F(code) at ``level``'s sigma (binned binet varifold,
        rotation, translation and a bounded log-scale about the template's centre): codes (K, P) ->
        [(Similarity, weight * Gamma + energy of the straight path 0 -> code)], Gamma on the coarse cells."""
        sigma = level.sigma * self.scale
        cell = PREALIGN_CELL * sigma
        weights = None if self.scan_weights is None else self.scan_weights.detach().cpu().numpy()
        scan = _coarse_measure(transform.apply(self.scan) - self.center, self.scan_faces.cpu().numpy(), weights, cell)
        faces, eye = self.faces.cpu().numpy(), torch.eye(3, dtype=torch.float64)
        out = []
        for code in codes:
            self.monitor.check()
            with torch.no_grad():
                verts = decode(self.template, self.fields, torch.as_tensor(code, dtype=self.dtype, device=self.device))
            verts = verts.detach().cpu().numpy().astype(np.float64) - self.center
            coarse = _CoarseVarifold(scan, _coarse_measure(verts, faces, None, cell), sigma)
            x, gamma, _ = minimize_lbfgs(lambda p: coarse(torch.cat([p[:6], _log_scale(p[6:])]), eye), np.zeros(7),
                                         max_iter=POSE_ALIGN_ITER, gtol=1e-9, ftol=1e-10)
            # F(code) moved by S: x -> e^l R (x - c) + tau + c; the scan moves by the inverse instead
            scale = math.exp(float(_log_scale(torch.as_tensor(x[6]))))
            rot = _rotation_np(x[:3])
            move = Similarity(rot, scale, x[3:6] + self.center - scale * rot @ self.center)
            out.append((move.inverse().compose(transform), level.weight * gamma + self.straight_energy(level, code)))
        return out

    def straight_energy(self, level, code):
        """Energy of the straight path 0 -> code in ``level.steps`` steps: (P,) -> float."""
        with torch.no_grad():
            code = torch.as_tensor(code, dtype=self.dtype, device=self.device)
            ramp = torch.linspace(0, 1, level.steps + 1, dtype=self.dtype, device=self.device)[:, None]
            return float(h2_metric.path_energy(decode(self.template, self.fields, ramp * code), self.faces,
                                               self.metric))

    def screen_score(self, level, code, transform, energy):
        """weight * Gamma + energy of a solved path at ``level``'s sigma and weight, Gamma on a
        binning of both surfaces with cells of SCREEN_CELL x sigma.

        A level's objective bins with cells of BIN_CELL x sigma; its error (a difference of large
        kernel sums) depends on how each alignment falls on the cells, enough to rank a wrong
        alignment first: finer cells make the objective comparable across alignments.
        code (P,), transform: the end of a ``solve_level`` result; energy: its path energy -> float.
        """
        sigma = level.sigma * self.scale
        target = torch.as_tensor(transform.apply(self.scan), dtype=self.dtype, device=self.device)
        code = torch.as_tensor(code, dtype=self.dtype, device=self.device)
        with torch.no_grad():
            final = decode(self.template, self.fields, code)
            loss = BinnedVarifoldLoss(final, self.faces, target, self.scan_faces, sigma, self.kernel,
                                      self.scan_weights, cell=SCREEN_CELL * sigma)
            return level.weight * float(loss(final, self.faces)) + energy

    def solve_level(self, level, path, transform, progress, message):
        """Minimise one level from path (T0+1, P) and the alignment -> (path (T+1, P), alignment, report)."""
        t0 = time.perf_counter()
        self.monitor.check()
        dtype, device, p_dim, steps = self.dtype, self.device, self.n_fields, level.steps
        sigma = level.sigma * self.scale
        target = torch.as_tensor(transform.apply(self.scan), dtype=dtype, device=device)
        loss = None
        if self.binning:
            code = torch.as_tensor(path[-1], dtype=dtype, device=device)
            loss = BinnedVarifoldLoss(decode(self.template, self.fields, code), self.faces, target,
                                      self.scan_faces, sigma, self.kernel, self.scan_weights)
            n_s, n_t = self.faces.shape[0], self.scan_faces.shape[0]
            pairs = loss.n_groups * (loss.n_groups + loss.n_target)
            if self.binning == "auto" and pairs > BIN_GAIN * n_s * (n_s + n_t):
                loss = None
        binned = loss is not None
        if not binned:
            loss = VarifoldLoss(target, self.scan_faces, sigma, kernel=self.kernel, backend=self.backend,
                                target_weights=self.scan_weights, cutoff=default_cutoff(sigma, FINE_TOL),
                                target_cell=None if SCAN_CELL is None else SCAN_CELL * sigma)
        if self.marks is not None:
            lm_pts = torch.as_tensor(transform.apply(self.marks[1]), dtype=dtype, device=device)
        terms = {}

        def objective(x):
            x = x.to(dtype=dtype, device=device)
            alpha = variables.path(x[:steps * p_dim].reshape(steps, p_dim))
            meshes = decode(self.template, self.fields, alpha)
            energy = h2_metric.path_energy(meshes, self.faces, self.metric)
            final = meshes[-1]
            if self.n_extra:
                p = x[steps * p_dim:] * units_t
                final = (self.center_t + torch.exp(_log_scale(p[6])) * (final - self.center_t) @ _rotation(p[:3]).T
                         + p[3:6])
            gamma = loss(final, self.faces)
            fit = gamma
            if self.marks is not None:
                fit = fit + (self.lm_w * ((final[self.lm_idx] - lm_pts) ** 2).sum(1)).sum()
            terms.update(energy=energy, gamma=gamma)
            return level.weight * fit + energy

        # the varifold of a surface offset by d along its normals is ~ 2 pi int d^2 (any sigma), so
        # weight * Gamma has Hessian ~ 4 pi weight N in the code (N = normal_gram) next to G-bar
        whiten_end = whitening(self.gram + 4 * math.pi * level.weight * self.normal_gram)
        variables = _PathVariables(steps, whiten_end, self.whiten)
        # similarity variables scaled so that a unit step moves the surface about as much as a
        # unit step of the (whitened) end code: a well-conditioned joint problem
        move = math.sqrt((np.tensordot(whiten_end, self.fields_np, axes=1) ** 2).sum(-1).mean())
        units = np.array([move / self.radius] * 3 + [move] * 3 + [move / self.radius])
        units_t = torch.as_tensor(units, dtype=dtype, device=device)
        x0 = np.concatenate([variables.variables(resample_in_time(path, steps)).ravel(), np.zeros(self.n_extra)])
        x, value, nit = minimize_lbfgs(objective, x0, self.monitor, max_iter=level.max_iter,
                                       progress=progress, message=message, ftol=LEVEL_FTOL, plateau=LEVEL_PLATEAU)
        with torch.no_grad():
            objective(torch.from_numpy(x))
        path = variables.path(torch.from_numpy(x[:steps * p_dim].reshape(steps, p_dim))).numpy()
        if self.n_extra:
            delta = _delta_similarity(x[steps * p_dim:], self.center, units)
            transform = delta.inverse().compose(transform)
        return path, transform, {"sigma": float(sigma), "weight": float(level.weight), "steps": int(steps),
                                 "iterations": int(nit), "energy": float(terms["energy"]),
                                 "varifold": float(terms["gamma"]), "objective": float(value),
                                 "binned": binned, "seconds": time.perf_counter() - t0}
