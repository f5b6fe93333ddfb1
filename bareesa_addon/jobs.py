"""Long solves off the main thread, with progress in the status bar and Esc to cancel.

An operator splits its work in three: ``prepare`` (main thread: read bpy data into
arrays, validate), ``solve(callback, cancel)`` (any thread: only arrays and the
core, never bpy) and ``apply`` (main thread: write the results). ``SolveOperator``
runs ``solve`` in a thread polled by a modal timer when invoked from the
interface, and synchronously from scripts and in background mode. Nothing is
written before ``solve`` succeeds, so a cancelled or failed solve leaves the
scene exactly as it was; the result is one undo step (pushed after the apply when it ran
from the modal timer).
"""

import sys
import threading
import traceback
from dataclasses import dataclass
from typing import Callable

import bpy

from . import solver
from .convert import ConversionError

#: Jobs running now (the panel draws their progress).
RUNNING = []


@dataclass
class Task:
    """What an operator prepared: a title, the solve (thread-safe, no bpy) and how to apply its result."""

    title: str
    solve: Callable  # solve(callback, cancel) -> result
    apply: Callable  # apply(context, result) -> message for the info report
    #: live preview while the solve runs from the interface: show(context, preview dict) on the main
    #: thread for the newest preview of a progress event; clear(context) removes what show made (before
    #: apply, or when the solve fails or is cancelled). None: no preview.
    show: Callable | None = None
    clear: Callable | None = None


def new_token():
    """A fresh cancellation token (tests replace this to simulate Esc)."""
    return solver.module("progress").CancelToken()


class Job:
    """One solve: ``start()`` runs it in a thread, ``run()`` in this one; ``cancel()`` from anywhere."""

    def __init__(self, title, solve, echo=False):
        self.title, self._solve, self.echo = title, solve, echo
        self.token = new_token()
        self.fraction, self.message = 0.0, title
        self.result = self.error = None
        self._thread = None
        self._printed = -1.0
        self.previews = {}  # newest preview per input ("item"), handed from the solve's thread
        self.previews_version = 0

    def _callback(self, event):
        self.fraction, self.message = float(event.fraction), event.message or self.title
        preview = getattr(event, "preview", None)
        if preview is not None:
            self.previews = {**self.previews, preview.get("item", 0): preview}  # a new dict: one atomic swap
            self.previews_version += 1
        if self.echo and (self.fraction - self._printed >= 0.1 or self.fraction >= 1.0 > self._printed):
            self._printed = self.fraction
            print(f"BaRe-ESA: {self.title}: {self.fraction:4.0%} {event.message}", flush=True)

    def run(self):
        """Run the solve here; the outcome is in ``result`` or ``error``."""
        try:
            self.result = self._solve(self._callback, self.token)
        except BaseException as err:  # noqa: BLE001 - handed to the main thread as is
            self.error = err

    def start(self):
        self._thread = threading.Thread(target=self.run, name=f"bareesa: {self.title}", daemon=True)
        self._thread.start()

    @property
    def done(self):
        return self._thread is None or not self._thread.is_alive()

    def cancel(self):
        self.token.cancel()

    def wait(self, timeout=None):
        if self._thread is not None:
            self._thread.join(timeout)


def is_user_error(err):
    """True for errors whose message is meant for the user (bad input, missing dependency, solver refusal)."""
    if isinstance(err, (ConversionError, solver.DependencyError)):
        return True
    try:
        return isinstance(err, solver.module("errors").BareEsaError)
    except solver.DependencyError:
        return False


def push_undo(message):
    """One undo step for what a background job's apply wrote (the modal timer's apply is not one by itself).

    bpy as a Python module (headless, no window) has no undo stack (no ``bpy.ed``): nothing to push.
    """
    ed = getattr(bpy, "ed", None)
    if ed is not None:
        ed.undo_push(message=message)


def _status(context, text):
    workspace = getattr(context, "workspace", None)
    if workspace is not None:
        workspace.status_text_set(text)


class SolveOperator:
    """Mixin for operators whose work is a solve: subclasses implement ``prepare(context) -> Task``."""

    bl_options = {"REGISTER", "UNDO"}

    def prepare(self, context):  # pragma: no cover - abstract
        raise NotImplementedError

    def _prepare(self, context):
        try:
            return self.prepare(context)
        except Exception as err:
            if not is_user_error(err):
                raise
            self.report({"ERROR"}, str(err))
            return None

    def execute(self, context):
        task = self._prepare(context)
        if task is None:
            return {"CANCELLED"}
        job = Job(task.title, task.solve, echo=bpy.app.background)
        job.run()
        return self._finish(context, task, job)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        task = self._prepare(context)
        if task is None:
            return {"CANCELLED"}
        self._task, self._job = task, Job(task.title, task.solve)
        self._shown = 0
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, 100)
        RUNNING.append(self._job)
        self._job.start()
        _status(context, f"BaRe-ESA: {task.title}... (Esc to cancel)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            _status(context, f"BaRe-ESA: cancelling {job.title}...")
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}  # the interface stays usable while the solve runs
        context.window_manager.progress_update(int(100 * job.fraction))
        if not job.done and self._task.show is not None and job.previews_version != self._shown:
            self._shown = job.previews_version
            try:
                for preview in job.previews.values():
                    self._task.show(context, preview)
            except Exception as err:  # a preview must never stop the solve
                print(f"BaRe-ESA: preview failed: {type(err).__name__}: {err}", file=sys.stderr)
        if not job.done:
            _status(context, f"BaRe-ESA: {job.message} {job.fraction:.0%} (Esc to cancel)")
            for area in context.screen.areas if context.screen else ():
                if area.type == "VIEW_3D":
                    area.tag_redraw()
            return {"RUNNING_MODAL"}
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        _status(context, None)
        if job in RUNNING:
            RUNNING.remove(job)
        outcome = self._finish(context, self._task, job)
        if outcome == {"FINISHED"}:
            push_undo(f"BaRe-ESA: {self._task.title}")
        return outcome

    def _finish(self, context, task, job):
        if task.clear is not None:
            task.clear(context)
        err = job.error
        if err is not None:
            if type(err).__name__ == "SolveCancelled":
                self.report({"WARNING"}, f"{task.title}: cancelled; nothing was changed")
            elif is_user_error(err):
                self.report({"ERROR"}, f"{task.title}: {err}")
            else:
                traceback.print_exception(type(err), err, err.__traceback__, file=sys.stderr)
                self.report({"ERROR"}, f"{task.title} failed: {type(err).__name__}: {err}")
            return {"CANCELLED"}
        try:
            message = task.apply(context, job.result)
        except Exception as err:
            if not is_user_error(err):
                raise
            self.report({"ERROR"}, f"{task.title}: {err}")
            return {"CANCELLED"}
        self.report({"INFO"}, message)
        return {"FINISHED"}

