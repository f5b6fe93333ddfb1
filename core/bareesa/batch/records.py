"""A batch's files: per-scan records (NAME.json / NAME.ply) that make a rerun resume, and the summary.

A scan's input is its mesh file and its side files (``SIDECARS``: ``SCAN.ignore.npy`` or ``.txt``,
``SCAN.landmarks.json`` or ``.csv``); its record holds the sha256 of that input and of the basis, and a
rerun skips a scan whose record matches both (``finished``). Every file is written atomically (a temp
file in the same folder, then ``os.replace``), so an interrupted batch never leaves half a file.
"""

import csv
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..mesh import save_mesh

SUMMARY_JSON = "summary.json"
SUMMARY_CSV = "summary.csv"
RECORD_VERSION = 1
#: Columns of summary.csv, in order.
SUMMARY_COLUMNS = ("index", "name", "scan", "status", "varifold", "chamfer", "residual", "poor_fit", "iterations",
                   "seconds", "worker", "warm_start", "mesh", "seam_jump", "seam_flagged", "error")
#: Files next to a scan (its stem + one of these) that a batch registers it with: its ignore mask and landmarks.
SIDECARS = {"ignore": (".ignore.npy", ".ignore.txt"), "landmarks": (".landmarks.json", ".landmarks.csv")}


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


def save_mesh_atomic(path, verts, faces):
    """save_mesh through a temp file in the same folder and os.replace."""
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    save_mesh(tmp, verts, faces)
    os.replace(tmp, path)


def output_names(scans):
    """One output name per scan (its file stem; stems that repeat get their index in front): -> list."""
    stems = [Path(s).stem for s in scans]
    return [f"{k:04d}_{s}" if stems.count(s) > 1 else s for k, s in enumerate(stems)]


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


def read_record(path):
    """A JSON file's content, or None when it is missing or not JSON."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def is_finished(record, input_hash, basis_hash, warm_start, mesh):
    """Whether a stored record is a finished registration of this input, basis and warm start."""
    return (record is not None and record.get("version") == RECORD_VERSION and record.get("status") == "ok"
            and record.get("input_hash") == input_hash and record.get("basis_hash") == basis_hash
            and record.get("warm_start") == warm_start and mesh.exists())


def summary_row(k, name, record):
    """The summary row (``SUMMARY_COLUMNS``) of scan k from its record (None: pending)."""
    r = record or {}
    return {"index": k, "name": name, "scan": r.get("scan"), "status": r.get("status", "pending"),
            "varifold": r.get("varifold"), "chamfer": r.get("chamfer"), "residual": r.get("residual"),
            "poor_fit": r.get("poor_fit"), "iterations": r.get("iterations"),
            "seconds": r.get("seconds"), "worker": r.get("worker"), "warm_start": r.get("warm_start"),
            "mesh": r.get("mesh"), "seam_jump": None, "seam_flagged": None, "error": r.get("error")}


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
        data = read_record(summary)
        if data is None or "rows" not in data:
            raise InputError(f"{summary} is not a register-batch summary; give the batch's output folder")
        rows = data["rows"]
    bad = [r["name"] for r in rows if r["status"] not in ("ok", "skipped")]
    if bad:
        raise InputError(f"{len(bad)} scan(s) of the batch in {summary.parent} are not registered (e.g. "
                         f"{bad[0]}): run register-batch on them again")
    return [summary.parent / r["mesh"] for r in sorted(rows, key=lambda r: int(r["index"]))]
