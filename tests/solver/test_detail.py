"""The detail layer after the basis fit (``registration.detail``) and what it is built on."""

import numpy as np
import pytest
import scipy.sparse
import torch
from scipy.spatial import cKDTree

from bareesa import h2_metric, optimize, synthetic
from bareesa.mesh import self_intersections
from bareesa.registration import DetailFit, RegistrationResult, fit_detail, register
from bareesa.registration.detail import (_crossing_vertices, bad_faces, fade, reached_faces, scan_noise,
                                        tangential_matrix, vertex_normals)

#: settings of the detail layer at the scale of the unit-sphere test basis (the defaults are a human body's)
SPHERE_DETAIL = {"sigmas": (0.05,), "weights": (1e3,)}
BUMP_CENTRE = np.array([0.0, 0.6, 0.8])


def _bump(u, height=0.06):
    """A bump no field of the basis makes: radial, Gaussian about BUMP_CENTRE on the unit sphere."""
    return height * np.exp(-((u - BUMP_CENTRE) ** 2).sum(1) / 0.15)[:, None] * u


@pytest.fixture(scope="module")
def bumped():
    """The sphere basis, a code, F(code), a finer scan of F(code) with the bump and a dense copy of that surface."""
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=3, n_fields=6, seed=0)
    alpha = 0.5 * np.random.default_rng(1).normal(size=6)
    us, fs = synthetic.resampled_sphere(4, seed=3)
    ud, _ = synthetic.icosphere(5)
    return {"basis": basis, "surface": surface, "alpha": alpha, "fit": basis.template + np.tensordot(alpha, basis.fields, 1),
            "scan": (surface(us, alpha) + _bump(us), fs), "dense": surface(ud, alpha) + _bump(ud)}


def test_the_detail_layer_takes_the_bump_the_basis_cannot_make_without_breaking_a_face(bumped):
    basis, fit, (scan, scan_faces) = bumped["basis"], bumped["fit"], bumped["scan"]
    distance = cKDTree(bumped["dense"]).query
    detail = fit_detail(fit, basis.faces, scan, scan_faces, DetailFit(**SPHERE_DETAIL), basis.shape_metric, basis.scale)
    assert detail.skipped is None and detail.displacement.shape == fit.shape
    detailed = fit + detail.displacement
    assert distance(fit)[0].max() > 0.05  # the basis fit misses the bump's top ...
    assert distance(detailed)[0].max() < 0.4 * distance(fit)[0].max()  # ... the detailed mesh takes it
    assert not bad_faces(detailed, basis.faces, fit).any()
    assert len(self_intersections(detailed, basis.faces)) == 0
    report = detail.to_json()
    assert report["kept"] and report["levels"][0]["iterations"] >= 1 and report["max"] > 0.02


def test_faces_over_a_hole_are_left_to_the_energy_and_do_not_reach_into_it(bumped):
    basis, fit, (scan, scan_faces) = bumped["basis"], bumped["fit"], bumped["scan"]
    centre = fit[np.argmin(fit[:, 2])]  # the bottom, far from the bump
    centres = scan[scan_faces].mean(1)
    holed = scan_faces[np.linalg.norm(centres - centre, axis=1) > 0.35]
    settings = DetailFit(**SPHERE_DETAIL)
    sigma = settings.sigmas[0] * basis.scale
    reached = reached_faces(fit, basis.faces, scan, holed, None, settings.reach * sigma)
    inside = np.linalg.norm(fit[basis.faces].mean(1) - centre, axis=1) < 0.1
    assert inside.any() and not reached[inside].any() and reached.mean() > 0.8
    detail = fit_detail(fit, basis.faces, scan, holed, settings, basis.shape_metric, basis.scale)
    moved = np.linalg.norm(detail.displacement, axis=1)
    near = np.linalg.norm(fit - centre, axis=1) < 0.2
    assert moved[near].max() < 0.1 * 0.35  # no spike into the hole (radius 0.35): carried by the energy


def test_register_returns_the_detailed_mesh_beside_the_basis_fit_and_can_leave_it_out(bumped):
    basis = bumped["basis"]
    scan, scan_faces = bumped["scan"]
    rot = synthetic.random_rotation(4)
    moved = 1.3 * scan @ rot.T + np.array([0.2, -0.1, 0.4])
    res = register(basis, moved, scan_faces, detail=SPHERE_DETAIL)
    assert res.detail is not None and res.detail.shape == basis.template.shape
    fit = basis.template + np.tensordot(res.code, basis.fields, 1)
    assert np.allclose(res.detailed_vertices, res.transform.invert(fit + res.detail), atol=1e-9)
    assert res.output_vertices is res.detailed_vertices
    report = res.to_json()["detail"]
    assert report["kept"] and report["residual"] < res.residual and report["chamfer"] < res.chamfer
    assert report["noise"] == pytest.approx(scan_noise(moved), rel=1e-6)  # in the scan's units
    back = RegistrationResult.from_state(res.to_state())
    assert np.array_equal(back.detail, res.detail) and back.detail_report == res.detail_report
    plain = register(basis, moved, scan_faces, detail={"enabled": False})
    assert plain.detail is None and plain.detailed_vertices is None and plain.output_vertices is plain.vertices
    assert plain.detail_report["skipped"] == "turned off"


def test_the_sparse_metric_is_the_h2_metric_on_vertex_fields():
    basis, _ = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=3, seed=0)
    t, f, h = basis.tensors()
    for weights in ("body", "face", (1.0, 2.0, -1.0, 0.5, 0.3, 0.7)):
        matrix = h2_metric.sparse_metric(t, f, weights)
        assert isinstance(matrix, scipy.sparse.csr_matrix) and matrix.shape == (3 * len(t),) * 2
        field = torch.as_tensor(np.random.default_rng(0).normal(size=t.shape))
        for v in (field, h[0], h[2]):
            flat = v.reshape(-1).numpy()
            assert flat @ (matrix @ flat) == pytest.approx(float(h2_metric.squared_norm(t, f, v, weights)), rel=1e-9)


def test_preconditioned_lbfgs_solves_a_stiff_problem_in_few_iterations():
    n = 400
    lap = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    stiff = (1e4 * lap @ lap + scipy.sparse.identity(n)).tocsr()  # condition number ~ 1e9
    rng = np.random.default_rng(0)
    b = rng.normal(size=n)
    quartic = 1e-3
    a = torch.as_tensor(stiff.toarray())

    def objective(x):  # stiff quadratic plus a small non-quadratic term
        return 0.5 * x @ (a @ x) - torch.as_tensor(b) @ x + quartic * (x ** 4).sum()

    x, value, iterations = optimize.minimize_preconditioned(objective, np.zeros(n), optimize.sparse_solver(stiff),
                                                            max_iter=50, ftol=1e-14)
    xt = torch.as_tensor(x).requires_grad_(True)
    (grad,) = torch.autograd.grad(objective(xt), xt)
    assert iterations < 30 and grad.norm() < 1e-6 * np.linalg.norm(b)
    _, _, plain = optimize.minimize_lbfgs(objective, np.zeros(n), max_iter=30, ftol=1e-14, gtol=1e-12)
    _, plain_value, _ = optimize.minimize_lbfgs(objective, np.zeros(n), max_iter=iterations, ftol=1e-14, gtol=1e-12)
    assert value < plain_value  # unpreconditioned L-BFGS is further from the minimum after as many iterations


def test_a_solve_started_from_the_callers_value_does_not_evaluate_it_again():
    n = 200
    lap = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    stiff = (1e3 * lap @ lap + scipy.sparse.identity(n)).tocsr()
    a, b = torch.as_tensor(stiff.toarray()), torch.as_tensor(np.random.default_rng(2).normal(size=n))
    calls = []

    def objective(x):
        calls.append(x.detach().numpy().copy())
        return 0.5 * x @ (a @ x) - b @ x + 1e-3 * (x ** 4).sum()

    x0 = np.random.default_rng(3).normal(size=n)
    xt = torch.from_numpy(x0.copy()).requires_grad_(True)
    value = objective(xt)
    start = (float(value.detach()), torch.autograd.grad(value, xt)[0].numpy())
    solve = optimize.sparse_solver(stiff)
    calls.clear()
    x, found, _ = optimize.minimize_preconditioned(objective, x0, solve, max_iter=60, ftol=1e-14, start=start)
    assert calls and not any(np.array_equal(c, x0) for c in calls)
    calls.clear()
    again, plain, _ = optimize.minimize_preconditioned(objective, x0, solve, max_iter=60, ftol=1e-14)
    assert any(np.array_equal(c, x0) for c in calls)  # (without it, x0 is evaluated)
    assert found == pytest.approx(plain, rel=1e-12) and np.allclose(x, again)


def test_the_noise_estimate_finds_the_std_of_the_noise_and_almost_none_on_a_clean_surface():
    for subdivisions in (4, 5):
        points, _ = synthetic.resampled_sphere(subdivisions, seed=3)
        assert scan_noise(points) < 1e-4
        for sigma, seed in ((0.005, 0), (0.02, 1)):
            noisy = points + np.random.default_rng(seed).normal(size=points.shape) * sigma
            assert scan_noise(noisy) == pytest.approx(sigma, rel=0.15)
            assert scan_noise(noisy, centres=1000) == pytest.approx(sigma, rel=0.15)  # measured at 1000 of them


def test_on_a_noisy_scan_the_layer_weighs_the_data_less_and_stays_near_the_true_surface(bumped):
    basis, surface, alpha, fit = bumped["basis"], bumped["surface"], bumped["alpha"], bumped["fit"]
    points, faces = synthetic.resampled_sphere(4, seed=3)
    noisy = surface(points, alpha) + np.random.default_rng(0).normal(size=(len(points), 3)) * 0.02
    truth = cKDTree(surface(synthetic.icosphere(5)[0], alpha)).query  # the basis fit is this surface already
    off, on = ({**SPHERE_DETAIL, "noise_floor": floor} for floor in (None, DetailFit.noise_floor))
    plain = fit_detail(fit, basis.faces, noisy, faces, DetailFit(**off), basis.shape_metric, basis.scale)
    quiet = fit_detail(fit, basis.faces, noisy, faces, DetailFit(**on), basis.shape_metric, basis.scale)
    assert plain.noise is None and quiet.noise == pytest.approx(0.02, rel=0.15)
    assert plain.levels[0]["weight"] == SPHERE_DETAIL["weights"][0] > 100 * quiet.levels[0]["weight"]
    assert truth(fit + quiet.displacement)[0].mean() < 0.3 * truth(fit + plain.displacement)[0].mean()
    clean = fit_detail(fit, basis.faces, surface(points, alpha), faces, DetailFit(**on), basis.shape_metric,
                       basis.scale)
    assert clean.levels[0]["weight"] == SPHERE_DETAIL["weights"][0]  # a clean scan keeps the whole weight


def test_fade_zeroes_the_displacement_at_the_vertices_and_keeps_it_away_from_them():
    verts, faces = synthetic.icosphere(2)
    displacement = np.ones_like(verts)
    out = fade(displacement, faces, np.array([0]), rings=2)
    assert np.all(out[0] == 0)
    ring = np.unique(faces[(faces == 0).any(1)])
    assert np.all((out[ring[ring != 0]] > 0) & (out[ring[ring != 0]] < 1))
    far = np.linalg.norm(verts - verts[0], axis=1) > 1.0
    assert np.all(out[far] == 1)


def test_the_tangential_penalty_is_the_squared_displacement_along_the_surface():
    verts, faces = synthetic.icosphere(2)
    d = np.random.default_rng(0).normal(size=verts.shape)
    normals = vertex_normals(verts, faces)
    assert ((normals * verts / np.linalg.norm(verts, axis=1, keepdims=True)).sum(1) > 0.99).all()  # outward
    along = d - (d * normals).sum(1, keepdims=True) * normals
    areas = np.asarray(face_areas_per_vertex(verts, faces))
    assert d.ravel() @ (tangential_matrix(verts, faces) @ d.ravel()) == pytest.approx((areas * (along ** 2).sum(1)).sum())
    radial = 0.01 * normals  # a displacement along the normals costs nothing
    assert radial.ravel() @ (tangential_matrix(verts, faces) @ radial.ravel()) == pytest.approx(0.0, abs=1e-12)


def face_areas_per_vertex(verts, faces):
    from bareesa.geometry import vertex_areas

    return vertex_areas(torch.as_tensor(verts), torch.as_tensor(faces)).numpy()


def test_a_layer_that_makes_the_surface_cross_itself_is_found_and_faded_out_there():
    verts, faces = synthetic.icosphere(2)
    d = np.zeros_like(verts)
    top = int(np.argmax(verts[:, 2]))
    d[top] = [0.0, 0.0, -2.3]  # the top vertex pushed out through the bottom of the sphere
    crossing = _crossing_vertices(verts + d, faces, verts)
    assert top in crossing and len(crossing) > 3
    assert len(_crossing_vertices(verts + 0.05 * verts, faces, verts)) == 0  # inflated: nothing crosses
    faded = fade(d, faces, crossing, rings=2)
    assert len(_crossing_vertices(verts + faded, faces, verts)) == 0
