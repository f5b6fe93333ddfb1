"""Register scan files on Dask's distributed scheduler, resumably: ``register_batch``.

It runs on a ``LocalCluster`` (one worker process per core asked for) or on an existing scheduler given
by address. The basis is scattered to the workers once; each worker reads its scan by path (a
multi-machine cluster needs the scans at the same path on every machine); the client alone writes the
outputs (``records``), as each scan finishes. Ctrl-C cancels what is left and keeps what finished.
"""

import json
import math
import time
from pathlib import Path

import numpy as np

from ..basis_io import resolve_basis_path
from ..errors import InputError, SolveCancelled
from ..progress import Monitor
from .frames import chain_frame, chunks_of, seam_jumps
from .records import (RECORD_VERSION, BatchReport, file_hash, input_hash, is_finished, output_names, read_record,
                      save_mesh_atomic, summary_row, write_atomic, write_summary)

MISSING_DASK = "install the batch extra: pip install 'bareesa[batch]' (Dask's distributed scheduler)"


def distributed_module():
    """The ``distributed`` module, or InputError saying how to install it."""
    try:
        import distributed
    except ImportError:
        raise InputError(MISSING_DASK) from None
    return distributed


def _open_client(scheduler, workers, threads_per_worker, client):
    """(client, close) for an existing client, a scheduler address, or a new LocalCluster on loopback."""
    if client is not None:
        return client, lambda: None
    distributed = distributed_module()
    if scheduler is not None:
        try:
            c = distributed.Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as err:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler} ({err}); start it with "
                             "'dask scheduler' and check the address") from None
        return c, c.close
    if workers < 1 or threads_per_worker < 1:
        raise InputError(f"--workers and --threads-per-worker must be at least 1, got {workers}, "
                         f"{threads_per_worker}")
    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=threads_per_worker, processes=True,
                                       host="127.0.0.1", dashboard_address="127.0.0.1:0")
    c = distributed.Client(cluster)

    def close():
        c.close()
        cluster.close()

    return c, close


def _dashboard(client):
    """The dashboard's address when the scheduler runs one (it needs bokeh), else None."""
    try:
        if "dashboard" in client.scheduler_info().get("services", {}):
            return client.dashboard_link
    except Exception:  # noqa: BLE001 - the dashboard is only reported, never needed
        return None
    return None


def register_batch(basis, scans, output, *, workers=2, threads_per_worker=1, scheduler=None, client=None,
                   sequence=False, chunk=None, options=None, progress=False, log=None, callback=None, cancel=None):
    """Register scan files onto a basis on a Dask cluster, resumably: -> BatchReport.

    basis: bundled name or .npz path (its file's sha256 goes in every record); scans: mesh paths (the
    frames of one capture, in order, with sequence=True); output: folder of NAME.ply, NAME.json and the
    summary; workers, threads_per_worker: of the LocalCluster started when neither scheduler (a Dask
    scheduler address) nor client (a ``distributed.Client``) is given; chunk: frames per parallel chunk
    in sequence mode (default: the frames shared evenly over the workers); options: keyword arguments of
    ``registration.register`` (schedule, metric, dtype...); progress: draw a tqdm bar; log: a print-like
    function for the dashboard address; callback, cancel: a ``bareesa.progress`` callback (fraction of scans
    done) and CancelToken (checked as each scan finishes).
    Raises InputError (no scans, missing files, Dask not installed); KeyboardInterrupt (Ctrl-C) or
    SolveCancelled after cancelling the pending scans and writing the summary of what finished.
    """
    from ..basis_io import load_basis

    start = time.perf_counter()
    scans = [Path(s).resolve() for s in scans]
    if not scans:
        raise InputError("no scans given: name scan files or a --list file")
    missing = [str(s) for s in scans if not s.is_file()]
    if missing:
        raise InputError(f"{len(missing)} scan file(s) do not exist, e.g. {missing[0]}")
    if options and {"prealign", "init_code", "refine_transform", "pose_candidates"} & set(options) and sequence:
        raise InputError("sequence mode sets prealign, init_code, refine_transform and pose_candidates itself")
    basis_path = resolve_basis_path(basis)
    basis_hash = file_hash(basis_path)
    loaded = load_basis(basis_path)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    names = output_names(scans)
    meshes = [output / f"{n}.ply" for n in names]
    records = [output / f"{n}.json" for n in names]
    input_hashes = [input_hash(s) for s in scans]
    monitor = Monitor("register-batch", callback, cancel)
    meta = {"version": RECORD_VERSION, "basis": str(basis_path), "basis_hash": basis_hash, "sequence": bool(sequence),
            "names": names}

    client_, close = _open_client(scheduler, workers, threads_per_worker, client)
    n_slots = max(1, sum(w.get("nthreads", 1) for w in client_.scheduler_info().get("workers", {}).values()))
    if sequence:
        chunk = chunk or math.ceil(len(scans) / n_slots)
        chunks = chunks_of(len(scans), chunk)
        meta["chunk"] = chunk
    else:
        chunks = [(k, k + 1) for k in range(len(scans))]
    warm = [None if k in {lo for lo, _ in chunks} else names[k - 1] for k in range(len(scans))]
    # what is finished already; in a sequence, every frame after one that runs again runs again
    done = [None] * len(scans)
    for lo, hi in chunks:
        for k in range(lo, hi):
            rec = read_record(records[k])
            if not is_finished(rec, input_hashes[k], basis_hash, warm[k], meshes[k]):
                break
            done[k] = rec
    rows = [summary_row(k, n, done[k]) for k, n in enumerate(names)]
    for k in range(len(scans)):
        if done[k] is not None:
            rows[k]["status"] = "skipped"
    report = BatchReport(rows=rows, output=output, dashboard=_dashboard(client_))
    if report.dashboard and log is not None:
        log(f"Dask dashboard: {report.dashboard}")

    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(scans), desc="register-batch", unit="scan", initial=sum(d is not None for d in done))
    futures = {}
    counts = {"ok": 0, "failed": 0, "skipped": sum(d is not None for d in done)}
    try:
        threads = threads_per_worker
        remote_basis = client_.scatter(loaded, broadcast=True, hash=False)  # a key of its own per batch
        opts = dict(options or {})
        for lo, hi in chunks:
            previous = None
            for k in range(lo, hi):
                if done[k] is not None:
                    previous = {key: done[k][key] for key in ("name", "status", "code", "transform")}
                    continue
                fut = client_.submit(chain_frame, remote_basis, str(scans[k]), names[k],
                                     previous if sequence else None, threads, opts, key=f"bareesa-{names[k]}-"
                                     f"{input_hashes[k][:12]}-{time.time_ns()}", pure=False)
                futures[fut] = k
                previous = fut
        distributed = distributed_module()
        finished = counts["skipped"]
        for fut in distributed.as_completed(list(futures)):
            k = futures[fut]
            try:
                rec = fut.result()
            except Exception as err:  # noqa: BLE001 - a bug on one scan is recorded; the batch goes on
                rec = {"status": "failed", "error": f"{type(err).__name__}: {err}".splitlines()[0],
                       "scan": str(scans[k]), "input_hash": input_hashes[k], "warm_start": warm[k]}
            vertices, layer = rec.pop("vertices", None), rec.pop("detail_layer", None)
            rec.update(version=RECORD_VERSION, name=names[k], index=k, basis=str(basis_path), basis_hash=basis_hash)
            if rec["status"] == "ok":
                save_mesh_atomic(meshes[k], vertices, loaded.faces)
                rec["mesh"] = meshes[k].name
                if layer is not None:  # the detail layer (template frame) beside the detailed mesh
                    layer_path = meshes[k].with_suffix(".detail.npy")
                    np.save(layer_path, layer)
                    rec["detail_layer"] = layer_path.name
            write_atomic(records[k], json.dumps(rec, indent=2))
            rows[k] = summary_row(k, names[k], rec)
            counts[rec["status"]] += 1
            finished += 1
            monitor.report(finished / len(scans), f"{names[k]}: {rec['status']}")
            monitor.check()
            if bar is not None:
                running = min(n_slots, sum(len(v) for v in client_.processing().values()))
                bar.set_postfix_str(f"ok {counts['ok']}, failed {counts['failed']}, running {running}", refresh=False)
                bar.update(1)
    except (KeyboardInterrupt, SolveCancelled):
        report.interrupted = True
        client_.cancel([f for f in futures if not f.done()])
        raise
    finally:
        if bar is not None:
            bar.close()
        close()
        counts["pending"] = sum(r["status"] == "pending" for r in rows)
        report.counts, report.seconds = counts, time.perf_counter() - start
        if sequence and not report.interrupted:
            report.seams = seam_jumps(chunks, names, meshes, rows)
        write_summary(output, report, meta)
    return report
