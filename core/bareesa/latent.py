"""The restricted latent space (paper section 3): a basis, its decoder and metric.

A basis is a template mesh q-bar (N vertices, F faces) and P deformation fields
h_i, split into named groups (e.g. ``pose`` and ``shape``). The affine decoder is
F(alpha) = q-bar + sum_i alpha_i h_i and the latent space carries the pull-back
metric G-bar(alpha) = [G_F(alpha)(h_i, h_j)] of the invariant H2 metric.

Files and the bundled bases are ``basis_io``'s; building a basis from registered
data is ``basis_building``'s; ``project_to_basis`` gives the code of a mesh already
in template topology.
"""

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from . import geometry, h2_metric
from .errors import InputError
from .h2_metric import H2Weights

FORMAT_VERSION = 1
#: ``Basis.extras`` keys of the stored template metrics, each with its H2 weights (key + "_weights"): the
#: basis' weights' (or the first ones asked for) and its shape weights'
TEMPLATE_METRIC_KEYS = ("template_metric", "shape_template_metric")


@dataclass(frozen=True)
class Level:
    """One level of the multiscale registration schedule.

    ``sigma`` is relative to the basis' reference scale (so it carries over to
    any units); ``weight`` multiplies the varifold term (the paper's lambda);
    ``steps`` is the number of time steps of the latent path; the level ends after ``max_iter``
    iterations, or when its objective fell by less than ``plateau`` (relative) over the last few
    iterations (None: ``RegistrationConfig.solve.plateau``); ``binned``: whether the level's
    varifold is summed over cells when the registration's binning is "auto" (None: its pair-count rule,
    ``RegistrationConfig.solve.bin_gain``); ``bin_cell``: the size of those cells in units of sigma
    (None: ``RegistrationConfig.solve.bin_cell``).
    """

    sigma: float
    weight: float
    steps: int
    max_iter: int = 200
    plateau: float | None = None
    binned: bool | None = None
    bin_cell: float | None = None

    def __post_init__(self):
        if not (self.sigma > 0 and self.weight > 0 and self.steps >= 1 and self.max_iter >= 1):
            raise InputError(f"invalid schedule level {self}: sigma, weight > 0 and steps, max_iter >= 1")
        if self.plateau is not None and not 0 < self.plateau < 1:
            raise InputError(f"invalid schedule level {self}: plateau is a relative fall between 0 and 1")
        if not (self.binned is None or isinstance(self.binned, bool)):
            raise InputError(f"invalid schedule level {self}: binned is true, false or null")
        if self.bin_cell is not None and not 0 < self.bin_cell <= 2:
            raise InputError(f"invalid schedule level {self}: bin_cell is a cell size in units of sigma, in (0, 2]")


#: The paper's body schedule (sigma 0.4 -> 0.1 -> 0.025 m on ~1.7 m bodies), relative to height.
#: Iteration caps are ours (a level also ends when it has plateaued): a held-out body pose needs them.
#: Bases store their schedule: changing these only affects bases built afterwards.
PAPER_BODY_SCHEDULE = (Level(0.4 / 1.7, 1e1, 2, 100), Level(0.1 / 1.7, 1e5, 3, 100), Level(0.025 / 1.7, 1e10, 5, 40))


@dataclass
class Basis:
    """Template, deformation fields and metadata of a latent space.

    template (N, 3) float64, faces (F, 3) int64, fields (P, N, 3);
    groups maps a name to its index range [start, stop) in 0..P.
    """

    template: np.ndarray
    faces: np.ndarray
    fields: np.ndarray
    groups: dict
    weights: H2Weights = field(default_factory=lambda: h2_metric.PRESETS["body"])
    schedule: tuple = PAPER_BODY_SCHEDULE
    scale: float = 1.0
    units: str = "m"
    name: str = "basis"
    provenance: dict = field(default_factory=dict)
    extras: dict = field(default_factory=dict)  # further arrays, e.g. a fitted distribution
    #: how a registration's residual compares with the basis' own (``registration.multiscale``):
    #: {"poor_fit_above": threshold, "held_out_p95": ..., "scans": n, "measured_by": ...}; {} uncalibrated
    fit_check: dict = field(default_factory=dict)
    #: the card's overrides of registration settings (``registration.RegistrationConfig.from_basis``):
    #: {"poses": {"finalists": 3}, "retry": false, ...}; {} none
    registration: dict = field(default_factory=dict)
    #: named anatomical landmarks of the template: {name: template vertex index}; {} none
    landmarks: dict = field(default_factory=dict)
    #: H2 weights for shapes reached from the template (None: ``weights``): registration's regularizer,
    #: the log map and the shooting of random bodies; ``weights`` stays the metric of motion paths
    #: (geodesics between frames, extrapolation). The schedule's balance terms are tuned to it
    shape_weights: H2Weights | None = None

    def __post_init__(self):
        validate_basis(self)

    @property
    def shape_metric(self):
        """The H2 weights measured from the template: ``shape_weights``, else ``weights``."""
        return self.shape_weights or self.weights

    @property
    def n_fields(self):
        """P, the dimension of the latent space."""
        return self.fields.shape[0]

    def group_slice(self, name):
        """Index slice of a named group."""
        if name not in self.groups:
            raise InputError(f"basis '{self.name}' has no group '{name}' (groups: {', '.join(self.groups)})")
        start, stop = self.groups[name]
        return slice(start, stop)

    def tensors(self, dtype=torch.float64, device="cpu"):
        """(template (N, 3), faces (F, 3) long, fields (P, N, 3)) as torch tensors."""
        return (torch.as_tensor(self.template, dtype=dtype, device=device),
                torch.as_tensor(self.faces, dtype=torch.long, device=device),
                torch.as_tensor(self.fields, dtype=dtype, device=device))

    def template_metric(self, weights=None):
        """G-bar(0), the latent metric at the template (P, P) float64 numpy, for ``weights``
        (default the basis'). Computed once and kept in ``extras`` (so saved with the basis) for the
        basis' weights and its shape weights (``TEMPLATE_METRIC_KEYS``; ``registration.prepare_basis``
        stores both in a basis file): solvers use it to precondition (``whitening``)."""
        w = H2Weights.parse(self.weights if weights is None else weights)
        for key in TEMPLATE_METRIC_KEYS:  # (one of another shape, e.g. from an edited file, is computed afresh)
            stored = self.extras.get(key)
            if (stored is not None and np.shape(stored) == (self.n_fields,) * 2
                    and np.array_equal(self.extras.get(key + "_weights"), w.as_tuple())):
                return stored
        others = self.__dict__.setdefault("_other_template_metrics", {})  # weights the basis does not name
        if w.as_tuple() in others:
            return others[w.as_tuple()]
        t, f, h = self.tensors()
        gram = h2_metric.assembled_metric_matrix(t, f, h, w).numpy()
        if w == self.weights or self.extras.get("template_metric") is None:
            key = "template_metric"
        elif w == self.shape_weights:
            key = "shape_template_metric"
        else:
            others[w.as_tuple()] = gram
            return gram
        self.extras[key], self.extras[key + "_weights"] = gram, np.array(w.as_tuple())
        return gram

    def card(self):
        """The JSON-able metadata of the basis."""
        return {"format": FORMAT_VERSION, "name": self.name, "n_vertices": int(self.template.shape[0]),
                "n_faces": int(self.faces.shape[0]), "n_fields": int(self.n_fields),
                "groups": {k: list(map(int, v)) for k, v in self.groups.items()},
                "metric": list(self.weights.as_tuple()),
                "schedule": [asdict(lv) for lv in self.schedule],
                "scale": float(self.scale), "units": self.units, "provenance": self.provenance,
                **({"shape_metric": list(H2Weights.parse(self.shape_weights).as_tuple())}
                   if self.shape_weights is not None else {}),
                **({"fit_check": self.fit_check} if self.fit_check else {}),
                **({"registration": self.registration} if self.registration else {}),
                **({"landmarks": self.landmarks} if self.landmarks else {})}


def validate_basis(b):
    """Check shapes, finiteness and groups of a basis; raise InputError naming the problem."""
    t, f, h = np.asarray(b.template), np.asarray(b.faces), np.asarray(b.fields)
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < 3:
        raise InputError(f"basis '{b.name}': template must be (N, 3) with N >= 3, got {t.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1 or not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"basis '{b.name}': faces must be an integer (F, 3) array, got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= t.shape[0]:
        raise InputError(f"basis '{b.name}': face indices must lie in 0..{t.shape[0] - 1}")
    if h.ndim != 3 or h.shape[1:] != t.shape or h.shape[0] < 1:
        raise InputError(f"basis '{b.name}': fields must be (P, {t.shape[0]}, 3), got {h.shape}")
    for what, arr in (("template", t), ("fields", h)):
        bad = ~np.isfinite(arr)
        if bad.any():
            raise InputError(f"basis '{b.name}': {what} has {int(bad.sum())} non-finite values")
    covered = np.zeros(h.shape[0], dtype=int)
    for name, rng in b.groups.items():
        if len(rng) != 2 or not 0 <= rng[0] < rng[1] <= h.shape[0]:
            raise InputError(f"basis '{b.name}': group '{name}' range {tuple(rng)} is not within 0..{h.shape[0]}")
        covered[rng[0]:rng[1]] += 1
    if b.groups and (covered != 1).any():
        raise InputError(f"basis '{b.name}': groups must cover every field exactly once")
    if not b.scale > 0:
        raise InputError(f"basis '{b.name}': reference scale must be positive, got {b.scale}")
    for name, vertex in (b.landmarks or {}).items():
        if not (isinstance(name, str) and name.strip()):
            raise InputError(f"basis '{b.name}': landmark names must be non-empty strings, got {name!r}")
        if isinstance(vertex, bool) or not isinstance(vertex, (int, np.integer)) or not 0 <= vertex < t.shape[0]:
            raise InputError(f"basis '{b.name}': landmark '{name}' must be a template vertex index in "
                             f"0..{t.shape[0] - 1}, got {vertex!r}")
    b.landmarks = {str(k): int(v) for k, v in (b.landmarks or {}).items()}
    b.template = t.astype(np.float64)
    b.fields = h.astype(np.float64)  # bases may be stored in float16/float32; compute in float64
    b.faces = f.astype(np.int64)
    b.groups = {k: (int(v[0]), int(v[1])) for k, v in (b.groups or {"all": (0, h.shape[0])}).items()}
    b.weights = H2Weights.parse(b.weights)
    if b.shape_weights is not None:
        b.shape_weights = H2Weights.parse(b.shape_weights)
    b.schedule = tuple(lv if isinstance(lv, Level) else Level(**lv) for lv in b.schedule)


def decode(template, fields, alpha):
    """F(alpha) = template + sum_i alpha_i h_i: (N, 3), (P, N, 3), (..., P) -> (..., N, 3)."""
    if alpha.shape[-1] != fields.shape[0]:
        raise InputError(f"code has {alpha.shape[-1]} coefficients but the basis has {fields.shape[0]} fields")
    return template + torch.tensordot(alpha, fields, dims=([-1], [0]))


def latent_metric(template, faces, fields, alpha, weights):
    """The latent metric matrix G-bar(alpha): alpha (P,) -> (P, P)."""
    return h2_metric.metric_matrix(decode(template, fields, alpha), faces, fields, weights)


def whitening(gram, floor=1e-10):
    """B (P, P) with B G B^T = I for a latent metric G (P, P): z @ B maps unit-metric
    coordinates z to latent vectors. Eigenvalues below floor x the largest are raised
    to it (near-null directions). Solvers optimise in such coordinates (preconditioning)."""
    g = torch.as_tensor(np.asarray(gram), dtype=torch.float64)
    if g.dim() != 2 or g.shape[0] != g.shape[1] or not torch.isfinite(g).all():
        raise InputError(f"a latent metric must be a finite square matrix, got shape {tuple(g.shape)}")
    evals, evecs = torch.linalg.eigh((g + g.T) / 2)
    top = float(evals.max())
    if not top > 0:
        raise InputError("the latent metric is not positive definite (all eigenvalues <= 0)")
    return (evecs / torch.sqrt(evals.clamp_min(floor * top))).T.numpy()


def time_whitening(n):
    """R^-1 (n, n) with R^T R = K, K = tridiag(-1, 2, -1) the energy of n interior time points
    of a path with fixed ends: whitens the time coupling of a discrete path energy."""
    k = 2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    return np.linalg.inv(np.linalg.cholesky(k).T)


def interior_whitening(n):
    """sqrt(dt) R^-1 (n, n) for the n interior time points of a path of n + 2 (dt = 1 / (n + 1),
    ``time_whitening``): interior deviations from the straight line r @ z @ B (B a ``whitening``) put the
    path energy near |z|^2 + const. The solvers of geodesics, registration levels and symmetric matching
    optimise in such coordinates."""
    return time_whitening(n) * math.sqrt(1.0 / (n + 1))


def latent_path_energy(template, faces, fields, path, weights, per_step=False):
    """Discrete energy of a latent path: path (..., T, P) -> (...).

    Equal to sum_k dbeta_k^T G-bar(mid_k) dbeta_k / dt, evaluated through the
    decoded meshes (cost O(T F), no P x P matrix is formed).
    """
    return h2_metric.path_energy(decode(template, fields, path), faces, weights, per_step=per_step)


#: Relative weight of the latent metric in ``project_to_basis``. Held-out shapes projected by plain
#: least squares load directions the data barely determines (fields of tiny variance) with large
#: coefficients, along which the metric bends so fast that geodesic shooting from the code fails;
#: this ridge keeps them near zero and moves a fit by about a millimetre on the humanoid mannequin (since retired).
PROJECTION_RIDGE = 5e-3


def project_to_basis(basis, verts, ridge=PROJECTION_RIDGE, weights=None):
    """Code of a mesh already in template topology: F(alpha) ~ verts.

    verts (N, 3) -> (alpha (P,), rms vertex residual), or a batch (M, N, 3) -> ((M, P), (M,)).
    Minimises the area-weighted |F(alpha) - verts|^2 + ridge * s * alpha^T G-bar(0) alpha,
    s = tr(M) / tr(G-bar(0)) with M the fields' area-weighted Gram matrix (so ``ridge`` is
    relative and unit-free); ridge=0 is plain least squares, exact for meshes in the span of the basis.
    G-bar(0) is the latent metric at the template in ``weights`` (default the basis' own: the metric the
    code's motions are solved in).
    """
    verts = np.asarray(verts, dtype=np.float64)
    if verts.shape[-2:] != basis.template.shape or verts.ndim not in (2, 3):
        raise InputError(f"mesh has {verts.shape[-2] if verts.ndim >= 2 else 0} vertices but basis "
                         f"'{basis.name}' has {basis.template.shape[0]}: register it as a scan instead")
    if not np.isfinite(verts).all():
        raise InputError("the mesh has NaN or infinite vertex coordinates")
    if not (np.isfinite(ridge) and ridge >= 0):
        raise InputError(f"ridge must be a finite number >= 0, got {ridge}")
    a = basis.fields.reshape(basis.n_fields, -1).T.astype(np.float64)
    batch = verts.reshape(-1, *basis.template.shape)
    target = (batch - basis.template).reshape(len(batch), -1).T  # (3N, M)
    if ridge > 0:
        areas = geometry.vertex_areas(torch.from_numpy(basis.template), torch.from_numpy(basis.faces)).numpy()
        weighted = a * np.repeat(areas, 3)[:, None]
        gram, metric = weighted.T @ a, basis.template_metric(weights)
        alpha = np.linalg.solve(gram + ridge * np.trace(gram) / np.trace(metric) * metric, weighted.T @ target)
    else:
        alpha, *_ = np.linalg.lstsq(a, target, rcond=None)
    residual = np.sqrt(((target - a @ alpha) ** 2).reshape(basis.template.shape[0], 3, -1).sum(1).mean(0))
    if verts.ndim == 2:
        return alpha[:, 0], float(residual[0])
    return alpha.T, residual


def off_basis_detail(basis, verts, code):
    """What a template-topology mesh has that its code does not: verts - F(code).

    verts (N, 3) and code (P,), or batches (M, N, 3) and (M, P) -> numpy of the shape of verts.
    Adding it back to F(code) gives the mesh exactly (``detail_along``).
    """
    verts, code = np.asarray(verts, dtype=np.float64), np.asarray(code, dtype=np.float64)
    if verts.shape[-2:] != basis.template.shape:
        raise InputError(f"mesh has {verts.shape[-2] if verts.ndim >= 2 else 0} vertices but basis "
                         f"'{basis.name}' has {basis.template.shape[0]}")
    if code.shape[-1] != basis.n_fields or code.shape[:-1] != verts.shape[:-2]:
        raise InputError(f"codes {code.shape} do not match meshes {verts.shape} of a {basis.n_fields}-field basis")
    return verts - basis.template - np.tensordot(code, basis.fields, axes=([-1], [0]))


def detail_along(start, end, times):
    """Off-basis detail of two keyframes carried along a path: start + t (end - start) for t in times.

    start, end (N, 3) ``off_basis_detail`` of the keyframes; times (T,): 0 and 1 at the keyframes,
    in between for interpolation, 2, 3, ... to continue it (extrapolation) -> (T, N, 3).
    Added to a latent path's decoded frames, it makes them pass through the keyframes exactly; added
    to the straight latent line, it gives exactly the vertex blend of the keyframes (F is affine).
    """
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    if start.shape != end.shape or start.ndim != 2:
        raise InputError(f"detail of the two keyframes must be two (N, 3) arrays, got {start.shape}, {end.shape}")
    times = np.asarray(times, dtype=np.float64)
    return start + times.reshape(-1, 1, 1) * (end - start)
