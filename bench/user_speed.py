"""What a user runs, timed: the default bundled basis, through ``bareesa.workflows`` as the CLI and
the add-on call it, every stage on (pre-alignment, pose candidates, refinement).

Rows: first use (a small scan registered first: KeOps builds its kernels at their first use on a
machine, ~15 s, timed apart so that the rows after it time the solves alone); registration of a ~50k-face
simulated scan (remeshed, noisy, holed, arbitrary rotation and scale) against its true vertices;
interpolation between two known codes at T = 24 frames; symmetric matching of two raw scans;
extrapolation of 10 frames; 20 random bodies. Each with wall
and CPU seconds (CPU over all threads of this process) and an accuracy or outcome beside it.
``--paper`` adds the paper-scale problem of ``bench.registration_speed`` (6,890 vertices, P = 170,
55k-face scan) as a second table.

    python -m bench.user_speed [--basis NAME|NPZ] [--paper] [--bodies SEED ...] [--device cpu] [--threads 2]
                               [--skip ...]
"""

import argparse
import time

import numpy as np
import torch

from bench.common import markdown_table, report
from bareesa import basis_io, evaluation, workflows
from bareesa.errors import BareEsaError
from bareesa.scan_simulator import apply_similarity, simulate_scan

TASKS = ("registration", "interpolation", "matching", "extrapolation", "random")


def timed(fn):
    """Run fn() -> (its result, wall seconds, CPU seconds)."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def scan_of(basis, code, seed, resolution):
    """A simulated scan of F(code) and its true vertices in the scan's frame: -> workflows.Scan, (N, 3)."""
    truth = basis.template + np.tensordot(code, basis.fields, axes=1)
    verts, faces, info = simulate_scan(truth, basis.faces, seed=seed, resolution=resolution)
    return workflows.Scan(verts, faces), apply_similarity(info, truth)


def error_text(basis, got, truth, scale):
    """Mean vertex error in the basis' units and as a share of its size."""
    err = evaluation.vertex_error(got, truth)["mean"] / scale
    size = float(np.ptp(basis.template, axis=0).max())
    value = f"{err * 1000:.1f} mm" if basis.units == "m" else f"{err:.3g} {basis.units or 'units'}"
    return f"vertex error mean {value} ({100 * err / size:.2f} % of size)"


def timed_row(task, fn, outcome):
    """A table row [task, wall, CPU, outcome(result)], or the one-line error of a failed solve as its
    outcome (a failure is a result: the table goes on)."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        text = outcome(fn())
    except BareEsaError as err:
        text = f"**failed**: {err}"
    row = [task, time.perf_counter() - t0, time.process_time() - c0, text]
    print("  ", *row, flush=True)
    return row


#: The first-use row registers a scan this coarse (~5k faces on the human): KeOps builds its kernels at
#: their first use on a machine (or in a new environment), ~15 s (~20 s before the faces' values came from
#: the gradient's formula), and a small scan needs the same ones as the registrations after it (measured
#: with an empty KeOps cache: 28.2 s for the small scan, then 8.8 s for the 60,928-face scan, 9.3 s for it
#: again; bench/README)
FIRST_USE_RESOLUTION = 0.03


def user_rows(basis, options, skip, resolution, first_use=True):
    """The table of what a user runs on ``basis``: rows [task, wall, CPU, outcome]; with first_use the first
    registers a small scan, so that the rows after it do not time KeOps building its kernels."""
    codes = workflows.random_bodies(basis, 2, 7, options).codes
    rows = []
    if first_use:
        small, truth = scan_of(basis, codes[1], 99, FIRST_USE_RESOLUTION)
        rows.append(timed_row(f"first use: registration of a {len(small.faces)}-face scan (KeOps builds its "
                              "kernels if this machine has not yet)",
                              lambda: workflows.code_of(basis, small, options).registration,
                              lambda reg: error_text(basis, reg.vertices, truth, 1.0)))
    if "registration" not in skip:
        scan, truth = scan_of(basis, codes[0], 11, resolution)
        rows.append(timed_row(f"registration, {len(scan.faces)}-face scan",
                              lambda: workflows.code_of(basis, scan, options).registration,
                              lambda reg: "; ".join([error_text(basis, reg.vertices, truth, 1.0),
                                                     f"residual {reg.residual:.3g}"])))
    if "interpolation" not in skip:
        ends = [workflows.KnownCode(c) for c in codes]
        rows.append(timed_row("interpolation, known codes, T = 24",
                              lambda: workflows.path_between(basis, *ends, 24, options),
                              lambda found: f"distance {found.distance:.4g}"))
    if "matching" not in skip:
        (scan_a, truth_a), (scan_b, truth_b) = scan_of(basis, codes[0], 12, resolution), \
            scan_of(basis, codes[1], 13, resolution)
        rows.append(timed_row("symmetric matching of two raw scans",
                              lambda: workflows.geodesic_between(basis, scan_a, scan_b, options),
                              lambda found: "; ".join(error_text(basis, e.registration.vertices, t, 1.0)
                                                      for e, t in zip(found.ends, (truth_a, truth_b)))))
    if "extrapolation" not in skip:
        a, b = workflows.KnownCode(codes[0]), workflows.KnownCode(codes[0] + 0.1 * (codes[1] - codes[0]))
        rows.append(timed_row("extrapolation, 10 frames",
                              lambda: workflows.extrapolate(basis, a, b, 10, options).shooting,
                              lambda rep: f"{rep.refinements} refinements (steps per frame up to {max(rep.substeps)})"))
    if "random" not in skip:
        rows.append(timed_row("20 random bodies", lambda: workflows.random_bodies(basis, 20, 3, options),
                              lambda bodies: f"{bodies.replaced} draws replaced"))
    return rows


def body_rows(basis, options, seeds, resolution):
    """Registration of one simulated scan (scale +-10 %) of a random body per seed (the first body of
    ``random_bodies(basis, 2, seed)``; scan seed 100 + seed): rows [seed, faces, mean mm, p95 mm,
    wall, CPU, iterations per level]."""
    rows = []
    for seed in seeds:
        code = workflows.random_bodies(basis, 2, seed, options).codes[0]
        truth = basis.template + np.tensordot(code, basis.fields, axes=1)
        verts, faces, info = simulate_scan(truth, basis.faces, seed=100 + seed, resolution=resolution, scale=0.1)
        found, wall, cpu = timed(lambda: workflows.code_of(basis, workflows.Scan(verts, faces), options))
        reg = found.registration
        err = evaluation.vertex_error(reg.vertices, apply_similarity(info, truth))
        unit = 1000.0 if basis.units == "m" else 1.0
        rows.append([seed, len(faces), unit * err["mean"], unit * err["p95"], wall, cpu,
                     "/".join(str(lv["iterations"]) for lv in reg.levels)])
        print("  ", *rows[-1], flush=True)
    return rows


def paper_rows(options, resolution):
    """The paper-scale registration and interpolation (``bench.registration_speed``'s problem)."""
    from bench.body_data import body_basis, body_scan

    basis = body_basis("user_speed")
    rng = np.random.default_rng(3)
    truth = rng.normal(size=basis.n_fields) * 0.15
    sv, sf = body_scan(basis, truth)
    found, wall, cpu = timed(lambda: workflows.code_of(basis, workflows.Scan(sv, sf), options))
    rows = [[f"registration, {len(sf)}-face scan", wall, cpu,
             error_text(basis, found.registration.vertices, basis.template + np.tensordot(truth, basis.fields, 1),
                        1.0)]]
    a0, a1 = (workflows.KnownCode(c) for c in rng.normal(size=(2, basis.n_fields)) * 0.5)
    path, wall, cpu = timed(lambda: workflows.path_between(basis, a0, a1, 24, options))
    rows.append(["interpolation, known codes, T = 24", wall, cpu, f"distance {path.distance:.4g}"])
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--basis", default=basis_io.DEFAULT_BASIS)
    parser.add_argument("--paper", action="store_true", help="add the paper-scale problem (needs ../shared/data)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--resolution", type=float, default=0.009,
                        help="scan remeshing pitch (share of the size; 0.009 gives 50-65k faces on the human)")
    parser.add_argument("--skip", nargs="*", default=(), choices=TASKS)
    parser.add_argument("--bodies", type=int, nargs="*", default=(), metavar="SEED",
                        help="also register a simulated scan of the random body of each seed (accuracy over many)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    options = workflows.Options(device=args.device)
    basis = basis_io.load_basis(args.basis)
    header = ["task", "wall s", "CPU s", "accuracy / outcome"]
    text = (f"# What a user runs: basis '{basis.name}', device {args.device}, torch threads {args.threads}\n\n"
            + markdown_table(header, user_rows(basis, options, set(args.skip), args.resolution,
                                               first_use=bool({"registration", "matching"} - set(args.skip))
                                               or bool(args.bodies) or args.paper), "{:.1f}"))
    if args.bodies:
        unit = "mm" if basis.units == "m" else basis.units or "units"
        text += (f"\n\n## Random bodies, one simulated scan each\n\n"
                 + markdown_table(["seed", "scan faces", f"mean {unit}", f"p95 {unit}", "wall s", "CPU s",
                                   "iterations per level"], body_rows(basis, options, args.bodies, args.resolution),
                                  "{:.2f}"))
    if args.paper:
        text += "\n\n## Paper scale\n\n" + markdown_table(header, paper_rows(options, args.resolution), "{:.1f}")
    report(f"user_speed_{basis.name}_{args.device}", text)


if __name__ == "__main__":
    main()
