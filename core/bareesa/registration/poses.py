r"""Pose candidates: typical poses tried as starts of the second level (``try_poses``).

The first level cannot find a pose far from the template (at coarse sigma raising an arm overhead
costs more energy than it gains in data term, so an elbow bends instead, and the finer levels keep
that local minimum). A basis may store typical poses (``extras["pose_prototypes"]``, k-means
centres of its training codes); before the second level each one's pose group, with the other
groups of the code so far, is re-aligned to the scan and scored at the second level's sigma; the
best few get the first iterations of a short second level next to the current path, and the one
that fits best at the next level's sigma runs the rest of it and goes on.
"""

from dataclasses import replace

import numpy as np

from ..errors import InputError

#: Pose candidates (a basis' stored ``pose_prototypes``, see ``try_poses``): before the second level each
#: prototype's pose coefficients, with the code's other groups, are re-aligned to the scan (at most
#: POSE_ALIGN_ITER L-BFGS steps) and scored at the second level's sigma with POSE_WEIGHT_GAIN x its
#: weight (the level's own weight prefers a bent elbow to an arm raised overhead: less energy); the best
#: POSE_FINALISTS within POSE_TIE x the current code's score get a short solve at that weight (POSE_ITER
#: iterations) next to the current path; the one that fits best at the next level's sigma goes on at
#: the level's own weight.
POSE_FINALISTS = 2
POSE_TIE = 2.0
#: ... only the POSE_REALIGN candidates that score best with their centroid matched to the scan's (no
#: iterations) are re-aligned: re-aligning each of the human basis' 32 prototypes cost ~1.5 s of CPU
POSE_REALIGN = 6
#: ... and none is when every candidate's centroid-matched score is above POSE_SKIP x the current code's
#: (scored alike): a candidate is picked only within POSE_TIE of the current code's re-aligned score, and
#: on 40 held-out `human` scans re-alignment lowered the best candidate's score to no less than 0.61 x its
#: centroid-matched one and the current code's to 0.59-0.98 x, so none above 3.2 x could have been picked
#: (none above 2.1 x was); 4 leaves a margin and skipped the re-alignments on 14 of the 40 (bench/README)
POSE_SKIP = 4.0
POSE_ITER = 40
POSE_WEIGHT_GAIN = 10.0
#: ... the short solves run on a one-step path (the end code is what the next level's sigma judges; the
#: level resumes from it on its own steps) with the level's cells coarsened to POSE_BIN_CELL x sigma: on
#: 4 `human` scans with pose finalists this picked the same candidate as the level's own steps and cells
#: and cut the stage by ~40 % (bench/README)
POSE_STEPS = 1
POSE_BIN_CELL = 0.8
#: ... the candidates are ranked after the first POSE_PICK_ITER of those iterations, and only the best one
#: runs the rest: on 10 held-out `human` scans with pose finalists the best after 20 iterations was the best
#: after 40 on 9 (the tenth a near-tie, 22.0 against 20.6 thousand), after 10 on 8; 14 held-out scans
#: registered both ways took 7 % less time at the same mean vertex error (bench/README)
POSE_PICK_ITER = 20


def check_pose_candidates(basis, candidates):
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



def stage_budget():
    """Steps x iterations of the pose stage's short solves at most (progress shares)."""
    first = min(POSE_PICK_ITER, POSE_ITER)
    return POSE_STEPS * ((POSE_FINALISTS + 1) * first + POSE_ITER - first)


def try_poses(problem, basis, level, judge, path, transform, candidates, progress, message, kernel="binet"):
    """The pose-candidate stage before ``level`` (see POSE_FINALISTS), its short solves with the level's
    ``kernel``: -> (path, transform, share of ``progress`` used). The path returned is the best short
    solve, or ``path`` when no candidate is close.

    Every start (the current end code and the POSE_REALIGN candidates that score best with their
    centroid matched to the scan's; none when they all score above POSE_SKIP x the current code) is
    first re-aligned to the scan on its own (``CoarseVarifold`` at the level's sigma, from the current
    alignment): the pre-alignment matched the scan's centroid and RMS radius to the template's, which a
    raised arm shifts by several cm.
    """
    code = path[-1]
    level = replace(level, weight=level.weight * POSE_WEIGHT_GAIN)
    starts = pose_starts(basis, candidates, code)
    energies = problem.straight_energies(level, [code, *starts])  # (the re-alignments' scores carry them)
    current, *quick = [score for _, score in problem.realign(level, [code, *starts], transform, max_iter=0,
                                                             energies=energies)]
    quick = np.array(quick)
    if quick.min() > POSE_SKIP * current:  # the current code fits far better than any candidate could
        return path, transform, 0.0
    keep = np.argsort(quick)[:POSE_REALIGN]
    starts = starts[keep]
    aligned, scores = zip(*problem.realign(level, [code, *starts], transform,
                                           energies=[energies[0], *(energies[1 + j] for j in keep)]))
    scores = np.array(scores)
    pick = [int(j) for j in np.argsort(scores[1:])[:POSE_FINALISTS] if scores[1 + j] <= POSE_TIE * scores[0]]
    if not pick:
        return path, transform, 0.0
    budget = stage_budget()
    share = budget / (level.steps * level.max_iter + budget)
    lo, hi = progress
    unit = (hi - lo) * share / budget  # progress per step x iteration of the short solves
    first = min(POSE_PICK_ITER, POSE_ITER)
    short = replace(level, max_iter=first, steps=POSE_STEPS)
    span = POSE_STEPS * first * unit
    firsts = [(path, aligned[0])] + [(np.stack([np.zeros_like(code), starts[j]]), aligned[1 + j]) for j in pick]
    tries = [problem.solve_level(short, p, t, (lo + i * span, lo + (i + 1) * span),
                                 f"{message} (pose {i + 1}/{len(pick) + 1})", kernel, orient=True,
                                 bin_cell=POSE_BIN_CELL)
             for i, (p, t) in enumerate(firsts)]
    best = int(np.argmin([problem.screen_score(judge, p[-1], t, r["energy"]) for p, t, r in tries]))
    path, transform = tries[best][0], tries[best][1]
    if POSE_ITER > first:  # only the best one runs the rest of the short solve
        rest = replace(short, max_iter=POSE_ITER - first)
        start = lo + len(firsts) * span
        end = start + POSE_STEPS * rest.max_iter * unit
        path, transform, _ = problem.solve_level(rest, path, transform, (start, end),
                                                 f"{message} (pose {best + 1}/{len(firsts)} going on)", kernel,
                                                 orient=True, bin_cell=POSE_BIN_CELL)
    return path, transform, share
