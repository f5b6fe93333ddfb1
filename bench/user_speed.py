"""What a user runs, timed: the default bundled basis, through ``bareesa.workflows`` as the CLI and
the add-on call it, every stage on (pre-alignment, pose candidates, refinement).

Rows: first use (a small scan registered first: KeOps builds its kernels at their first use on a
machine, timed apart so that the rows after it time the solves alone); registration of a ~50k-face
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

from bench.common import markdown_table, report, table, variant_of, write_results
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


def error_text(basis, got, truth, scale, figures=None, key=None):
    """Mean vertex error in the basis' units and as a share of its size (also into ``figures`` as
    <key>_error_mm, or _error_units for a basis not in metres, and <key>_error_pct_size)."""
    err = evaluation.vertex_error(got, truth)["mean"] / scale
    size = float(np.ptp(basis.template, axis=0).max())
    if figures is not None:
        figures[f"{key}_error_{'mm' if basis.units == 'm' else 'units'}"] = err * 1000 if basis.units == "m" else err
        figures[f"{key}_error_pct_size"] = 100 * err / size
    value = f"{err * 1000:.1f} mm" if basis.units == "m" else f"{err:.3g} {basis.units or 'units'}"
    return f"vertex error mean {value} ({100 * err / size:.2f} % of size)"


def timed_row(task, fn, outcome, figures=None, key=None):
    """A table row [task, wall, CPU, outcome(result)], or the one-line error of a failed solve as its
    outcome (a failure is a result: the table goes on); its seconds into ``figures`` as <key>_wall_s and
    <key>_cpu_s (<key>_failed = 1 instead for a failure)."""
    t0, c0 = time.perf_counter(), time.process_time()
    failed = False
    try:
        text = outcome(fn())
    except BareEsaError as err:
        text, failed = f"**failed**: {err}", True
    row = [task, time.perf_counter() - t0, time.process_time() - c0, text]
    if figures is not None:
        figures.update({f"{key}_failed": 1} if failed else {f"{key}_wall_s": row[1], f"{key}_cpu_s": row[2]})
    print("  ", *row, flush=True)
    return row


#: The first-use row registers a scan this coarse (~5k faces on the human): it needs the same KeOps
#: kernels as the registrations after it, so they are built (once per machine) before those are timed.
FIRST_USE_RESOLUTION = 0.03


def user_rows(basis, options, skip, resolution, first_use=True, figures=None):
    """The table of what a user runs on ``basis``: rows [task, wall, CPU, outcome]; with first_use the first
    registers a small scan, so that the rows after it do not time KeOps building its kernels. ``figures``
    (a dict) receives each row's seconds and outcome as numbers."""
    figures = {} if figures is None else figures
    codes = workflows.random_bodies(basis, 2, 7, options).codes
    rows = []

    def registered(reg):
        figures["registration_residual"] = reg.residual
        return "; ".join([error_text(basis, reg.vertices, truth, 1.0, figures, "registration"),
                          f"residual {reg.residual:.3g}"])

    def interpolated(found):
        figures["interpolation_distance"] = found.distance
        return f"distance {found.distance:.4g}"

    def extrapolated(rep):
        figures["extrapolation_refinements"] = rep.refinements
        return f"{rep.refinements} refinements (steps per frame up to {max(rep.substeps)})"

    def drawn(bodies):
        figures["random_bodies_replaced"] = bodies.replaced
        return f"{bodies.replaced} draws replaced"

    if first_use:
        small, truth = scan_of(basis, codes[1], 99, FIRST_USE_RESOLUTION)
        figures["first_use_scan_faces"] = len(small.faces)
        rows.append(timed_row(f"first use: registration of a {len(small.faces)}-face scan (KeOps builds its "
                              "kernels if this machine has not yet)",
                              lambda: workflows.code_of(basis, small, options).registration,
                              lambda reg: error_text(basis, reg.vertices, truth, 1.0, figures, "first_use"),
                              figures, "first_use"))
    if "registration" not in skip:
        scan, truth = scan_of(basis, codes[0], 11, resolution)
        figures["registration_scan_faces"] = len(scan.faces)
        rows.append(timed_row(f"registration, {len(scan.faces)}-face scan",
                              lambda: workflows.code_of(basis, scan, options).registration, registered,
                              figures, "registration"))
    if "interpolation" not in skip:
        ends = [workflows.KnownCode(c) for c in codes]
        rows.append(timed_row("interpolation, known codes, T = 24",
                              lambda: workflows.path_between(basis, *ends, 24, options), interpolated,
                              figures, "interpolation"))
    if "matching" not in skip:
        (scan_a, truth_a), (scan_b, truth_b) = scan_of(basis, codes[0], 12, resolution), \
            scan_of(basis, codes[1], 13, resolution)
        rows.append(timed_row("symmetric matching of two raw scans",
                              lambda: workflows.geodesic_between(basis, scan_a, scan_b, options),
                              lambda found: "; ".join(error_text(basis, e.registration.vertices, t, 1.0, figures,
                                                                 f"matching_end{i + 1}")
                                                      for i, (e, t) in enumerate(zip(found.ends, (truth_a, truth_b)))),
                              figures, "matching"))
    if "extrapolation" not in skip:
        a, b = workflows.KnownCode(codes[0]), workflows.KnownCode(codes[0] + 0.1 * (codes[1] - codes[0]))
        rows.append(timed_row("extrapolation, 10 frames",
                              lambda: workflows.extrapolate(basis, a, b, 10, options).shooting, extrapolated,
                              figures, "extrapolation"))
    if "random" not in skip:
        rows.append(timed_row("20 random bodies", lambda: workflows.random_bodies(basis, 20, 3, options), drawn,
                              figures, "random_bodies"))
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
    figures = {}
    rows = user_rows(basis, options, set(args.skip), args.resolution,
                     first_use=bool({"registration", "matching"} - set(args.skip)) or bool(args.bodies) or args.paper,
                     figures=figures)
    title = f"What a user runs: basis '{basis.name}', device {args.device}, torch threads {args.threads}"
    text = f"# {title}\n\n" + markdown_table(header, rows, "{:.1f}")
    tables = [table(title, header, rows)]
    if args.bodies:
        unit = "mm" if basis.units == "m" else basis.units or "units"
        found = body_rows(basis, options, args.bodies, args.resolution)
        body_header = ["seed", "scan faces", f"mean {unit}", f"p95 {unit}", "wall s", "CPU s", "iterations per level"]
        text += ("\n\n## Random bodies, one simulated scan each\n\n" + markdown_table(body_header, found, "{:.2f}"))
        tables.append(table("Random bodies, one simulated scan each", body_header, found))
        suffix = "mm" if basis.units == "m" else "units"
        figures |= {f"bodies_error_mean_{suffix}": float(np.mean([r[2] for r in found])),
                    f"bodies_error_p95_{suffix}": float(np.mean([r[3] for r in found])),
                    "bodies_wall_mean_s": float(np.mean([r[4] for r in found]))}
    if args.paper:
        found = paper_rows(options, args.resolution)
        text += "\n\n## Paper scale\n\n" + markdown_table(header, found, "{:.1f}")
        tables.append(table("Paper scale", header, found))
        figures |= {"paper_registration_wall_s": found[0][1], "paper_interpolation_wall_s": found[1][1]}
    report(f"user_speed_{basis.name}_{args.device}", text)
    faces = figures.get("registration_scan_faces")
    labels = {"registration_wall_s": f"registration of a {faces:,}-face simulated scan" if faces else "registration",
              "registration_error_mm": "its mean vertex error", "registration_error_units": "its mean vertex error",
              "interpolation_wall_s": "interpolation between known codes, T = 24",
              "matching_wall_s": "symmetric matching of two raw scans",
              "extrapolation_wall_s": "extrapolation, 10 frames", "random_bodies_wall_s": "20 random bodies"}
    on_gpu = args.device != "cpu"
    targets = {"registration_wall_s": {"target": 1.0 if on_gpu else 10.0, "better": "lower"},
               "interpolation_wall_s": {"target": 3.0, "better": "lower"},
               "matching_wall_s": {"target": 25.0, "better": "lower"}}
    headline = ["registration_wall_s", "registration_error_mm", "registration_error_units", "interpolation_wall_s",
                "matching_wall_s", "extrapolation_wall_s", "random_bodies_wall_s"]
    write_results("user_speed", figures, tables, targets, variant=variant_of(parser, args), labels=labels,
                  headline=[k for k in headline if k in figures])

if __name__ == "__main__":
    main()
