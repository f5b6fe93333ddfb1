"""Does KeOps compile and run on this device? One varifold value + gradient of two small random
meshes, KeOps against dense torch (exit 1 with the reason if not, or if they disagree).

    python -m bench.keops_check [--device cuda]
"""

import argparse
import sys
import time

import numpy as np
import torch

from bareesa import varifold as V


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
    results = {}
    for backend in ("keops", "dense"):
        t = time.perf_counter()
        d = V.varifold_distance(source, faces, target, faces, 0.5, backend=backend)
        (g,) = torch.autograd.grad(d, source)
        results[backend] = (d.item(), g)
        print(f"{backend} on {args.device}: d^2 = {results[backend][0]:.10g}, {time.perf_counter() - t:.1f} s",
              flush=True)
    (dk, gk), (dd, gd) = results["keops"], results["dense"]
    err = abs(dk - dd) / abs(dd), float((gk - gd).norm() / gd.norm())
    print(f"relative difference: value {err[0]:.1e}, gradient {err[1]:.1e}")
    if max(err) > 1e-6:
        sys.exit("keops_check: KeOps and dense torch disagree")


if __name__ == "__main__":
    main()
