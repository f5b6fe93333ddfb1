"""Register scans held in memory in local worker processes: the add-on's *Register Scans* with several
scans selected (``register_scans``).

A LocalCluster of single-threaded processes registers the scans; one progress bar is fed by the workers'
events (with the live preview); cancelling stops the processes; the results are returned, not written.
"""

import math
import os
import time

import numpy as np

from .. import errors, registration
from ..errors import BareEsaError, InputError
from ..progress import Monitor
from ..transforms import Similarity
from .cluster import distributed_module
from .vendored import SolverFunction, alias_solver, solver_preload

#: Topic of the progress events a worker sends to the client (``Worker.log_event``).
PROGRESS_TOPIC = "bareesa-progress"
#: A worker sends at most one progress event this often (seconds), and the last one.
PROGRESS_EVERY = 0.5
#: How often the client looks at finished scans, progress and cancellation (seconds).
POLL_EVERY = 0.2

_WORKER_BASES = {}


def _worker_basis(path):
    """The basis file at path, loaded once per worker process (again when the file changes)."""
    from ..basis_io import load_basis

    key = (str(path), os.stat(path).st_mtime_ns)
    if key not in _WORKER_BASES:
        _WORKER_BASES.clear()
        _WORKER_BASES[key] = load_basis(path)
    return _WORKER_BASES[key]


def plain_options(options):
    """``registration.register`` keyword arguments of a ``workflows.Options`` as plain values (no class of
    this package, so that a worker importing the solver under another name reads them): -> dict."""
    from dataclasses import asdict

    from ..h2_metric import H2Weights

    weights = options.weights.as_tuple() if isinstance(options.weights, H2Weights) else options.weights
    schedule = None if options.schedule is None else [asdict(lv) if not isinstance(lv, dict) else lv
                                                      for lv in options.schedule]
    return {"schedule": schedule, "prealign": bool(options.prealign), "metric": weights, "kernel": options.kernel,
            "dtype": options.dtype, "device": options.device, **dict(options.registration)}


def register_array(basis_path, scan, index, options, threads=1, progress_every=PROGRESS_EVERY):
    """Register one scan held in memory (run on a worker): scan {"verts" (M, 3), "faces" (G, 3),
    "face_weights" (G,) or None, "landmarks" or None}; index its place in the batch; options
    ``plain_options``: -> ``RegistrationResult.to_state()``, or {"error": one line, "kind": error class}.
    Sends progress to the client as ``PROGRESS_TOPIC`` events, at most one per ``progress_every`` seconds
    (and the last), each with the newest preview."""
    import torch

    torch.set_num_threads(threads)
    try:
        from distributed import get_worker
        worker = get_worker()
    except (ImportError, ValueError):
        worker = None
    sent, newest = [-math.inf], [None]

    def callback(event):
        if event.preview is not None:
            newest[0] = {"code": np.asarray(event.preview["code"], dtype=np.float64).tolist(),
                         "transform": event.preview["transform"].to_dict()}
        now = time.monotonic()
        if worker is None or (now - sent[0] < progress_every and event.fraction < 1.0):
            return
        sent[0] = now
        message = {"item": index, "fraction": float(event.fraction), "message": event.message}
        if newest[0] is not None:
            message["preview"], newest[0] = newest[0], None
        worker.log_event(PROGRESS_TOPIC, message)

    try:
        res = registration.register(_worker_basis(basis_path), scan["verts"], scan["faces"],
                                    scan_face_weights=scan.get("face_weights"), landmarks=scan.get("landmarks"),
                                    callback=callback, **options)
    except BareEsaError as err:
        return {"error": str(err).splitlines()[0] if str(err) else type(err).__name__, "kind": type(err).__name__}
    return res.to_state()


def register_scans(basis, scans, options, *, workers=2, callback=None, cancel=None, progress_every=PROGRESS_EVERY):
    """Register scans held in memory on a LocalCluster of ``workers`` single-threaded processes (at most one
    per scan): -> list, in input order, of a ``RegistrationResult`` or, for a scan that failed, the
    ``BareEsaError`` it raised (the others are still registered).

    basis: a bundled name or .npz path (each worker loads it once); scans: objects with verts, faces,
    face_weights and landmarks (``workflows.Scan``); options: a ``workflows.Options``. callback gets one
    progress bar over all the scans (the mean of their fractions) and each scan's preview
    ({"code", "transform", "item"}); cancel (a CancelToken) stops the processes at once and raises
    SolveCancelled; progress_every: seconds between two events a worker sends. Raises WorkersUnavailable
    when Dask is not installed or its local cluster does not start.
    """
    from ..basis_io import resolve_basis_path

    if not scans:
        return []
    try:
        distributed = distributed_module()
    except InputError as err:
        raise errors.WorkersUnavailable(str(err)) from None
    basis_path = str(resolve_basis_path(basis))
    if workers < 1:
        raise InputError(f"workers must be at least 1, got {workers}")
    monitor = Monitor("register", callback, cancel)
    plain = plain_options(options)
    fractions, previews, messages = [0.0] * len(scans), {}, {}

    def on_event(event):  # the client's event loop thread: only store, the loop below reports
        message = event[1]
        k = message["item"]
        fractions[k] = max(fractions[k], message["fraction"])
        messages[k] = message["message"]
        if "preview" in message:
            previews[k] = message["preview"]

    n_workers = min(workers, len(scans))
    monitor.report(0.0, f"starting {n_workers} worker processes")
    alias_solver()
    try:
        cluster = distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                           host="127.0.0.1", dashboard_address=None, preload=solver_preload())
        client = distributed.Client(cluster)
    except Exception as err:  # noqa: BLE001 - the caller can register in its own process instead
        raise errors.WorkersUnavailable(f"could not start {n_workers} worker processes ({type(err).__name__}: "
                                        f"{err})".splitlines()[0]) from err
    try:
        client.subscribe_topic(PROGRESS_TOPIC, on_event)
        task = SolverFunction("register_array")
        futures = [client.submit(task, basis_path, {"verts": np.asarray(s.verts), "faces": np.asarray(s.faces),
                                                    "face_weights": s.face_weights, "landmarks": s.landmarks},
                                 k, plain, 1, progress_every, key=f"bareesa-scan-{k}-{time.time_ns()}", pure=False)
                   for k, s in enumerate(scans)]
        results = [None] * len(scans)
        while any(r is None for r in results):
            monitor.check()
            for k, fut in enumerate(futures):
                if results[k] is None and fut.done():
                    try:
                        state = fut.result()
                    except Exception as err:  # noqa: BLE001 - e.g. a worker killed: this scan fails, not the others
                        state = {"error": f"{type(err).__name__}: {err}".splitlines()[0], "kind": "BareEsaError"}
                    if "error" in state:
                        kind = getattr(errors, state["kind"], BareEsaError)
                        kind = kind if isinstance(kind, type) and issubclass(kind, BareEsaError) else BareEsaError
                        results[k] = kind(f"scan {k + 1}: {state['error']}")
                    else:
                        results[k] = registration.RegistrationResult.from_state(state)
                    fractions[k] = 1.0
            done = sum(r is not None for r in results)
            for k, preview in list(previews.items()):
                if results[k] is None:
                    monitor.report(sum(fractions) / len(scans), messages.get(k, ""),
                                   preview={"code": np.asarray(preview["code"]),
                                            "transform": Similarity.from_dict(preview["transform"]), "item": k})
            previews.clear()
            monitor.report(sum(fractions) / len(scans), f"{done} of {len(scans)} scans registered")
            if done < len(scans):
                time.sleep(POLL_EVERY)
        return results
    finally:
        client.close()
        cluster.close()
