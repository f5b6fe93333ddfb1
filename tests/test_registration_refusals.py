"""Scans that cannot be registered are refused up front, with the reason, before any solve."""

import numpy as np
import pytest
import trimesh

from bareesa import registration, synthetic
from bareesa.errors import InputError
from bareesa.registration import multiscale


@pytest.fixture(scope="module")
def basis():
    return synthetic.smooth_sphere_basis(subdivisions=2, n_fields=4, seed=0)[0]


def test_one_triangle_scan_is_refused_before_any_solve(basis, monkeypatch):
    def solve(*args, **kwargs):
        raise AssertionError("the pre-alignment ran for a scan that should have been refused")

    monkeypatch.setattr(multiscale, "prealign_candidates", solve)
    with pytest.raises(InputError, match=r"1 face with area: too few to register onto basis"):
        registration.register(basis, np.eye(3), np.array([[0, 1, 2]]))


def test_a_scan_with_too_few_faces_for_the_template_is_refused(basis):
    need = min(multiscale.MIN_SCAN_FACES, basis.faces.shape[0] // 8)
    sphere = trimesh.creation.icosphere(subdivisions=0)  # 20 faces
    assert len(sphere.faces) < need
    with pytest.raises(InputError, match=f"at least {need}"):
        registration.register(basis, sphere.vertices, sphere.faces)


def test_a_flat_sheet_is_refused_and_a_real_scan_is_not(basis):
    sheet = trimesh.creation.box(extents=(1.0, 1.0, 1e-3)).subdivide().subdivide().subdivide()
    with pytest.raises(InputError, match="the scan is flat"):
        multiscale.check_plausible_scan(basis, sheet.vertices, sheet.faces)
    u, faces = synthetic.resampled_sphere(2, seed=3)
    multiscale.check_plausible_scan(basis, 2.5 * u, faces)  # a sphere of another size: accepted


def test_faces_weighted_zero_do_not_count(basis):
    u, faces = synthetic.resampled_sphere(2, seed=3)
    weights = np.zeros(len(faces))
    weights[:10] = 1.0
    with pytest.raises(InputError, match="10 faces with area"):
        multiscale.check_plausible_scan(basis, u, faces, weights)
