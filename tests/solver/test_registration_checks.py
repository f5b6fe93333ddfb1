"""Scans that cannot be registered are refused up front, with the reason, before any solve; a poor fit is flagged."""

import dataclasses

import numpy as np
import pytest
import trimesh

from bareesa import registration, synthetic
from bareesa.errors import InputError, MeshError
from bareesa.registration import checks, multiscale
from bareesa.registration.config import Prealignment, RegistrationConfig, Screening


@pytest.fixture(scope="module")
def basis():
    return synthetic.smooth_sphere_basis(subdivisions=2, n_fields=4, seed=0)[0]


def _remeshed_body(basis, code):
    """F(code) on another triangulation (the nearest template point of each vertex of a resampled
    sphere): -> scan (M, 3), faces (G, 3)."""
    u, faces = synthetic.resampled_sphere(2, seed=3)
    truth = basis.template + np.tensordot(code, basis.fields, axes=1)
    return truth[np.argmin(((u[:, None] - synthetic.icosphere(2)[0][None]) ** 2).sum(-1), axis=1)], faces


def test_one_triangle_scan_is_refused_before_any_solve(basis, monkeypatch):
    def solve(*args, **kwargs):
        raise AssertionError("the pre-alignment ran for a scan that should have been refused")

    monkeypatch.setattr(multiscale, "prealign_candidates", solve)
    with pytest.raises(InputError, match=r"1 face with area: too few to register onto basis"):
        registration.register(basis, np.eye(3), np.array([[0, 1, 2]]))


def test_a_scan_with_too_few_faces_for_the_template_is_refused(basis):
    need = min(RegistrationConfig().min_scan_faces, basis.faces.shape[0] // 8)
    sphere = trimesh.creation.icosphere(subdivisions=0)  # 20 faces
    assert len(sphere.faces) < need
    with pytest.raises(InputError, match=f"at least {need}"):
        registration.register(basis, sphere.vertices, sphere.faces)


def test_a_flat_sheet_is_refused_and_a_real_scan_is_not(basis):
    sheet = trimesh.creation.box(extents=(1.0, 1.0, 1e-3)).subdivide().subdivide().subdivide()
    with pytest.raises(InputError, match="the scan is flat"):
        checks.check_plausible_scan(basis, sheet.vertices, sheet.faces)
    u, faces = synthetic.resampled_sphere(2, seed=3)
    checks.check_plausible_scan(basis, 2.5 * u, faces)  # a sphere of another size: accepted


def test_faces_weighted_zero_do_not_count(basis):
    u, faces = synthetic.resampled_sphere(2, seed=3)
    weights = np.zeros(len(faces))
    weights[:10] = 1.0
    with pytest.raises(InputError, match="10 faces with area"):
        checks.check_plausible_scan(basis, u, faces, weights)



def test_a_wrong_shape_is_flagged_as_a_poor_fit_and_a_scan_of_the_basis_is_not(basis):
    from bareesa.latent import Level

    schedule = (Level(0.25, 1e3, 1, 10), Level(0.1, 1e5, 1, 10))
    good, faces = _remeshed_body(basis, np.array([0.4, -0.3, 0.2, 0.3]))  # a shape of the basis, remeshed
    tv, tf = synthetic.torus(24, 12)
    torus = tv * np.sqrt((basis.template ** 2).sum(1).mean() / (tv ** 2).sum(1).mean())
    uncalibrated = registration.register(basis, good, faces, schedule=schedule)
    assert uncalibrated.poor_fit is None and uncalibrated.residual > 0
    basis.fit_check = {"poor_fit_above": 2 * uncalibrated.residual}
    try:
        assert multiscale.is_poor_fit(basis, uncalibrated.residual) is False
        flagged = registration.register(basis, torus, tf, schedule=schedule)
        assert flagged.residual > 3 * uncalibrated.residual
        assert flagged.poor_fit is True and flagged.to_json()["poor_fit"] is True
    finally:
        basis.fit_check = {}


def test_update_card_stores_entries_in_the_file_and_beside_it(basis, tmp_path):
    import json

    from bareesa import basis_io

    path = tmp_path / "b.npz"
    basis_io.save_basis(path, basis)
    card = json.loads(path.with_suffix(".json").read_text()) | {"accuracy": {"kept": 1}}
    path.with_suffix(".json").write_text(json.dumps(card))
    basis_io.update_card(path, fit_check={"poor_fit_above": 0.05})
    loaded = basis_io.load_basis(path)
    assert loaded.fit_check == {"poor_fit_above": 0.05}
    assert np.array_equal(loaded.fields, basis.fields) and np.array_equal(loaded.faces, basis.faces)
    side = json.loads(path.with_suffix(".json").read_text())
    assert side["fit_check"] == {"poor_fit_above": 0.05} and side["accuracy"] == {"kept": 1}


def test_prealignment_scale_stays_bounded_and_finite_on_a_scan_with_far_clutter():
    """A speck of clutter far from the body inflates the scan's moments; the refinement may change the
    moment-matched scale by at most ``prealignment.log_scale_limit`` (an unbounded log-scale overflowed)."""
    import math

    from bareesa import synthetic
    from bareesa.registration.prealign import prealign_candidates, surface_moments

    verts, faces = synthetic.icosphere(2)
    speck_v, speck_f = synthetic.icosphere(0)
    scan_v = np.concatenate([verts, 0.05 * speck_v + [40.0, 0.0, 0.0]])
    scan_f = np.concatenate([faces, speck_f + len(verts)])
    rho = lambda v, f: math.sqrt(np.trace(surface_moments(v, f)[2]))  # noqa: E731
    matched = rho(verts, faces) / rho(scan_v, scan_f)
    for score, sim, *_ in prealign_candidates(verts, faces, scan_v, scan_f):
        assert np.isfinite(score) and np.isfinite(sim.matrix()).all()
        assert abs(math.log(sim.scale / matched)) <= Prealignment().log_scale_limit + 1e-9


def test_a_poor_fit_is_registered_again_from_other_alignments(basis, monkeypatch):
    """Started only from the right alignment turned half a turn, the fit is poor; the retry from the
    half turns of that fit finds the right one (a human scan registered facing backwards, in miniature).
    When the retry's short screening picks a poor fit again, the same alignments are screened deeper,
    ranked by the fit residual, and the best fit of all is kept; with pose candidates, each alignment of the
    deeper screening gets the pose stage after its first level, as a registration does."""
    from bareesa.latent import Level

    schedule = (Level(0.25, 1e3, 1, 10), Level(0.1, 1e5, 1, 10))
    code = np.array([0.6, -0.5, 0.4, 0.5])
    scan, faces = _remeshed_body(basis, code)
    right = registration.register(basis, scan, faces, schedule=schedule)
    flips = multiscale.half_turns(basis)
    assert all(np.allclose(f.compose(f).rotation, np.eye(3)) for f in flips)
    basis.fit_check = {"poor_fit_above": 2 * right.residual}
    residuals, screens = [], []
    real_residual, real_deep = multiscale._residual, multiscale._deep_screen

    def residual_spy(*args):
        out = real_residual(*args)
        residuals.append(out[1])
        return out

    staged = []  # "deep" ... "done" around a deeper screening, "pose" for each pose stage
    real_poses = multiscale.try_poses

    def deep_spy(*args):
        residuals.clear()
        staged.append("deep")
        out = real_deep(*args)
        staged.append("done")
        screens.append((list(residuals), out, len(args[2])))  # args[2]: the candidates
        return out

    def poses_spy(*args, **kwargs):
        staged.append("pose")
        return real_poses(*args, **kwargs)

    monkeypatch.setattr(multiscale, "_residual", residual_spy)
    monkeypatch.setattr(multiscale, "_deep_screen", deep_spy)
    monkeypatch.setattr(multiscale, "try_poses", poses_spy)
    try:
        for flip in flips:
            wrong_start = [multiscale.Alignment(0.0, flip.compose(right.transform))]
            monkeypatch.setattr(multiscale, "prealign_candidates", lambda *a, **k: list(wrong_start))
            once = registration.register(basis, scan, faces, schedule=schedule, retry=False)
            if not once.poor_fit:
                continue  # this half turn is a symmetry of the scan: nothing to retry
            again = registration.register(basis, scan, faces, schedule=schedule)
            assert not screens  # the short screening of the retry sufficed: nothing screened deeper
            assert once.retried_alignments == 0 and again.retried_alignments >= 3
            assert again.poor_fit is False and again.to_json()["retried_alignments"] == again.retried_alignments
            assert again.residual < 0.5 * once.residual and again.residual < 1.5 * right.residual

            real_fit = multiscale._fit

            def short_retry_fails(*args, deep=False, **kwargs):
                out = real_fit(*args, deep=deep, **kwargs)
                if not deep and len(args[2]) > 1:  # the retry's short screening (args[2]: the candidates)
                    out = dataclasses.replace(out, poor=True, residual=10 * once.residual)
                return out

            monkeypatch.setattr(multiscale, "_fit", short_retry_fails)
            staged.clear()
            deeper = registration.register(basis, scan, faces, schedule=schedule, pose_candidates=code[None] + 0.1)
            (screened, start, n_candidates), = screens
            order, best = start.order, start.best
            assert len(screened) == n_candidates == deeper.retried_alignments
            inside = staged[staged.index("deep") + 1:staged.index("done")]
            assert inside == ["pose"] * n_candidates  # one pose stage per alignment screened deeper
            assert list(order) == list(np.argsort(screened)) and best == int(np.argmin(screened))
            assert deeper.poor_fit is False and deeper.residual < 1.5 * right.residual
            break
        else:
            pytest.fail("no half turn of the right alignment gave a poor fit: the test proves nothing")
    finally:
        basis.fit_check = {}


def test_with_pose_prototypes_the_first_fit_starts_from_the_best_prealignment(basis, monkeypatch):
    """With pose prototypes the pre-alignment's ranking decides the first fit (no screening of the others,
    unless they score within ``prealignment.tie`` of the best); a poor fit is retried from the other candidates in
    that order, then the fit's half turns. Without prototypes every candidate is screened, as before."""
    from bareesa.latent import Level

    schedule = (Level(0.25, 1e3, 1, 10), Level(0.1, 1e5, 1, 10))
    code = np.array([0.6, -0.5, 0.4, 0.5])
    scan, faces = _remeshed_body(basis, code)
    right = registration.register(basis, scan, faces, schedule=schedule, pose_candidates=None, retry=False)
    flips = multiscale.half_turns(basis)
    ranked = [multiscale.Alignment(0.1 * (k + 1), t) for k, t in
              enumerate([right.transform] + [f.compose(right.transform) for f in flips[:2]])]
    monkeypatch.setattr(multiscale, "prealign_candidates", lambda *a, **k: list(ranked))
    tried, real_fit = [], multiscale._fit

    def fit_spy(*args, **kwargs):
        tried.append(list(args[2]))  # args[2]: the candidate alignments
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(multiscale, "_fit", fit_spy)
    prototypes = code[None] + 0.1
    first = registration.register(basis, scan, faces, schedule=schedule, pose_candidates=prototypes, retry=False)
    assert tried == [ranked[:1]] and first.prealignment is right.transform
    tried.clear()
    registration.register(basis, scan, faces, schedule=schedule, pose_candidates=None, retry=False)
    assert tried == [ranked]  # no prototypes: every candidate screened
    tried.clear()
    basis.fit_check = {"poor_fit_above": 0.0}  # every fit poor: the retry runs, short then deeper
    try:
        again = registration.register(basis, scan, faces, schedule=schedule, pose_candidates=prototypes)
    finally:
        basis.fit_check = {}
    assert tried[0] == ranked[:1] and len(tried) == 3
    assert tried[1][:2] == ranked[1:] and len(tried[1]) == 2 + len(flips) == again.retried_alignments
    assert tried[2] == tried[1]  # the deeper screening of the same alignments
    tried.clear()
    tie = [ranked[0], ranked[1]._replace(score=ranked[0].score * (0.99 + Prealignment().tie) / 2), ranked[2]]
    monkeypatch.setattr(multiscale, "prealign_candidates", lambda *a, **k: list(tie))
    registration.register(basis, scan, faces, schedule=schedule, pose_candidates=prototypes, retry=False)
    assert tried == [tie[:2]]  # the pre-alignment cannot tell the best two apart: both screened


def test_with_pose_prototypes_the_first_level_is_the_short_screening_solve(basis):
    """With pose prototypes even a lone alignment runs the first level as the screening does (one step,
    1/``screening.divisor`` of its iterations) and a short second level, from which the pose stage and the second
    level go on; without prototypes a lone alignment runs the whole first level, and the code is as close."""
    from bareesa.latent import Level

    schedule = (Level(0.25, 1e3, 2, 160), Level(0.1, 1e5, 1, 30))
    code = np.array([0.6, -0.5, 0.4, 0.5])
    scan, faces = _remeshed_body(basis, code)
    messages = []
    quick = registration.register(basis, scan, faces, schedule=schedule, prealign=False,
                                  pose_candidates=code[None] + 0.1, callback=lambda e: messages.append(e.message))
    plain = []
    whole = registration.register(basis, scan, faces, schedule=schedule, prealign=False, pose_candidates=None,
                                  callback=lambda e: plain.append(e.message))
    screen_iter = 160 // Screening().divisor
    assert quick.levels[0]["steps"] == 1 and quick.levels[0]["iterations"] <= screen_iter
    assert any("(screening)" in m for m in messages)
    assert whole.levels[0]["steps"] == 2 and not any("(screening)" in m for m in plain)
    assert np.linalg.norm(quick.code - code) < 1.5 * np.linalg.norm(whole.code - code) < 0.15


def _box_figure(left_arm, right_arm):
    """A body box with two arm boxes, each turned (axis, degrees) about its shoulder: (V, 3), (F, 3)."""
    parts = [trimesh.creation.box(extents=(0.4, 0.2, 1.0))]
    for side, (axis, degrees) in ((1, left_arm), (-1, right_arm)):
        arm = trimesh.creation.box(extents=(0.6, 0.1, 0.1))
        arm.apply_translation((side * 0.3, 0, 0))
        arm.apply_transform(trimesh.transformations.rotation_matrix(np.radians(degrees), axis))
        arm.apply_translation((side * 0.2, 0, 0.4))
        parts.append(arm)
    mesh = trimesh.util.concatenate(parts).subdivide().subdivide()
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def test_a_pose_far_from_the_template_is_prealigned_against_a_reference_surface():
    """Arms in a T the template, one arm up and one forward the scan: the template's principal axes tie the
    right alignment with its half turn; the posed reference surface (a decoded pose prototype) decides."""
    from scipy.spatial.transform import Rotation

    from bareesa.registration.prealign import prealign_candidates
    from bareesa.transforms import rotation_angle

    template, faces = _box_figure(((0, 1, 0), 0), ((0, 1, 0), 0))
    posed, _ = _box_figure(((0, 1, 0), -80), ((0, 0, 1), -70))
    turn = Rotation.random(random_state=3).as_matrix()
    scan = posed @ turn.T + [1.0, 2.0, 3.0]
    alone = prealign_candidates(template, faces, scan, faces)
    assert all(c.reference is None for c in alone)
    assert alone[1].score < 1.05 * alone[0].score  # a tie: the surfaces alone cannot tell the two apart
    helped = prealign_candidates(template, faces, scan, faces, references=np.stack([template, posed]))
    best = helped[0]
    assert best.reference == 1 and rotation_angle(best.transform.rotation, turn.T) < 5.0
    assert best.score < 0.1 * alone[0].score and best.score < 0.1 * helped[1].score
    assert np.allclose(best.transform.apply(scan), posed, atol=0.05)


def test_a_candidate_found_against_a_pose_prototype_is_screened_from_it():
    poses = np.arange(12.0).reshape(3, 4)
    zero = np.zeros((2, 4))
    start = multiscale._start(zero, poses, multiscale.Alignment(0.1, None, 2))
    assert np.array_equal(start, np.stack([np.zeros(4), poses[2]]))
    assert multiscale._start(zero, poses, multiscale.Alignment(0.1, None)) is zero
    given = np.stack([np.zeros(4), np.ones(4)])  # a caller's init_code wins
    assert multiscale._start(given, poses, multiscale.Alignment(0.1, None, 2)) is given


def test_surface_centroid_is_surface_moments_area_and_centroid_bit_for_bit():
    """The pose stage centres each start by ``surface_centroid``: the same numbers as ``surface_moments``
    (so no alignment moves), weighted or not, and the same refusal of a surface without area."""
    from bareesa.registration.prealign import surface_centroid, surface_moments
    verts, faces = synthetic.blob_mesh(2, seed=5)
    weights = np.random.default_rng(0).uniform(0.0, 2.0, len(faces))
    for w in (None, weights):
        area, center = surface_centroid(verts, faces, w)
        assert (area, *center) == (surface_moments(verts, faces, w)[0], *surface_moments(verts, faces, w)[1])
    with pytest.raises(MeshError, match="zero"):
        surface_centroid(verts, faces, np.zeros(len(faces)))


def test_surface_moments_are_the_exact_integrals_of_a_rectangle_and_move_with_it():
    """A 2 x 1 rectangle of two triangles: area 2, centroid its centre, second moment about it
    diag(4, 1, 0) / 12 (int x^2 dA / A = a^2 / 12 per side a), exactly; rotated, the moment is R M R^T."""
    from bareesa.registration.prealign import surface_moments
    from bareesa.transforms import axis_angle_rotation
    verts = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    area, center, second = surface_moments(verts, faces)
    assert area == pytest.approx(2.0) and np.allclose(center, [1.0, 0.5, 0.0], atol=1e-15)
    assert np.allclose(second, np.diag([4.0, 1.0, 0.0]) / 12, atol=1e-15)
    rotation = axis_angle_rotation(np.array([0.3, -0.5, 0.2]))
    moved = surface_moments(verts @ rotation.T + [1.0, 2.0, 3.0], faces)[2]
    assert np.allclose(moved, rotation @ second @ rotation.T, atol=1e-14)
