"""The background-solve machinery: a thread polled by a modal timer, progress, Esc cancels, apply on the main thread.

Headless Blender has no window to run a modal operator in, so the operator mixin is
driven here with a stand-in context and events, exactly as the window manager would.
"""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from tests.addon.support import bpy, drive, fake_context, make_operator


@pytest.fixture
def interactive(monkeypatch):
    """Pretend Blender runs with a window (the operator then goes modal)."""
    from bareesa_addon import jobs

    monkeypatch.setattr(jobs, "bpy", SimpleNamespace(app=SimpleNamespace(background=False)))


def test_modal_solve_runs_in_a_thread_reports_progress_and_applies_on_main_thread(interactive, tiny):
    from bareesa.geodesics import geodesic

    basis = tiny[0]
    threads = []

    def solve(callback, cancel):
        threads.append(threading.current_thread() is threading.main_thread())
        g = geodesic(*basis.tensors(), np.zeros(4), np.array([0.5, -0.5, 0.3, 0.2]), basis.weights, steps=5,
                     callback=callback, cancel=cancel)
        return round(g.distance, 6)

    applied = []
    op, context = make_operator(solve, applied), fake_context()
    assert op.invoke(context, None) == {"RUNNING_MODAL"}
    assert context.window_manager.handlers == [op]
    assert op.modal(context, SimpleNamespace(type="MOUSEMOVE", value="NOTHING")) == {"PASS_THROUGH"}
    assert drive(op, context) == {"FINISHED"}
    assert threads == [False]  # the solve ran off the main thread
    assert len(applied) == 1 and applied[0][1] and applied[0][0] > 0
    wm = context.window_manager
    assert wm.progress[0] == "begin" and wm.progress[-1] == "end" and wm.timers == 0
    assert context.workspace.status[-1] is None  # status bar restored
    assert op.reports[-1][0] == {"INFO"}


def test_escape_cancels_the_solve_and_nothing_is_applied(interactive):
    started = threading.Event()

    def solve(callback, cancel):
        started.set()
        while True:
            cancel.check()
            time.sleep(0.01)

    applied = []
    op, context = make_operator(solve, applied), fake_context()
    assert op.invoke(context, None) == {"RUNNING_MODAL"}
    started.wait(5)
    assert drive(op, context, events=["ESC"]) == {"CANCELLED"}
    assert applied == []
    assert op.reports[-1][0] == {"WARNING"} and "cancelled" in op.reports[-1][1]
    from bareesa_addon import jobs

    assert jobs.RUNNING == []


def test_failed_solve_reports_the_error_and_applies_nothing(interactive):
    from bareesa.errors import InputError

    def solve(callback, cancel):
        raise InputError("the scan has no faces")

    applied = []
    op, context = make_operator(solve, applied), fake_context()
    op.invoke(context, None)
    assert drive(op, context) == {"CANCELLED"}
    assert applied == [] and op.reports[-1] == ({"ERROR"}, "test solve: the scan has no faces")


def test_background_mode_runs_the_solve_synchronously():
    applied = []
    op = make_operator(lambda callback, cancel: 42, applied)
    assert bpy.app.background
    assert op.invoke(SimpleNamespace(window=None), None) == {"FINISHED"}
    assert applied == [(42, True)]


def test_scaled_callback_maps_sub_task_progress_into_its_share():
    from bareesa.progress import Monitor, ProgressEvent

    scaled_callback = lambda callback, lo, hi: Monitor("register", callback).scaled(lo, hi)  # noqa: E731

    seen = []
    inner = scaled_callback(seen.append, 0.5, 0.75)
    inner(ProgressEvent("register", 0.5, "half"))
    assert seen[0].fraction == pytest.approx(0.625) and seen[0].message == "half"
    assert scaled_callback(None, 0, 1) is None


def test_install_dependencies_command_targets_the_extension_directory_and_keeps_numpy(tmp_path):
    import numpy
    import sys

    from bareesa_addon.preferences import TORCH_CPU_INDEX, pip_commands

    commands, constraints, pins = pip_commands(tmp_path, ["torch", "sklearn", "pykeops"])
    assert all(c[:4] == [sys.executable, "-m", "pip", "install"] for c in commands)
    assert all(str(tmp_path) in c and str(constraints) in c for c in commands)
    assert commands[0][-1] == "torch" and TORCH_CPU_INDEX in commands[0]
    assert "scikit-learn" in commands[1] and "pykeops" in commands[1]
    assert pins == f"numpy=={numpy.__version__}\n"
    assert pip_commands(tmp_path, [])[0] == []
