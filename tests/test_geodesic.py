import numpy as np
import pytest
import torch

from core import geodesic, latent, synthetic
from core.errors import InputError, SolveCancelled
from core.progress import CancelToken
from tests.test_latent import small_basis


def test_geodesic_has_lower_energy_than_straight_line_and_fixed_endpoints():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.array([0.0, 0.0, 0.0, 0.0]), np.array([2.0, -1.5, 1.0, 1.5])
    g = geodesic.geodesic(t, f, h, a0, a1, b.weights, steps=6)
    straight = latent.latent_path_energy(t, f, h, torch.tensor(geodesic.straight_path(a0, a1, 6)), b.weights)
    assert g.energy < 0.99 * float(straight)
    assert np.array_equal(g.path[0], a0) and np.array_equal(g.path[-1], a1)
    assert g.distance == pytest.approx(np.sqrt(g.energy))
    lengths = geodesic.step_lengths(t, f, h, g.path, b.weights)
    assert lengths.std() < 0.05 * lengths.mean()  # discrete geodesics have constant speed


def test_geodesic_is_straight_line_when_metric_is_constant():
    v, f = synthetic.blob_mesh(2)
    translations = np.stack([np.broadcast_to(e, v.shape) for e in np.eye(3)])  # G-bar independent of alpha
    b = latent.Basis(template=v, faces=f, fields=translations, groups={}, weights="body")
    t, ft, h = b.tensors()
    a0, a1 = np.array([0.0, 1.0, -1.0]), np.array([2.0, -1.0, 0.5])
    bent = geodesic.straight_path(a0, a1, 5) + np.sin(np.linspace(0, np.pi, 5))[:, None] * 0.7
    g = geodesic.geodesic(t, ft, h, a0, a1, b.weights, steps=5, init=bent)
    assert np.abs(g.path - geodesic.straight_path(a0, a1, 5)).max() < 1e-6


def test_distance_is_symmetric():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.array([0.5, 0.0, -1.0, 0.2]), np.array([-1.0, 1.5, 1.0, 0.0])
    d01 = geodesic.geodesic(t, f, h, a0, a1, b.weights, steps=5).distance
    d10 = geodesic.geodesic(t, f, h, a1, a0, b.weights, steps=5).distance
    assert d01 == pytest.approx(d10, rel=1e-5)


def test_resample_path_gives_even_metric_speed_and_keeps_endpoints():
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), np.array([2.0, -1.5, 1.0, 1.5])
    s = np.array([0.0, 0.05, 0.1, 0.6, 1.0])[:, None]  # badly paced
    path = a0 + s * (a1 - a0)
    out = geodesic.resample_path(t, f, h, path, b.weights, 9)
    assert out.shape == (9, 4)
    assert np.array_equal(out[0], a0) and np.array_equal(out[-1], a1)
    lengths = geodesic.step_lengths(t, f, h, out, b.weights)
    before = geodesic.step_lengths(t, f, h, path, b.weights)
    assert lengths.std() < 0.05 * lengths.mean() < before.std()


def test_cancellation_stops_the_solve_and_returns_nothing():
    b = small_basis()
    t, f, h = b.tensors()
    token = CancelToken()
    events = []

    def callback(event):
        events.append(event)
        token.cancel()

    with pytest.raises(SolveCancelled):
        geodesic.geodesic(t, f, h, np.zeros(4), np.ones(4), b.weights, steps=5, callback=callback, cancel=token)
    assert len(events) == 1


def test_bad_codes_raise_input_error():
    b = small_basis()
    t, f, h = b.tensors()
    with pytest.raises(InputError, match="4 coefficients"):
        geodesic.geodesic(t, f, h, np.zeros(3), np.ones(4), b.weights)
    with pytest.raises(InputError, match="NaN"):
        geodesic.geodesic(t, f, h, np.full(4, np.nan), np.ones(4), b.weights)


def test_symmetric_matching_of_two_raw_scans_recovers_codes_and_geodesic():
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    rng = np.random.default_rng(2)
    codes = 0.7 * rng.normal(size=(2, 6))
    rot = synthetic.random_rotation(9)
    scans = []
    for k, c in enumerate(codes):  # both scans remeshed differently, in one common (rotated, scaled) frame
        u, faces = synthetic.resampled_sphere(2, seed=10 + k)
        scans.append((2.0 * surface(u, c) @ rot.T + [1.0, 0.0, -2.0], faces))
    events = []
    m = geodesic.symmetric_match(basis, scans[0], scans[1], steps=5, callback=events.append)
    assert np.abs(m.path[0] - codes[0]).max() < 0.03 * np.abs(codes).max()
    assert np.abs(m.path[-1] - codes[1]).max() < 0.03 * np.abs(codes).max()
    t, f, h = basis.tensors()
    truth = geodesic.geodesic(t, f, h, codes[0], codes[1], basis.weights, steps=5)
    assert m.distance == pytest.approx(truth.distance, rel=0.05)
    # the frames come back in the scans' frame: the ends overlay the scans
    ends = m.vertices(t, h, m.path[[0, -1]])
    truth_ends = [2.0 * surface(synthetic.icosphere(2)[0], c) @ rot.T + [1.0, 0.0, -2.0] for c in codes]
    for e, tr in zip(ends, truth_ends):
        assert np.abs(e - tr).max() < 0.03 * np.abs(tr).max()
    fractions = [e.fraction for e in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
