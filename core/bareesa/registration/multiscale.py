r"""``register``: the latent code of an unregistered scan, from pre-alignment to the finest level.

The scan is pre-aligned from any orientation (against the template and, with pose prototypes, the
prototypes nearest its moments). With prototypes the first fit starts from the best candidate (those
within ``prealignment.tie`` of it screened too): the pre-alignment's ranking is the more reliable one
(docs/decisions/006-first-fit-from-the-best-prealignment.md), and the first level is only the screening's
short solve and a short second level, from which the pose stage and the second level go on. Without
prototypes a deformed scan of a nearly symmetric template can match a flipped template better, so a
short first level runs from each candidate within ``prealignment.ratio`` of the best, they are ranked
by ``screen_score`` and, when the best two are within ``screening.tie``, a short second level decides.

A fit that is still poor (``is_poor_fit``; most often a body facing backwards) is registered again from
the other candidates and from itself turned half a turn about each principal axis (``half_turns``); if
that is poor too, the same alignments are screened deeper (the whole first level, the pose stage and
``screening.deep_iterations`` of the second, ranked by the fit residual) and the best fit is kept.

Every setting is in the ``RegistrationConfig`` (``config.py``); the helpers below take it and one
``RegistrationState`` and return ``Start`` / ``Fit`` dataclasses.
"""

import time
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..evaluation import chamfer
from ..mesh import validate_mesh
from ..progress import Monitor
from ..threads import with_one_blas_thread
from ..transforms import Similarity
from ..varifold import build_keops_kernels
from .articulated import Skeleton, articulated_start
from .checks import (check_face_weights, check_landmarks, check_plausible_scan, fit_residual, is_poor_fit,
                     level_kernels)
from .config import RegistrationConfig
from .detail import Detail, detail_of
from .poses import stage_budget, try_poses
from .prealign import Alignment, landmark_alignment, prealign_candidates, surface_moments
from .prepared import reference_moments
from .problem import RegistrationProblem, normal_spread
from .result import RegistrationResult

#: What the progress says while KeOps' kernels are loaded, or built at their first use on a machine
#: (``varifold.build_keops_kernels``: the bar stands still meanwhile)
KEOPS_BUILD_MESSAGE = "registration: KeOps' kernels (built once per machine, at their first use)"
#: The share of the progress bar of the basis fit when a detail layer follows it
DETAIL_SHARE = 0.85
#: ``register`` keywords that name a setting by another name than the configuration's
SETTING_ALIASES = {"pose_candidates": "poses.candidates"}


@dataclass
class RegistrationState:
    """What the helpers of one registration share: the problem (scan, template tensors, objective), the
    basis, the schedule's levels and their kernels, the pose candidates (K, P) or None, the initial path
    (2, P), the scan points that count (M', 3), the progress monitor and the bar's share before the
    levels (``lo``)."""

    problem: RegistrationProblem
    basis: object
    levels: tuple
    kernels: list
    poses: np.ndarray | None
    path: np.ndarray
    used: np.ndarray
    monitor: Monitor
    lo: float


@dataclass
class Start:
    """Where the levels after the first go on from: path (T+1, P), transform, the first level's report,
    the candidates' order by their screening and the index of the best."""

    path: np.ndarray
    transform: Similarity
    first: dict
    order: list
    best: int


@dataclass
class Fit:
    """A registration from one set of candidate alignments: path (T+1, P), transform, vertices (N, 3) in
    the scan's frame, one report per level, the candidate it started from, the fit residual and whether it
    is poor, the candidates' order and the index of the best."""

    path: np.ndarray
    transform: Similarity
    vertices: np.ndarray
    levels: list
    initial: Similarity
    residual: float
    poor: bool | None
    order: list
    best: int


#: A scan started from a known code (a capture's previous frame, or the frame another scan of it gives) skips
#: the schedule's coarsest level and runs at most this many of its finest levels: from such a code the finest
#: level alone converges more slowly than the two finest, and a third level costs time for no better fit
#: (docs/decisions/017).
WARM_LEVELS = 2


def warm_schedule(schedule):
    """The levels a warm-started registration runs: all but the coarsest of ``schedule``, at most the
    WARM_LEVELS finest (a one-level schedule: that level) -> tuple."""
    schedule = tuple(schedule)
    return schedule[max(len(schedule) - WARM_LEVELS, min(1, len(schedule) - 1)):]


def moved_landmarks(marks, transform):
    """Scan landmarks [(vertex, (x, y, z)[, weight])] mapped by a Similarity (None stays None)."""
    if marks is None:
        return None
    points = transform.apply(np.array([m[1] for m in marks], dtype=np.float64))
    return [(m[0], p, *m[2:]) for m, p in zip(marks, points)]


def register_in_frame(basis, scan_verts, scan_faces, transform, init_code, config=None, *, landmarks=None,
                      scan_face_weights=None, refine_transform=False, callback=None, cancel=None, **settings):
    """A scan registered in a frame given for it: mapped by ``transform`` (a Similarity, scan -> template
    frame, e.g. another scan's of the same capture, or a capture's previous frame's), started from init_code
    (P,), the schedule's warm levels only (``warm_schedule``), the alignment kept as it is unless
    refine_transform; ``settings`` override config as ``register``'s do: -> RegistrationResult in the scan's
    frame (its transform the alignment from the scan). Two scans of one capture registered in one frame differ
    in their codes by the motion between them, not also by a difference of alignments the pose fields absorb."""
    config = RegistrationConfig.from_basis(basis) if config is None else config
    config = config.with_overrides({SETTING_ALIASES.get(k, k): v for k, v in settings.items()})
    config = config.with_overrides({"schedule": warm_schedule(config.schedule or basis.schedule), "prealign": False,
                                    "refine_transform": refine_transform, "poses.candidates": None})
    res = register(basis, transform.apply(np.asarray(scan_verts, np.float64)), scan_faces, config,
                   landmarks=moved_landmarks(landmarks, transform), scan_face_weights=scan_face_weights,
                   init_code=init_code, callback=callback, cancel=cancel)
    report = dict(res.detail_report)
    for key in ("noise", "chamfer"):  # (lengths: into the scan's units)
        if report.get(key) is not None:
            report[key] /= float(transform.scale)
    return replace(res, vertices=transform.invert(res.vertices), transform=res.transform.compose(transform),
                   chamfer=res.chamfer / float(transform.scale), prealignment=transform, detail_report=report,
                   detailed_vertices=None if res.detailed_vertices is None else transform.invert(res.detailed_vertices))


@with_one_blas_thread
def register(basis, scan_verts, scan_faces, config=None, *, landmarks=None, scan_face_weights=None,
             init_code=None, callback=None, cancel=None, **settings):
    """Latent code of an unregistered scan: basis, scan (M, 3), (G, 3) -> RegistrationResult.

    config: a ``RegistrationConfig`` (None: ``RegistrationConfig.from_basis(basis)``); keyword
    ``settings`` override it (``schedule=``, ``prealign=``, ``kernel=``, ``dtype=``, ``pose_candidates=``,
    dotted names through ``config.with_overrides``). landmarks: [(template vertex, scan xyz[, weight])],
    adding weight * landmark_weight * A * sum_i w_i |S F(alpha)_i - T p_i|^2 / sum w (A the template's
    area); scan_face_weights (G,) >= 0 (0 ignores a face, e.g. a floor); init_code (P,) starts from the
    straight path 0 -> init_code. Raises MeshError/InputError on bad input (``check_plausible_scan``),
    SolveCancelled when cancelled (no partial result).
    """
    start_time = time.perf_counter()
    config = RegistrationConfig.from_basis(basis) if config is None else config
    config = config.with_overrides({SETTING_ALIASES.get(k, k): v for k, v in settings.items()})
    if config.schedule is None:
        config = config.with_overrides(schedule=basis.schedule)
    outer = Monitor("register", callback, cancel)  # the basis fit reports into its share, the detail layer after
    monitor = Monitor("register", outer.scaled(0.0, DETAIL_SHARE if config.detail.enabled else 1.0), cancel)
    validate_mesh(scan_verts, scan_faces, "scan")
    sv, sf = np.asarray(scan_verts, np.float64), np.asarray(scan_faces, np.int64)
    face_w = check_face_weights(scan_face_weights, sf.shape[0])
    check_plausible_scan(basis, sv, sf, face_w, config)
    marks = check_landmarks(landmarks, basis.template.shape[0])
    levels = config.schedule
    spread = normal_spread(sv, sf, face_w)
    kernels = level_kernels(config.kernel, len(levels), noisy=spread > config.noisy_spread)
    path = np.zeros((2, basis.n_fields))
    if init_code is not None:
        init = np.asarray(init_code, dtype=np.float64)
        if init.shape != (basis.n_fields,) or not np.isfinite(init).all():
            raise InputError(f"init_code must be {basis.n_fields} finite coefficients, got shape {init.shape}")
        path[1] = init
    poses = config.pose_candidates(basis)

    monitor.report(0.0, "registration: pre-aligning" if config.prealign else "registration: starting")
    monitor.check()
    candidates = _candidates(config, basis, sv, sf, face_w, marks, poses, monitor)
    problem = RegistrationProblem(basis, sv, sf, config, monitor, face_w, marks)
    lo = config.prealignment.progress_share if config.prealign else 0.0
    if config.backend != "dense":  # KeOps builds its kernels at their first use on a machine: say so, not in a level
        build_keops_kernels(config.dtype, config.device, kernels,
                            announce=lambda: monitor.report(lo, KEOPS_BUILD_MESSAGE))
    used = sv if face_w is None else sv[np.unique(sf[face_w > 0])]
    state = RegistrationState(problem, basis, levels, kernels, poses, path, used, monitor, lo)
    # with pose prototypes the pre-alignment's ranking decides the first fit, unless it cannot tell the
    # best candidates apart
    screened = candidates if poses is None else [c for c in candidates
                                                 if c.score <= config.prealignment.tie * candidates[0].score]
    skeleton = Skeleton.of_basis(basis) if config.prealign and config.articulated.enabled else None
    articulated = None
    if skeleton is not None and init_code is None:
        # the skeleton posed from the best few alignments: the first fit starts from its pose's code (a scan
        # near rest skips the search; a poor fit is retried from the pre-alignment's candidates)
        monitor.report(lo, "registration: posing the skeleton")
        t0 = time.perf_counter()
        tried = candidates[:config.articulated.alignments]
        found = articulated_start(basis, skeleton, sv, sf, [c.transform for c in tried], config.articulated, face_w,
                                  monitor, metric=problem.metric)
        articulated = {"score": None, "start": -1, "seconds": None}
        if found is not None:
            code, transform, pose = found
            posed = Alignment(tried[0].score, transform, None, code)
            screened, candidates = [posed], [posed] + candidates
            articulated.update(score=pose.score, start=pose.start)
        articulated["seconds"] = time.perf_counter() - t0
    posed_start = articulated is not None and articulated["score"] is not None
    fit = _fit(config, _after_pose(config, state) if posed_start else state, screened)
    retried = 0
    if fit.poor and config.prealign and config.retry:
        # a poor fit is most often the body turned the wrong way round: go again from the other alignments
        # (the screened ones in their order, then the pre-alignment's next ones) and the fit's half turns
        others = [screened[j] for j in fit.order if j != fit.best] + candidates[len(screened):]
        others += [Alignment(0.0, flip.compose(fit.transform)) for flip in half_turns(basis)]
        monitor.report(lo, f"registration: poor fit (residual {fit.residual:.3g}), retrying from "
                           f"{len(others)} other alignments")
        again = _fit(config, state, others)
        if again.poor:  # the short screening can rank the right alignment last: screen deeper
            monitor.report(lo, f"registration: still poor (residual {again.residual:.3g}), screening the "
                               f"{len(others)} alignments deeper")
            deeper = _fit(config, state, others, deep=True)
            again = min(again, deeper, key=lambda f: f.residual)
        retried = len(others)
        if again.residual < fit.residual:
            fit = again
    detail = _detail(config, basis, problem, fit, outer)
    detailed = None if detail.displacement is None else fit.vertices + fit.transform.invert_vectors(
        detail.displacement)
    report = {**detail.to_json(), "chamfer": None, "residual": None}
    if report["noise"] is not None:  # in the scan's units, as the distances
        report["noise"] /= float(fit.transform.scale)
    if detailed is not None:
        report.update(chamfer=chamfer(detailed, used), residual=fit_residual(basis, detailed, used, fit.transform))
    return RegistrationResult(code=fit.path[-1], vertices=fit.vertices, path=fit.path, transform=fit.transform,
                              levels=fit.levels, varifold=fit.levels[-1]["varifold"],
                              chamfer=chamfer(fit.vertices, used), seconds=time.perf_counter() - start_time,
                              prealignment=fit.initial, residual=fit.residual, poor_fit=fit.poor,
                              normal_spread=spread, retried_alignments=retried, articulated=articulated,
                              detail=detail.displacement, detailed_vertices=detailed, detail_report=report)


def _detail(config, basis, problem, fit, monitor):
    """The detail layer of the final fit (``detail.fit_detail``), or why there is none -> Detail."""
    settings = config.detail
    if not settings.enabled:
        return Detail(None, [], skipped="turned off")
    if fit.poor and not settings.poor_fits:
        monitor.report(1.0, "registration: no detail layer on a poor fit")
        return Detail(None, [], skipped="the basis fit is flagged poor")
    monitor.report(DETAIL_SHARE, "registration: detail")
    marks = None
    if problem.marks is not None:
        marks = (problem.pull, problem.landmark_points(fit.transform).detach().double())
    return detail_of(basis, fit.path[-1], fit.transform, problem.scan, problem.scan_faces_np, config,
                     problem.scan_weights_np, marks, monitor, (DETAIL_SHARE, 1.0))


def _candidates(config, basis, sv, sf, face_w, marks, poses, monitor):
    """The candidate alignments [Alignment], best first: the pre-alignment's within ``prealignment.ratio``
    of the best (after the landmarks' own alignment when three or more fix one), or the identity."""
    if not config.prealign:
        return [Alignment(0.0, Similarity())]
    references = None if poses is None else basis.template + np.tensordot(poses, basis.fields, axes=1)
    settings = config.prealignment
    candidates = prealign_candidates(basis.template, basis.faces, sv, sf, face_w, monitor=monitor,
                                     progress=(0.0, settings.progress_share), references=references,
                                     reference_moments=None if poses is None else reference_moments(
                                         basis, poses, references), settings=settings)
    candidates = [c for c in candidates if c.score <= settings.ratio * candidates[0].score + 1e-12]
    if marks is not None:  # three or more landmarks fix the orientation the surfaces alone may not
        by_marks = landmark_alignment(basis.template[marks[0]], marks[1], marks[2])
        if by_marks is not None:
            candidates = [Alignment(0.0, by_marks)] + candidates
    return candidates


def half_turns(basis):
    """Half turns about the template's principal axes through its centroid (template frame): -> 3 Similarity."""
    _, center, second = surface_moments(basis.template, basis.faces)
    out = []
    for axis in np.linalg.eigh(second)[1].T:
        rotation = 2.0 * np.outer(axis, axis) - np.eye(3)
        out.append(Similarity(rotation, 1.0, center - rotation @ center))
    return out


def _after_pose(config, state):
    """The state the first fit solves in after an articulated start: the schedule's levels no coarser than
    the articulated fit's coarsest sigma (the last one at least) and no pose stage, the fitted pose standing
    in for the prototypes (unless ``articulated.coarse_levels``) -> RegistrationState."""
    if config.articulated.coarse_levels:
        return state
    coarsest = max(config.articulated.sigmas)
    first = next((k for k, level in enumerate(state.levels) if level.sigma <= coarsest), len(state.levels) - 1)
    return replace(state, levels=state.levels[first:], kernels=state.kernels[first:], poses=None)


def _start(path, poses, alignment):
    """The path (2, P) a candidate alignment is screened from: the straight path to its own start code
    (``Alignment.code``, the articulated fit's) or to the pose prototype it was found against
    (``Alignment.reference``), else ``path`` (also when that already leads somewhere: an init_code)."""
    if np.any(path[-1]):
        return path
    if alignment.code is not None:
        return np.stack([np.zeros_like(path[-1]), alignment.code])
    if alignment.reference is None or poses is None:
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


def _bounds(config, state, candidates, screen, quick, deep):
    """The progress bar's bounds (n_levels + 1,) of the levels, the first one's share covering the
    screening of every candidate."""
    levels, screening = state.levels, config.screening
    budget = np.array([lv.steps * lv.max_iter for lv in levels], dtype=np.float64)
    if deep:
        budget[0] = len(candidates) * (budget[0] + levels[1].steps * screening.deep_iterations)
    elif quick:
        budget[0] = len(candidates) * screen.max_iter + levels[1].steps * screening.second_iterations * min(
            len(candidates), screening.finalists)
    else:
        budget[0] *= 1 + (len(candidates) / screening.divisor if len(candidates) > 1 else 0)
    if state.poses is not None and len(levels) > 1:
        budget[1] += stage_budget(config.poses)
    return state.lo + (1 - state.lo) * np.concatenate([[0.0], np.cumsum(budget) / budget.sum()])


def _fit(config, state, candidates, deep=False):
    """Every level from the best of candidate alignments [Alignment] (screened, see the module docstring;
    deep: each screened with the whole first level, the pose stage and ``screening.deep_iterations`` of
    the second, ranked by the fit residual): -> Fit."""
    levels, problem, screening = state.levels, state.problem, config.screening
    deep = deep and len(candidates) > 1 and len(levels) > 1
    # with pose prototypes the first level is only ever the screening's short solve
    quick = state.poses is not None and len(levels) > 1
    screen = levels[0] if len(candidates) == 1 and not quick else replace(
        levels[0], steps=1, max_iter=max(10, levels[0].max_iter // screening.divisor))
    bounds = _bounds(config, state, candidates, screen, quick, deep)
    if deep:
        return _rest(config, state, candidates, bounds, _deep_screen(config, state, candidates, bounds[:2]))
    name = lambda k: _level_name(k, len(levels))  # noqa: E731
    # screen every candidate alignment with a short first level; only the best one gets the full level
    # (none with pose prototypes: the second level goes on from the best one's short second level)
    share = len(candidates) / screening.divisor
    mid = bounds[1] if screen is levels[0] or quick else bounds[0] + (bounds[1] - bounds[0]) * share / (1 + share)
    tries = []
    for j, candidate in enumerate(candidates):
        span = (mid - bounds[0]) / len(candidates)
        tries.append(problem.solve_level(screen, _start(state.path, state.poses, candidate), candidate.transform,
                                         (bounds[0] + j * span, bounds[0] + (j + 1) * span),
                                         name(0) + (f" (alignment {j + 1}/{len(candidates)})" if j else ""),
                                         state.kernels[0]))
    best, resume, order, finalists = 0, None, [0], [0]
    if len(tries) > 1:
        # the screened objectives ranked on fine cells; the finer second level decides between the best
        scores = [problem.screen_score(levels[0], p[-1], t, r["energy"]) for p, t, r in tries]
        order = np.argsort(scores)
        best = int(order[0])
        finalists = [int(j) for j in order[:screening.finalists] if scores[j] <= screening.tie * scores[best]]
    if len(levels) > 1 and (len(finalists) > 1 or quick):
        short = replace(levels[1], max_iter=screening.second_iterations)
        second = [problem.solve_level(short, tries[j][0], tries[j][1], (mid, mid), name(1) + " (screening)",
                                      state.kernels[1], orient=True) for j in finalists]
        k = 0 if len(second) == 1 else int(np.argmin([problem.screen_score(levels[1], p[-1], t, r["energy"])
                                                      for p, t, r in second]))
        best, resume = finalists[k], second[k]  # the second level goes on from the winner's short one
    path, transform, first = tries[best]
    if resume is not None:
        path, transform = resume[0], resume[1]
    elif screen is not levels[0]:
        path, transform, first = problem.solve_level(levels[0], path, transform, (mid, bounds[1]), name(0),
                                                     state.kernels[0])
    return _rest(config, state, candidates, bounds, Start(path, transform, first, [int(j) for j in order], best))


def _deep_screen(config, state, candidates, span):
    """The whole first level, the pose stage (with pose candidates) and ``screening.deep_iterations``
    second-level iterations from each candidate, ranked by the fit residual: -> Start of the best."""
    levels, problem, kernels = state.levels, state.problem, state.kernels
    short = replace(levels[1], max_iter=config.screening.deep_iterations)
    step = (span[1] - span[0]) / len(candidates)
    tries, residuals = [], []
    for j, candidate in enumerate(candidates):
        a, m, b = span[0] + j * step, span[0] + (j + 0.7) * step, span[0] + (j + 1) * step
        label = f" (alignment {j + 1}/{len(candidates)}, retry)"
        p, t, first = problem.solve_level(levels[0], _start(state.path, state.poses, candidate),
                                          candidate.transform, (a, m), _level_name(0, len(levels)) + label,
                                          kernels[0])
        if state.poses is not None:  # as the full registration goes on: a body far from every start needs its pose
            p, t, _ = try_poses(problem, state.basis, levels[1], _pose_judge(levels), p, t, state.poses, (m, m),
                                _level_name(1, len(levels)) + label, kernels[1])
        p, t, _ = problem.solve_level(short, p, t, (m, b), _level_name(1, len(levels)) + label,
                                      kernels[1], orient=True)
        tries.append((p, t, first))
        residuals.append(_residual(state.basis, p, t, state.used)[1])
    order = np.argsort(residuals)
    best = int(order[0])
    return Start(*tries[best], [int(j) for j in order], best)


def _rest(config, state, candidates, bounds, start):
    """The levels after the first from ``start`` (a Start) -> Fit."""
    levels, problem = state.levels, state.problem
    path, transform = start.path, start.transform
    name = lambda k: _level_name(k, len(levels))  # noqa: E731
    report = [start.first]
    state.monitor.report(bounds[1], f"{name(0)} done", start.first["objective"])
    for k in range(1, len(levels)):
        span = (bounds[k], bounds[k + 1])
        if k == 1 and state.poses is not None:
            path, transform, share = try_poses(problem, state.basis, levels[1], _pose_judge(levels), path,
                                               transform, state.poses, span, name(1), state.kernels[1])
            span = (span[0] + share * (span[1] - span[0]), span[1])
        path, transform, lv_report = problem.solve_level(levels[k], path, transform, span, name(k),
                                                         state.kernels[k], orient=True)
        report.append(lv_report)
        state.monitor.report(bounds[k + 1], f"{name(k)} done", lv_report["objective"])
    vertices, residual = _residual(state.basis, path, transform, state.used)
    return Fit(path, transform, vertices, report, candidates[start.best].transform, residual,
               is_poor_fit(state.basis, residual), start.order, start.best)
