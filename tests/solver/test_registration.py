"""Registration of unregistered scans: latent code retrieval, pre-alignment, landmarks, clutter."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from bareesa import evaluation, registration, synthetic
from bareesa.registration import checks, poses, prepared
from bareesa.registration import problem as level_problem
from bareesa.registration.config import LevelSolve, PoseSearch, RegistrationConfig
from bareesa.transforms import Similarity, axis_angle_rotation
from bareesa.errors import InputError, MeshError, SolveCancelled
from bareesa.h2_metric import H2Weights
from bareesa.latent import Level
from bareesa.progress import CancelToken, Monitor

SCALE, SHIFT = 3.7, np.array([1.0, -2.0, 0.5])


@pytest.fixture(scope="module")
def space():
    """A smooth 6-field latent space on icosphere(2), a code alpha* and F(alpha*) on another mesh."""
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    alpha = 0.8 * np.random.default_rng(1).normal(size=6)
    u, faces = synthetic.resampled_sphere(2, seed=3)
    truth = surface(synthetic.icosphere(2)[0], alpha)  # F(alpha*) vertex by vertex
    return {"basis": basis, "alpha": alpha, "truth": truth, "scan": surface(u, alpha), "faces": faces,
            "rotation": synthetic.random_rotation(5), "surface": surface}


def to_scan_frame(space, points):
    return SCALE * points @ space["rotation"].T + SHIFT


@pytest.fixture(scope="module")
def moved(space):
    """Registration of the remeshed scan after an arbitrary rotation, x 3.7 and a translation."""
    events = []
    res = registration.register(space["basis"], to_scan_frame(space, space["scan"]), space["faces"],
                                backend="dense", callback=events.append)
    return res, events


@pytest.fixture(scope="module")
def aligned(space):
    """Registration of the remeshed scan given in the template frame (no pre-alignment)."""
    return registration.register(space["basis"], space["scan"], space["faces"], prealign=False, backend="dense")


def test_register_recovers_code_of_remeshed_rotated_rescaled_scan(space, moved):
    res, _ = moved
    alpha = space["alpha"]
    assert np.abs(res.code - alpha).max() < 1e-2 * np.linalg.norm(alpha)
    truth = to_scan_frame(space, space["truth"])
    size = np.ptp(truth, axis=0).max()
    assert np.linalg.norm(res.vertices - truth, axis=1).mean() < 5e-3 * size
    assert res.transform.scale == pytest.approx(1 / SCALE, rel=1e-2)
    assert np.allclose(res.vertices, res.transform.invert(space["basis"].template
                                                          + np.tensordot(res.code, space["basis"].fields, 1)))
    assert res.path.shape == (space["basis"].schedule[-1].steps + 1, 6) and not res.path[0].any()


def test_register_in_template_frame_recovers_code(space, aligned):
    assert np.abs(aligned.code - space["alpha"]).max() < 1e-2 * np.linalg.norm(space["alpha"])
    assert np.linalg.norm(aligned.vertices - space["truth"], axis=1).mean() < 5e-3 * 2.0


def test_prealignment_recovers_known_rotation_and_scale_of_template(space):
    basis = space["basis"]
    verts, faces = synthetic.remesh_same_surface(basis.template, basis.faces, seed=4)
    rot = synthetic.random_rotation(11)
    scan = 0.37 * verts @ rot.T + np.array([-3.0, 0.2, 7.0])
    t = registration.align_to_template(basis.template, basis.faces, scan, faces)
    angle = np.degrees(np.arccos(np.clip((np.trace(t.rotation @ rot) - 1) / 2, -1, 1)))
    assert angle < 1.0
    assert t.scale == pytest.approx(1 / 0.37, rel=1e-2)
    assert np.abs(t.apply(scan) - verts).max() < 0.02 * np.ptp(verts, axis=0).max()


def test_a_scan_with_randomly_flipped_faces_registers_as_the_clean_one(space, moved):
    """The default data term sees a face and its flip alike down to the finest level (binet), whose
    oriented kernel runs on the scan's faces wound consistently and turned like the fit: scans with
    inconsistent normals (a third of the faces flipped) register to the same code and alignment."""
    faces = space["faces"].copy()
    flip = np.random.default_rng(7).random(len(faces)) < 1 / 3
    faces[flip] = faces[flip][:, ::-1]
    res = registration.register(space["basis"], to_scan_frame(space, space["scan"]), faces, backend="dense")
    clean, _ = moved
    assert np.abs(res.code - clean.code).max() < 1e-6 * np.linalg.norm(clean.code)
    assert np.abs(res.vertices - clean.vertices).max() < 1e-6 * np.ptp(clean.vertices, axis=0).max()


def test_landmarks_pull_the_solution_towards_them(space, aligned):
    basis = space["basis"]
    other = space["alpha"] + np.array([0.6, -0.6, 0.0, 0.5, 0.0, -0.5])
    target = basis.template + np.tensordot(other, basis.fields, 1)
    idx = [0, 40, 80, 120, 160]
    marks = [(i, target[i]) for i in idx]
    res = registration.register(basis, space["scan"], space["faces"], prealign=False, backend="dense",
                                landmarks=marks, landmark_weight=20.0)
    before = np.linalg.norm(aligned.vertices[idx] - target[idx], axis=1).mean()
    after = np.linalg.norm(res.vertices[idx] - target[idx], axis=1).mean()
    assert after < 0.5 * before
    assert np.linalg.norm(res.code - other) < np.linalg.norm(aligned.code - other)


def test_bad_landmarks_and_inputs_raise_input_errors(space):
    basis, scan, faces = space["basis"], space["scan"], space["faces"]
    n = basis.template.shape[0]
    for marks in ([(n, [0.0, 0.0, 0.0])], [(-1, [0.0, 0.0, 0.0])], [(1.5, [0.0, 0.0, 0.0])],
                  [(0, [0.0, np.nan, 0.0])], [(0, [0.0, 0.0])], [(0,)]):
        with pytest.raises(InputError, match="landmark"):
            registration.register(basis, scan, faces, landmarks=marks)
    with pytest.raises(InputError, match="face weights"):
        registration.register(basis, scan, faces, scan_face_weights=np.ones(len(faces) + 1))
    with pytest.raises(InputError, match="face weights"):
        registration.register(basis, scan, faces, scan_face_weights=-np.ones(len(faces)))
    with pytest.raises(InputError, match="zero"):
        registration.register(basis, scan, faces, scan_face_weights=np.zeros(len(faces)))
    with pytest.raises(MeshError, match="empty"):
        registration.register(basis, np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    bad = scan.copy()
    bad[3, 1] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        registration.register(basis, bad, faces)
    with pytest.raises(InputError, match="schedule"):
        registration.register(basis, scan, faces, schedule=())
    with pytest.raises(InputError, match="init_code"):
        registration.register(basis, scan, faces, init_code=np.zeros(5))


def test_zero_weight_clutter_is_ignored(space, moved):
    """A floor plane under the scan, weighted 0, changes neither the alignment nor the code."""
    scan = to_scan_frame(space, space["scan"])
    g = np.linspace(-2.0, 2.0, 6)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    plane = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, -1.4)], 1)
    a = (np.arange(5)[:, None] * 6 + np.arange(5)[None, :]).ravel()
    plane_faces = np.concatenate([np.stack([a, a + 6, a + 7], 1), np.stack([a, a + 7, a + 1], 1)])
    verts = np.concatenate([scan, to_scan_frame(space, plane)])
    faces = np.concatenate([space["faces"], plane_faces + len(scan)])
    weights = np.r_[np.ones(len(space["faces"])), np.zeros(len(plane_faces))]
    res = registration.register(space["basis"], verts, faces, scan_face_weights=weights, backend="dense")
    assert np.abs(res.code - moved[0].code).max() < 1e-3 * np.linalg.norm(space["alpha"])
    assert res.chamfer == pytest.approx(moved[0].chamfer, rel=1e-3)


def test_cancel_from_callback_raises_solve_cancelled(space):
    token = CancelToken()
    seen = []

    def callback(event):
        seen.append(event)
        token.cancel()

    with pytest.raises(SolveCancelled):
        registration.register(space["basis"], space["scan"], space["faces"], backend="dense",
                              callback=callback, cancel=token)
    assert len(seen) == 1 and seen[0].task == "register"


def test_cancel_during_optimisation_raises_solve_cancelled(space):
    token = CancelToken()
    seen = []

    def callback(event):
        seen.append(event)
        if len(seen) == 5:
            token.cancel()

    with pytest.raises(SolveCancelled):
        registration.register(space["basis"], space["scan"], space["faces"], prealign=False, backend="dense",
                              callback=callback, cancel=token)
    assert len(seen) == 5


def test_progress_is_monotone_and_reaches_one(moved):
    fractions = [e.fraction for e in moved[1]]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0
    assert all(b >= a for a, b in zip(fractions, fractions[1:]))


def test_to_json_has_finite_summary(moved):
    res = moved[0]
    out = json.loads(json.dumps(res.to_json()))
    assert {"code", "varifold", "chamfer", "seconds", "levels"} <= set(out)
    assert len(out["code"]) == 6 and np.isfinite(out["code"]).all()
    assert all(np.isfinite(out[k]) for k in ("varifold", "chamfer", "seconds"))
    assert len(out["levels"]) == len(res.levels) == 2
    for lv in out["levels"]:
        assert {"sigma", "weight", "steps", "iterations", "energy", "varifold", "seconds"} <= set(lv)
        assert all(np.isfinite(v) for k, v in lv.items() if k not in ("kernel", "turned_faces"))
        assert lv["kernel"] in ("binet", "linear") and lv["turned_faces"] in (None, 0)


def test_similarity_apply_invert_compose_roundtrip():
    a = Similarity(synthetic.random_rotation(1), 2.5, [1.0, 2.0, 3.0])
    b = Similarity(synthetic.random_rotation(2), 0.3, [0.0, -1.0, 0.5])
    x = np.random.default_rng(0).normal(size=(10, 3))
    assert np.allclose(a.invert(a.apply(x)), x)
    assert np.allclose(a.compose(b).apply(x), a.apply(b.apply(x)))
    assert np.allclose(a.inverse().apply(x), a.invert(x))
    xt = torch.as_tensor(x)
    assert torch.allclose(a.apply(xt), torch.as_tensor(a.apply(x)))
    c = Similarity.from_dict(json.loads(json.dumps(a.to_dict())))
    assert np.allclose(c.apply(x), a.apply(x))
    with pytest.raises(InputError):
        Similarity(np.diag([1.0, 1.0, -1.0]), 1.0, np.zeros(3))


def test_float32_objective_matches_float64(space, aligned):
    schedule = (Level(0.25, 1e3, 1, 60),)
    r64 = registration.register(space["basis"], space["scan"], space["faces"], prealign=False, backend="dense",
                                schedule=schedule)
    r32 = registration.register(space["basis"], space["scan"], space["faces"], prealign=False, backend="dense",
                                schedule=schedule, dtype=torch.float32)
    assert np.abs(r32.code - r64.code).max() < 1e-3 * np.linalg.norm(space["alpha"])


def test_binned_varifold_matches_exact_varifold_at_coarse_sigma(space):
    from bareesa.varifold import BinnedVarifoldLoss, VarifoldLoss

    basis = space["basis"]
    src, src_faces = (torch.as_tensor(x) for x in synthetic.remesh_same_surface(basis.template, basis.faces, seed=1))
    tgt, tgt_faces = (torch.as_tensor(x) for x in synthetic.remesh_same_surface(space["truth"], basis.faces, seed=2))
    for kernel in ("binet", "linear"):
        exact = VarifoldLoss(tgt, tgt_faces, 1.0, kernel=kernel, backend="dense")(src, src_faces)
        binned = BinnedVarifoldLoss(src, src_faces, tgt, tgt_faces, 1.0, kernel=kernel)
        assert binned.n_groups < src_faces.shape[0] / 4
        assert float(binned(src, src_faces)) == pytest.approx(float(exact), rel=0.05)


def test_fine_level_scan_binning_keeps_the_code(space, monkeypatch):
    # a scan 16x denser than the template: at the unbinned levels the scan measure is summed over
    # cells of SCAN_CELL x sigma (fewer points), which must not move the recovered code (observed:
    # 0.9% of |alpha| apart, both ~5-8% from alpha, the error of this coarse basis on this scan)
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    u, faces = synthetic.resampled_sphere(4, seed=4)
    scan = surface(u, space["alpha"])
    seen = []
    real = level_problem.VarifoldLoss

    def spy(*args, **kwargs):
        loss = real(*args, **kwargs)
        seen.append(loss.target_points)
        return loss

    monkeypatch.setattr(level_problem, "VarifoldLoss", spy)
    binned = registration.register(basis, scan, faces, prealign=False, backend="dense")
    assert LevelSolve().scan_cell is not None and max(seen) < 0.5 * faces.shape[0]
    seen.clear()
    exact = registration.register(basis, scan, faces, prealign=False, backend="dense", **{"solve.scan_cell": None})
    assert seen and set(seen) == {faces.shape[0]}
    scale = np.linalg.norm(space["alpha"])
    assert np.linalg.norm(binned.code - exact.code) < 0.02 * scale
    assert np.linalg.norm(binned.code - space["alpha"]) < np.linalg.norm(exact.code - space["alpha"]) + 0.02 * scale


def test_screen_score_tracks_the_exact_objective_and_ranks_alignments_like_it(space):
    # candidate alignments are ranked by screen_score: at the second level's sigma, on fine cells,
    # it must agree with the unbinned objective weight * Gamma + E (the level's coarse binning does not)
    from bareesa.varifold import varifold_distance

    basis = space["basis"]
    level = basis.schedule[min(1, len(basis.schedule) - 1)]
    problem = _problem(space)
    exact, scores = [], []
    for degrees in (0.0, 10.0, 30.0, 180.0):
        r = axis_angle_rotation(np.radians(degrees) * np.array([0.0, 0.6, 0.8]))
        transform = Similarity(r, 1.0, np.zeros(3))
        final = torch.as_tensor(basis.template + np.tensordot(space["alpha"], basis.fields, 1))
        gamma = float(varifold_distance(final, torch.as_tensor(basis.faces),
                                        torch.as_tensor(transform.apply(space["scan"])),
                                        torch.as_tensor(space["faces"]), level.sigma * basis.scale))
        exact.append(level.weight * gamma + 1.0)
        scores.append(problem.screen_score(level, space["alpha"], transform, 1.0))
    assert np.allclose(scores, exact, rtol=0.02)
    assert np.argsort(scores).tolist() == np.argsort(exact).tolist() and np.argmin(scores) == 0


def _problem(space, **overrides):
    """The level problem of the space's scan (dense sums, the similarity refined, the basis' path metric),
    its settings changed by ``overrides`` (dotted keys)."""
    basis = space["basis"]
    config = RegistrationConfig(metric=basis.weights, backend="dense", refine_transform=True)
    return level_problem.RegistrationProblem(basis, space["scan"], space["faces"], config.with_overrides(overrides),
                                             Monitor("test"))


def test_a_level_reports_the_energy_and_varifold_of_the_point_it_returns(space):
    # the report's terms are those of the returned path and alignment (kept from the optimiser's own
    # evaluation of that point): weight * varifold + energy is the objective it returns, and the energy
    # is the returned path's
    from bareesa import h2_metric
    from bareesa.latent import decode

    problem, level = _problem(space), space["basis"].schedule[-1]
    path, _, report = problem.solve_level(level, np.zeros((2, 6)), Similarity(), (0.0, 1.0), "test")
    assert report["iterations"] > 0
    assert report["objective"] == pytest.approx(level.weight * report["varifold"] + report["energy"], rel=1e-12)
    meshes = decode(problem.template, problem.fields, torch.as_tensor(path))
    assert report["energy"] == pytest.approx(float(h2_metric.path_energy(meshes, problem.faces, problem.metric)),
                                             rel=1e-5)


def test_pose_starts_take_only_the_pose_group_of_each_candidate(space):
    from dataclasses import replace

    rng = np.random.default_rng(0)
    candidates, code = rng.normal(size=(3, 6)), rng.normal(size=6)
    grouped = replace(space["basis"], groups={"pose": (0, 4), "shape": (4, 6)})
    starts = registration.pose_starts(grouped, candidates, code)
    assert np.array_equal(starts[:, :4], candidates[:, :4]) and np.array_equal(starts[:, 4:], np.tile(code[4:], (3, 1)))
    assert np.array_equal(registration.pose_starts(space["basis"], candidates, code), candidates)  # no pose group


def test_realign_moves_a_shifted_rescaled_scan_back_onto_the_surface(space):
    problem, level = _problem(space), space["basis"].schedule[1]
    size = np.ptp(space["scan"], axis=0).max()
    off = Similarity(axis_angle_rotation(np.radians(4) * np.array([0.0, 0.6, 0.8])), 1.08,
                                  np.array([0.05, -0.03, 0.04]) * size)
    (fixed, score), = problem.realign(level, [space["alpha"]], off)
    error = lambda t: np.linalg.norm(t.apply(space["scan"]) - space["scan"], axis=1).mean()  # noqa: E731
    assert error(fixed) < 0.25 * error(off)
    energy = problem.straight_energies(level, [space["alpha"]])[0]
    screened = lambda t: problem.screen_score(level, space["alpha"], t, energy)  # noqa: E731
    assert screened(fixed) < screened(off)
    assert math.isfinite(score) and score > 0


def test_straight_energies_in_batches_are_each_straight_paths_energy(space, monkeypatch):
    """``straight_energies`` sums ``solve.straight_batch`` paths a call (here 4, over 11 codes): each energy is the
    path energy of its own straight path 0 -> code, and a code's energy does not depend on its batch."""
    from bareesa import h2_metric
    from bareesa.latent import decode

    problem, level = _problem(space, **{"solve.straight_batch": 4}), space["basis"].schedule[1]
    codes = space["alpha"] * np.random.default_rng(8).uniform(0.2, 1.5, size=(11, 1))
    got = problem.straight_energies(level, codes)
    ramp = torch.linspace(0, 1, level.steps + 1, dtype=torch.float64)[:, None]
    for code, energy in zip(codes, got):
        path = decode(problem.template, problem.fields, ramp * torch.as_tensor(code))
        alone = float(h2_metric.path_energy(path, problem.faces, problem.metric, compute_dtype=LevelSolve().energy_dtype))
        assert energy == pytest.approx(alone, rel=1e-12)
    assert problem.straight_energies(level, codes[5:7]) == pytest.approx(got[5:7], rel=1e-12)
    assert len(set(got)) == 11


def test_realign_scores_all_codes_against_one_scan_loss_as_one_by_one(space, monkeypatch):
    # one loss against the scan for all codes (its self term summed once): the same scores as one code
    # at a time
    problem, level = _problem(space), space["basis"].schedule[1]
    codes = space["alpha"] + 0.3 * np.random.default_rng(6).normal(size=(5, 6))
    built = []

    class Counted(level_problem.BinnedMeasureLoss):
        def __init__(self, *args, **kwargs):
            built.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(level_problem, "BinnedMeasureLoss", Counted)
    together = problem.realign(level, codes, Similarity(), max_iter=0)
    assert len(built) == 1
    alone = [problem.realign(level, [c], Similarity(), max_iter=0)[0] for c in codes]
    assert len(built) == 6
    scores = [s for _, s in together]
    assert np.allclose(scores, [s for _, s in alone], rtol=1e-12) and len(set(np.round(scores, 9))) == 5


def test_pose_short_solves_run_on_a_one_step_path_and_coarser_cells(space, monkeypatch):
    basis, alpha = space["basis"], space["alpha"]
    problem = _problem(space, **{"poses.iterations": 2})
    solved = []
    solve = problem.solve_level

    def spy(level, *args, **kwargs):
        solved.append((level.steps, level.max_iter, kwargs.get("bin_cell")))
        return solve(level, *args, **kwargs)

    problem.solve_level = spy
    poses.try_poses(problem, basis, basis.schedule[1], basis.schedule[-1], np.zeros((2, 6)), Similarity(),
                    alpha[None] + 0.05, (0.0, 1.0), "test")
    assert solved and set(solved) == {(PoseSearch().steps, 2, PoseSearch().bin_cell)}
    assert PoseSearch().steps < basis.schedule[1].steps and PoseSearch().bin_cell > LevelSolve().bin_cell


def test_pose_candidates_are_ranked_after_a_few_iterations_and_only_the_best_goes_on(space, monkeypatch):
    basis, alpha = space["basis"], space["alpha"]
    rng = np.random.default_rng(4)
    candidates = np.concatenate([rng.normal(size=(4, 6)), [alpha + 0.05 * rng.normal(size=6)]])
    problem = _problem(space, **{"poses.iterations": 5, "poses.pick_iterations": 2})
    solved, solve = [], problem.solve_level

    def spy(level, path, *args, **kwargs):
        out = solve(level, path, *args, **kwargs)
        solved.append((level.max_iter, path[-1].copy(), out[0][-1].copy(), args[1]))
        return out

    problem.solve_level = spy
    path, _, share = poses.try_poses(problem, basis, basis.schedule[1], basis.schedule[-1], np.zeros((2, 6)),
                                     Similarity(), candidates, (0.0, 1.0), "test")
    *ranked, (rest_iter, rest_start, rest_end, rest_progress) = solved
    assert len(ranked) >= 2 and [it for it, *_ in ranked] == [2] * len(ranked) and rest_iter == 3
    ends = [end for _, _, end, _ in ranked]
    assert any(np.array_equal(rest_start, end) for end in ends)  # the rest goes on from one of the ranked
    assert np.array_equal(path[-1], rest_end) and np.linalg.norm(path[-1] - alpha) < 0.2 * np.linalg.norm(alpha)
    assert ranked[0][3][0] == 0.0 and ranked[-1][3][1] <= rest_progress[0] < rest_progress[1] <= share + 1e-12


def test_pose_stage_starts_the_level_from_the_candidate_that_fits(space, monkeypatch):
    # short solves of 2 iterations barely move: the stage must hand on the candidate near alpha*,
    # not the template it was given or the far candidates
    basis, alpha = space["basis"], space["alpha"]
    rng = np.random.default_rng(4)
    candidates = np.concatenate([rng.normal(size=(4, 6)), [alpha + 0.05 * rng.normal(size=6)]])
    path, transform, share = poses.try_poses(_problem(space, **{"poses.iterations": 2}), basis, basis.schedule[1], basis.schedule[-1],
                                                     np.zeros((2, 6)), Similarity(), candidates,
                                                     (0.0, 1.0), "test")
    assert 0 < share < 1
    assert np.linalg.norm(path[-1] - alpha) < 0.2 * np.linalg.norm(alpha)
    assert np.linalg.norm(transform.apply(space["scan"]) - space["scan"], axis=1).max() < 0.05


def test_pose_stage_realigns_only_the_best_centroid_matched_candidates_and_still_finds_the_fit(space, monkeypatch):
    # 10 far candidates and one near alpha*: the cheap score (centroid matched, no iterations) must keep
    # the near one among the POSE_REALIGN that get the full re-alignment
    basis, alpha = space["basis"], space["alpha"]
    rng = np.random.default_rng(5)
    candidates = np.concatenate([2 * rng.normal(size=(10, 6)), [alpha + 0.05 * rng.normal(size=6)]])
    problem = _problem(space, **{"poses.iterations": 2, "poses.realign": 2})
    calls, summed = [], []
    realign, straight = problem.realign, problem.straight_energies

    def spy(level, codes, transform, max_iter=15, energies=None):
        calls.append((len(codes), max_iter))
        # the straight paths' energies are summed once for the stage and handed to every re-alignment
        assert energies is not None and len(energies) == len(codes)
        assert np.allclose(energies, straight(level, codes), rtol=1e-12, atol=0)
        return realign(level, codes, transform, max_iter, energies)

    problem.realign = spy
    problem.straight_energies = lambda level, codes: summed.append(len(codes)) or straight(level, codes)
    path, transform, _ = poses.try_poses(problem, basis, basis.schedule[1], basis.schedule[-1], np.zeros((2, 6)),
                                         Similarity(), candidates, (0.0, 1.0), "test")
    assert calls[0] == (12, 0)  # the current code and every candidate scored once, centroid matched
    assert [n for n, it in calls if it > 0] == [3]  # the current code and the 2 best re-aligned
    assert summed == [12]
    assert np.linalg.norm(path[-1] - alpha) < 0.2 * np.linalg.norm(alpha)


@pytest.mark.parametrize("skip", [PoseSearch().skip, math.inf])
def test_pose_stage_is_skipped_when_the_current_code_fits_far_better_than_every_candidate(space, monkeypatch, skip):
    # the current path ends at alpha* (the scan's own code) and every candidate is far: only the cheap
    # centroid-matched scores are taken, and the path comes back as it was; with no skip (inf) the same
    # stage re-aligns the current code and the best candidates
    basis, alpha = space["basis"], space["alpha"]
    candidates = 3 * np.random.default_rng(7).normal(size=(6, 6))
    problem = _problem(space, **{"poses.skip": skip, "poses.iterations": 2})
    calls, solved = [], []
    realign, solve = problem.realign, problem.solve_level

    def spy(level, codes, transform, max_iter=15, energies=None):
        calls.append((len(codes), max_iter))
        return realign(level, codes, transform, max_iter, energies)

    problem.realign = spy
    problem.solve_level = lambda *args, **kwargs: solved.append(1) or solve(*args, **kwargs)
    start = np.stack([np.zeros(6), alpha])
    path, transform, share = poses.try_poses(problem, basis, basis.schedule[1], basis.schedule[-1], start,
                                             Similarity(), candidates, (0.0, 1.0), "test")
    assert calls[0] == (7, 0)
    if skip == math.inf:
        assert any(it > 0 for _, it in calls[1:])
        return
    assert calls == [(7, 0)] and not solved and share == 0.0
    assert path is start and np.array_equal(transform.apply(space["scan"]), space["scan"])


def test_a_prepared_basis_carries_its_constants_and_prealigns_exactly_as_one_computed_afresh(space, tmp_path,
                                                                                            monkeypatch):
    # prepare_basis keeps the shape weights' template metric and the pose prototypes' surface moments in the
    # extras; saved and loaded, registration uses them as stored, with the very candidates it computes
    # without them; moments stored for other prototypes are not used
    from bareesa import basis_io, h2_metric
    from bareesa.registration import prealign

    basis = replace(space["basis"], extras=dict(space["basis"].extras), shape_weights=H2Weights(2, 1, 1, 1, 1, 5))
    protos = 0.5 * np.random.default_rng(8).normal(size=(5, 6))
    basis.extras["pose_prototypes"] = protos
    refs = basis.template + np.tensordot(protos, basis.fields, axes=1)
    registration.prepare_basis(basis)
    basis_io.save_basis(tmp_path / "p.npz", basis)
    loaded = basis_io.load_basis(tmp_path / "p.npz")
    assert set(registration.PREPARED_EXTRAS) <= set(loaded.extras)
    table = loaded.extras[prepared.PROTOTYPE_MOMENTS]
    assert np.array_equal(table, prealign.moment_table(refs, basis.faces)) and table.shape == (5, 12)
    scan = to_scan_frame(space, space["scan"])
    with monkeypatch.context() as patch:
        patch.setattr(prepared, "moment_table", lambda *a: pytest.fail("moments recomputed"))
        patch.setattr(h2_metric, "assembled_metric_matrix", lambda *a, **k: pytest.fail("metric recomputed"))
        assert prepared.reference_moments(loaded, protos, refs) is table
        assert np.array_equal(loaded.template_metric(loaded.shape_weights), basis.template_metric(basis.shape_weights))
    stored = prealign.prealign_candidates(basis.template, basis.faces, scan, space["faces"], references=refs,
                                          reference_moments=table)
    fresh = prealign.prealign_candidates(basis.template, basis.faces, scan, space["faces"], references=refs)
    assert [(c.score, c.reference) for c in stored] == [(c.score, c.reference) for c in fresh]
    assert all(np.array_equal(a.transform.apply(scan), b.transform.apply(scan)) for a, b in zip(stored, fresh))
    other = protos[::-1].copy()
    moments = prepared.reference_moments(loaded, other, refs[::-1])
    assert np.array_equal(moments, table[::-1]) and loaded.extras[prepared.PROTOTYPE_MOMENTS] is table
    loaded.extras[prepared.PROTOTYPE_MOMENTS] = table[:, :9]  # a damaged table is computed afresh
    assert np.array_equal(prepared.reference_moments(loaded, protos, refs), table)


def test_keops_kernels_are_built_before_the_levels_and_are_the_ones_a_registration_sums_with(space, monkeypatch,
                                                                                            tmp_path):
    # KeOps compiles a formula at its first use in an environment (~5 s each): a registration has them built
    # before its first level and says so, sums with no formula that was not built, and leaves a marker by
    # which later processes (and registrations) skip it
    from bareesa.registration import multiscale
    from bareesa.varifold import backends, keops_available

    if not keops_available():
        pytest.skip("pykeops does not import here")
    seen, real = [], backends._keops_sums

    def spy(x, u, y, v, g, kind, grad, ranges=None):
        seen.append((type(kind).__name__, getattr(kind, "dim", None), grad, ranges is not None, x.dtype))
        return real(x, u, y, v, g, kind, grad, ranges)

    marker = tmp_path / "built"
    monkeypatch.setattr(backends, "_keops_sums", spy)
    monkeypatch.setattr(backends, "_built_marker", lambda dtype, device, formulas: marker)
    monkeypatch.setattr(backends, "_built", set())
    for run in ("first", "same process", "next process"):
        if run == "next process":
            monkeypatch.setattr(backends, "_built", set())
        events, seen[:] = [], []
        registration.register(space["basis"], space["scan"], space["faces"], prealign=False, backend="truncated",
                              callback=events.append)
        messages = [e.message for e in events]
        if run != "first":
            assert multiscale.KEOPS_BUILD_MESSAGE not in messages and seen and marker.exists()
            continue
        said = messages.index(multiscale.KEOPS_BUILD_MESSAGE)
        assert not any("level" in m for m in messages[:said])
        n = len(backends.keops_formulas())
        built, summed = set(seen[:n]), set(seen[n:])
        assert len(built) == n and summed and summed <= built


def test_a_machine_where_keops_cannot_build_its_kernels_registers_with_torch_sums_after_a_warning(space, aligned,
                                                                                                 monkeypatch, tmp_path):
    # pykeops imports but its compiler fails (no g++, a broken toolchain): the registration is not lost, KeOps
    # is turned off for the process with a one-line warning, and the torch sums give the same fit
    from bareesa.varifold import backends, kernels

    def broken(*args, **kwargs):
        raise RuntimeError("[KeOps] Error: g++ not found\nmore lines")

    monkeypatch.setattr(kernels, "_KEOPS", True)
    monkeypatch.setattr(backends, "_keops_sums", broken)
    monkeypatch.setattr(backends, "_built", set())
    monkeypatch.setattr(backends, "_built_marker", lambda dtype, device, formulas: tmp_path / "built")
    with pytest.warns(RuntimeWarning, match="KeOps cannot build its kernels here .*g\\+\\+ not found.*torch's sums"):
        res = registration.register(space["basis"], space["scan"], space["faces"], prealign=False)
    assert not kernels.keops_available() and not (tmp_path / "built").exists()
    assert np.abs(res.code - aligned.code).max() < 1e-6 * np.linalg.norm(aligned.code)


def test_pose_candidates_auto_without_prototypes_changes_nothing_and_bad_ones_are_refused(space, aligned):
    basis = space["basis"]
    assert "pose_prototypes" not in basis.extras
    again = registration.register(basis, space["scan"], space["faces"], prealign=False, backend="dense",
                                  pose_candidates=None)
    assert np.array_equal(again.code, aligned.code)
    for bad in (np.zeros((2, 5)), np.full((1, 6), np.nan), "all"):
        with pytest.raises(InputError, match="pose"):
            registration.register(basis, space["scan"], space["faces"], pose_candidates=bad)


def test_a_level_changes_the_scale_by_a_bounded_factor():
    # a free scale let a wrong alignment grow the template over a body scan (x1.9) and win the screening
    units = np.ones(7)
    center = np.array([0.1, -0.2, 0.3])
    bound = LevelSolve().scale_log_limit
    limit = math.exp(bound)
    for l in (-50.0, -1.0, 1.0, 50.0):
        s = level_problem.delta_similarity(np.r_[np.zeros(6), l], center, units, bound).scale
        assert 1 / limit - 1e-12 <= s <= limit + 1e-12
    small = level_problem.delta_similarity(np.r_[np.zeros(6), 0.01], center, units, bound)
    assert np.isclose(small.scale, math.exp(0.01), rtol=1e-3)  # near identity the scale is unchanged
    np.testing.assert_allclose(small.apply(center[None]), center[None], atol=1e-15)
    # the objective's map is the same bound as the transform a level returns
    t = level_problem.log_scale(torch.tensor([-50.0, 0.01, 50.0], dtype=torch.float64), bound)
    scales = [level_problem.delta_similarity(np.r_[np.zeros(6), x], center, units, bound).scale for x in (-50.0, 0.01, 50.0)]
    np.testing.assert_allclose(np.exp(t.numpy()), scales, rtol=1e-14)


def _winding_classes(faces):
    """Each face's vertex cycle started at its smallest index (a face and its rotations compare equal)."""
    start = np.argmin(faces, axis=1)
    return np.stack([np.roll(f, -k) for f, k in zip(faces, start)])


def test_orient_like_restores_flipped_faces_and_turns_nothing_on_a_consistent_noisy_scan(space):
    basis = space["basis"]
    rng = np.random.default_rng(2)
    noisy = space["scan"] + 0.03 * rng.normal(size=space["scan"].shape)  # some small faces point backwards
    faces = space["faces"]
    same, turned = level_problem.orient_like(noisy, faces, basis.template, basis.faces)
    assert turned == 0 and np.array_equal(same, faces)
    flip = rng.random(len(faces)) < 0.4
    broken = faces.copy()
    broken[flip] = broken[flip][:, ::-1]
    fixed, turned = level_problem.orient_like(noisy, broken, basis.template, basis.faces)
    assert turned == flip.sum()
    assert np.array_equal(_winding_classes(fixed), _winding_classes(faces))
    inside_out, turned = level_problem.orient_like(noisy, faces[:, ::-1], basis.template, basis.faces)
    assert turned == len(faces) and np.array_equal(_winding_classes(inside_out), _winding_classes(faces))


def test_level_kernels_default_is_binet_and_linear_at_the_finest_level_of_a_noisy_scan():
    kernels = checks.level_kernels
    assert kernels("auto", 3) == ["binet", "binet", "binet"]
    assert kernels("auto", 3, noisy=True) == ["binet", "binet", "linear"]
    assert kernels("auto", 1, noisy=True) == ["binet"]
    assert kernels("linear", 2) == ["linear", "linear"]
    assert kernels(("constant", "binet+linear"), 2) == ["constant", "binet+linear"]
    with pytest.raises(InputError, match="2 kernels given for a schedule of 3 levels"):
        kernels(("binet", "linear"), 3)
    with pytest.raises(InputError, match="unknown varifold kernel 'cosine'"):
        kernels("cosine", 3)


def test_normal_spread_grows_with_noise_and_ignores_similarities(space):
    scan, faces = space["scan"], space["faces"]
    noise = np.random.default_rng(4).normal(size=scan.shape)
    spreads = [level_problem.normal_spread(scan + s * noise, faces) for s in (0.0, 0.02, 0.06)]
    assert spreads[0] < 0.01 < spreads[1] < spreads[2] < 1
    moved = to_scan_frame(space, scan + 0.02 * noise)
    assert level_problem.normal_spread(moved, faces) == pytest.approx(spreads[1], rel=1e-9)
    flipped = faces.copy()
    flipped[::3] = flipped[::3][:, ::-1]
    assert level_problem.normal_spread(scan + 0.02 * noise, flipped) == pytest.approx(spreads[1], rel=1e-9)


def test_default_data_term_is_not_biased_by_scan_noise_as_binet_is(space):
    """A noisy scan's normals are spread, which biases the binet kernel's minimiser (it matches the
    spread with wrinkles); on a scan this noisy the default uses the oriented linear kernel at the
    finest level, which the noise does not bias. Three remeshed scans, noise 6 % of the radius."""
    basis, truth = space["basis"], space["truth"]
    errors = {"binet": [], "default": []}
    for seed in range(3):
        u, faces = synthetic.resampled_sphere(3, seed=10 + seed)
        noisy = space["surface"](u, space["alpha"]) + 0.06 * np.random.default_rng(seed).normal(size=u.shape)
        binet = registration.register(basis, noisy, faces, prealign=False, backend="dense", kernel="binet")
        res = registration.register(basis, noisy, faces, prealign=False, backend="dense")
        assert res.normal_spread > RegistrationConfig().noisy_spread and res.levels[-1]["kernel"] == "linear"
        for name, r in (("binet", binet), ("default", res)):
            errors[name].append(np.linalg.norm(r.vertices - truth, axis=1).mean())
    assert np.mean(errors["default"]) < 0.8 * np.mean(errors["binet"])


def test_a_noisy_scan_with_flipped_faces_registers_as_the_clean_one(space):
    """The oriented finest level of a noisy scan runs on its faces wound consistently and turned like
    the fit: a third of them flipped changes nothing."""
    basis = space["basis"]
    u, faces = synthetic.resampled_sphere(3, seed=10)
    noisy = space["surface"](u, space["alpha"]) + 0.06 * np.random.default_rng(6).normal(size=u.shape)
    clean = registration.register(basis, noisy, faces, prealign=False, backend="dense")
    faces = faces.copy()
    flip = np.random.default_rng(7).random(len(faces)) < 1 / 3
    faces[flip] = faces[flip][:, ::-1]
    res = registration.register(basis, noisy, faces, prealign=False, backend="dense")
    assert clean.levels[-1]["kernel"] == "linear" and res.levels[-1]["turned_faces"] == flip.sum()
    assert np.abs(res.vertices - clean.vertices).max() < 1e-6 * np.ptp(clean.vertices, axis=0).max()


def test_a_levels_own_plateau_reaches_its_solve_and_is_checked(space, monkeypatch):
    """Level.plateau replaces LEVEL_PLATEAU's tolerance for that level alone; the other levels keep the default."""
    basis = space["basis"]
    coarse, fine = basis.schedule
    seen = []
    real = level_problem.minimize_lbfgs
    monkeypatch.setattr(level_problem, "minimize_lbfgs", lambda *a, **k: (seen.append(k["plateau"]), real(*a, **k))[1])
    res = registration.register(basis, space["scan"], space["faces"], prealign=False, backend="dense",
                                schedule=(coarse, replace(fine, plateau=0.25)))
    n, tol = LevelSolve().plateau_window, LevelSolve().plateau
    assert seen == [(n, tol), (n, 0.25)] and tol != 0.25
    assert np.abs(res.code - space["alpha"]).max() < 0.1 * np.linalg.norm(space["alpha"])
    for bad in (0.0, 1.0, -1e-3):
        with pytest.raises(InputError, match="plateau"):
            Level(0.1, 1e3, 2, 10, plateau=bad)


def test_a_level_binned_by_its_schedule_is_binned_unless_the_caller_says_otherwise(space):
    """Level.binned decides a level's binning under binning="auto" (the pair-count rule otherwise);
    register(binning=False / True) still overrides it."""
    basis = space["basis"]
    coarse, fine = basis.schedule
    args = (basis, space["scan"], space["faces"])
    auto = registration.register(*args, prealign=False, backend="dense", schedule=(coarse, fine))
    assert auto.levels[-1]["binned"] is False  # the rule leaves the fine level on faces
    own = registration.register(*args, prealign=False, backend="dense", schedule=(coarse, replace(fine, binned=True)))
    assert own.levels[-1]["binned"] is True and own.levels[0]["binned"] == auto.levels[0]["binned"]
    assert own.levels[-1]["varifold"] != auto.levels[-1]["varifold"]
    off = registration.register(*args, prealign=False, backend="dense", binning=False,
                                schedule=(coarse, replace(fine, binned=True)))
    assert [lv["binned"] for lv in off.levels] == [False, False]
    for res in (own, off):
        assert np.abs(res.code - space["alpha"]).max() < 0.1 * np.linalg.norm(space["alpha"])
    for bad in ("yes", 1):
        with pytest.raises(InputError, match="binned"):
            Level(0.1, 1e3, 2, 10, binned=bad)


def test_a_binned_level_uses_its_own_cell_size_unless_the_caller_gives_one(space, monkeypatch):
    """Level.bin_cell sets a binned level's cells (units of sigma; None: varifold.BIN_CELL); a caller's
    bin_cell (the pose stage's) still wins."""
    basis = space["basis"]
    fine = replace(basis.schedule[-1], max_iter=3, binned=True)
    seen = []
    real = level_problem.RegistrationProblem.level_loss
    monkeypatch.setattr(level_problem.RegistrationProblem, "level_loss",
                        lambda self, *a, **k: (seen.append(a[5]), real(self, *a, **k))[1])
    config = RegistrationConfig(backend="dense", refine_transform=False)
    problem = level_problem.RegistrationProblem(basis, space["scan"], np.asarray(space["faces"]), config,
                                                Monitor("test", None, None))
    path = np.zeros((2, basis.n_fields))
    reports = [problem.solve_level(lv, path, Similarity(), (0, 1), "level", bin_cell=cell)[2]
               for lv, cell in ((fine, None), (replace(fine, bin_cell=0.9), None), (replace(fine, bin_cell=0.9), 1.3))]
    assert seen == [LevelSolve().bin_cell, 0.9, 1.3] and LevelSolve().bin_cell not in (0.9, 1.3)
    assert all(r["binned"] for r in reports) and len({r["varifold"] for r in reports}) == 3
    for bad in (0.0, -0.5, 3.0):
        with pytest.raises(InputError, match="bin_cell"):
            Level(0.1, 1e3, 2, 10, bin_cell=bad)


def test_a_scan_registered_in_a_given_frame_keeps_that_alignment_and_answers_in_its_own_frame(space, moved):
    """``register_in_frame``: another scan of the capture, mapped by the first one's alignment and started
    from its code, runs the warm levels only; its code is the scan's, its alignment the one given, and the
    registered mesh and distances are in the scan's own frame and units."""
    basis, first = space["basis"], moved[0]
    other = space["alpha"] + np.array([0.3, 0.0, -0.2, 0.0, 0.2, 0.0])
    u, faces = synthetic.resampled_sphere(2, seed=8)
    scan = to_scan_frame(space, space["surface"](u, other))
    config = RegistrationConfig.from_basis(basis).with_overrides(backend="dense")
    res = registration.register_in_frame(basis, scan, faces, first.transform, first.code, config)
    assert len(res.levels) == len(registration.warm_schedule(basis.schedule)) < len(basis.schedule)
    assert np.allclose(res.transform.rotation, first.transform.rotation)
    assert res.transform.scale == pytest.approx(first.transform.scale)
    assert np.allclose(res.transform.translation, first.transform.translation)
    assert np.abs(res.code - other).max() < 2e-2 * np.linalg.norm(other)
    truth = to_scan_frame(space, space["surface"](synthetic.icosphere(2)[0], other))
    assert np.linalg.norm(res.vertices - truth, axis=1).mean() < 5e-3 * SCALE
    assert np.allclose(res.vertices, res.transform.invert(basis.template + np.tensordot(res.code, basis.fields, 1)))
    assert res.chamfer == pytest.approx(evaluation.chamfer(res.vertices, scan), rel=1e-6)


def test_warm_schedule_skips_the_coarsest_level_and_keeps_at_most_the_finest_warm_levels():
    levels = [Level(s, 10.0, 1, 10) for s in (0.4, 0.2, 0.1, 0.05)]
    assert registration.warm_schedule(levels) == tuple(levels[-registration.WARM_LEVELS:])
    assert registration.warm_schedule(levels[:2]) == (levels[1],)
    assert registration.warm_schedule(levels[:1]) == (levels[0],)
