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


def pose_starts(basis, candidates, code):
    """Start codes from pose candidates: each candidate's "pose" group with ``code``'s other groups
    (the candidates themselves when the basis has no "pose" group or nothing else): (K, P), (P,) -> (K, P)."""
    starts = np.array(candidates, dtype=np.float64)
    if "pose" in basis.groups and len(basis.groups) > 1:
        keep = np.ones(basis.n_fields, dtype=bool)
        keep[basis.group_slice("pose")] = False
        starts[:, keep] = code[keep]
    return starts


def stage_budget(settings):
    """Steps x iterations of the pose stage's short solves at most (progress shares): settings a
    ``config.PoseSearch``."""
    first = min(settings.pick_iterations, settings.iterations)
    return settings.steps * ((settings.finalists + 1) * first + settings.iterations - first)


def try_poses(problem, basis, level, judge, path, transform, candidates, progress, message, kernel="binet"):
    """The pose-candidate stage before ``level``, its short solves with the level's ``kernel``, as
    ``problem.config.poses`` (a ``config.PoseSearch``) sets it: -> (path, transform, share of ``progress``
    used). The path returned is the best short solve, or ``path`` when no candidate is close.

    Every start (the current end code and the ``realign`` candidates that score best with their centroid
    matched to the scan's; none when they all score above ``skip`` x the current code) is first
    re-aligned to the scan on its own (``CoarseVarifold`` at the level's sigma, from the current
    alignment): the pre-alignment matched the scan's centroid and RMS radius to the template's, which a
    raised arm shifts by several cm. The best ``finalists`` within ``tie`` x the current code's score get
    a short solve at ``weight_gain`` x the level's weight (the level's own weight prefers a bent elbow to
    an arm raised overhead), ranked after ``pick_iterations`` by ``judge``'s sigma; the best goes on.
    """
    settings = problem.config.poses
    code = path[-1]
    level = replace(level, weight=level.weight * settings.weight_gain)
    starts = pose_starts(basis, candidates, code)
    energies = problem.straight_energies(level, [code, *starts])  # (the re-alignments' scores carry them)
    current, *quick = [score for _, score in problem.realign(level, [code, *starts], transform, max_iter=0,
                                                             energies=energies)]
    quick = np.array(quick)
    if quick.min() > settings.skip * current:  # the current code fits far better than any candidate could
        return path, transform, 0.0
    keep = np.argsort(quick)[:settings.realign]
    starts = starts[keep]
    aligned, scores = zip(*problem.realign(level, [code, *starts], transform,
                                           energies=[energies[0], *(energies[1 + j] for j in keep)]))
    scores = np.array(scores)
    pick = [int(j) for j in np.argsort(scores[1:])[:settings.finalists] if scores[1 + j] <= settings.tie * scores[0]]
    if not pick:
        return path, transform, 0.0
    budget = stage_budget(settings)
    share = budget / (level.steps * level.max_iter + budget)
    lo, hi = progress
    unit = (hi - lo) * share / budget  # progress per step x iteration of the short solves
    first = min(settings.pick_iterations, settings.iterations)
    short = replace(level, max_iter=first, steps=settings.steps)
    span = settings.steps * first * unit
    firsts = [(path, aligned[0])] + [(np.stack([np.zeros_like(code), starts[j]]), aligned[1 + j]) for j in pick]
    tries = [problem.solve_level(short, p, t, (lo + i * span, lo + (i + 1) * span),
                                 f"{message} (pose {i + 1}/{len(pick) + 1})", kernel, orient=True,
                                 bin_cell=settings.bin_cell)
             for i, (p, t) in enumerate(firsts)]
    best = int(np.argmin([problem.screen_score(judge, p[-1], t, r["energy"]) for p, t, r in tries]))
    path, transform = tries[best][0], tries[best][1]
    if settings.iterations > first:  # only the best one runs the rest of the short solve
        rest = replace(short, max_iter=settings.iterations - first)
        start = lo + len(firsts) * span
        end = start + settings.steps * rest.max_iter * unit
        path, transform, _ = problem.solve_level(rest, path, transform, (start, end),
                                                 f"{message} (pose {best + 1}/{len(firsts)} going on)", kernel,
                                                 orient=True, bin_cell=settings.bin_cell)
    return path, transform, share
