"""numpy's and scipy's BLAS pools are held to one thread while the solver runs, and restored after."""

import threading

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from bareesa import geodesics, registration, shooting, synthetic, threads
from bareesa.errors import SolveCancelled
from bareesa.optimize import minimize_lbfgs
from bareesa.progress import CancelToken
from bareesa.threads import one_blas_thread
from tests.solver.support import small_basis


def blas_threads():
    """The thread counts of the BLAS libraries loaded in this process (numpy's, scipy's)."""
    return sorted({lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"})


@pytest.fixture
def two_blas_threads():
    """BLAS pools at two threads around the test (one-core machines included), so that one can be seen."""
    if not blas_threads():
        pytest.skip("no BLAS library that threadpoolctl can see is loaded")
    with threadpool_limits(limits=2, user_api="blas"):
        assert blas_threads() == [2]
        yield


def test_one_blas_thread_holds_the_pools_to_one_and_restores_them(two_blas_threads):
    with one_blas_thread():
        assert blas_threads() == [1]
    assert blas_threads() == [2]


def test_every_l_bfgs_evaluation_runs_with_one_blas_thread(two_blas_threads):
    seen = []

    def objective(x):
        seen.append(blas_threads())
        return ((x - 1.0) ** 2).sum()

    x, _, _ = minimize_lbfgs(objective, np.zeros(5))
    assert np.allclose(x, 1.0) and seen and all(s == [1] for s in seen)
    assert blas_threads() == [2]


def test_registration_geodesic_and_shooting_run_with_one_blas_thread_and_restore_it(two_blas_threads):
    seen = []
    record = lambda event: seen.append(blas_threads())  # noqa: E731
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    u, faces = synthetic.resampled_sphere(2, seed=3)
    scan = surface(u, 0.5 * np.random.default_rng(1).normal(size=6))
    registration.register(basis, scan, faces, backend="dense", callback=record)
    b = small_basis()
    t, f, h = b.tensors()
    a0, a1 = np.zeros(4), np.array([1.0, -0.5, 0.5, 0.5])
    geodesics.geodesic(t, f, h, a0, a1, b.weights, steps=4, callback=record)
    shooting.shoot(t, f, h, a0, a1, b.weights, steps=3, callback=record)
    assert len(seen) > 10 and all(s == [1] for s in seen)
    assert blas_threads() == [2]


def test_a_solve_cancelled_midway_restores_the_blas_pools(two_blas_threads):
    b = small_basis()
    t, f, h = b.tensors()
    token, seen = CancelToken(), []

    def cancel_at_first_report(event):
        seen.append(blas_threads())
        token.cancel()

    with pytest.raises(SolveCancelled):
        geodesics.geodesic(t, f, h, np.zeros(4), np.ones(4), b.weights, steps=4, callback=cancel_at_first_report,
                           cancel=token)
    assert seen and all(s == [1] for s in seen)
    assert blas_threads() == [2]


def test_solves_side_by_side_in_threads_share_the_limit_and_the_last_one_out_restores_it(monkeypatch):
    """As the add-on runs two jobs at once: the first solve out must not lift the limit under the other,
    and the last one out puts back what was there before the first came in. (Recorded on a stand-in for
    threadpoolctl: OpenBLAS stops reporting limits set from other threads once the main one has set one.)"""
    log = []

    class Limit:
        def __init__(self, limits, user_api):
            log.append(("set", limits, user_api))

        def restore_original_limits(self):
            log.append(("restored",))

    monkeypatch.setattr(threads, "threadpool_limits", Limit)
    first_in, second_in, first_out, second_done = (threading.Event() for _ in range(4))
    seen = {}

    def first():
        with one_blas_thread():
            first_in.set()
            second_in.wait(10)
        first_out.set()

    def second():
        first_in.wait(10)
        with one_blas_thread():
            second_in.set()
            first_out.wait(10)
            seen["log after the first left"] = list(log)
        second_done.set()

    workers = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in workers:
        t.start()
    for t in workers:
        t.join(20)
    assert second_done.is_set() and seen["log after the first left"] == [("set", 1, "blas")]
    assert log == [("set", 1, "blas"), ("restored",)]
    with one_blas_thread():  # and the next solve sets it again
        pass
    assert log[2:] == [("set", 1, "blas"), ("restored",)]


def test_a_solve_in_a_worker_thread_is_limited_also_after_one_on_the_main_thread(two_blas_threads):
    """As in Blender: a solve on the main thread (a script), then one in a job's thread, then one in a
    thread while another thread's solve is still inside; each sees one BLAS thread, and two after."""
    seen = {}

    def solve(tag):
        with one_blas_thread():
            seen[tag] = blas_threads()

    solve("main")
    worker = threading.Thread(target=solve, args=("worker",))
    worker.start()
    worker.join(20)
    assert blas_threads() == [2]
    inside, leave = threading.Event(), threading.Event()

    def long_solve():
        with one_blas_thread():
            inside.set()
            leave.wait(10)
            seen["long, after the other left"] = blas_threads()

    first = threading.Thread(target=long_solve)
    first.start()
    inside.wait(10)
    second = threading.Thread(target=solve, args=("beside it",))
    second.start()
    second.join(20)
    leave.set()
    first.join(20)
    assert seen == {"main": [1], "worker": [1], "beside it": [1], "long, after the other left": [1]}
    assert blas_threads() == [2]
