import dataclasses

import numpy as np
import pytest
import torch

from bareesa import basis_io, geodesics, h2_metric, latent, registration, synthetic
from bareesa.errors import InputError, SolveCancelled
from bareesa.progress import CancelToken, Monitor
from tests.solver.support import limb_basis, small_basis


def test_geodesic_has_lower_energy_than_straight_line_and_fixed_endpoints():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.array([0.0, 0.0, 0.0, 0.0]), np.array([2.0, -1.5, 1.0, 1.5])
    g = geodesics.geodesic(t, f, h, a0, a1, b.weights, steps=6)
    straight = latent.latent_path_energy(t, f, h, torch.tensor(geodesics.straight_path(a0, a1, 6)), b.weights)
    assert g.energy < 0.99 * float(straight)
    assert np.array_equal(g.path[0], a0) and np.array_equal(g.path[-1], a1)
    assert g.distance == pytest.approx(np.sqrt(g.energy))
    lengths = geodesics.step_lengths(t, f, h, g.path, b.weights)
    assert lengths.std() < 0.05 * lengths.mean()  # discrete geodesics have constant speed


def test_geodesic_is_straight_line_when_metric_is_constant():
    v, f = synthetic.blob_mesh(2)
    translations = np.stack([np.broadcast_to(e, v.shape) for e in np.eye(3)])  # G-bar independent of alpha
    b = latent.Basis(template=v, faces=f, fields=translations, groups={}, weights="body")
    t, ft, h = b.tensors()
    a0, a1 = np.array([0.0, 1.0, -1.0]), np.array([2.0, -1.0, 0.5])
    bent = geodesics.straight_path(a0, a1, 5) + np.sin(np.linspace(0, np.pi, 5))[:, None] * 0.7
    g = geodesics.geodesic(t, ft, h, a0, a1, b.weights, steps=5, init=bent)
    assert np.abs(g.path - geodesics.straight_path(a0, a1, 5)).max() < 1e-6


def test_distance_is_symmetric():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.array([0.5, 0.0, -1.0, 0.2]), np.array([-1.0, 1.5, 1.0, 0.0])
    d01 = geodesics.geodesic(t, f, h, a0, a1, b.weights, steps=5).distance
    d10 = geodesics.geodesic(t, f, h, a1, a0, b.weights, steps=5).distance
    assert d01 == pytest.approx(d10, rel=1e-5)


def test_resample_path_gives_even_metric_speed_and_keeps_endpoints():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), np.array([2.0, -1.5, 1.0, 1.5])
    s = np.array([0.0, 0.05, 0.1, 0.6, 1.0])[:, None]  # badly paced
    path = a0 + s * (a1 - a0)
    out = geodesics.resample_path(t, f, h, path, b.weights, 9, pace="metric")
    assert out.shape == (9, 4)
    assert np.array_equal(out[0], a0) and np.array_equal(out[-1], a1)
    lengths = geodesics.step_lengths(t, f, h, out, b.weights)
    before = geodesics.step_lengths(t, f, h, path, b.weights)
    assert lengths.std() < 0.05 * lengths.mean() < before.std()


def _shape_steps(t, h, path):
    verts = geodesics.decode_path(t, h, path)
    return np.linalg.norm(np.diff(verts, axis=0), axis=2).mean(axis=1)


def test_keyframes_are_paced_by_shape_change_where_the_metric_barely_sees_a_motion():
    """A lift (a translation: only the a0 term sees it), then a bend of the limb: paced by the metric the
    frames race through the lift and crawl through the bend; paced by shape (the default) every frame
    moves the vertices by the same mean distance."""
    b, _ = limb_basis()
    t, f, h = b.tensors()
    path = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.5, 0.0, 1.0]])
    metric = geodesics.resample_path(t, f, h, path, b.weights, 13, pace="metric")
    steps = _shape_steps(t, h, metric)
    assert steps.max() > 3 * steps.min()  # the defect: stalls, then snaps
    shape = geodesics.resample_path(t, f, h, path, b.weights, 13)
    steps = _shape_steps(t, h, shape)
    assert steps.max() < 1.02 * steps.min()
    assert np.array_equal(shape[0], path[0]) and np.array_equal(shape[-1], path[-1])
    assert np.allclose(geodesics.vertex_step_lengths(t, h, shape), steps)
    with pytest.raises(InputError, match="pace"):
        geodesics.resample_path(t, f, h, path, b.weights, 5, pace="even")


def test_cancellation_stops_the_solve_and_returns_nothing():
    b = small_basis()
    t, f, h = b.tensors()
    token = CancelToken()
    events = []

    def callback(event):
        events.append(event)
        token.cancel()

    with pytest.raises(SolveCancelled):
        geodesics.geodesic(t, f, h, np.zeros(4), np.ones(4), b.weights, steps=5, callback=callback, cancel=token)
    assert len(events) == 1


def test_bad_codes_raise_input_error():
    b = small_basis()
    t, f, h = b.tensors()
    with pytest.raises(InputError, match="4 coefficients"):
        geodesics.geodesic(t, f, h, np.zeros(3), np.ones(4), b.weights)
    with pytest.raises(InputError, match="NaN"):
        geodesics.geodesic(t, f, h, np.full(4, np.nan), np.ones(4), b.weights)


def test_translation_codes_find_only_the_translations_a_basis_spans():
    b, _ = limb_basis()
    axes, codes = geodesics.translation_codes(b.tensors()[2])
    assert axes.tolist() == [2]
    assert np.allclose(codes, [[0.0, 0.0, 1.0]], atol=1e-9)
    axes, codes = geodesics.translation_codes(small_basis().tensors()[2])
    assert axes.shape == (0,) and codes.shape == (0, 4)


def test_anchor_path_removes_a_sinking_body_and_keeps_the_limb_motion():
    b, limb = limb_basis()
    assert limb.mean() < 0.4
    t, f, h = b.tensors()
    line = geodesics.straight_path([0.0, 0.0, 0.0], [1.5, 0.0, 0.0], 7)
    path = line.copy()
    bump = np.sin(np.linspace(0, np.pi, 7))
    path[:, 1] += 0.3 * bump   # the limb takes another way (what a geodesic does)...
    path[:, 2] -= 0.05 * bump  # ...and the whole body sinks mid-path
    out = geodesics.anchor_path(t, h, path, line)
    assert np.array_equal(out[[0, -1]], path[[0, -1]])
    assert np.allclose(out[:, :2], path[:, :2])  # the limb's own motion is kept
    assert np.abs(out[:, 2] - line[:, 2]).max() < 1e-9  # the sinking is gone
    body = ~limb
    before = np.abs(geodesics.decode_path(t, h, path) - geodesics.decode_path(t, h, line))[:, body].max()
    after = np.abs(geodesics.decode_path(t, h, out) - geodesics.decode_path(t, h, line))[:, body].max()
    assert before > 0.04 and after < 1e-9
    # an extrapolation keeps its two given frames and anchors every predicted one, the last included
    ahead = geodesics.anchor_path(t, h, path[3:], line[3:], fixed=(0, 1))
    assert np.array_equal(ahead[:2], path[3:5])
    assert np.abs(ahead[2:, 2] - line[5:, 2]).max() < 1e-9 and np.allclose(ahead[:, :2], path[3:, :2])


def test_anchor_path_leaves_a_basis_without_translations_alone_and_checks_shapes():
    b = small_basis()
    t, f, h = b.tensors()
    path = geodesics.straight_path(np.zeros(4), np.ones(4), 5)
    bent = path + 0.1 * np.sin(np.linspace(0, np.pi, 5))[:, None]
    assert np.array_equal(geodesics.anchor_path(t, h, bent, path), bent)
    with pytest.raises(InputError, match="same shape"):
        geodesics.anchor_path(t, h, bent, path[:4])


def test_keyframe_path_anchors_then_paces_evenly():
    b, _ = limb_basis()
    t, f, h = b.tensors()
    line = geodesics.straight_path([0.0, 0.0, 0.0], [1.5, 0.0, 0.0], 7)
    path = line + np.sin(np.linspace(0, np.pi, 7))[:, None] * np.array([0.0, 0.3, -0.05])
    out = geodesics.keyframe_path(t, f, h, path, b.weights, 5)
    assert np.allclose(out, geodesics.resample_path(t, f, h, geodesics.anchor_path(t, h, path, line), b.weights, 5))
    free = geodesics.keyframe_path(t, f, h, path, b.weights, 5, anchor=False)
    assert np.allclose(free, geodesics.resample_path(t, f, h, path, b.weights, 5))
    assert np.abs(free - out)[1:-1, 2].max() > 0.01


def test_anchored_geodesic_of_the_bundled_human_keeps_the_feet_on_the_floor():
    """Rest -> the highest-reaching pose, in the paper's weights (the basis' ``shape_metric``), whose L2
    term keeps the centroid still: the geodesic as solved sinks the feet (~4 cm), the anchored one does
    not. (The basis' motion weights keep the geodesic nearer the line: ~7 mm.)"""
    b = basis_io.load_basis("human")
    t, f, h = b.tensors()
    protos = b.extras["pose_prototypes"]
    up = protos[np.argmax(geodesics.decode_path(t, h, protos)[:, :, 2].max(1))]
    rest = np.zeros(b.n_fields)
    g = geodesics.geodesic(t, f, h, rest, up, b.shape_metric, steps=5, metric=b.template_metric(b.shape_metric))
    line = geodesics.straight_path(rest, up, 5)
    feet = b.template[:, 2] < b.template[:, 2].min() + 0.05

    def sink(path):  # the feet's median height below where the line puts them, per frame
        gap = geodesics.decode_path(t, h, line)[:, feet, 2] - geodesics.decode_path(t, h, path)[:, feet, 2]
        return np.abs(np.median(gap, axis=1))

    assert sink(g.path).max() > 0.01
    assert sink(geodesics.anchor_path(t, h, g.path, line)).max() < 0.005


def _two_sphere_scans(seed=2):
    """A sphere basis, two codes and their surfaces remeshed differently, in one common (rotated, scaled)
    frame: -> basis, surface, codes (2, 6), rotation, scans [(verts, faces)] * 2."""
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    codes = 0.7 * np.random.default_rng(seed).normal(size=(2, 6))
    rot = synthetic.random_rotation(9)
    scans = []
    for k, c in enumerate(codes):
        u, faces = synthetic.resampled_sphere(2, seed=10 + k)
        scans.append((2.0 * surface(u, c) @ rot.T + [1.0, 0.0, -2.0], faces))
    return basis, surface, codes, rot, scans


def test_symmetric_matching_of_two_raw_scans_recovers_codes_and_geodesic():
    basis, surface, codes, rot, scans = _two_sphere_scans()
    events = []
    m = registration.symmetric_match(basis, scans[0], scans[1], steps=5, callback=events.append)
    assert np.abs(m.path[0] - codes[0]).max() < 0.03 * np.abs(codes).max()
    assert np.abs(m.path[-1] - codes[1]).max() < 0.03 * np.abs(codes).max()
    t, f, h = basis.tensors()
    truth = geodesics.geodesic(t, f, h, codes[0], codes[1], basis.weights, steps=5)
    assert m.distance == pytest.approx(truth.distance, rel=0.05)
    # the frames come back in the scans' frame: the ends overlay the scans
    ends = m.vertices(t, h, m.path[[0, -1]])
    truth_ends = [2.0 * surface(synthetic.icosphere(2)[0], c) @ rot.T + [1.0, 0.0, -2.0] for c in codes]
    for e, tr in zip(ends, truth_ends):
        assert np.abs(e - tr).max() < 0.03 * np.abs(tr).max()
    fractions = [e.fraction for e in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_symmetric_matchings_joint_solve_moves_the_ends_and_the_path_with_them():
    """Started from registrations whose codes are off, the joint solve brings the ends back onto their scans
    and its interior is the geodesic between the ends it returns (the path converged, not only the ends)."""
    basis, _, codes, _, scans = _two_sphere_scans(seed=5)
    regs = [registration.register(basis, *scan) for scan in scans]
    rng = np.random.default_rng(0)
    off = [dataclasses.replace(r, code=r.code + 0.3 * rng.normal(size=r.code.shape)) for r in regs]
    path, energy, gammas = registration.symmetric.match_registered(basis, scans, off, 6, basis.schedule[-1],
                                                                   basis.weights, Monitor("test"))
    for end, r in zip(path[[0, -1]], regs):
        assert np.abs(end - r.code).max() < 0.1 * 0.3
    t, f, h = basis.tensors()
    between = geodesics.geodesic(t, f, h, path[0], path[-1], basis.weights, steps=6)
    assert energy == pytest.approx(between.energy, rel=0.01)
    assert max(gammas) < 2 * max(r.varifold for r in regs)


def _with_floor(scan, rot):
    """A scan of _two_sphere_scans with a square floor under it (the same frame): -> (verts, faces, weights (G,)),
    the weights 1 on the scan's faces and 0 on the floor's."""
    grid = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 9), np.linspace(-1.5, 1.5, 9), indexing="ij"), -1).reshape(-1, 2)
    floor = np.column_stack([grid, np.full(len(grid), -1.3)])
    floor = 2.0 * floor @ rot.T + [1.0, 0.0, -2.0]
    quads = [(i * 9 + j, (i + 1) * 9 + j, (i + 1) * 9 + j + 1, i * 9 + j + 1) for i in range(8) for j in range(8)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]) + len(scan[0])
    verts, faces = np.concatenate([scan[0], floor]), np.concatenate([scan[1], tris])
    return verts, faces, np.r_[np.ones(len(scan[1])), np.zeros(len(tris))]


def test_symmetric_matching_keeps_a_scans_mask_and_landmarks_in_the_joint_solve():
    """A floor under one scan, masked out (weight 0), changes nothing: both registrations and the joint solve
    ignore it; the joint solve's fit term of that end equals the floorless scan's, and a landmark pulls."""
    basis, surface, codes, rot, scans = _two_sphere_scans()
    verts, faces, weights = _with_floor(scans[0], rot)
    m = registration.symmetric_match(basis, (verts, faces), scans[1], steps=5, face_weights=(weights, None))
    for end, code in zip(m.path[[0, -1]], codes):
        assert np.abs(end - code).max() < 0.03 * np.abs(codes).max()
    reg = registration.register(basis, verts, faces, scan_face_weights=weights)
    level, gram = basis.schedule[-1], basis.template_metric()
    fit = basis.template + np.tensordot(reg.code, basis.fields, 1)
    mesh, tri = torch.as_tensor(fit), torch.as_tensor(basis.faces)
    masked = registration.symmetric._end_terms(basis, (verts, faces), reg, level, gram, weights, None, 1.0,
                                               torch.float64, "cpu")
    bare = registration.symmetric._end_terms(basis, scans[0], reg, level, gram, None, None, 1.0, torch.float64, "cpu")
    assert float(masked[0](mesh, tri)) == pytest.approx(float(bare[0](mesh, tri)), rel=1e-9)
    assert float(masked[1](mesh)) == 0.0  # no landmarks, no pull
    # a landmark: zero where the fit's vertex is, area-weighted squared distance elsewhere
    at = reg.transform.invert(fit[:1])[0]
    off = at + reg.transform.invert(np.array([[0.0, 0.0, 0.1]]))[0] - reg.transform.invert(np.zeros((1, 3)))[0]
    pull_at = registration.symmetric._end_terms(basis, scans[0], reg, level, gram, None, [(0, at)], 2.0,
                                                torch.float64, "cpu")[1]
    pull_off = registration.symmetric._end_terms(basis, scans[0], reg, level, gram, None, [(0, off)], 2.0,
                                                 torch.float64, "cpu")[1]
    area = registration.surface_moments(basis.template, basis.faces)[0]
    assert float(pull_at(mesh)) == pytest.approx(0.0, abs=1e-18)
    assert float(pull_off(mesh)) == pytest.approx(2.0 * area * 0.1 ** 2, rel=1e-9)
    # the second scan's bad mask is refused before the first scan is registered
    with pytest.raises(InputError, match="face weights must have shape"):
        registration.symmetric_match(basis, scans[0], scans[1], face_weights=(None, np.ones(3)),
                                     callback=lambda e: pytest.fail("a solve started"))


def test_geodesics_default_preconditioner_is_the_metric_at_the_mean_code():
    basis, _ = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    t, f, h = basis.tensors()
    a, b = 0.5 * np.ones(6), -0.3 * np.arange(6)
    gram = geodesics.midpoint_metric(t, f, h, a, b, basis.weights)
    with torch.no_grad():
        exact = latent.latent_metric(t, f, h, torch.as_tensor((a + b) / 2), basis.weights).numpy()
    assert np.allclose(gram, exact, rtol=1e-8, atol=1e-10 * np.abs(exact).max())
    assert not np.allclose(gram, basis.template_metric(), rtol=1e-3)
    # where the mean code's surface has a degenerate face, the template's metric instead
    flat = np.zeros((6, *t.shape))
    flat[0, f[0, 0]] = (t[f[0, 2]] - t[f[0, 0]]).numpy()  # corner 0 of face 0 onto corner 2 at code 1
    flat_t = torch.as_tensor(flat)
    gram = geodesics.midpoint_metric(t, f, flat_t, 2 * np.eye(6)[0], np.zeros(6), basis.weights)
    assert np.allclose(gram, h2_metric.assembled_metric_matrix(t, f, flat_t, basis.weights).numpy())
