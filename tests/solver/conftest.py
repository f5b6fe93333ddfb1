"""Fixtures shared by the solver's tests (helpers and data: tests/solver/support.py)."""

import numpy as np
import pytest

from bareesa import synthetic
from bareesa.statistics import fit_distribution


@pytest.fixture(scope="module")
def sphere():
    """A 4-field smooth sphere basis with a fitted distribution, and its surface map."""
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=4, seed=0)
    rng = np.random.default_rng(0)
    basis.extras.update(fit_distribution(0.5 * rng.normal(size=(12, 4)), basis.groups,
                                         {g: 1 for g in basis.groups}, seed=0))
    return basis, surface
