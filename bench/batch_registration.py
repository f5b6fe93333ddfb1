"""Batch registration on Dask (issue 19): throughput at 1 and 2 workers, sequence mode vs independent.

Simulated scans of the default basis (``human``; ``--basis``): held-out bodies decoded from codes drawn from its
stored distribution (``statistics.sample_velocities``), each turned into a remeshed, noisy, holed,
randomly moved scan (``scan_simulator.simulate_scan``); and one 4D capture, a motion between two drawn
codes seen by a fixed scanner (one similarity for every frame). Reports scans per minute (cluster start
included) at each worker count, the mean vertex error against the true vertices (in units of the body
size), the peak RSS per worker process, and for the capture, sequence mode (warm starts, chunks) vs
independent registration: seconds, error, frame-to-frame jitter (mean |registered motion - true motion|
per frame step) and the seam check.
Run: python -m bench.batch_registration [--scans 40] [--frames 20] [--workers 1,2] [--chunk K]
(the issue's setting; try --scans 2 --frames 3 first).
"""

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import markdown_table, report, table, variant_of, write_results
from bareesa import batch
from bareesa import basis_io
from bareesa.basis_io import load_basis, resolve_basis_path
from bareesa.mesh import load_mesh, save_mesh
from bareesa.scan_simulator import apply_similarity, simulate_scan
from bareesa.statistics import sample_velocities
from bareesa.transforms import Similarity
from bareesa.workflows import stored_distribution


def decode(basis, codes):
    """F(codes): (K, P) -> (K, N, 3)."""
    return basis.template + np.einsum("kp,pnd->knd", codes, basis.fields)


def held_out_scans(basis, n, folder, seed):
    """n simulated scans of bodies drawn from the basis distribution: -> (paths, true scan-frame vertices, sizes)."""
    codes = sample_velocities(stored_distribution(basis), basis.groups, n, seed=seed + 1000)
    paths, truths, sizes = [], [], []
    for k, verts in enumerate(decode(basis, codes)):
        v, f, info = simulate_scan(verts, basis.faces, seed=seed + k)
        paths.append(folder / f"scan_{k:03d}.ply")
        save_mesh(paths[-1], v, f)
        truths.append(apply_similarity(info, verts))
        sizes.append(info["size"] * info["scale"])
    return paths, truths, sizes


def capture(basis, n, folder, seed):
    """n frames of one motion between two drawn codes, a fixed scanner pose: -> (paths, truths, sizes)."""
    a, b = sample_velocities(stored_distribution(basis), basis.groups, 2, seed=seed + 2000)
    b[basis.groups["shape"][0]:basis.groups["shape"][1]] = a[basis.groups["shape"][0]:basis.groups["shape"][1]]
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    scanner = Similarity(q * np.sign(np.linalg.det(q)), 1.0, rng.normal(size=3))
    paths, truths, sizes = [], [], []
    for k, verts in enumerate(decode(basis, a + np.linspace(0, 1, n)[:, None] * (b - a))):
        v, f, info = simulate_scan(verts, basis.faces, seed=seed + 100 + k, rigid=False)
        paths.append(folder / f"frame_{k:03d}.ply")
        save_mesh(paths[-1], scanner.apply(v), f)
        truths.append(scanner.apply(verts))
        sizes.append(info["size"])
    return paths, truths, sizes


def errors(report_, out, truths, sizes):
    """Mean vertex error per scan over the body size (NaN for a failed scan): -> (K,) and the verts."""
    verts = [load_mesh(out / r["mesh"])[0] if r["status"] in ("ok", "skipped") else None for r in report_.rows]
    err = np.array([np.nan if v is None else np.linalg.norm(v - t, axis=1).mean() / s
                    for v, t, s in zip(verts, truths, sizes)])
    return err, verts


def jitter(verts, truths, sizes):
    """Mean |(v_k+1 - v_k) - (t_k+1 - t_k)| over vertices and frame steps, over the body size."""
    steps = [np.linalg.norm((verts[k + 1] - verts[k]) - (truths[k + 1] - truths[k]), axis=1).mean() / sizes[k]
             for k in range(len(verts) - 1) if verts[k] is not None and verts[k + 1] is not None]
    return float(np.mean(steps)) if steps else float("nan")


def peak_rss(client):
    """Peak resident memory of each worker process, MiB: -> list."""
    return [v / 1024 for v in client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss).values()]


def run(basis_name, scans, out, workers, **kwargs):
    """A batch on a fresh LocalCluster of `workers` processes: -> (report, peak RSS per worker MiB)."""
    import distributed

    with distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as cluster, distributed.Client(cluster) as client:
        t0 = time.perf_counter()
        rep = batch.register_batch(basis_name, scans, out, client=client, progress=True, **kwargs)
        rep.seconds = time.perf_counter() - t0
        return rep, peak_rss(client)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--basis", default=basis_io.DEFAULT_BASIS)
    parser.add_argument("--scans", type=int, default=40, help="held-out scans for the throughput rows")
    parser.add_argument("--frames", type=int, default=20, help="frames of the simulated capture (0: skip)")
    parser.add_argument("--workers", default="1,2", help="worker counts of the throughput rows")
    parser.add_argument("--chunk", type=int, default=None, help="sequence chunk (default: frames / 2 workers)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--keep", type=Path, default=None, help="folder to keep the scans and outputs in")
    args = parser.parse_args(argv)
    basis = load_basis(args.basis)
    basis_path = resolve_basis_path(args.basis)
    root = args.keep or Path(tempfile.mkdtemp(prefix="bareesa-batch-bench-"))
    (root / "scans").mkdir(parents=True, exist_ok=True)
    (root / "capture").mkdir(exist_ok=True)
    lines = [f"basis {basis.name}: {basis.template.shape[0]} vertices, {basis.n_fields} fields; "
             f"{args.scans} held-out scans, {args.frames}-frame capture; files in {root}"]

    rows, figures, tables = [], {}, []
    if args.scans:
        scans, truths, sizes = held_out_scans(basis, args.scans, root / "scans", args.seed)
        for n in [int(w) for w in args.workers.split(",")]:
            rep, rss = run(basis_path, scans, root / f"out_w{n}", n)
            err, _ = errors(rep, root / f"out_w{n}", truths, sizes)
            per_scan = np.mean([r["seconds"] for r in rep.rows if r["seconds"] is not None])
            rows.append((n, rep.counts["ok"] + rep.counts["skipped"], rep.counts["failed"], rep.seconds,
                         60 * len(scans) / rep.seconds, per_scan, float(np.nanmean(err)), float(np.nanmax(err)),
                         max(rss)))
            print(f"{n} worker(s): {rows[-1]}", file=sys.stderr)
        head = ["workers", "ok", "failed", "seconds", "scans/min", "s/scan (worker)", "mean err/size", "max err/size",
                "peak RSS/worker MiB"]
        lines += ["", "throughput (LocalCluster, 1 torch thread per worker, cluster start included)", "",
                  markdown_table(head, rows)]
        tables.append(table("Throughput (LocalCluster, 1 torch thread per worker, cluster start included)", head,
                            rows))
        for r in rows:
            figures |= {f"workers{r[0]}_scans_per_min": r[4], f"workers{r[0]}_failed": r[2],
                        f"workers{r[0]}_mean_error_rel_size": r[6], f"workers{r[0]}_max_error_rel_size": r[7],
                        f"workers{r[0]}_peak_rss_mb": r[8]}

    if args.frames:
        frames, truths, sizes = capture(basis, args.frames, root / "capture", args.seed)
        seq_rows, seams = [], []
        for mode in ("independent", "sequence"):
            out = root / f"capture_{mode}"
            rep, rss = run(basis_path, frames, out, 2, sequence=mode == "sequence", chunk=args.chunk)
            err, verts = errors(rep, out, truths, sizes)
            its = [r["iterations"] for r in rep.rows if r["iterations"] is not None]
            seq_rows.append((mode, rep.seconds, 60 * len(frames) / rep.seconds, float(np.mean(its)),
                             float(np.nanmean(err)), jitter(verts, truths, sizes), max(rss)))
            seams = rep.seams if mode == "sequence" else seams
            print(f"{mode}: {seq_rows[-1]}", file=sys.stderr)
        head = ["mode", "seconds", "frames/min", "iterations/frame", "mean err/size", "jitter/size",
                "peak RSS/worker MiB"]
        lines += ["", "4D capture on 2 workers: independent vs sequence mode (warm starts, chunks in parallel)", "",
                  markdown_table(head, seq_rows)]
        tables.append(table("4D capture on 2 workers: independent vs sequence mode", head, seq_rows))
        for r in seq_rows:
            figures |= {f"capture_{r[0]}_s": r[1], f"capture_{r[0]}_iterations_per_frame": r[3],
                        f"capture_{r[0]}_mean_error_rel_size": r[4], f"capture_{r[0]}_jitter_rel_size": r[5]}
        if seams:
            head = ["before", "after", "jump", "median motion", "ratio", "flagged"]
            seam_rows = [(s["before"], s["after"], s["jump"], s["median_motion"], s["ratio"], s["flagged"])
                         for s in seams]
            lines += ["", "seams (vertex jump across a chunk boundary vs the median frame-to-frame motion)", "",
                      markdown_table(head, seam_rows)]
            tables.append(table("Seams (vertex jump across a chunk boundary vs the median frame-to-frame motion)",
                                head, seam_rows))
            figures["capture_seams_flagged"] = sum(bool(s["flagged"]) for s in seams)
    report("batch_registration", "\n".join(lines))
    write_results("batch_registration", figures, tables, variant=variant_of(parser, args, ("keep",)),
                  argv=sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    main()
