"""Every workflow on a CUDA device gives what it gives on the CPU (skipped without a GPU): the solvers
move the optimiser's CPU variables to the basis' device (a geodesic once did not)."""

import numpy as np
import pytest
import torch

from bareesa import synthetic, workflows
from tests.solver.support import A, B

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def both(run, **options):
    """run(options) on the CPU and on CUDA."""
    return run(workflows.Options(device="cpu", **options)), run(workflows.Options(device="cuda", **options))


def test_interpolation_and_extrapolation_on_cuda_match_the_cpu(sphere):
    basis, _ = sphere
    a, b = workflows.KnownCode(A), workflows.KnownCode(B)
    cpu, gpu = both(lambda o: workflows.path_between(basis, a, b, 8, o))
    # solved in float32 (Options.path_dtype): the devices' sums round differently
    assert np.abs(gpu.frames - cpu.frames).max() < 2e-3 * np.abs(cpu.frames).max()
    assert gpu.distance == pytest.approx(cpu.distance, rel=1e-3)
    cpu, gpu = both(lambda o: workflows.extrapolate(basis, a, b, 3, o))
    assert np.abs(gpu.path - cpu.path).max() < 1e-4 * np.abs(cpu.path).max()


def test_registration_and_random_bodies_on_cuda_match_the_cpu(sphere):
    basis, surface = sphere
    u, faces = synthetic.resampled_sphere(1, seed=3)
    scan = workflows.Scan(surface(u, A), faces)
    # a sphere has no preferred orientation: registered as it lies
    cpu, gpu = both(lambda o: workflows.code_of(basis, scan, o), prealign=False)
    assert np.abs(cpu.code - A).max() < 0.1  # a coarse scan: near, not at, its code
    assert np.abs(gpu.code - cpu.code).max() < 1e-3
    cpu, gpu = both(lambda o: workflows.random_bodies(basis, 3, 11, o))
    assert np.isfinite(gpu.codes).all() and gpu.codes.shape == cpu.codes.shape
    assert np.abs(gpu.codes - cpu.codes).max() < 1e-4 * np.abs(cpu.codes).max()
