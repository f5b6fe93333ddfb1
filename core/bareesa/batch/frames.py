"""Registering one scan file on a worker, and the frames of a sequence: warm starts, chunks, seams.

A sequence's frames are cut into chunks that run in parallel: a chunk's first frame is registered
fully, each further frame starts from the previous frame's code and alignment (the scan mapped by the
previous transform, no pre-alignment, no pose candidates, at most the schedule's WARM_LEVELS finest
levels: ``registration.warm_schedule``). The seams between chunks are checked for jumps against the median
frame-to-frame motion.
"""

import time
from pathlib import Path

import numpy as np

from .. import registration
from ..errors import BareEsaError, InputError
from ..evaluation import chamfer
from ..landmarks import read_scan_landmarks
from ..masks import read_face_weights
from ..mesh import load_mesh, validate_mesh
from ..transforms import Similarity
from .records import input_hash, scan_sidecars

#: A seam whose vertex jump is above this many times the median frame-to-frame motion is flagged.
SEAM_FACTOR = 3.0


def chunks_of(n, chunk):
    """Frame index ranges of the chunks of a sequence of n frames, chunk frames each: -> [(lo, hi)]."""
    if chunk < 1:
        raise InputError(f"a sequence chunk must hold at least 1 frame, got {chunk}")
    return [(lo, min(lo + chunk, n)) for lo in range(0, n, chunk)]


def _worker_address():
    try:
        from distributed import get_worker
        return get_worker().address
    except (ImportError, ValueError):
        return "local"


def register_one(basis, scan, previous=None, threads=1, options=None):
    """Register one scan file (run on a worker): -> record dict (status "ok" with the result, or "failed"
    with the one-line error; "vertices" the registered mesh in the scan's frame, detailed when the detail
    layer was kept, "detail" its report, "detail_layer" (N, 3) the layer in the template frame or None).
    previous: the previous frame's record (warm start from its code and transform) or None (full
    registration); options: keyword arguments of ``registration.register``."""
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
            # warm start: in the previous frame's alignment (refined), from its code, on the finest levels
            # only (the coarser ones find a far pose the previous frame gives)
            res = registration.register_in_frame(basis, verts, faces, Similarity.from_dict(previous["transform"]),
                                                 np.asarray(previous["code"]), landmarks=marks,
                                                 refine_transform=True, **kwargs)
            out["warm_start"] = previous["name"]
        else:
            res = registration.register(basis, verts, faces, landmarks=marks, **kwargs)
            out["warm_start"] = None
        transform, vertices, basis_fit = res.transform, res.output_vertices, res.vertices
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
            "detail": res.detail_report, "basis_fit_chamfer": chamfer(basis_fit, verts),
            "seconds": time.perf_counter() - start, "vertices": vertices, "detail_layer": res.detail}


def chain_frame(basis, scan, name, previous, threads, options):
    """One frame of a sequence: register_one warm-started from previous (a record, or None) -> record."""
    rec = register_one(basis, scan, previous, threads, options)
    rec["name"] = name
    return rec


def seam_jumps(chunks, names, meshes, rows):
    """Vertex jump across each chunk seam vs the median frame-to-frame motion: -> list of dicts (and the
    seam columns of each chunk's first row filled in)."""
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
