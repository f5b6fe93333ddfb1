"""Every exception a user can see: messages a user can act on (the CLI prints them without a traceback)."""


class BareEsaError(Exception):
    """Base class of every error the solver raises on purpose."""


class MeshError(BareEsaError, ValueError):
    """A mesh is unusable: empty, non-finite, bad indices, unreadable file..."""


class InputError(BareEsaError, ValueError):
    """An argument is inconsistent: wrong shapes, vertex counts, unknown names..."""


class SolveCancelled(BareEsaError):
    """A long solve was cancelled by its caller; no partial result is returned."""


class SolveDiverged(BareEsaError):
    """The objective of a solve became non-finite; it stops instead of returning NaNs."""


class ShootingFailed(BareEsaError):
    """A step of the initial value problem did not converge or produced non-finite values; ``frames``
    the codes (K, P) of the frames reached before it, when the shot got that far (else None); ``reached``
    what a workflow made of them (``workflows.extrapolate``: a Continuation), else None."""

    def __init__(self, message, frames=None):
        super().__init__(message)
        self.frames = frames
        self.reached = None


class FrameRejected(BareEsaError):
    """A frame of a shot was refused by the caller's check (``shooting.extrapolate(frame_check=)``); the
    shot stops there; ``frames`` the codes (K, P) of the frames before it (or None)."""

    def __init__(self, message, frames=None):
        super().__init__(message)
        self.frames = frames


class WorkersUnavailable(BareEsaError):
    """Worker processes could not be started (Dask missing or its local cluster failing)."""
