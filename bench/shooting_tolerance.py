"""How accurately must a geodesic step be solved, and how far may a step change the speed?

Random bodies of a bundled basis (its stored distribution, shot from the template as ``sample``
does) are shot with every step solved only to a tolerance tol (the remaining quasi-Newton
correction relative to the step length, metric norm) and compared with a reference solved to
1e-9: the largest vertex deviation over the shot frames, in the basis' units and relative to its
size. This chooses ``shooting.ACCEPT_TOL``: a step whose iteration stalls is accepted when its
correction is below it. The same shots at 2 and 4 substeps per frame give the time-discretisation
error next to it, and the largest change of metric speed between consecutive steps
(``ShootingReport.max_speed_change``) at each resolution, which chooses ``shooting.SPEED_TOL``.

    python -m bench.shooting_tolerance [--basis NAME|NPZ] [--seeds 8] [--steps 8] [--threads 2] [--device cuda]
"""

import argparse
import time

import numpy as np
import torch

from bench.common import markdown_table, report, variant_of, write_results
from bench.common import table as results_table
from bareesa import basis_io, shooting, statistics
from bareesa.geodesics import decode_path

TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-6)


def shot(basis, velocity, steps, tol, substeps=1, device="cpu"):
    """Frames (steps + 1, N, 3) of the geodesic from the template, every step solved to ``tol`` at a fixed
    time resolution (no refinement), and its report."""
    t, f, h = basis.tensors(device=device)
    alpha1 = velocity / steps
    path, rep = shooting.extrapolate(t, f, h, np.zeros_like(velocity), alpha1, basis.weights, steps - 1, tol=tol,
                                     accept_tol=max(tol, 1e-6), substeps=substeps, max_substeps=substeps,
                                     speed_tol=np.inf, with_report=True)
    return decode_path(t, h, path), rep


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--basis", default=basis_io.DEFAULT_BASIS)
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    basis = basis_io.load_basis(args.basis)
    size = float((basis.template.max(0) - basis.template.min(0)).max())
    dist = {k: v for k, v in basis.extras.items() if k.startswith("gmm_")}
    rows_tol, rows_time = {tol: [] for tol in TOLERANCES}, {k: [] for k in (2, 4)}
    speed = {k: [] for k in (1, 2, 4)}
    failed = []
    for seed in range(args.seeds):
        v = statistics.sample_velocities(dist, basis.groups, 1, seed)[0]
        t0 = time.perf_counter()
        try:
            ref, rep = shot(basis, v, args.steps, 1e-9, device=args.device)
        except shooting.ShootingFailed as err:
            failed.append(f"seed {seed}: {err}")
            print(f"seed {seed}: reference failed: {err}", flush=True)
            continue
        speed[1].append(rep.max_speed_change)
        for tol in TOLERANCES:
            try:
                frames, _ = shot(basis, v, args.steps, tol, device=args.device)
                rows_tol[tol].append(np.abs(frames - ref).max())
            except shooting.ShootingFailed as err:
                failed.append(f"seed {seed}, tol {tol:g}: {err}")
        for k in (2, 4):
            try:
                frames, rep_k = shot(basis, v, args.steps, 1e-9, substeps=k, device=args.device)
                rows_time[k].append(np.abs(frames - ref).max())
                speed[k].append(rep_k.max_speed_change)
            except shooting.ShootingFailed as err:
                failed.append(f"seed {seed}, {k} substeps: {err}")
        print(f"seed {seed}: done in {time.perf_counter() - t0:.0f} s; largest speed change {rep.max_speed_change:.3g}",
              flush=True)
    unit = basis.units or "units"
    table = [[f"solved to {tol:g}", len(d), float(np.max(d)) if d else float("nan"),
              float(np.max(d)) / size if d else float("nan")] for tol, d in rows_tol.items()]
    table += [[f"{k} substeps per frame (time discretisation)", len(d), float(np.max(d)) if d else float("nan"),
               float(np.max(d)) / size if d else float("nan")] for k, d in rows_time.items()]
    head1 = ["shots", "n", f"max deviation ({unit})", "relative to size"]
    head2 = ["steps per frame", "n", "median", "max"]
    speeds = [[k, len(s), float(np.median(s)) if s else float("nan"), float(np.max(s)) if s else float("nan")]
              for k, s in speed.items()]
    text = (f"# Shooting tolerance: basis '{basis.name}', {args.seeds} random bodies, {args.steps} steps\n\n"
            f"Largest vertex deviation from the reference (every step solved to 1e-9, 1 step per frame):\n\n"
            + markdown_table(head1, table, "{:.3g}")
            + "\n\nLargest change of metric speed between consecutive steps (accepted shots):\n\n"
            + markdown_table(head2, speeds, "{:.3g}")
            + ("\n\nFailures:\n" + "\n".join(f"- {x}" for x in failed) if failed else "\n\nNo failures."))
    report("shooting_tolerance", text)
    figures = {f"max_deviation_tol_{tol:g}_rel_size": row[3] for tol, row in zip(TOLERANCES, table)}
    figures |= {f"max_deviation_{k}_substeps_rel_size": row[3] for k, row in zip((2, 4), table[len(TOLERANCES):])}
    figures |= {f"max_speed_change_{row[0]}_steps_per_frame": row[3] for row in speeds}
    figures["failures"] = len(failed)
    write_results("shooting_tolerance", figures,
                  [results_table("Largest vertex deviation from the reference (every step solved to 1e-9)", head1,
                                 table),
                   results_table("Largest change of metric speed between consecutive steps", head2, speeds)]
                  + ([results_table("Failures", ["failure"], [[x] for x in failed])] if failed else []),
                  variant=variant_of(parser, args))


if __name__ == "__main__":
    main()
