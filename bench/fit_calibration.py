"""Calibrate a basis' poor-fit threshold: what residual does it reach on its own held-out scans?

Random bodies of the basis (its stored distribution, shot as ``sample`` does) are turned into
simulated scans (``scan_simulator`` defaults: remeshed, noisy, holed, arbitrary rotation and
scale) and registered as the CLI does; the residual of each (``registration.multiscale.fit_residual``:
mean distance from the scan to the registered surface over the basis' size) gives the held-out
distribution, and a torus of the template's size registered the same way shows what a wrong
shape scores. ``--write`` stores the threshold (FACTOR x the held-out 95th percentile) in the
basis card (``fit_check``), which ``register`` then uses to flag a poor fit.

    python -m bench.fit_calibration --basis deformables --scans 8 [--write] [--threads 2] [--device cuda]
"""

import argparse
import time

import numpy as np
import torch

from bench.common import markdown_table, report, table, variant_of, write_results
from bareesa import basis_io, registration, synthetic, workflows
from bareesa.scan_simulator import simulate_scan

#: A residual above FACTOR x the held-out 95th percentile is a poor fit: the default of --factor for a
#: card not calibrated yet (a card keeps its own factor, chosen between its right and wrong fits' scores).
FACTOR = 3.0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--basis", default=basis_io.DEFAULT_BASIS)
    parser.add_argument("--scans", type=int, default=8)
    parser.add_argument("--seed", type=int, default=100, help="first seed (held out: the build never uses them)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--write", action="store_true", help="store the threshold in the basis card")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--factor", type=float, default=None,
                        help=f"poor fit above this x the held-out p95 (default: the card's, else {FACTOR:g})")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    basis = basis_io.load_basis(args.basis)
    if args.factor is None:  # a recalibration keeps the factor the card was calibrated with
        args.factor = float(basis.fit_check.get("factor", FACTOR))
    options = workflows.Options(device=args.device)
    bodies = workflows.random_bodies(basis, args.scans, args.seed, options, shoot_steps=4)
    rows, residuals = [], []
    for k, code in enumerate(bodies.codes):
        truth = basis.template + np.tensordot(code, basis.fields, axes=1)
        scan_v, scan_f, _ = simulate_scan(truth, basis.faces, seed=args.seed + k)
        t0 = time.perf_counter()
        res = registration.register(basis, scan_v, scan_f, device=args.device)
        residuals.append(res.residual)
        rows.append([f"held-out body {k}", len(scan_f), res.residual, time.perf_counter() - t0])
        print(f"body {k}: residual {res.residual:.4g} ({rows[-1][-1]:.0f} s)", flush=True)
    u, faces = synthetic.torus(64, 32)
    center = basis.template.mean(0)
    radius = np.sqrt(((basis.template - center) ** 2).sum(1).mean())
    torus_v, torus_f, _ = simulate_scan(center + radius * u / np.sqrt((u ** 2).sum(1).mean()), faces, seed=args.seed)
    foreign = registration.register(basis, torus_v, torus_f, device=args.device).residual
    rows.append(["a torus (a shape no basis here makes)", len(torus_f), foreign, float("nan")])
    p95 = float(np.percentile(residuals, 95))
    threshold = args.factor * p95
    text = (f"# Fit calibration: basis '{basis.name}', {args.scans} held-out simulated scans\n\n"
            + markdown_table(["scan", "faces", "residual (of size)", "seconds"], rows, "{:.4g}")
            + f"\n\nheld-out median {np.median(residuals):.4g}, 95th percentile {p95:.4g}, max {max(residuals):.4g};"
            f" poor fit above {threshold:.4g} ({args.factor:g} x p95); the torus scores {foreign:.4g}"
            f" ({foreign / threshold:.2g} x the threshold)")
    report(f"fit_calibration_{basis.name}", text)
    write_results("fit_calibration", {
        "held_out_median_residual": float(np.median(residuals)), "held_out_p95_residual": p95,
        "held_out_max_residual": float(max(residuals)), "poor_fit_threshold": threshold,
        "torus_residual": foreign, "torus_over_threshold": foreign / threshold,
        "registration_mean_wall_s": float(np.mean([r[-1] for r in rows[:-1]]))},
        [table(f"Fit calibration: basis '{basis.name}', {args.scans} held-out simulated scans",
               ["scan", "faces", "residual (of size)", "seconds"], rows)],
        {"torus_over_threshold": {"target": 1.0, "better": "higher"}},
        variant=variant_of(parser, args, ("write",)),
        labels={"torus_over_threshold": "a torus' residual over the poor-fit threshold (flagged above 1)"})
    if args.write:
        basis_io.update_card(args.basis, fit_check={
            "residual": "mean distance from the scan to the registered surface / basis size (template frame)",
            "held_out_median": float(np.median(residuals)), "held_out_p95": p95, "held_out_max": float(max(residuals)),
            "poor_fit_above": threshold, "factor": args.factor, "scans": int(args.scans), "foreign_torus": float(foreign),
            "measured_by": f"python -m bench.fit_calibration --basis {args.basis} --scans {args.scans} "
                           f"--factor {args.factor:g} --write",
            "date": time.strftime("%Y-%m-%d")})
        print(f"wrote fit_check into the card of {basis_io.resolve_basis_path(args.basis)}")


if __name__ == "__main__":
    main()
