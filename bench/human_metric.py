"""Candidate H2 weights for the ``human`` basis' geodesics, compared on *training* motions.

Held-out identities 5 and 6 (never seen by the build; ``bench.human_accuracy`` measures identities
0-3) perform four training motions (arms raise front, punch, biceps curl, reach), regenerated with
Anny (needs the ``[bases]`` extra). In fixed windows (``WINDOWS``: frames k -> k + 2h, h = 5, at
24 fps) each candidate metric is compared as ``bench.human_accuracy`` compares methods: the CLI
default (anchored geodesic + the ends' off-basis detail) against the latent line and the vertex
blend, at a quarter, half and three quarters of the way; extrapolation from (k, k + h) to k + 2h and
k + 3h (the shooting's failures are counted and left out). End codes are projections of the true
frames with each candidate's metric (the projection's ridge uses it too).

It chose ``bases.build.human.MOTION_WEIGHTS``, the shipped basis' metric of motion paths; registration
and random bodies keep the paper's weights (its ``shape_metric``).

Usage: python -m bench.human_metric [--weights A0,A1,B1,C1,D1,A2 ...] [--threads 2]
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

IDENTITIES = (5, 6)
MOTIONS = ("arms_raise_front", "punch", "biceps_curl", "reach")
#: (identity, motion, first frame k, half span h)
WINDOWS = ((5, "arms_raise_front", 6, 5), (5, "punch", 6, 5), (5, "biceps_curl", 24, 5), (5, "reach", 6, 5),
           (6, "punch", 24, 5), (6, "reach", 24, 5), (6, "arms_raise_front", 24, 5), (6, "biceps_curl", 6, 5))
CANDIDATES = ("1,1000,100,1,1,1", "1e4,1000,100,1,1,0.01", "1e5,1000,100,1,1,1")
METHODS = ("CLI default", "latent line", "vertex blend")


def training_motions():
    """{(identity, motion): (T, N, 3) every frame} for the held-out identities in training motions."""
    from bases.build import human as hb

    gen = hb.Human(lambda *_: None)
    _, test = hb.identities(model=gen.model)
    return {(i, m): gen.motion(hb._take(test, i), m, step=1) for i in IDENTITIES for m in MOTIONS}


def compare(basis, seqs, windows=WINDOWS):
    """-> ({task: {method: [(hausdorff, chamfer, varifold) per window]}}, shooting failures)."""
    from bareesa.errors import ShootingFailed
    from bareesa.latent import off_basis_detail, project_to_basis
    from bench.humanoid_accuracy import extrapolation_window, interpolation_window

    # this bench's method names -> the window functions'
    shown = dict(zip(METHODS, ("H2 anchored + detail", "latent line", "vertex blend")))
    out = {task: {m: [] for m in METHODS} for task in ("interpolation", "extrapolation")}
    failures = 0
    for ident, motion, k, half in windows:
        full = seqs[(ident, motion)].astype(np.float64)
        seq = full[k:k + 3 * half + 1]
        sigma = 0.025 * float(full[0][:, 2].max() - full[0][:, 2].min())
        codes = project_to_basis(basis, seq)[0]
        detail = off_basis_detail(basis, seq, codes)
        found = interpolation_window(basis, seq, codes, detail, 0, half, sigma)
        for name in METHODS:
            out["interpolation"][name].append(found[shown[name]])
        try:
            found = extrapolation_window(basis, seq, codes, detail, 0, half, [2 * half, 3 * half], sigma)
        except ShootingFailed:
            failures += 1
            continue
        for name in METHODS:
            out["extrapolation"][name].append(found[shown[name]])
    return out, failures


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", nargs="*", default=list(CANDIDATES), help="candidate metrics a0,a1,b1,c1,d1,a2")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    from bareesa.basis_io import load_basis
    from bareesa.h2_metric import H2Weights

    from bench.common import table, variant_of, write_results

    seqs = training_motions()
    print("weights                      task           method        hausdorff_mm  chamfer_mm  varifold  n  "
          "shooting failures  seconds")
    rows, figures = [], {}
    for c, spec in enumerate(args.weights):
        basis = load_basis("human")
        basis.weights = H2Weights.parse(spec)
        start = time.perf_counter()
        out, failures = compare(basis, seqs)
        seconds = time.perf_counter() - start
        for task, per_method in out.items():
            for name, ds in per_method.items():
                if ds:
                    m = np.mean(ds, axis=0)
                    print(f"{spec:28s} {task:14s} {name:13s} {1e3 * m[0]:12.1f} {1e3 * m[1]:11.2f} {m[2]:9.3g} "
                          f"{len(ds):2d}  {failures:17d}  {seconds:7.0f}", flush=True)
                    rows.append([spec, task, name, 1e3 * m[0], 1e3 * m[1], m[2], len(ds), failures, seconds])
                    if name == "CLI default":  # candidate c's figures; the table names its weights
                        figures[f"candidate{c + 1}_{task}_chamfer_mm"] = 1e3 * m[1]
                        figures[f"candidate{c + 1}_{task}_hausdorff_mm"] = 1e3 * m[0]
        figures[f"candidate{c + 1}_shooting_failures"] = failures
    write_results("human_metric", figures,
                  [table("Candidate H2 weights on windows of training motions of held-out identities",
                         ["weights", "task", "method", "hausdorff_mm", "chamfer_mm", "varifold", "n",
                          "shooting failures", "seconds"], rows)],
                  variant=variant_of(parser, args), argv=sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    main()
