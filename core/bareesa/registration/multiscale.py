r"""``register``: the latent code of an unregistered scan, from pre-alignment to the finest level.

A basis with pose prototypes lends them to the pre-alignment (a crouching scan's principal axes say
nothing of the template's), and the first fit starts from the best pre-alignment candidate (the
candidates within PREALIGN_TIE of it screened as below when there are several): its rigid
varifold against the template and the prototypes nearest the scan ranked a right alignment first on
all 104 held-out `human` scans measured, while the latent screening below ranked one first on 82
(bench/README, 2026-12-05): a candidate found against a prototype is screened from the straight path
to that prototype's code (``_start``), so its screened objective carries that path's energy and shape
and does not compare with the others'. With prototypes the first level is only ever that screening's
short solve, followed by a short second level, and the pose stage and the second level go on from there
(the whole first level, run for a lone candidate, bought no accuracy: on 14 held-out scans the fits were
as good and 10 % faster without it, bench/README). Without prototypes a deformed scan of a nearly symmetric
template can match a flipped template better than the right one, so ``register`` runs a short first
level from each distinct pre-alignment candidate whose varifold is within PREALIGN_RATIO of the best,
ranks them by ``screen_score`` and, when the best two are within SCREEN_TIE, runs a short second level
from both and keeps the one that fits better at the second level's sigma (at the first level's sigma
a body is nearly front/back symmetric). A fit that is
still poor (``is_poor_fit``; most often a body registered facing backwards) is registered again from
the other pre-alignment candidates and from itself turned half a turn about each of the template's
principal axes (``half_turns``), screened as above; if that fit is poor too, the same alignments are
screened deeper (the whole first level and RETRY_SECOND_ITER iterations of the second, ranked by the
fit residual), and the fit with the smallest residual is kept.
"""

import math
import time
from dataclasses import dataclass, fields, replace

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..errors import InputError
from ..evaluation import chamfer
from ..h2_metric import H2Weights
from ..latent import Level
from ..mesh import face_geometry, validate_mesh
from ..progress import Monitor
from ..threads import with_one_blas_thread
from ..transforms import Similarity
from ..varifold import KERNELS, build_keops_kernels
from .poses import check_pose_candidates, stage_budget, try_poses
from .prealign import (PREALIGN_RATIO, Alignment, landmark_alignment, moment_table, prealign_candidates,
                       surface_moments)
from .problem import RegistrationProblem, normal_spread

SCREEN_DIVISOR = 8          # candidate alignments are screened with 1/8 of the first level's iterations
#                             and a one-step path (the end code decides between alignments)
SCREEN_FINALISTS = 2        # the best screened alignments get a short second level, which decides: at the
SCREEN_SECOND_ITER = 5      # first level's sigma a body is nearly front/back symmetric...
SCREEN_TIE = 1.5            # ... when the second best scored within this factor of the best
#: A retry that is still poor screens the alignments deeper: the whole first level, then this many
#: iterations of the second, ranked by the fit residual. The short screening ranked a body facing
#: backwards first on 2 of 40 held-out `human` scans, in the first try and in the retry; after 30
#: second-level iterations the right alignment has the smallest residual on both. Not as the only
#: retry: on a third scan the right alignment is still far off after 30 iterations, and the short
#: screening finds it (bench/README). Each alignment gets the pose stage between the two, as a
#: registration does: without it a body far from every pose start (a held-out scan, code norm 75) still
#: scored 0.04-0.1 after 30 iterations from every alignment and the backwards one won; with it the right
#: ones scored 0.0047 against 0.046 and the retry ended right (bench/README, 2026-12-05).
RETRY_SECOND_ITER = 30
PREALIGN_FRACTION = 0.1     # share of the progress bar given to the pre-alignment
#: With pose prototypes the first fit starts from the best pre-alignment candidate, and only the candidates
#: scoring within this factor of it are screened: on 101 held-out `human` scans with a wrong candidate the
#: best wrong one scored at least 1.073 x the best right one; on one more (seed 30 scan 3 of
#: ``held_out_scans``) a backwards candidate scored best, 1.024 x below the right one, and the screening
#: picked the right one (bench/README)
PREALIGN_TIE = 1.05
#: "auto" registers the finest level with the oriented linear kernel when the scan's normal spread
#: (``problem.normal_spread``) is above this, else with binet: the spread biases binet's minimiser
#: (3.6 mm at paper scale, spread 0.08) and not linear's (0.88 mm), but linear is blind at sigma to thin
#: parts whose two sides cancel (hands), so on smooth scans (spread ~0.015) binet is better
#: (bench/registration_accuracy)
NOISY_SPREAD = 0.05
#: A scan with fewer (non-zero-weight) faces than this, or than an eighth of the template's faces when
#: that is fewer, is refused: it cannot say which of the basis' shapes it is (a one-triangle "scan"
#: once registered for 21 minutes and came back as a full body).
MIN_SCAN_FACES = 100
#: A scan whose thinnest extent (smallest eigenvalue of its second moment of area, over the largest) is
#: below this share of the template's is refused as flat (a sheet, a wall, a single view of a plane).
MIN_FLATNESS_RATIO = 0.02
#: What the progress says while KeOps' kernels are loaded, or built at their first use on a machine
#: (``varifold.build_keops_kernels``; the bar stands still for ~15 s then)
KEOPS_BUILD_MESSAGE = "registration: KeOps' kernels (built at their first use on a machine, ~15 s)"
#: ``Basis.extras`` key of the surface moments of the decoded pose prototypes (``prealign.moment_table``),
#: with the codes they are of under this key + "_codes" (``prepare_basis``): 33 surface moments cost ~0.1 s
#: of every registration's pre-alignment
PROTOTYPE_MOMENTS = "pose_prototype_moments"
#: The extras ``prepare_basis`` computes (a basis' own template metric, "template_metric", is the basis'
#: and stays as it was built)
PREPARED_EXTRAS = ("shape_template_metric", "shape_template_metric_weights", PROTOTYPE_MOMENTS,
                   PROTOTYPE_MOMENTS + "_codes")


@dataclass
class RegistrationResult:
    """Latent code of a scan and the registered template.

    code (P,); vertices (N, 3) registered template in the scan's frame and units; path (T+1, P)
    the final latent path from 0 to code; transform the similarity scan -> template frame
    (pre-alignment refined by the registration: vertices = transform.invert(F(code)));
    levels one dict per schedule level {sigma, weight, steps, iterations, energy, varifold,
    objective, binned, seconds}; varifold the squared varifold residual at the finest sigma (template
    frame); chamfer between vertices and the scan (scan frame); seconds of wall time;
    prealignment the candidate alignment the registration started from; residual the mean distance
    from the scan to the registered surface over the basis' size (``fit_residual``); poor_fit whether
    it is far above what the basis reaches on its own scans (``basis.fit_check``; None uncalibrated);
    normal_spread the scan's (``problem.normal_spread``), which chose the finest kernel of "auto";
    retried_alignments how many other alignments a poor fit was tried again from (0: none; the result
    is the better of the two tries).
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
    residual: float = None
    poor_fit: bool = None
    normal_spread: float = None
    retried_alignments: int = 0

    def to_json(self):
        """JSON-ready summary {code, varifold, chamfer, residual, poor_fit, retried_alignments, normal_spread,
        seconds, levels, transform}."""
        return {"code": [float(c) for c in self.code], "varifold": float(self.varifold),
                "normal_spread": None if self.normal_spread is None else float(self.normal_spread),
                "chamfer": float(self.chamfer), "seconds": float(self.seconds),
                "residual": None if self.residual is None else float(self.residual), "poor_fit": self.poor_fit,
                "retried_alignments": int(self.retried_alignments),
                "levels": [{k: (float(v) if isinstance(v, float) else v) for k, v in lv.items()}
                           for lv in self.levels],
                "transform": self.transform.to_dict()}

    def to_state(self):
        """Everything as numpy arrays, numbers and dicts (no class of this package; what a worker process
        sends back): the inverse of ``from_state``."""
        state = {f.name: getattr(self, f.name) for f in fields(self)}
        state["transform"] = self.transform.to_dict()
        state["prealignment"] = None if self.prealignment is None else self.prealignment.to_dict()
        return state

    @classmethod
    def from_state(cls, state):
        """The result ``to_state`` gave."""
        state = dict(state)
        state["transform"] = Similarity.from_dict(state["transform"])
        if state.get("prealignment") is not None:
            state["prealignment"] = Similarity.from_dict(state["prealignment"])
        return cls(**state)



def _check_schedule(schedule):
    try:
        levels = tuple(lv if isinstance(lv, Level) else Level(**lv) for lv in schedule)
    except TypeError as err:
        raise InputError(f"a schedule is a sequence of Level(sigma, weight, steps, max_iter): {err}") from None
    if not levels:
        raise InputError("the registration schedule is empty")
    return levels


def level_kernels(kernel, n_levels, noisy=False):
    """The varifold kernel of each level: "auto" binet on every level, except that the finest is linear
    when the scan is ``noisy`` (see ``register``; a one-level schedule stays binet: no fit to orient
    the scan by); a name of ``KERNELS`` (or a sum, "binet+linear") on every level; or a sequence of
    names, one per level."""
    if isinstance(kernel, str):
        auto = ["binet"] * (n_levels - 1) + ["linear" if noisy and n_levels > 1 else "binet"]
        names = auto if kernel == "auto" else [kernel] * n_levels
    else:
        names = list(kernel)
        if len(names) != n_levels:
            raise InputError(f"kernel: {len(names)} kernels given for a schedule of {n_levels} levels")
    for name in names:
        if not (isinstance(name, str) and all(part in KERNELS for part in name.split("+"))):
            raise InputError(f"unknown varifold kernel {name!r}; choose 'auto', one of {sorted(KERNELS)} "
                             "or a sum of them such as 'binet+linear'")
    return names


def check_face_weights(weights, n_faces):
    """Scan face weights (G,) >= 0, not all zero, or None -> float64 (G,) or None (InputError otherwise)."""
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


def check_landmarks(landmarks, n_verts):
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



def check_plausible_scan(basis, verts, faces, face_weights=None):
    """Refuse a scan that cannot be registered onto ``basis`` (InputError naming why): fewer faces than
    MIN_SCAN_FACES (capped at an eighth of the template's), or flat against the template's extent
    (MIN_FLATNESS_RATIO). verts (M, 3), faces (G, 3), face_weights (G,) or None."""
    used = int(np.count_nonzero(face_geometry(verts, faces)[1] * (1.0 if face_weights is None else face_weights)))
    need = min(MIN_SCAN_FACES, basis.faces.shape[0] // 8)
    if used < need:
        raise InputError(f"the scan has {used} face{'s' * (used != 1)} with area: too few to register onto basis "
                         f"'{basis.name}' (at least {need}); give the whole scanned mesh, not a piece of it")
    extent = lambda v, f, w: np.linalg.eigvalsh(surface_moments(v, f, w)[2])  # noqa: E731
    scan, template = extent(verts, faces, face_weights), extent(basis.template, basis.faces, None)
    flat, reference = scan[0] / scan[-1], template[0] / template[-1]
    if flat < MIN_FLATNESS_RATIO * reference:
        raise InputError(f"the scan is flat (its thinnest extent is {math.sqrt(flat):.2g} of its longest; the "
                         f"template's {math.sqrt(reference):.2g}): it cannot be a shape of basis '{basis.name}'; check "
                         "that the right object is selected and that floors or walls are masked out")


def fit_residual(basis, vertices, scan_points, transform):
    """Mean distance from scan points (M, 3) to the registered surface (vertices (N, 3), both in the
    scan's frame) over the basis' size, in the template frame (units and scale of the scan cancel): the
    surface is sampled at its vertices and face barycentres -> float."""
    surface = np.concatenate([vertices, face_geometry(vertices, basis.faces)[2]])
    return float(cKDTree(surface).query(scan_points, k=1)[0].mean() * transform.scale / basis.scale)


def is_poor_fit(basis, residual):
    """Whether a residual (``fit_residual``) is far above what the basis reaches on its own held-out scans
    (``basis.fit_check["poor_fit_above"]``); None when the basis is not calibrated."""
    threshold = basis.fit_check.get("poor_fit_above")
    return None if threshold is None else bool(residual > threshold)


@with_one_blas_thread
def prepare_basis(basis):
    """Compute the per-basis constants every registration would otherwise compute once per process and
    keep them in ``basis.extras`` (a basis saved afterwards carries them): the template metric of its shape
    weights (``Basis.template_metric``) and the surface moments of its decoded pose prototypes
    (``PROTOTYPE_MOMENTS``) -> basis. ~0.3 s on `human`; ``python -m bases.build --derived`` stores them
    in the bundled files."""
    basis.template_metric()  # (the basis' own weights first: the first metric asked for would take its key)
    basis.template_metric(basis.shape_metric)
    poses = check_pose_candidates(basis, "auto")
    if poses is not None:
        _reference_moments(basis, poses, basis.template + np.tensordot(poses, basis.fields, axes=1))
    return basis


def _reference_moments(basis, poses, references):
    """The surface moments of the decoded pose candidates (K, N, 3) (``prealign.moment_table``): stored in
    ``basis.extras`` when they are the basis' own pose prototypes (PROTOTYPE_MOMENTS, with the codes they
    are of), else computed -> (K, 12)."""
    key = PROTOTYPE_MOMENTS
    stored, of = basis.extras.get(key), basis.extras.get(key + "_codes")
    if (stored is not None and of is not None and np.shape(stored) == (len(poses), 12)
            and np.isfinite(stored).all() and np.array_equal(of, poses)):
        return stored
    table = moment_table(references, basis.faces)
    if np.array_equal(poses, basis.extras.get("pose_prototypes")):
        basis.extras[key], basis.extras[key + "_codes"] = table, np.array(poses, dtype=np.float64)
    return table


@with_one_blas_thread
def register(basis, scan_verts, scan_faces, *, schedule=None, prealign=True, landmarks=None,
             landmark_weight=1.0, scan_face_weights=None, metric=None, kernel="auto", backend="auto",
             binning="auto", refine_transform=None, init_code=None, pose_candidates="auto", callback=None, cancel=None,
             dtype=torch.float64, device="cpu", retry=True):
    """Latent code of an unregistered scan: basis, scan (M, 3), (G, 3) -> RegistrationResult.

    schedule: Levels (default basis.schedule); prealign: align the scan to the template first
    (else it must be in the template frame already); landmarks: [(template vertex, scan xyz
    [, weight])], adding weight * landmark_weight * A * sum_i w_i |S F(alpha)_i - T p_i|^2 / sum w
    (A the template area: comparable to the varifold of a surface offset by the same distance);
    scan_face_weights (G,) >= 0 (0 ignores a face, e.g. a floor); metric: H2 weights (default
    the basis' ``shape_metric``); kernel: of the varifold, per level
    (``level_kernels``): "auto" (default) is binet
    (orientation-free) on every level, except that a noisy scan (``normal_spread`` above NOISY_SPREAD)
    is matched at the finest level with the oriented linear kernel, whose minimiser the noise does not
    bias; an oriented kernel on a level after the first runs on the scan's faces wound consistently and
    turned like the fit so far (``problem.orient_like``), so flipped faces do no harm; backend: of the
    varifold (``bareesa.varifold``); binning: "auto" evaluates a level's varifold on cell sums
    (``BinnedVarifoldLoss``) when the level says so (``Level.binned``), or when it does not and sigma
    is so large that this cuts the face pairs 20-fold, True always, False never (an unbinned level
    still sums the scan alone over cells of SCAN_CELL x sigma when that leaves fewer points,
    ``VarifoldLoss(target_cell=)``, and truncates the kernel at FINE_TOL); refine_transform: optimise the
    similarity jointly with the path (default: as prealign); init_code (P,) starts from the
    straight path 0 -> init_code; pose_candidates (K, P): codes whose pose group (the whole code
    when the basis has no other group) is tried as a start of the second level (see ``poses.POSE_FINALISTS``),
    "auto" the basis' ``extras["pose_prototypes"]`` if it has them, None none; dtype: precision of
    the objective (the optimiser is float64); retry: when the fit is poor (and prealign), register
    again from other alignments and keep the better (``retried_alignments``).
    Raises MeshError/InputError on bad input (``check_plausible_scan``: too few faces, flat), SolveCancelled
    when cancelled (no partial result).
    """
    start_time = time.perf_counter()
    monitor = Monitor("register", callback, cancel)
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise InputError(f"dtype must be a torch floating point dtype, got {dtype!r}")
    validate_mesh(scan_verts, scan_faces, "scan")
    sv, sf = np.asarray(scan_verts, np.float64), np.asarray(scan_faces, np.int64)
    face_w = check_face_weights(scan_face_weights, sf.shape[0])
    check_plausible_scan(basis, sv, sf, face_w)
    marks = check_landmarks(landmarks, basis.template.shape[0])
    if not (math.isfinite(landmark_weight) and landmark_weight >= 0):
        raise InputError(f"landmark_weight must be finite and >= 0, got {landmark_weight}")
    levels = _check_schedule(basis.schedule if schedule is None else schedule)
    spread = normal_spread(sv, sf, face_w)
    kernels = level_kernels(kernel, len(levels), noisy=spread > NOISY_SPREAD)
    if binning not in ("auto", True, False):
        raise InputError(f"binning must be 'auto', True or False, got {binning!r}")
    metric = H2Weights.parse(basis.shape_metric if metric is None else metric)
    refine_transform = prealign if refine_transform is None else bool(refine_transform)
    path = np.zeros((2, basis.n_fields))
    if init_code is not None:
        init = np.asarray(init_code, dtype=np.float64)
        if init.shape != (basis.n_fields,) or not np.isfinite(init).all():
            raise InputError(f"init_code must be {basis.n_fields} finite coefficients, got shape {init.shape}")
        path[1] = init
    poses = check_pose_candidates(basis, pose_candidates)

    monitor.report(0.0, "registration: pre-aligning" if prealign else "registration: starting")
    monitor.check()
    if prealign:
        references = None if poses is None else basis.template + np.tensordot(poses, basis.fields, axes=1)
        candidates = prealign_candidates(basis.template, basis.faces, sv, sf, face_w, monitor=monitor,
                                         progress=(0.0, PREALIGN_FRACTION), references=references,
                                         reference_moments=None if poses is None else _reference_moments(
                                             basis, poses, references))
        candidates = [c for c in candidates if c.score <= PREALIGN_RATIO * candidates[0].score + 1e-12]
        if marks is not None:  # three or more landmarks fix the orientation the surfaces alone may not
            by_marks = landmark_alignment(basis.template[marks[0]], marks[1], marks[2])
            if by_marks is not None:
                candidates = [Alignment(0.0, by_marks)] + candidates
    else:
        candidates = [Alignment(0.0, Similarity())]
    problem = RegistrationProblem(basis, sv, sf, face_w, marks, landmark_weight, metric, backend, binning,
                                  refine_transform, dtype, device, monitor)
    lo = PREALIGN_FRACTION if prealign else 0.0
    if backend != "dense":  # KeOps builds its kernels at their first use on a machine: say so, not in a level
        build_keops_kernels(dtype, device, kernels, announce=lambda: monitor.report(lo, KEOPS_BUILD_MESSAGE))
    used = sv if face_w is None else sv[np.unique(sf[face_w > 0])]
    # with pose prototypes the pre-alignment's ranking decides the first fit (see the module docstring),
    # unless it cannot tell the best candidates apart
    screened = candidates if poses is None else [c for c in candidates
                                                 if c.score <= PREALIGN_TIE * candidates[0].score]
    fit = _fit(problem, basis, levels, kernels, poses, path, screened, used, monitor, lo)
    retried = 0
    if fit["poor"] and prealign and retry:
        # a poor fit is most often the body turned the wrong way round (a human scan facing backwards
        # fits with a residual 2-15 times the right one's): go again from the other alignments (the
        # screened ones in their screened order, then the pre-alignment's next ones) and from the fit
        # turned half a turn about each of the template's principal axes
        others = [screened[j] for j in fit["order"] if j != fit["best"]] + candidates[len(screened):]
        others += [Alignment(0.0, flip.compose(fit["transform"])) for flip in half_turns(basis)]
        monitor.report(lo, f"registration: poor fit (residual {fit['residual']:.3g}), retrying from "
                           f"{len(others)} other alignments")
        again = _fit(problem, basis, levels, kernels, poses, path, others, used, monitor, lo)
        if again["poor"]:
            # the short screening can rank the right alignment last (2 of 40 held-out `human` scans):
            # screen the same alignments deeper, ranked by the fit residual
            monitor.report(lo, f"registration: still poor (residual {again['residual']:.3g}), screening the "
                               f"{len(others)} alignments deeper")
            deeper = _fit(problem, basis, levels, kernels, poses, path, others, used, monitor, lo, deep=True)
            again = min(again, deeper, key=lambda f: f["residual"])
        retried = len(others)
        if again["residual"] < fit["residual"]:
            fit = again
    code, transform, vertices = fit["path"][-1], fit["transform"], fit["vertices"]
    return RegistrationResult(code=code, vertices=vertices, path=fit["path"], transform=transform,
                              levels=fit["levels"], varifold=fit["levels"][-1]["varifold"],
                              chamfer=chamfer(vertices, used), seconds=time.perf_counter() - start_time,
                              prealignment=fit["initial"], residual=fit["residual"], poor_fit=fit["poor"],
                              normal_spread=spread, retried_alignments=retried)


def half_turns(basis):
    """Half turns about the template's principal axes through its centroid (template frame): -> 3 Similarity."""
    _, center, second = surface_moments(basis.template, basis.faces)
    out = []
    for axis in np.linalg.eigh(second)[1].T:
        rotation = 2.0 * np.outer(axis, axis) - np.eye(3)
        out.append(Similarity(rotation, 1.0, center - rotation @ center))
    return out


def _start(path, poses, alignment):
    """The path (2, P) a candidate alignment is screened from: the straight path to the pose prototype it was
    found against (``Alignment.reference``), or ``path`` (also when that already leads somewhere: an init_code)."""
    if alignment.reference is None or poses is None or np.any(path[-1]):
        return path
    return np.stack([np.zeros_like(path[-1]), poses[alignment.reference]])


def _pose_judge(levels):
    """The level whose sigma judges the pose stage's short solves (``try_poses``' judge): the one after the
    second, the second itself in a two-level schedule."""
    return levels[min(2, len(levels) - 1)]


def _level_name(k, n_levels):
    """The progress message of level k (0-based) of n_levels."""
    return f"registration level {k + 1}/{n_levels}"


def _residual(basis, path, transform, used):
    """The registered vertices (N, 3) in the scan's frame and their ``fit_residual``."""
    vertices = transform.invert(basis.template + np.tensordot(path[-1], basis.fields, axes=1))
    return vertices, fit_residual(basis, vertices, used, transform)


def _fit(problem, basis, levels, kernels, poses, path, candidates, used, monitor, lo, deep=False):
    """Every level from the best of candidate alignments [Alignment] (screened, see the module
    docstring; deep: each screened with the whole first level and RETRY_SECOND_ITER iterations of the
    second, ranked by the fit residual): -> {path, transform, vertices, levels, initial, residual,
    poor, order, best}."""
    deep = deep and len(candidates) > 1 and len(levels) > 1
    # with pose prototypes the first level is only ever the screening's short solve (see the module docstring)
    quick = poses is not None and len(levels) > 1
    screen = levels[0] if len(candidates) == 1 and not quick else replace(
        levels[0], steps=1, max_iter=max(10, levels[0].max_iter // SCREEN_DIVISOR))
    # progress: the first level is tried from every candidate alignment
    budget = np.array([lv.steps * lv.max_iter for lv in levels], dtype=np.float64)
    if deep:
        budget[0] = len(candidates) * (budget[0] + levels[1].steps * RETRY_SECOND_ITER)
    elif quick:
        budget[0] = len(candidates) * screen.max_iter + levels[1].steps * SCREEN_SECOND_ITER * min(
            len(candidates), SCREEN_FINALISTS)
    else:
        budget[0] *= 1 + (len(candidates) / SCREEN_DIVISOR if len(candidates) > 1 else 0)
    if poses is not None and len(levels) > 1:
        budget[1] += stage_budget()
    bounds = lo + (1 - lo) * np.concatenate([[0.0], np.cumsum(budget) / budget.sum()])
    if deep:
        return _rest(problem, basis, levels, kernels, poses, candidates, used, monitor, bounds,
                     _deep_screen(problem, basis, levels, kernels, poses, path, candidates, used, bounds[:2]))
    name = lambda k: _level_name(k, len(levels))  # noqa: E731
    # screen every candidate alignment with a short first level; only the best one gets the full level
    # (none with pose prototypes: the second level goes on from the best one's short second level)
    share = len(candidates) / SCREEN_DIVISOR
    mid = bounds[1] if screen is levels[0] or quick else bounds[0] + (bounds[1] - bounds[0]) * share / (1 + share)
    tries = []
    for j, candidate in enumerate(candidates):
        span = (mid - bounds[0]) / len(candidates)
        tries.append(problem.solve_level(screen, _start(path, poses, candidate), candidate.transform,
                                         (bounds[0] + j * span, bounds[0] + (j + 1) * span),
                                         name(0) + (f" (alignment {j + 1}/{len(candidates)})" if j else ""),
                                         kernels[0]))
    best, resume, order, finalists = 0, None, [0], [0]
    if len(tries) > 1:
        # the screened objectives ranked on fine cells; the finer second level decides between the best
        scores = [problem.screen_score(levels[0], p[-1], t, r["energy"]) for p, t, r in tries]
        order = np.argsort(scores)
        best = int(order[0])
        finalists = [int(j) for j in order[:SCREEN_FINALISTS] if scores[j] <= SCREEN_TIE * scores[best]]
    if len(levels) > 1 and (len(finalists) > 1 or quick):
        short = replace(levels[1], max_iter=SCREEN_SECOND_ITER)
        second = [problem.solve_level(short, tries[j][0], tries[j][1], (mid, mid), name(1) + " (screening)",
                                      kernels[1], orient=True) for j in finalists]
        k = 0 if len(second) == 1 else int(np.argmin([problem.screen_score(levels[1], p[-1], t, r["energy"])
                                                      for p, t, r in second]))
        best, resume = finalists[k], second[k]  # the second level goes on from the winner's short one
    path, transform, first = tries[best]
    if resume is not None:
        path, transform = resume[0], resume[1]
    elif screen is not levels[0]:
        path, transform, first = problem.solve_level(levels[0], path, transform, (mid, bounds[1]), name(0),
                                                     kernels[0])
    return _rest(problem, basis, levels, kernels, poses, candidates, used, monitor, bounds,
                 (path, transform, first, order, best))


def _deep_screen(problem, basis, levels, kernels, poses, path, candidates, used, span):
    """The whole first level, the pose stage (with pose candidates) and RETRY_SECOND_ITER second-level
    iterations from each candidate, ranked by the fit residual: -> (path, transform, first-level report,
    order, best) of the best."""
    short = replace(levels[1], max_iter=RETRY_SECOND_ITER)
    step = (span[1] - span[0]) / len(candidates)
    tries, residuals = [], []
    for j, candidate in enumerate(candidates):
        a, m, b = span[0] + j * step, span[0] + (j + 0.7) * step, span[0] + (j + 1) * step
        label = f" (alignment {j + 1}/{len(candidates)}, retry)"
        p, t, first = problem.solve_level(levels[0], _start(path, poses, candidate), candidate.transform, (a, m),
                                          _level_name(0, len(levels)) + label, kernels[0])
        if poses is not None:  # as the full registration goes on: a body far from every start needs its pose
            p, t, _ = try_poses(problem, basis, levels[1], _pose_judge(levels), p, t, poses, (m, m),
                                _level_name(1, len(levels)) + label, kernels[1])
        p, t, _ = problem.solve_level(short, p, t, (m, b), _level_name(1, len(levels)) + label,
                                      kernels[1], orient=True)
        tries.append((p, t, first))
        residuals.append(_residual(basis, p, t, used)[1])
    order = np.argsort(residuals)
    best = int(order[0])
    return (*tries[best], order, best)


def _rest(problem, basis, levels, kernels, poses, candidates, used, monitor, bounds, start):
    """The levels after the first from start = (path, transform, first-level report, order, best):
    -> ``_fit``'s dict."""
    path, transform, first, order, best = start
    initial = candidates[best].transform
    name = lambda k: _level_name(k, len(levels))  # noqa: E731
    tries_poses = poses is not None and len(levels) > 1
    report = [first]
    monitor.report(bounds[1], f"{name(0)} done", first["objective"])
    for k in range(1, len(levels)):
        span = (bounds[k], bounds[k + 1])
        if k == 1 and tries_poses:
            path, transform, share = try_poses(problem, basis, levels[1], _pose_judge(levels), path, transform,
                                                poses, span, name(1), kernels[1])
            span = (span[0] + share * (span[1] - span[0]), span[1])
        path, transform, lv_report = problem.solve_level(levels[k], path, transform, span, name(k), kernels[k],
                                                         orient=True)
        report.append(lv_report)
        monitor.report(bounds[k + 1], f"{name(k)} done", lv_report["objective"])

    vertices, residual = _residual(basis, path, transform, used)
    return {"path": path, "transform": transform, "vertices": vertices, "levels": report, "initial": initial,
            "residual": residual,
            "poor": is_poor_fit(basis, residual), "order": [int(j) for j in order], "best": best}
