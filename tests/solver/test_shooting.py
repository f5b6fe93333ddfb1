import numpy as np
import pytest
import torch

from bareesa import geodesics, h2_metric, latent, shooting, synthetic
from bareesa.errors import InputError, SolveCancelled
from bareesa.progress import CancelToken
from tests.solver.support import small_basis


def test_shooting_with_constant_metric_is_straight_line():
    v, f = synthetic.blob_mesh(2)
    translations = np.stack([np.broadcast_to(e, v.shape) for e in np.eye(3)])
    b = latent.Basis(template=v, faces=f, fields=translations, groups={}, weights="body")
    t, ft, h = b.tensors()
    a0, vel = np.array([0.5, 0.0, -1.0]), np.array([1.0, 2.0, -0.5])
    path = shooting.shoot(t, ft, h, a0, vel, b.weights, steps=6)
    assert path.shape == (7, 3)
    assert np.abs(path - (a0 + np.linspace(0, 1, 7)[:, None] * vel)).max() < 1e-9


def test_shooting_with_initial_velocity_of_bvp_geodesic_reproduces_it():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.array([0.2, 0.0, -0.3, 0.1]), np.array([1.5, -1.0, 0.8, 1.2])
    g = geodesics.geodesic(t, f, h, a0, a1, b.weights, steps=6)
    straight = geodesics.straight_path(a0, a1, 6)
    assert np.abs(g.path - straight).max() > 1e-2  # the geodesic is genuinely curved
    shot = shooting.shoot(t, f, h, a0, shooting.initial_velocity(g.path), b.weights, steps=5)
    assert np.abs(shot - g.path).max() < 1e-5 * np.abs(g.path).max()


def test_energy_is_conserved_along_shot_path():
    b = small_basis()
    t, f, h = b.tensors()
    path = shooting.shoot(t, f, h, np.zeros(4), np.array([1.5, -1.0, 0.8, 1.2]), b.weights, steps=16)
    steps = latent.latent_path_energy(t, f, h, torch.tensor(path), b.weights, per_step=True).numpy()
    assert steps.std() < 0.02 * steps.mean()
    # a curved metric: the path is not the straight continuation of its first step
    assert np.abs(path[-1] - 16 * (path[1] - path[0])).max() > 1e-2


def test_extrapolate_keeps_given_frames_and_appends_new_ones():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), np.array([0.1, -0.05, 0.02, 0.1])
    path = shooting.extrapolate(t, f, h, a0, a1, b.weights, n_new=3)
    assert path.shape == (5, 4)
    assert np.array_equal(path[0], a0) and np.array_equal(path[1], a1)
    for k in range(2, 5):  # every point is the geodesic continuation of the two before
        step = shooting.geodesic_step(t, f, h, path[k - 2], path[k - 1], b.weights)
        assert np.abs(step - path[k]).max() < 1e-8


def test_anchored_extrapolation_keeps_the_unmoving_body_on_the_straight_line():
    from tests.solver.support import limb_basis

    b, limb = limb_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(3), np.array([0.3, 0.1, 0.0])
    free = shooting.extrapolate(t, f, h, a0, a1, b.weights, n_new=3)
    out = shooting.extrapolate(t, f, h, a0, a1, b.weights, n_new=3, anchor=True)
    line = a0 + np.arange(5)[:, None] * (a1 - a0)
    assert np.allclose(out, geodesics.anchor_path(t, h, free, line, fixed=(0, 1)))
    assert np.array_equal(out[:2], free[:2]) and np.allclose(out[:, :2], free[:, :2])
    body = geodesics.decode_path(t, h, out)[:, ~limb] - geodesics.decode_path(t, h, line)[:, ~limb]
    assert np.abs(body).max() < 1e-9


def test_cancelled_extrapolation_raises_and_returns_nothing():
    b = small_basis()
    t, f, h = b.tensors()
    token = CancelToken()
    token.cancel()
    with pytest.raises(SolveCancelled):
        shooting.extrapolate(t, f, h, np.zeros(4), np.ones(4) * 0.1, b.weights, n_new=3, cancel=token)


def test_bad_codes_raise_input_error():
    b = small_basis()
    t, f, h = b.tensors()
    with pytest.raises(InputError, match="4 coefficients"):
        shooting.extrapolate(t, f, h, np.zeros(3), np.zeros(4), b.weights, n_new=2)
    with pytest.raises(InputError, match="at least one step"):
        shooting.shoot(t, f, h, np.zeros(4), np.zeros(4), b.weights, steps=0)


def test_non_finite_codes_raise_input_error_naming_the_code():
    b = small_basis()
    t, f, h = b.tensors()
    with pytest.raises(InputError, match="alpha1 contains 1 NaN"):
        shooting.geodesic_step(t, f, h, np.zeros(4), np.array([1.0, np.nan, 0.0, 0.0]), b.weights)
    with pytest.raises(InputError, match="velocity contains 1 NaN"):
        shooting.shoot(t, f, h, np.zeros(4), np.array([np.inf, 0.0, 0.0, 0.0]), b.weights)
    bad = h.clone()
    bad[1, 3, 0] = float("nan")
    with pytest.raises(InputError, match="infinite values in the basis fields"):
        shooting.extrapolate(t, f, bad, np.zeros(4), np.ones(4) * 0.1, b.weights, n_new=2)


def test_overflowing_step_raises_shooting_failed_not_a_numpy_error():
    b = small_basis()
    t, f, h = b.tensors()
    with pytest.raises(shooting.ShootingFailed, match="not finite"):
        shooting.geodesic_step(t, f, h, np.zeros(4), np.full(4, 1e155), b.weights)


@pytest.mark.parametrize("max_iter", [40, 0])  # quasi-Newton, and the exact-Newton fallback
def test_energy_turning_nan_during_a_step_raises_shooting_failed(monkeypatch, max_iter):
    b = small_basis()
    t, f, h = b.tensors()
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        e = h2_metric.path_energy(*args, **kwargs)
        return e * float("nan") if calls["n"] > 2 else e

    monkeypatch.setattr(shooting, "path_energy", flaky)
    with pytest.raises(shooting.ShootingFailed, match="not finite"):
        shooting.geodesic_step(t, f, h, np.zeros(4), np.array([1.5, -1.0, 0.8, 1.2]), b.weights, max_iter=max_iter)


def test_newton_fallback_finishes_a_step_quasi_newton_did_not(monkeypatch):
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), np.array([0.5, -0.3, 0.3, 0.4])
    full = shooting.geodesic_step(t, f, h, a0, a1, b.weights)
    calls = []
    real = shooting._Stepper._newton
    monkeypatch.setattr(shooting._Stepper, "_newton", lambda self, *a: calls.append(1) or real(self, *a))
    fallback = shooting.geodesic_step(t, f, h, a0, a1, b.weights, max_iter=1)
    assert calls and np.abs(full - fallback).max() < 1e-7


def test_linearly_dependent_fields_still_extrapolate_to_finite_codes():
    b = small_basis()
    t, f, h = b.tensors()
    dup = torch.cat([h, h[:1]])  # field 4 repeats field 0: a singular metric matrix
    path = shooting.extrapolate(t, f, dup, np.zeros(5), np.array([0.1, -0.05, 0.02, 0.1, 0.0]), b.weights, 3)
    assert np.isfinite(path).all()
    ref = shooting.extrapolate(t, f, h, np.zeros(4), np.array([0.1, -0.05, 0.02, 0.1]), b.weights, 3)
    shapes = latent.decode(t, dup, torch.tensor(path)) - latent.decode(t, h, torch.tensor(ref))
    assert shapes.abs().max() < 1e-6  # the same meshes, whatever the split between the twin fields


@pytest.mark.parametrize("weights", ["body", "face", h2_metric.H2Weights(0.5, 3, -2, 0, 2, 0)])
def test_jacobian_metric_equals_h2_metric_matrix(weights):
    b = small_basis(p=5)
    t, f, h = b.tensors()
    verts = latent.decode(t, h, torch.tensor([0.4, -0.3, 0.2, 0.5, -0.1], dtype=torch.float64))
    fast = shooting.jacobian_metric(verts, f, h, weights)
    ref = h2_metric.metric_matrix(verts, f, h, weights)
    assert torch.allclose(fast, ref, rtol=1e-10, atol=1e-12 * ref.abs().max())


def test_extrapolation_computes_the_metric_matrix_rarely(monkeypatch):
    b = small_basis()
    t, f, h = b.tensors()
    calls = {"n": 0}
    real = shooting.jacobian_metric

    def counted(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(shooting, "jacobian_metric", counted)
    path = shooting.extrapolate(t, f, h, np.zeros(4), np.array([0.1, -0.05, 0.02, 0.1]), b.weights, n_new=12)
    assert calls["n"] <= 4  # one at the start, refreshed only when the iteration stops contracting
    steps = latent.latent_path_energy(t, f, h, torch.tensor(path), b.weights, per_step=True).numpy()
    assert steps.std() < 0.02 * steps.mean()


def test_substeps_converge_towards_the_continuous_geodesic_and_keep_the_inputs():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), np.array([0.4, -0.25, 0.2, 0.4])
    paths = {k: shooting.extrapolate(t, f, h, a0, a1, b.weights, n_new=2, substeps=k) for k in (1, 2, 4, 8)}
    for p in paths.values():
        assert p.shape == (4, 4) and np.array_equal(p[0], a0) and np.array_equal(p[1], a1)
    errs = [np.abs(paths[k][2:] - paths[8][2:]).max() for k in (1, 2, 4)]
    assert errs[0] > 1e-3 and errs[0] > 3 * errs[1] and errs[1] > 3 * errs[2]  # second order in the time step
    with pytest.raises(InputError, match="substeps"):
        shooting.extrapolate(t, f, h, a0, a1, b.weights, n_new=2, substeps=0)


def _curved_motion():
    """A small basis and two codes whose geodesic bends too fast for one step per frame."""
    b = small_basis()
    t, f, h = b.tensors()
    return b, (t, f, h), np.zeros(4), 0.75 * np.array([1.5, -1.0, 0.8, 1.2])


def test_strongly_curved_step_is_refined_and_matches_a_finer_step_reference():
    b, (t, f, h), a0, a1 = _curved_motion()
    with pytest.raises(shooting.ShootingFailed, match="frame 1 of 2: .* even at 1/1 of the frame step"):
        shooting.extrapolate(t, f, h, a0, a1, b.weights, 2, max_substeps=1)  # no refinement allowed
    path, report = shooting.extrapolate(t, f, h, a0, a1, b.weights, 2, with_report=True)
    assert report.refinements > 0 and max(report.substeps) > 1 and len(report.substeps) == 2
    assert report.max_correction <= shooting.ACCEPT_TOL and report.max_speed_change <= shooting.SPEED_TOL
    assert set(report.to_json()) >= {"substeps", "refinements", "max_correction"}
    reference = shooting.extrapolate(t, f, h, a0, a1, b.weights, 2, substeps=16, max_substeps=16)
    verts, ref_verts = geodesics.decode_path(t, h, path), geodesics.decode_path(t, h, reference)
    size = np.ptp(ref_verts[0], axis=0).max()
    assert np.abs(verts - ref_verts).max() < 0.005 * size
    assert np.array_equal(path[:2], np.stack([a0, a1]))


def test_a_frame_that_cannot_be_reached_says_how_many_were_and_carries_them():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), 0.6 * np.array([1.5, -1.0, 0.8, 1.2])  # one step per frame reaches frame 1, not 2
    with pytest.raises(shooting.ShootingFailed, match="frame 2 of 4: .*ask for at most 1 frame or start") as err:
        shooting.extrapolate(t, f, h, a0, a1, b.weights, 4, max_substeps=1)
    reached = shooting.extrapolate(t, f, h, a0, a1, b.weights, 1, max_substeps=1)  # the advice holds
    assert err.value.frames.shape == (1, 4) and np.allclose(err.value.frames, reached[2:], rtol=0, atol=1e-12)
    with pytest.raises(shooting.ShootingFailed, match="frame 1 of 4: .*smoothly: start from closer") as err:
        shooting.extrapolate(t, f, h, a0, a1 / 0.6 * 0.75, b.weights, 4, max_substeps=1)
    assert err.value.frames.shape == (0, 4)


def test_a_stalled_step_is_accepted_within_accept_tol_and_refused_beyond_it():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), np.array([0.5, -0.3, 0.3, 0.4])
    strict = shooting._Stepper(t, f, h, b.weights, tol=0.0, max_iter=2)  # tol floors at rounding level
    with pytest.raises(shooting.StepNotConverged) as err:
        strict.step(a0, a1, newton=False)
    lenient = shooting._Stepper(t, f, h, b.weights, tol=0.0, max_iter=2, accept_tol=2 * err.value.correction)
    x, _, correction = lenient.step(a0, a1, newton=False)
    assert correction == pytest.approx(err.value.correction) and np.isfinite(x).all()


def test_shoot_reports_refinement_and_keeps_the_start():
    b, (t, f, h), a0, a1 = _curved_motion()
    path, report = shooting.shoot(t, f, h, a0, 3 * a1, b.weights, steps=3, with_report=True)
    assert path.shape == (4, 4) and np.array_equal(path[0], a0) and np.isfinite(path).all()
    assert len(report.substeps) == 2 and report.refinements == int(np.log2(max(report.substeps)))


def test_a_solved_step_whose_speed_changes_is_kept_at_the_finest_refinement_and_reported():
    b, (t, f, h), a0, a1 = _curved_motion()
    # a speed tolerance nothing meets: every frame is refined to the finest step, then kept there
    path, report = shooting.extrapolate(t, f, h, a0, a1, b.weights, 2, speed_tol=1e-15, max_substeps=8,
                                        with_report=True)
    assert report.speed_relaxed == [1, 2] and report.substeps == [8, 8]
    assert report.to_json()["speed_relaxed"] == [1, 2] and report.max_speed_change > 1e-15
    reference = shooting.extrapolate(t, f, h, a0, a1, b.weights, 2, substeps=8, max_substeps=8)
    verts, ref_verts = geodesics.decode_path(t, h, path), geodesics.decode_path(t, h, reference)
    assert np.abs(verts - ref_verts).max() < 0.005 * np.ptp(ref_verts[0], axis=0).max()
    # the default tolerance keeps nothing unchecked on the same motion
    assert shooting.extrapolate(t, f, h, a0, a1, b.weights, 2, with_report=True)[1].speed_relaxed == []


def test_a_frame_refused_by_the_frame_check_stops_the_shot_there_and_names_it():
    from bareesa.errors import FrameRejected

    b = small_basis()
    t, f, h = b.tensors()
    velocity = np.array([1.5, -1.0, 0.8, 1.2])
    plain = shooting.shoot(t, f, h, np.zeros(4), velocity, b.weights, steps=6)
    seen = []

    def check(code):  # refuses the third new frame (path index 4)
        seen.append(np.array(code))
        return "too far" if len(seen) == 3 else None

    with pytest.raises(FrameRejected, match="frame 3 of 5: too far"):
        shooting.shoot(t, f, h, np.zeros(4), velocity, b.weights, steps=6, frame_check=check)
    # the check saw the frames the plain shot computes, in order, and none after the refused one
    assert len(seen) == 3 and np.allclose(np.stack(seen), plain[2:5], rtol=0, atol=1e-12)
    # a check that refuses nothing changes nothing
    kept = shooting.shoot(t, f, h, np.zeros(4), velocity, b.weights, steps=6, frame_check=lambda code: None)
    assert np.array_equal(kept, plain)


def test_a_frame_no_step_reaches_is_finished_in_the_frozen_metric_and_shooting_resumes_after_it():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), 0.6 * np.array([1.5, -1.0, 0.8, 1.2])  # one step per frame reaches frame 1, not 2
    with pytest.raises(shooting.ShootingFailed, match="frame 2 of 3"):
        shooting.extrapolate(t, f, h, a0, a1, b.weights, 3, max_substeps=1)
    path, report = shooting.extrapolate(t, f, h, a0, a1, b.weights, 5, max_substeps=1, with_report=True,
                                        frozen=True)
    assert report.frozen[0] == 2 and 4 not in report.frozen and report.to_json()["frozen"] == report.frozen
    exact = shooting.extrapolate(t, f, h, a0, a1, b.weights, 1, max_substeps=1)
    assert np.allclose(path[:3], exact, rtol=0, atol=1e-12)  # frames before it are the exact shot's
    # a frozen frame is the straight step at the last velocity (the geodesic of a constant metric) ...
    for k in report.frozen:
        assert np.allclose(path[k + 1], 2 * path[k] - path[k - 1], rtol=0, atol=1e-12)
    # ... and frame 4, which a step reaches, is shot exactly from the two frames before it
    step = shooting.geodesic_step(t, f, h, path[3], path[4], b.weights)
    assert np.allclose(path[5], step, rtol=0, atol=1e-6 * np.abs(step).max())
    # with refinement allowed the motion needs no freezing at all
    assert shooting.extrapolate(t, f, h, a0, a1, b.weights, 5, with_report=True, frozen=True)[1].frozen == []
