"""Tests of bareesa.transforms' axis-angle rotations (Rodrigues' formula and its derivative)."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from bareesa import transforms
from bareesa.transforms import axis_angle_rotation


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.09, 0.1, 0.11, 0.5, 2.0, 3.1, 6.0])
def test_axis_angle_rotation_is_scipys_rotation_with_matrix_exps_gradient(angle):
    """The rotation of w matches scipy's from_rotvec to rounding on both sides of the series' threshold
    (SMALL_ANGLE_SQ = 0.01: angle 0.1), and its gradient matches autograd through torch's matrix_exp."""
    rng = np.random.default_rng(int(angle * 1000))
    weights = torch.tensor(rng.normal(size=(3, 3)))
    for _ in range(5):
        axis = rng.normal(size=3)
        w = angle * axis / np.linalg.norm(axis)
        assert np.abs(axis_angle_rotation(w) - Rotation.from_rotvec(w).as_matrix()).max() < 1e-15
        wt = torch.tensor(w, requires_grad=True)
        got = torch.autograd.grad((axis_angle_rotation(wt) * weights).sum(), wt)[0]
        want = torch.autograd.grad((transforms._exp_skew(wt) * weights).sum(), wt)[0]
        assert torch.allclose(got, want, rtol=0, atol=1e-13)


def test_axis_angle_rotation_has_first_and_second_derivatives_in_its_dtype():
    w = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_rotation, (w,))
    assert torch.autograd.gradgradcheck(axis_angle_rotation, (w,))
    zero = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_rotation, (zero,))  # exact and smooth at 0
    assert axis_angle_rotation(torch.zeros(3, dtype=torch.float32)).dtype == torch.float32
    assert axis_angle_rotation(np.zeros(3)).dtype == np.float64
