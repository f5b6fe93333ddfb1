"""Does KeOps compile and run on this device? One varifold value + gradient of two small random
meshes, KeOps against dense torch (exit 1 with the reason if not, or if they disagree).

    python -m bench.keops_check [--device cuda]   # writes bench/results/keops_check[--device-cuda].json
"""

import argparse
import sys
import time

import numpy as np
import torch

from bareesa import varifold as V
from bench.common import table, write_results


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    if not V.kernels.keops_available():
        sys.exit("keops_check: pykeops does not import")
    rng = np.random.default_rng(0)
    faces = torch.tensor(rng.integers(0, 500, size=(800, 3)), device=args.device)
    source = torch.tensor(rng.normal(size=(500, 3)), device=args.device, requires_grad=True)
    target = torch.tensor(rng.normal(size=(500, 3)) + 0.1, device=args.device)
    results, seconds = {}, {}
    for backend in ("keops", "dense"):
        t = time.perf_counter()
        d = V.varifold_distance(source, faces, target, faces, 0.5, backend=backend)
        (g,) = torch.autograd.grad(d, source)
        results[backend], seconds[backend] = (d.item(), g), time.perf_counter() - t
        print(f"{backend} on {args.device}: d^2 = {results[backend][0]:.10g}, {seconds[backend]:.1f} s", flush=True)
    (dk, gk), (dd, gd) = results["keops"], results["dense"]
    err = abs(dk - dd) / abs(dd), float((gk - gd).norm() / gd.norm())
    print(f"relative difference: value {err[0]:.1e}, gradient {err[1]:.1e}")
    # the device is the variant: a CPU and a GPU check are kept apart, whichever is the default here
    write_results("keops_check", {"keops_first_call_s": seconds["keops"], "dense_s": seconds["dense"],
                                  "rel_diff_value": err[0], "rel_diff_grad": err[1]},
                  [table(f"KeOps against dense torch on {args.device} (800 faces, sigma 0.5, value + gradient)",
                         ["backend", "d^2", "seconds (first call)"],
                         [[b, results[b][0], seconds[b]] for b in ("keops", "dense")])],
                  {"rel_diff_value": {"target": 1e-6, "better": "lower"},
                   "rel_diff_grad": {"target": 1e-6, "better": "lower"}},
                  variant="" if args.device == "cpu" else f"device-{args.device}")
    if max(err) > 1e-6:
        sys.exit("keops_check: KeOps and dense torch disagree")


if __name__ == "__main__":
    main()
