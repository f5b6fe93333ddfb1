"""L-BFGS wrapper: plateau stopping, divergence and cancellation."""

import numpy as np
import pytest
import torch

from bareesa.errors import SolveCancelled
from bareesa.errors import SolveDiverged
from bareesa.optimize import minimize_lbfgs
from bareesa.progress import CancelToken, Monitor


def rosenbrock(x):
    return ((1 - x[:-1]) ** 2).sum() + 100 * ((x[1:] - x[:-1] ** 2) ** 2).sum()


def test_plateau_stops_a_slow_tail_early_close_to_the_full_solve():
    # like a registration objective, it levels off at a non-zero value (1 here) after a slow valley
    objective = lambda x: 1.0 + rosenbrock(x)  # noqa: E731
    x0 = np.full(8, -1.2)
    _, full_value, full_it = minimize_lbfgs(objective, x0, max_iter=500)
    _, value, it = minimize_lbfgs(objective, x0, max_iter=500, plateau=(5, 1e-2))
    assert it < full_it
    start = float(objective(torch.from_numpy(x0)))
    assert full_value - 1e-12 <= value < 1.0 + 0.01 * (start - 1.0)  # 99 % of the decrease


def test_plateau_does_not_stop_a_steady_decrease():
    # a well-conditioned quadratic decreases steadily: the plateau rule must not cut it short
    target = np.linspace(-1.0, 1.0, 10)
    quadratic = lambda x: ((x - torch.from_numpy(target)) ** 2 * torch.linspace(1, 3, 10, dtype=x.dtype)).sum()  # noqa: E731
    x, value, _ = minimize_lbfgs(quadratic, np.zeros(10), max_iter=200, plateau=(5, 1e-3))
    assert np.allclose(x, target, atol=1e-6) and value < 1e-10


def test_stall_ends_line_searches_lost_in_rounding_noise_and_keeps_the_best_point():
    # like a float32 energy near its minimum: the value carries noise (1e-3) its gradient does not see
    target = torch.linspace(-1.0, 1.0, 20, dtype=torch.float64)
    scales = torch.linspace(1.0, 50.0, 20, dtype=torch.float64)
    values = []

    def noisy(x):
        value = 10.0 + ((x - target) ** 2 * scales).sum() + 1e-3 * torch.sin(1e7 * x.detach().sum())
        values[-1].append(float(value.detach()))
        return value

    results = []
    for stall in (None, 10):
        values.append([])
        results.append(minimize_lbfgs(noisy, np.zeros(20), max_iter=300, plateau=(5, 1e-9), stall=stall))
    (_, value_free, _), (x, value, _) = results
    # evaluations spent once the value is within the noise of the end (81 -> 42 evaluations in all,
    # 62 -> 23 of them lost, with scipy 1.17)
    lost = [len(v) - int(np.argmax(np.asarray(v) <= value_free + 2e-3)) for v in values]
    assert lost[1] < lost[0] / 2 and len(values[1]) < len(values[0])
    assert value <= value_free + 2e-3  # as low as the free solve, to the noise
    assert np.abs(x - target.numpy()).max() < 0.01


def test_a_longer_memory_solves_an_ill_conditioned_quadratic_in_fewer_iterations():
    # 40 curvatures spread over 1e4: with as many past steps as dimensions L-BFGS keeps what it learnt
    # of every scale (644 iterations to 1e-26 here); with 3 it keeps relearning them (1880)
    scales = torch.logspace(0, 4, 40, dtype=torch.float64)
    x0 = np.ones(40)
    iterations = {}
    for memory in (3, 40):
        x, value, iterations[memory] = minimize_lbfgs(lambda x: (scales * x ** 2).sum(), x0, max_iter=2000,
                                                      gtol=1e-12, ftol=1e-30, memory=memory)
        assert value < 1e-10
    assert iterations[40] < 0.6 * iterations[3]


def test_non_finite_objective_raises_solve_diverged():
    with pytest.raises(SolveDiverged):
        minimize_lbfgs(lambda x: (x**2).sum() / (x**2).sum().detach() * float("nan"), np.ones(3))


def test_cancel_token_stops_the_solve():
    token = CancelToken()
    token.cancel()
    with pytest.raises(SolveCancelled):
        minimize_lbfgs(rosenbrock, np.zeros(4), Monitor("test", None, token))
