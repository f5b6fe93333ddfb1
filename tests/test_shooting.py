import numpy as np
import pytest
import torch

from core import geodesic, latent, shooting, synthetic
from core.errors import InputError, SolveCancelled
from core.progress import CancelToken
from tests.test_latent import small_basis


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
    g = geodesic.geodesic(t, f, h, a0, a1, b.weights, steps=6)
    straight = geodesic.straight_path(a0, a1, 6)
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
