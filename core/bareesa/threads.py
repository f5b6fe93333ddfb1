r"""Thread pools during a solve: numpy's and scipy's BLAS held to one thread (``one_blas_thread``).

torch runs a solve's heavy work (varifold sums, path energies) on its own thread pool. numpy and scipy
bring their own OpenBLAS, each with a pool whose threads spin for a while after every call (scipy's
L-BFGS-B makes a few per iteration), on the very cores torch's threads then wait for: a registration
ran about twice as long so (docs/decisions/011-blas-pools-one-thread.md). The solver's own numpy linear
algebra is small (140 x 140 and below), so one thread costs it nothing. threadpoolctl sets and restores
the limits; torch's pool (its OpenMP runtime, the MKL inside it) is not touched.
"""

import threading
from contextlib import contextmanager
from functools import wraps

from threadpoolctl import OpenBLASController, threadpool_limits

#: The BLAS limit is the process's, and the add-on runs solves in threads side by side: the first solve
#: in sets it, the last one out restores what was there before it (``_held`` counts the solves inside).
_lock = threading.Lock()
_held = {"depth": 0, "limiter": None}


def _free_openblas():
    """Let any thread set OpenBLAS' limits next: threadpoolctl lets only the thread that set one last
    (until it leaves a ``with threadpool_limits``), and a limit set and restored outside a ``with`` kept the
    main thread in control, so that a worker thread's later limit did nothing
    (``test_a_solve_in_a_worker_thread_is_limited_also_after_one_on_the_main_thread``)."""
    OpenBLASController.clear_controlling_thread(force=True)


@contextmanager
def one_blas_thread():
    """Context manager: numpy's and scipy's BLAS libraries on one thread inside, as before after the last
    solve (of any thread) inside has left; nested and concurrent uses share one limit."""
    with _lock:
        if _held["depth"] == 0:
            _free_openblas()
            _held["limiter"] = threadpool_limits(limits=1, user_api="blas")
            _free_openblas()
        _held["depth"] += 1
    try:
        yield
    finally:
        with _lock:
            _held["depth"] -= 1
            if _held["depth"] == 0:
                _free_openblas()
                _held["limiter"].restore_original_limits()
                _held["limiter"] = None
                _free_openblas()


def with_one_blas_thread(func):
    """Decorator: ``func`` runs inside ``one_blas_thread``."""
    @wraps(func)
    def run(*args, **kwargs):
        with one_blas_thread():
            return func(*args, **kwargs)
    return run
