import numpy as np
import pytest
import torch

from bareesa import basis_building, h2_metric, latent, shooting, statistics, synthetic
from bareesa.errors import InputError
from tests.solver.support import small_basis


def test_motion_transfer_swaps_identity_and_keeps_pose():
    b = small_basis(p=4)  # pose 0..3, shape 3..4
    frames = np.random.default_rng(0).normal(size=(5, 4))
    identity = np.array([9.0, 9.0, 9.0, -2.5])
    out = statistics.transfer_motion(frames, identity, b.group_slice("shape"))
    assert np.array_equal(out[:, :3], frames[:, :3])
    assert np.all(out[:, 3] == -2.5)
    with pytest.raises(InputError):
        statistics.transfer_motion(frames, identity[:3], b.group_slice("shape"))


def test_shooting_the_log_map_returns_the_code():
    b = small_basis()
    t, f, h = b.tensors()
    codes = np.array([[0.8, -0.5, 0.3, 0.6], [-0.4, 0.2, 0.7, -0.3]])
    vel = statistics.log_map(t, f, h, codes, b.weights, steps=6)
    for v, c in zip(vel, codes):
        end = shooting.shoot(t, f, h, np.zeros(4), v, b.weights, steps=5)[-1]
        assert np.abs(end - c).max() < 1e-5


def test_gaussian_mixture_sampling_is_seeded_and_matches_fit():
    rng = np.random.default_rng(1)
    vel = np.concatenate([rng.normal(size=(300, 4)) * [1, 2, 0.5, 1] + [3, 0, 0, 0],
                          rng.normal(size=(300, 4)) * 0.3 - [3, 0, 0, 0]])
    groups = {"pose": (0, 3), "shape": (3, 4)}
    dist = statistics.fit_distribution(vel, groups, {"pose": 2, "shape": 1}, seed=0)
    assert dist["gmm_pose_means"].shape == (2, 3) and dist["gmm_shape_covariances"].shape == (1, 1, 1)
    a = statistics.sample_velocities(dist, groups, 4000, seed=5)
    assert np.array_equal(a, statistics.sample_velocities(dist, groups, 4000, seed=5))
    assert not np.array_equal(a, statistics.sample_velocities(dist, groups, 4000, seed=6))
    assert np.allclose(a.mean(0), vel.mean(0), atol=0.15)
    assert np.allclose(a.std(0), vel.std(0), rtol=0.1)
    assert (a[:, 0] > 0).mean() == pytest.approx(0.5, abs=0.05)  # both modes are sampled


def test_sample_codes_shoots_sampled_velocities_from_template():
    b = small_basis()
    t, f, h = b.tensors()
    dist = statistics.fit_distribution(np.random.default_rng(0).normal(size=(20, 4)) * 0.3, b.groups,
                                       {"pose": 2, "shape": 1})
    codes = statistics.sample_codes(t, f, h, dist, b.groups, b.weights, n=2, seed=3, steps=4)
    vel = statistics.sample_velocities(dist, b.groups, 2, seed=3)
    for c, v in zip(codes, vel):
        assert np.allclose(c, shooting.shoot(t, f, h, np.zeros(4), v, b.weights, steps=4)[-1])


def test_vertex_geodesic_beats_linear_blend_and_fixes_ends():
    v, f = synthetic.blob_mesh(1)
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    rotated = v @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    w = h2_metric.H2Weights(1, 10, 10, 10, 1, 0)
    path = basis_building.vertex_geodesic(v, rotated, f, w, steps=5, max_iter=200)
    assert np.array_equal(path[0], v) and np.array_equal(path[-1], rotated)
    blend = np.linspace(0, 1, 5)[:, None, None] * (rotated - v) + v
    e_geo = h2_metric.path_energy(torch.tensor(path), torch.tensor(f), w)
    e_lin = h2_metric.path_energy(torch.tensor(blend), torch.tensor(f), w)
    assert e_geo < 0.9 * e_lin


def test_elastic_basis_spans_the_identity_differences():
    b = small_basis(p=3)
    ids = np.stack([b.template + c * b.fields[2] + abs(c) * 0.3 * b.fields[0] for c in (0.0, 1.0, -1.0)])
    built = basis_building.build_basis(b.template, b.faces, {"shape": [ids]}, {"shape": 8}, weights="face",
                               elastic=("shape",), elastic_steps=4)
    assert built.provenance["groups"]["shape"]["construction"] == "elastic H2 geodesics"
    q, _ = np.linalg.qr(built.fields.reshape(built.n_fields, -1).T)
    for d in (ids[1] - ids[0], ids[2] - ids[1]):
        d = d.ravel()
        assert np.linalg.norm(d - q @ (q.T @ d)) < 1e-6 * np.linalg.norm(d)
    with pytest.raises(InputError, match="unknown groups"):
        basis_building.build_basis(b.template, b.faces, {"shape": [ids]}, {"shape": 2}, elastic=("pose",))


def test_whitened_vertex_geodesic_reaches_the_plain_solvers_energy_in_few_iterations(monkeypatch):
    v, f = synthetic.blob_mesh(1)
    c, s = np.cos(np.pi / 3), np.sin(np.pi / 3)
    bent = v @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + 0.2 * np.sin(v)
    w = h2_metric.H2Weights(1, 10, 10, 10, 1, 1)
    energy = lambda p: float(h2_metric.path_energy(torch.tensor(p), torch.tensor(f), w))  # noqa: E731
    fast = basis_building.vertex_geodesic(v, bent, f, w, steps=5, max_iter=60)
    monkeypatch.setattr(basis_building, "WHITENED_MAX_VERTICES", 0)
    plain = basis_building.vertex_geodesic(v, bent, f, w, steps=5, max_iter=3000)
    plain_short = basis_building.vertex_geodesic(v, bent, f, w, steps=5, max_iter=60)
    assert np.array_equal(fast[0], v) and np.array_equal(fast[-1], bent)
    assert energy(fast) <= energy(plain) * (1 + 1e-9) < energy(plain_short)
    assert np.abs(fast - plain).max() < 1e-4 * np.abs(bent - v).max()


def test_pose_prototypes_are_the_centres_of_the_training_poses():
    from dataclasses import replace

    basis, _ = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=6, seed=0)
    basis = replace(basis, groups={"pose": (0, 4), "shape": (4, 6)})
    rng = np.random.default_rng(2)
    poses = np.array([[0.5, 0, 0, 0], [0, -0.5, 0.3, 0], [0, 0, 0, 0.6]])
    codes = np.concatenate([np.concatenate([poses[i % 3] + 0.01 * rng.normal(size=4), rng.normal(size=2)])[None]
                            for i in range(30)])
    frames = basis.template + np.tensordot(codes, basis.fields, axes=1)
    protos = statistics.pose_prototypes(basis, frames, k=3)
    assert protos.shape == (3, 6)
    # clustered on the pose group only: the shape coefficients vary at random and do not split clusters
    proj = latent.project_to_basis(basis, frames)[0]
    expected = np.stack([proj[i::3].mean(0) for i in range(3)])  # each cluster's mean code
    gaps = np.linalg.norm(expected[:, None] - protos[None], axis=-1)
    assert gaps.min(1).max() < 1e-9 and sorted(gaps.argmin(1)) == [0, 1, 2]
    assert np.linalg.norm(poses[:, None] - protos[None, :, :4], axis=-1).min(1).max() < 0.05
    assert len(statistics.pose_prototypes(basis, frames[:2], k=24)) == 2  # never more centres than frames
