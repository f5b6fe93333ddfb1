"""Tests of bareesa.evaluation: Chamfer, Hausdorff, vertex and geodesic errors, varifold wiring."""

import sys
import types

import numpy as np
import pytest
import torch

from bareesa.errors import InputError
from bareesa.evaluation import (SIGMA_FRACTION, chamfer, default_sigma, geodesic_error, hausdorff,
                             mesh_metrics, surface_graph, varifold, vertex_error)
from bareesa.mesh import normalise
from bareesa.synthetic import blob_mesh, icosphere, random_rotation, torus


def _brute_distances(a, b):
    return np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)


def _grid(n=21, spacing=0.1):
    """Flat n x n grid in the z=0 plane, split along one diagonal: -> verts, faces."""
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing, indexing="ij")
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


# ----------------------------------------------------------- chamfer, hausdorff


def test_chamfer_and_hausdorff_match_brute_force():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(37, 3)), rng.normal(size=(53, 3)) + 0.3
    d = _brute_distances(a, b)
    assert chamfer(a, b) == pytest.approx(d.min(1).mean() + d.min(0).mean(), rel=1e-12)
    assert hausdorff(a, b) == pytest.approx(max(d.min(1).max(), d.min(0).max()), rel=1e-12)


def test_chamfer_is_symmetric_and_zero_for_identical_sets():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(40, 3)), rng.normal(size=(25, 3))
    assert chamfer(a, b) == pytest.approx(chamfer(b, a), rel=1e-12)
    assert chamfer(a, a) == 0.0 and hausdorff(a, a) == 0.0
    assert chamfer(a, b) > 0


def test_chamfer_is_not_squared():
    a = np.zeros((1, 3))
    b = np.array([[3.0, 0.0, 0.0]])
    assert chamfer(a, b) == pytest.approx(6.0)


def test_hausdorff_of_translated_copy_is_translation_length():
    v, _ = icosphere(2)
    shift = np.array([0.3, -0.4, 1.2])  # longer than the vertex spacing: nearest is the copy
    assert hausdorff(v, v + 10 * shift) == pytest.approx(10 * np.linalg.norm(shift), rel=1e-12)
    tiny = 1e-3 * shift / np.linalg.norm(shift)
    assert hausdorff(v, v + tiny) == pytest.approx(1e-3, rel=1e-9)


def test_hausdorff_is_sensitive_to_one_outlier_chamfer_much_less():
    v, _ = icosphere(3)
    w = np.vstack([v, [[5.0, 0.0, 0.0]]])
    assert hausdorff(v, w) == pytest.approx(4.0)
    assert chamfer(v, w) < 0.01


def test_point_metrics_reject_bad_shapes():
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        chamfer(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(InputError, match="non-empty"):
        hausdorff(np.zeros((0, 3)), np.zeros((4, 3)))


# ---------------------------------------------------------------- vertex error


def test_vertex_error_hand_computed_example():
    true = np.zeros((4, 3))
    pred = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    err = vertex_error(pred, true)  # distances 5, 1, 0, 2
    assert err["mse"] == pytest.approx((25 + 1 + 0 + 4) / 4)
    assert err["mean"] == pytest.approx(2.0)
    assert err["max"] == pytest.approx(5.0)
    assert err["p95"] == pytest.approx(2 + 0.85 * 3)  # linear interpolation between 2 and 5


def test_vertex_error_shape_mismatch_names_both_counts():
    with pytest.raises(InputError, match="pred has 5, true has 7"):
        vertex_error(np.zeros((5, 3)), np.zeros((7, 3)))


# -------------------------------------------------------------- geodesic error


def test_geodesic_error_on_flat_grid_equals_euclidean_along_edges():
    v, f = _grid()
    ids = np.array([0, 0, 5, 222])  # vertex (i, j) has index 21 i + j
    targets = np.array([20, 440, 215, 227])  # along y, along the diagonal, along x, along y
    expected = np.linalg.norm(v[ids] - v[targets], axis=1).mean()
    assert geodesic_error(v[targets], ids, v, f) == pytest.approx(expected, rel=1e-12)


def test_geodesic_error_on_flat_grid_close_to_euclidean_any_direction():
    v, f = _grid()
    rng = np.random.default_rng(2)
    ids, targets = rng.integers(0, len(v), 50), rng.integers(0, len(v), 50)
    euclid = np.linalg.norm(v[ids] - v[targets], axis=1).mean()
    edges_only = geodesic_error(v[targets], ids, v, f, unfold=False)
    unfolded = geodesic_error(v[targets], ids, v, f)
    assert euclid <= unfolded <= edges_only
    # one-diagonal grid: edges alone follow 3 directions only (~16% too long on average)
    assert unfolded == pytest.approx(euclid, rel=0.05)
    assert edges_only == pytest.approx(euclid, rel=0.20)


def test_geodesic_error_antipodal_on_icosphere_is_pi():
    v, f = icosphere(4)
    ids = np.arange(0, len(v), 97)
    antipodes = -v[ids]  # snapped to the antipodal vertex
    assert geodesic_error(antipodes, ids, v, f) == pytest.approx(np.pi, rel=0.01)
    assert geodesic_error(antipodes, ids, v, f, unfold=False) == pytest.approx(np.pi, rel=0.07)


def test_geodesic_error_zero_for_exact_correspondences_and_snaps_points():
    v, f = icosphere(2)
    ids = np.arange(len(v))
    assert geodesic_error(v, ids, v, f) == 0.0
    assert geodesic_error(1.01 * v, ids, v, f) == 0.0  # points off the surface snap back


def test_geodesic_error_chunking_does_not_change_result():
    v, f = blob_mesh(2)
    rng = np.random.default_rng(3)
    ids = rng.integers(0, len(v), 200)
    pred = v[rng.integers(0, len(v), 200)]
    assert geodesic_error(pred, ids, v, f, chunk=7) == geodesic_error(pred, ids, v, f)


def test_geodesic_error_is_rotation_invariant():
    v, f = torus()
    ids = np.arange(0, len(v), 11)
    pred = v[(ids + 37) % len(v)]
    r = random_rotation(4)
    assert geodesic_error(pred @ r.T, ids, v @ r.T, f) == pytest.approx(
        geodesic_error(pred, ids, v, f), rel=1e-9)


def test_geodesic_error_across_components_raises():
    v, f = icosphere(1)
    v2 = np.vstack([v, v + 10.0])
    f2 = np.vstack([f, f + len(v)])
    with pytest.raises(InputError, match="1 predicted points lie on another connected component"):
        geodesic_error(v2[[3, len(v) + 4]], np.array([5, len(v) + 2]) - [0, len(v)], v2, f2)


def test_geodesic_error_rejects_bad_ids():
    v, f = icosphere(1)
    with pytest.raises(InputError, match="one per predicted point"):
        geodesic_error(v[:3], np.array([0, 1]), v, f)
    with pytest.raises(InputError, match=r"0\.\.41"):
        geodesic_error(v[:2], np.array([0, 42]), v, f)


def test_surface_graph_handles_coincident_vertices():
    v, f = icosphere(1)
    v = np.vstack([v, v[:1]])  # vertex 42 duplicates vertex 0
    f = np.vstack([f, [[0, 42, 1]]])
    g = surface_graph(v, f)
    assert g[0, 42] > 0 or g[42, 0] > 0  # kept as an edge, not dropped as an explicit zero


# ----------------------------------------------------------- varifold, sigma


def test_default_sigma_is_fraction_of_normalised_size():
    v, f = blob_mesh(3)
    vn, norm = normalise(v, f, size=1.0)
    assert default_sigma(vn, f) == pytest.approx(SIGMA_FRACTION, rel=1e-12)
    assert default_sigma(7.0 * v, f) == pytest.approx(7.0 * default_sigma(v, f), rel=1e-12)


def test_varifold_wrapper_passes_float64_tensors_and_returns_squared_distance(monkeypatch):
    calls = {}

    def fake_varifold_distance(verts, faces, target_verts, target_faces, sigma, kernel):
        calls.update(dtypes=(verts.dtype, target_verts.dtype, faces.dtype, target_faces.dtype),
                     sigma=sigma, kernel=kernel)
        return torch.tensor(9.0, dtype=torch.float64)

    fake = types.ModuleType("bareesa.varifold")
    fake.varifold_distance = fake_varifold_distance
    monkeypatch.setitem(sys.modules, "bareesa.varifold", fake)
    v, f = icosphere(1)
    out = mesh_metrics(v, f, v + 0.1, f, kernel="gaussian")
    assert out["varifold"] == 9.0
    assert calls["dtypes"] == (torch.float64, torch.float64, torch.long, torch.long)
    assert calls["kernel"] == "gaussian"
    assert calls["sigma"] == pytest.approx(default_sigma(v, f)) == out["sigma"]
    assert out["chamfer"] == pytest.approx(chamfer(v, v + 0.1))
    assert out["hausdorff"] == pytest.approx(hausdorff(v, v + 0.1))


def test_varifold_zero_for_identical_and_positive_for_translated():
    v, f = icosphere(2)
    sigma = default_sigma(v, f)
    moved = varifold(v, f, v + [0.2, 0, 0], f, sigma=sigma)
    assert moved > 0
    assert varifold(v, f, v, f, sigma=sigma) <= 1e-10 * moved  # zero up to round-off (squared)


def test_varifold_nearly_invariant_to_remeshing():
    v3, f3 = blob_mesh(3)
    v4, f4 = blob_mesh(4)
    sigma = 0.2 * default_sigma(v3, f3) / SIGMA_FRACTION
    same = varifold(v3, f3, v4, f4, sigma=sigma)
    moved = varifold(v3, f3, v4 + [0.1, 0, 0], f4, sigma=sigma)
    assert same < 0.04 * moved  # squared distances
