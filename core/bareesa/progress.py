"""Progress reporting and cancellation shared by every long solve.

One callback type serves the CLI (tqdm) and Blender (status bar): a callable
taking a ``ProgressEvent``. Cancellation is a ``CancelToken`` checked inside the
optimisation loop; a cancelled solve raises ``SolveCancelled`` and returns nothing.
"""

import threading
from dataclasses import dataclass

from .errors import SolveCancelled


@dataclass(frozen=True)
class ProgressEvent:
    """fraction in [0, 1] of the whole task, a short message, the current energy if any, and a
    preview of the result so far if the solver has one (a registration: {"code": (P,),
    "transform": Similarity}, plus "item": its index when several inputs are solved)."""

    task: str
    fraction: float
    message: str = ""
    energy: float | None = None
    preview: dict | None = None


class CancelToken:
    """Thread-safe cancellation flag: ``cancel()`` from any thread, ``check()`` in the solver."""

    def __init__(self):
        self._event = threading.Event()

    def cancel(self):
        self._event.set()

    @property
    def cancelled(self):
        return self._event.is_set()

    def check(self):
        """Raise SolveCancelled if cancellation was requested."""
        if self._event.is_set():
            raise SolveCancelled("the solve was cancelled; nothing was written")


class Monitor:
    """What a solver holds: a callback (or None) and a cancel token (or None)."""

    def __init__(self, task, callback=None, cancel=None):
        self.task, self.callback, self.cancel = task, callback, cancel

    def report(self, fraction, message="", energy=None, preview=None):
        if self.callback is not None:
            self.callback(ProgressEvent(self.task, min(max(float(fraction), 0.0), 1.0), message,
                                        None if energy is None else float(energy), preview))

    @property
    def wants_preview(self):
        """Whether anyone listens (a solver skips building previews otherwise)."""
        return self.callback is not None

    def check(self):
        if self.cancel is not None:
            self.cancel.check()

    def scaled(self, lo, hi, tag=None):
        """A callback for a sub-task that reports into [lo, hi] of this task (or None); ``tag`` (a dict)
        is merged into the sub-task's previews (e.g. which input they belong to)."""
        if self.callback is None:
            return None

        def forward(event):
            preview = event.preview if tag is None or event.preview is None else {**event.preview, **tag}
            self.report(lo + (hi - lo) * event.fraction, event.message, event.energy, preview)

        return forward


def tqdm_callback(desc, disable=None):
    """A progress callback drawing a tqdm bar (for the CLI); returns (callback, close)."""
    from tqdm import tqdm

    bar = tqdm(total=1000, desc=desc, disable=disable, leave=False,
               bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed} {postfix}")

    def callback(event):
        bar.n = int(event.fraction * 1000)
        bar.set_postfix_str(event.message, refresh=False)
        bar.refresh()

    return callback, bar.close
