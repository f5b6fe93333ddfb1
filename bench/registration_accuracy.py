"""Where registration accuracy goes, factor by factor (issue: converge as far as the paper's code).

Three kinds of input, each registered with the shipped default and with one factor changed at a time:
1. ``paper``: the paper-scale instance of ``bench.registration_speed`` (6,890-vertex DFAUST template,
   P = 170 smooth fields, a 55k-face scan with 2 mm noise, true code known): vertex error.
2. ``human``: simulated scans (voxel remesh, holes, random rotation and scale, vertex noise 1 and 4 mm)
   of held-out people of the bundled ``human`` basis in a held-out motion (lunge, middle frame;
   regenerated with Anny, the ``[bases]`` extra, or read from ``--truths FILE`` written by an earlier
   run): vertex error.
3. ``real``: the DFAUST template (a real body) in random orientations, registered with ``human``:
   mean surface distance both ways and Hausdorff (needs ``bpy``).
The factors are ``RegistrationConfig`` settings (each row builds a variant of the basis' configuration);
a row says what it changes from the default. Wall and CPU seconds beside (2-core CPU: compare rows of
one run only).

Usage: python -m bench.registration_accuracy [--parts paper human real] [--scans N] [--real N]
       [--truths FILE] [--threads 1]
"""

import argparse
import time
from dataclasses import replace

import numpy as np
import torch

import bench.common  # noqa: F401  (puts the repo on sys.path)
from bench.common import OUT, markdown_table, report, table, variant_of, write_results
from bareesa import evaluation
from bareesa.basis_io import load_basis
from bareesa.registration import RegistrationConfig, register
from bareesa.registration.problem import normal_spread
from bareesa.scan_simulator import apply_similarity, simulate_scan

#: The shipped state before this bench chose the default: binet on every level, the scan summed
#: over cells of sigma / 2 at the finest level (whatever the kernel), its normals as they are.
BEFORE = {"kernel": "binet", "solve.scan_cell": 0.5, "solve.oriented_scan_cell": 0.5}
LINEAR_FINEST = ("binet", "binet", "linear")

#: (name, changes) for the paper-scale instance; changes are ``RegistrationConfig`` settings (dotted keys
#: for nested ones), "iters" (each level's max_iter), "finest_weight" (x the finest level's weight) and
#: "half_sigma_level" (a fourth level at half the finest sigma).
PAPER_FACTORS = [
    ("before: binet, scan cells sigma/2", BEFORE),
    ("binet, scan cells sigma/4", {**BEFORE, "solve.scan_cell": 0.25}),
    ("binet, scan not binned, truncation 1e-6", {**BEFORE, "solve.scan_cell": None, "solve.fine_tol": 1e-6}),
    ("binet, no plateau stop, caps 100/100/200", {**BEFORE, "solve.plateau": 0.0, "iters": (100, 100, 200)}),
    ("binet, finest weight x10", {**BEFORE, "finest_weight": 10.0}),
    ("binet, a fourth level at sigma/2", {**BEFORE, "half_sigma_level": True}),
    ("binet, float32", {**BEFORE, "dtype": "float32"}),
    ("linear on every level", {**BEFORE, "kernel": "linear"}),
    ("binet, linear at the finest level", {**BEFORE, "kernel": LINEAR_FINEST}),
    ("binet, linear at the finest level, scan cells sigma/4",
     {**BEFORE, "kernel": LINEAR_FINEST, "solve.oriented_scan_cell": 0.25}),
    ("binet, linear at the finest level, scan not binned",
     {**BEFORE, "kernel": LINEAR_FINEST, "solve.oriented_scan_cell": None}),
    ("binet, binet+linear at the finest level", {**BEFORE, "kernel": ("binet", "binet", "binet+linear")}),
    ("default now (noisy scan: linear at the finest level, scan cells sigma/3.3)", {}),
    ("default now, float32", {"dtype": "float32"}),
]
#: the rows of the human and real-body parts (fewer: each registration there is slow)
BODY_FACTORS = [
    ("before: binet, scan cells sigma/2", BEFORE),
    ("default now", {}),
    ("linear at the finest level (forced)", {"kernel": LINEAR_FINEST}),
]
#: vertex noise (m) of the human scans: the simulator's default, and four times it (normal spread
#: ~0.015 and ~0.135: the default's finest kernel is binet for the first, linear for the second)
HUMAN_NOISE = (0.001, 0.004)
HUMAN_SCAN = dict(remesh="voxel", holes=3, scale=0.1)


def run(basis, verts, faces, changes):
    """register() with ``changes`` -> (result, wall s, CPU s)."""
    schedule = list(basis.schedule)
    if "iters" in changes:
        schedule = [replace(lv, max_iter=m) for lv, m in zip(schedule, changes["iters"])]
    if "finest_weight" in changes:
        schedule[-1] = replace(schedule[-1], weight=schedule[-1].weight * changes["finest_weight"])
    if changes.get("half_sigma_level"):
        schedule.append(replace(schedule[-1], sigma=schedule[-1].sigma / 2, max_iter=40))
    settings = {k: v for k, v in changes.items() if k not in ("iters", "finest_weight", "half_sigma_level")}
    if "kernel" in changes and not isinstance(changes["kernel"], str) and len(schedule) != 3:
        raise SystemExit("a per-level kernel row needs a three-level schedule")
    config = RegistrationConfig.from_basis(basis, settings, schedule=schedule)  # a variant, no global patched
    t0, c0 = time.perf_counter(), time.process_time()
    res = register(basis, verts, faces, config)
    return res, time.perf_counter() - t0, time.process_time() - c0


def paper_rows(log=print):
    from bench.body_data import body_basis, body_scan

    basis = body_basis("registration_accuracy")
    truth = np.random.default_rng(3).normal(size=basis.n_fields) * 0.15  # registration_speed's instance
    sv, sf = body_scan(basis, truth)
    true_v = basis.template + np.tensordot(truth, basis.fields, 1)
    rows = []
    for name, changes in PAPER_FACTORS:
        res, wall, cpu = run(basis, sv, sf, changes)
        err = evaluation.vertex_error(res.vertices, true_v)
        rows.append([name, res.levels[-1]["kernel"], 1e3 * err["mean"], 1e3 * err["p95"], wall, cpu,
                     "/".join(str(lv["iterations"]) for lv in res.levels)])
        log("  ", *(f"{x:.3g}" if isinstance(x, float) else x for x in rows[-1]), flush=True)
    return (f"Scan normal spread {normal_spread(sv, sf):.3f}.\n\n"
            + recorded("paper", ["paper-scale instance", "finest kernel", "mean mm", "p95 mm", "wall s", "CPU s",
                                 "iterations"], rows))


def human_rows(n, truths, log=print):
    from bench.landmarks_masks import held_out_frames

    basis = load_basis("human")
    rows = []
    for key, truth in held_out_frames(truths, n, motion="lunge").items():
        for noise in HUMAN_NOISE:
            seed = 500 + sum(map(ord, key))
            sv, sf, info = simulate_scan(truth, basis.faces, seed=seed, noise=noise, **HUMAN_SCAN)
            unit = 1e3 / info["scale"]  # scan units -> mm of the true body
            true_v = apply_similarity(info, truth)
            for name, changes in BODY_FACTORS:
                res, wall, cpu = run(basis, sv, sf, changes)
                err = evaluation.vertex_error(res.vertices, true_v)
                rows.append([key, f"{1e3 * noise:g} mm", f"{res.normal_spread:.3f}", name, res.levels[-1]["kernel"],
                             unit * err["mean"], unit * err["p95"], wall, cpu])
                log("  ", *(f"{x:.3g}" if isinstance(x, float) else x for x in rows[-1]), flush=True)
    return recorded("human", ["held-out scan", "noise", "normal spread", "registration", "finest kernel", "mean mm",
                              "p95 mm", "wall s", "CPU s"], rows)


def real_rows(n, log=print):
    import bpy  # noqa: F401  (surface_distances uses bpy's mathutils)
    import trimesh

    from bench.human_accuracy import DFAUST, surface_distances
    from bareesa.synthetic import random_rotation
    from bareesa.transforms import Similarity

    if not DFAUST.exists():
        log(f"(no {DFAUST}: the real-body rows are skipped)")
        return ""
    mesh = trimesh.load(DFAUST, process=False)
    body_v, body_f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    basis = load_basis("human")
    rng = np.random.default_rng(0)
    rows = []
    for k in range(n):
        sim = Similarity(rotation=random_rotation(100 + k), scale=1.0, translation=rng.normal(size=3))
        for name, changes in BODY_FACTORS:
            res, wall, cpu = run(basis, sim.apply(body_v), body_f, changes)
            d_rb, d_br, haus = surface_distances(sim.invert(res.vertices), basis.faces, body_v, body_f)
            rows.append([f"orientation {k + 1}", name, res.levels[-1]["kernel"], 1e3 * d_rb, 1e3 * d_br, 1e3 * haus,
                         wall, cpu])
            log("  ", *(f"{x:.3g}" if isinstance(x, float) else x for x in rows[-1]), flush=True)
    return recorded("real", ["DFAUST template", "registration", "finest kernel", "registered->body mm",
                             "body->registered mm", "Hausdorff mm", "wall s", "CPU s"], rows)


#: each part's table of this run, {part: (header, rows)}, for the results file
TABLES = {}


def recorded(part, header, rows):
    """Keep a part's table for the results file: -> its markdown."""
    TABLES[part] = (header, rows)
    return markdown_table(header, rows)


def row_key(name):
    """'default' / 'before' for the rows the figures report (the shipped default, the state before), else None."""
    if name == "default now" or name.startswith("default now ("):
        return "default"
    return "before" if name.startswith("before") else None


def figures_of(tables):
    """Headline figures of the parts' tables: the default's and the before-state's errors and seconds."""
    figures = {}
    for name, kernel, mean, p95, wall, *_ in tables.get("paper", (None, []))[1]:
        if row_key(name):
            figures |= {f"paper_{row_key(name)}_error_mean_mm": mean, f"paper_{row_key(name)}_error_p95_mm": p95,
                        f"paper_{row_key(name)}_wall_s": wall}
    groups = {}
    for _, noise, _, name, _, mean, p95, wall, _ in tables.get("human", (None, []))[1]:
        if row_key(name):
            groups.setdefault(f"human_noise{noise.replace(' ', '')}_{row_key(name)}", []).append((mean, p95, wall))
    for _, name, _, rb, br, haus, wall, _ in tables.get("real", (None, []))[1]:
        if row_key(name):
            groups.setdefault(f"real_{row_key(name)}", []).append((rb, br, haus, wall))
    for key, values in groups.items():
        m = np.mean(values, axis=0)
        names = (("error_mean_mm", "error_p95_mm", "wall_s") if key.startswith("human")
                 else ("reg_to_body_mm", "body_to_reg_mm", "hausdorff_mm", "wall_s"))
        figures |= {f"{key}_{n}": float(v) for n, v in zip(names, m)}
    return figures


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="*", default=["paper", "human", "real"], choices=["paper", "human", "real"])
    parser.add_argument("--name", default="registration_accuracy", help="output file bench/out/NAME.md")
    parser.add_argument("--scans", type=int, default=2, help="held-out people (each scanned at two noise levels)")
    parser.add_argument("--real", type=int, default=2, help="orientations of the real body")
    parser.add_argument("--truths", type=lambda p: __import__("pathlib").Path(p),
                        default=OUT / "held_out_wave_frames.npz", help="cache of the held-out Anny frames")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    sections = {"paper": ("Paper-scale instance", paper_rows),
                "human": ("Held-out human scans (lunge)", lambda: human_rows(args.scans, args.truths)),
                "real": ("Real body (DFAUST template, human basis)", lambda: real_rows(args.real))}
    text = []
    for part in args.parts:
        title, rows = sections[part]
        print(f"## {title}", flush=True)
        text.append(f"## {title}\n\n{rows()}")
    report(args.name, "\n\n".join(text))
    write_results("registration_accuracy", figures_of(TABLES),
                  [table(sections[part][0], *TABLES[part]) for part in args.parts if part in TABLES],
                  variant=variant_of(parser, args, ("truths",)), argv=argv)


if __name__ == "__main__":
    main()
