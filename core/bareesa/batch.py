"""Register many scans on a Dask ``distributed`` cluster: a registered mesh and a JSON record per scan.

``register_batch`` runs ``registration.register`` on a ``LocalCluster`` (one single-threaded worker
process per core asked for) or on an existing scheduler given by address. The basis is scattered to
the workers once; each worker reads its scan by path (a multi-machine cluster needs the scans at
the same path on every machine; outputs are written by the client only). As each scan finishes the
client writes, atomically, ``NAME.ply`` (the registered template in the scan's frame) and
``NAME.json`` (code, alignment, varifold / Chamfer / fit residuals, seconds, worker, input and basis
hashes), and at the end the summary table ``summary.csv`` / ``summary.json``. A scan's ignore mask and
landmarks are files next to it (``SIDECARS``: ``SCAN.ignore.npy`` or ``.txt``, ``SCAN.landmarks.json``
or ``.csv``, the formats of ``bareesa.masks`` and ``bareesa.landmarks``). A rerun skips the scans whose
record matches the input's (mesh and sidecar files) and the basis' sha256; a scan that fails (a ``BareEsaError``)
is recorded with its one-line error and the others go on; Ctrl-C cancels what is left and keeps
what finished.

With ``sequence=True`` the scans are the frames of one 4D capture, in order, cut into chunks that
run in parallel: a chunk's first frame is registered fully, each further frame starts from the
previous frame's code and alignment (the scan mapped by the previous transform, no pre-alignment,
no pose candidates, at most the schedule's WARM_LEVELS finest levels: ``warm_schedule``). The seams
between chunks are checked for jumps against the median frame-to-frame motion.
``register_scans`` is the same on scans in memory (the add-on's *Register Scans* with several
selected): a LocalCluster of single-threaded processes, one progress bar fed by the workers'
events (with the live preview), cancellation that stops the processes, and the results returned,
not written. The workers import the solver as ``bareesa`` from its own folder, so a copy vendored
inside another package (the Blender extension) runs on them as well.
Dask is an optional dependency (``pip install 'bareesa[batch]'``), imported only when a batch runs.
"""

import csv
import hashlib
import importlib
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import registration
from .basis_io import resolve_basis_path
from . import errors
from .errors import BareEsaError, InputError, SolveCancelled
from .evaluation import chamfer
from .landmarks import read_scan_landmarks
from .masks import read_face_weights
from .mesh import load_mesh, save_mesh, validate_mesh
from .progress import Monitor
from .transforms import Similarity

SUMMARY_JSON = "summary.json"
SUMMARY_CSV = "summary.csv"
RECORD_VERSION = 1
#: A seam whose vertex jump is above this many times the median frame-to-frame motion is flagged.
SEAM_FACTOR = 3.0
#: A warm-started frame of a sequence skips the schedule's coarsest level (the previous frame gives the far
#: pose it finds) and runs at most this many of its finest levels. On a human capture the finest level alone
#: took twice as long as the two finest from the previous code (3 levels); with the 4-level schedule the two
#: finest took 24 s a frame against 31 s for the three finest, at the same error (bench/README).
WARM_LEVELS = 2
#: Columns of summary.csv, in order.
SUMMARY_COLUMNS = ("index", "name", "scan", "status", "varifold", "chamfer", "residual", "poor_fit", "iterations",
                   "seconds", "worker", "warm_start", "mesh", "seam_jump", "seam_flagged", "error")
#: Files next to a scan (its stem + one of these) that a batch registers it with: its ignore mask and landmarks.
SIDECARS = {"ignore": (".ignore.npy", ".ignore.txt"), "landmarks": (".landmarks.json", ".landmarks.csv")}
MISSING_DASK = "install the batch extra: pip install 'bareesa[batch]' (Dask's distributed scheduler)"


def _distributed():
    """The ``distributed`` module, or InputError saying how to install it."""
    try:
        import distributed
    except ImportError:
        raise InputError(MISSING_DASK) from None
    return distributed


def file_hash(path):
    """sha256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def scan_sidecars(scan):
    """The ignore mask and landmark files next to a scan file (``SIDECARS``): -> {"ignore": Path or None,
    "landmarks": Path or None}. InputError when a scan has two files of one kind."""
    scan = Path(scan)
    out = {}
    for kind, suffixes in SIDECARS.items():
        found = [scan.with_name(scan.stem + suffix) for suffix in suffixes]
        found = [p for p in found if p.is_file()]
        if len(found) > 1:
            raise InputError(f"scan {scan.name} has two {kind} files ({found[0].name}, {found[1].name}): keep one")
        out[kind] = found[0] if found else None
    return out


def input_hash(scan):
    """sha256 hex digest of a scan's input: its file's, combined with its sidecar files' when it has any (a
    changed mask or landmark file registers the scan again)."""
    digest = file_hash(scan)
    extra = [p for p in scan_sidecars(scan).values() if p is not None]
    if not extra:
        return digest
    h = hashlib.sha256(digest.encode())
    for path in extra:
        h.update(path.name.encode() + b"\0" + file_hash(path).encode())
    return h.hexdigest()


def _moved_landmarks(marks, transform):
    """Scan landmarks [(vertex, (x, y, z), weight)] mapped by a Similarity (or None)."""
    if marks is None:
        return None
    points = transform.apply(np.array([m[1] for m in marks], dtype=np.float64))
    return [(m[0], p, *m[2:]) for m, p in zip(marks, points)]


def write_atomic(path, text):
    """Write text to path through a temp file in the same folder and os.replace (never half a file)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _save_mesh_atomic(path, verts, faces):
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    save_mesh(tmp, verts, faces)
    os.replace(tmp, path)


def output_names(scans):
    """One output name per scan (its file stem; stems that repeat get their index in front): -> list."""
    stems = [Path(s).stem for s in scans]
    return [f"{k:04d}_{s}" if stems.count(s) > 1 else s for k, s in enumerate(stems)]


def chunks_of(n, chunk):
    """Frame index ranges of the chunks of a sequence of n frames, chunk frames each: -> [(lo, hi)]."""
    if chunk < 1:
        raise InputError(f"a sequence chunk must hold at least 1 frame, got {chunk}")
    return [(lo, min(lo + chunk, n)) for lo in range(0, n, chunk)]


# ------------------------------------------------------------------------------------- on a worker


def _worker_address():
    try:
        from distributed import get_worker
        return get_worker().address
    except (ImportError, ValueError):
        return "local"


def warm_schedule(schedule):
    """The levels a warm-started frame runs: all but the coarsest of ``schedule``, at most the WARM_LEVELS
    finest (a one-level schedule: that level) -> tuple."""
    schedule = tuple(schedule)
    return schedule[max(len(schedule) - WARM_LEVELS, min(1, len(schedule) - 1)):]


def register_one(basis, scan, previous=None, threads=1, options=None):
    """Register one scan file (run on a worker): -> record dict (status "ok" with the result, or "failed"
    with the one-line error). previous: the previous frame's record (warm start from its code and
    transform) or None (full registration); options: keyword arguments of ``registration.register``."""
    import torch

    torch.set_num_threads(threads)
    start = time.perf_counter()
    out = {"worker": _worker_address(), "scan": str(scan)}
    try:
        out["input_hash"] = input_hash(scan)
        verts, faces = load_mesh(scan)
        validate_mesh(verts, faces, name=Path(scan).name)
        kwargs = dict(options or {})
        side = scan_sidecars(scan)
        out.update({kind: None if path is None else path.name for kind, path in side.items()})
        if side["ignore"] is not None:
            kwargs["scan_face_weights"] = read_face_weights(side["ignore"], faces, len(verts))
        marks = None if side["landmarks"] is None else read_scan_landmarks(side["landmarks"], basis)
        if previous is not None and previous.get("status") == "ok":
            # warm start: map the scan by the previous alignment, start from the previous code
            # and run the finest levels only (the coarser ones find a far pose the previous frame gives)
            before = Similarity.from_dict(previous["transform"])
            kwargs["schedule"] = warm_schedule(basis.schedule if kwargs.get("schedule") is None
                                               else kwargs["schedule"])
            res = registration.register(basis, before.apply(verts), faces, prealign=False, refine_transform=True,
                                        init_code=np.asarray(previous["code"]), pose_candidates=None,
                                        landmarks=_moved_landmarks(marks, before), **kwargs)
            transform = res.transform.compose(before)
            vertices = before.invert(res.vertices)
            out["warm_start"] = previous["name"]
        else:
            res = registration.register(basis, verts, faces, landmarks=marks, **kwargs)
            transform, vertices = res.transform, res.vertices
            out["warm_start"] = None
    except BareEsaError as err:
        return {**out, "status": "failed", "error": f"{type(err).__name__}: {err}".splitlines()[0],
                "seconds": time.perf_counter() - start}
    levels = [{k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in lv.items()}
              for lv in res.levels]
    return {**out, "status": "ok", "error": None, "code": [float(c) for c in res.code],
            "transform": transform.to_dict(), "varifold": float(res.varifold),
            "chamfer": chamfer(vertices, verts), "levels": levels,
            "residual": None if getattr(res, "residual", None) is None else float(res.residual),
            "poor_fit": getattr(res, "poor_fit", None),
            "retried_alignments": int(getattr(res, "retried_alignments", 0)),
            "iterations": int(sum(lv.get("iterations", 0) for lv in levels)),
            "seconds": time.perf_counter() - start, "vertices": vertices}


def _chain_frame(basis, scan, name, previous, threads, options):
    """One frame of a sequence: register_one warm-started from previous (a record, or None) -> record."""
    rec = register_one(basis, scan, previous, threads, options)
    rec["name"] = name
    return rec


# ------------------------------------------------------------------------------------- on the client


@dataclass
class BatchReport:
    """What a batch did: rows (one summary dict per scan, in input order), seams (sequence mode: one dict
    per chunk seam), counts {ok, failed, skipped, pending}, the output folder, seconds, interrupted."""

    rows: list
    seams: list = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    output: Path = None
    seconds: float = 0.0
    interrupted: bool = False
    dashboard: str | None = None


def _read_record(path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def _finished(record, input_hash, basis_hash, warm_start, mesh):
    """Whether a stored record is a finished registration of this input, basis and warm start."""
    return (record is not None and record.get("version") == RECORD_VERSION and record.get("status") == "ok"
            and record.get("input_hash") == input_hash and record.get("basis_hash") == basis_hash
            and record.get("warm_start") == warm_start and mesh.exists())


def _row(k, name, record):
    r = record or {}
    return {"index": k, "name": name, "scan": r.get("scan"), "status": r.get("status", "pending"),
            "varifold": r.get("varifold"), "chamfer": r.get("chamfer"), "residual": r.get("residual"),
            "poor_fit": r.get("poor_fit"), "iterations": r.get("iterations"),
            "seconds": r.get("seconds"), "worker": r.get("worker"), "warm_start": r.get("warm_start"),
            "mesh": r.get("mesh"), "seam_jump": None, "seam_flagged": None, "error": r.get("error")}


def _open_client(scheduler, workers, threads_per_worker, client):
    """(client, close) for an existing client, a scheduler address, or a new LocalCluster on loopback."""
    if client is not None:
        return client, lambda: None
    distributed = _distributed()
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


def _seams(chunks, names, meshes, rows):
    """Vertex jump across each chunk seam vs the median frame-to-frame motion: -> list of dicts."""
    verts = [load_mesh(m)[0] if r["status"] in ("ok", "skipped") else None for m, r in zip(meshes, rows)]
    motion = lambda a, b: float(np.linalg.norm(verts[a] - verts[b], axis=1).mean())  # noqa: E731
    starts = {lo for lo, _ in chunks}
    inner = [motion(k - 1, k) for k in range(1, len(verts))
             if k not in starts and verts[k] is not None and verts[k - 1] is not None]
    median = float(np.median(inner)) if inner else None
    out = []
    for lo, _ in chunks[1:]:
        if verts[lo] is None or verts[lo - 1] is None:
            out.append({"before": names[lo - 1], "after": names[lo], "jump": None, "median_motion": median,
                        "ratio": None, "flagged": None})
            continue
        jump = motion(lo - 1, lo)
        ratio = jump / median if median else None
        out.append({"before": names[lo - 1], "after": names[lo], "jump": jump, "median_motion": median,
                    "ratio": ratio, "flagged": bool(ratio is not None and ratio > SEAM_FACTOR)})
        rows[lo]["seam_jump"], rows[lo]["seam_flagged"] = jump, out[-1]["flagged"]
    return out


def write_summary(output, report, meta):
    """summary.json (meta, counts, seams, rows) and summary.csv (a row per scan), atomically."""
    write_atomic(output / SUMMARY_JSON, json.dumps({**meta, "counts": report.counts, "seams": report.seams,
                                                    "interrupted": report.interrupted, "rows": report.rows},
                                                   indent=2))
    lines = []

    class _Lines:
        def write(self, text):
            lines.append(text)

    writer = csv.DictWriter(_Lines(), fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in report.rows:
        writer.writerow({k: ("" if row.get(k) is None else row[k]) for k in SUMMARY_COLUMNS})
    write_atomic(output / SUMMARY_CSV, "".join(lines))


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
    from .basis_io import load_basis

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
            rec = _read_record(records[k])
            if not _finished(rec, input_hashes[k], basis_hash, warm[k], meshes[k]):
                break
            done[k] = rec
    rows = [_row(k, n, done[k]) for k, n in enumerate(names)]
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
                fut = client_.submit(_chain_frame, remote_basis, str(scans[k]), names[k],
                                     previous if sequence else None, threads, opts, key=f"bareesa-{names[k]}-"
                                     f"{input_hashes[k][:12]}-{time.time_ns()}", pure=False)
                futures[fut] = k
                previous = fut
        distributed = _distributed()
        finished = counts["skipped"]
        for fut in distributed.as_completed(list(futures)):
            k = futures[fut]
            try:
                rec = fut.result()
            except Exception as err:  # noqa: BLE001 - a bug on one scan is recorded; the batch goes on
                rec = {"status": "failed", "error": f"{type(err).__name__}: {err}".splitlines()[0],
                       "scan": str(scans[k]), "input_hash": input_hashes[k], "warm_start": warm[k]}
            vertices = rec.pop("vertices", None)
            rec.update(version=RECORD_VERSION, name=names[k], index=k, basis=str(basis_path), basis_hash=basis_hash)
            if rec["status"] == "ok":
                _save_mesh_atomic(meshes[k], vertices, loaded.faces)
                rec["mesh"] = meshes[k].name
            write_atomic(records[k], json.dumps(rec, indent=2))
            rows[k] = _row(k, names[k], rec)
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
            report.seams = _seams(chunks, names, meshes, rows)
        write_summary(output, report, meta)
    return report


def registered_meshes(source):
    """The registered meshes of a batch, in input order: a batch folder or its summary.json/.csv -> Paths.
    Raises InputError when there is no summary or a scan is not registered (failed or pending)."""
    source = Path(source)
    summary = source / SUMMARY_JSON if source.is_dir() else source
    if summary.suffix == ".csv":
        try:
            with open(summary, newline="") as f:
                rows = list(csv.DictReader(f))
        except OSError as err:
            raise InputError(f"cannot read batch summary {summary}: {err}") from None
    else:
        data = _read_record(summary)
        if data is None or "rows" not in data:
            raise InputError(f"{summary} is not a register-batch summary; give the batch's output folder")
        rows = data["rows"]
    bad = [r["name"] for r in rows if r["status"] not in ("ok", "skipped")]
    if bad:
        raise InputError(f"{len(bad)} scan(s) of the batch in {summary.parent} are not registered (e.g. "
                         f"{bad[0]}): run register-batch on them again")
    return [summary.parent / r["mesh"] for r in sorted(rows, key=lambda r: int(r["index"]))]


# ------------------------------------------------------------------- scans in memory, local processes

#: Topic of the progress events a worker sends to the client (``Worker.log_event``).
PROGRESS_TOPIC = "bareesa-progress"
#: A worker sends at most one progress event this often (seconds), and the last one.
PROGRESS_EVERY = 0.5
#: How often the client looks at finished scans, progress and cancellation (seconds).
POLL_EVERY = 0.2


class _Module:
    """Pickles as ``importlib.import_module(name)``."""

    def __init__(self, name):
        self.name = name

    def __reduce__(self):
        return importlib.import_module, (self.name,)


class _SolverFunction:
    """A function of this module that pickles as ``bareesa.batch.<name>`` whatever this module's own name:
    the workers import the solver as ``bareesa`` (``_solver_preload``), also when the client runs a copy
    vendored inside another package."""

    def __init__(self, name):
        self.name = name

    def __call__(self, *args, **kwargs):
        return globals()[self.name](*args, **kwargs)

    def __reduce__(self):  # by name only: never by this copy's own module name, also when a scheduler re-pickles
        return _Attribute("bareesa.batch", "_SolverFunction"), (self.name,)


class _Attribute:
    """Pickles as ``getattr(importlib.import_module(module), name)``."""

    def __init__(self, module, name):
        self.module, self.name = module, name

    def __call__(self, *args):
        return getattr(importlib.import_module(self.module), self.name)(*args)

    def __reduce__(self):
        return getattr, (_Module(self.module), self.name)


def _solver_preload():
    """Dask preload texts that let a worker import this solver as ``bareesa``: none when it is installed
    under that name, else its parent folder put first on the worker's sys.path."""
    if __package__ == "bareesa":
        return []
    return [f"import sys\nsys.path.insert(0, {str(Path(__file__).resolve().parent.parent)!r})\n"]


def _alias_solver():
    """Let this process import a vendored copy of the solver as ``bareesa`` too: a LocalCluster's scheduler
    runs here and unpickles the tasks, whose function is ``bareesa.batch.<name>`` (``_SolverFunction``).
    Every loaded module of the copy is entered in sys.modules under its ``bareesa`` name as well (the same
    module objects, so the add-on's classes stay one), unless a ``bareesa`` is loaded already."""
    if __package__ == "bareesa" or "bareesa" in sys.modules:
        return
    prefix = __package__
    for name, module in list(sys.modules.items()):
        if name == prefix or name.startswith(prefix + "."):
            sys.modules.setdefault("bareesa" + name[len(prefix):], module)


_WORKER_BASES = {}


def _worker_basis(path):
    """The basis file at path, loaded once per worker process (again when the file changes)."""
    from .basis_io import load_basis

    key = (str(path), os.stat(path).st_mtime_ns)
    if key not in _WORKER_BASES:
        _WORKER_BASES.clear()
        _WORKER_BASES[key] = load_basis(path)
    return _WORKER_BASES[key]


def plain_options(options):
    """``registration.register`` keyword arguments of a ``workflows.Options`` as plain values (no class of
    this package, so that a worker importing the solver under another name reads them): -> dict."""
    from dataclasses import asdict

    from .h2_metric import H2Weights

    weights = options.weights.as_tuple() if isinstance(options.weights, H2Weights) else options.weights
    schedule = None if options.schedule is None else [asdict(lv) if not isinstance(lv, dict) else lv
                                                      for lv in options.schedule]
    return {"schedule": schedule, "prealign": bool(options.prealign), "metric": weights, "kernel": options.kernel,
            "dtype": options.dtype, "device": options.device}


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
    from .basis_io import resolve_basis_path

    if not scans:
        return []
    try:
        distributed = _distributed()
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
    _alias_solver()
    try:
        cluster = distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                           host="127.0.0.1", dashboard_address=None, preload=_solver_preload())
        client = distributed.Client(cluster)
    except Exception as err:  # noqa: BLE001 - the caller can register in its own process instead
        raise errors.WorkersUnavailable(f"could not start {n_workers} worker processes ({type(err).__name__}: "
                                        f"{err})".splitlines()[0]) from err
    try:
        client.subscribe_topic(PROGRESS_TOPIC, on_event)
        task = _SolverFunction("register_array")
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
