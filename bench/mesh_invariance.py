"""Mesh invariance of the varifold distance (the paper's appendix figure).

    python -m bench.mesh_invariance     # writes bench/out/mesh_invariance.{md,png}, bench/results/mesh_invariance.json

face-reference.ply (57,836 faces) normalised to diameter 1 versus its quadric decimation to
2,000 faces; relative error d_Var(q, q') / ||q'||_Var for log-spaced sigma (binet kernel).
Needs trimesh's quadric decimation, i.e. the optional ``fast-simplification`` package
(``pip install fast-simplification``); the PNG needs matplotlib (skipped with a message
otherwise). Data: ../shared/data (override with BAREESA_SHARED).
"""

import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bareesa import varifold as V  # noqa: E402
from bench.common import shared_data, table, write_results  # noqa: E402

SIGMAS = np.geomspace(0.005, 0.5, 13)


def diameter(v):
    hull = trimesh.convex.convex_hull(v).vertices
    d2 = ((hull[:, None, :] - hull[None, :, :]) ** 2).sum(-1)
    return float(np.sqrt(d2.max()))


def mean_triangle_diameter(v, f):
    p = v[f]
    edges = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=-1)
    return float(edges.max(1).mean())


def main():
    data = shared_data("mesh_invariance", "faces/face-reference.ply")
    m = trimesh.load(data / "faces" / "face-reference.ply", process=False)
    v = np.asarray(m.vertices, np.float64)
    v = (v - v.mean(0)) / diameter(v)
    full = trimesh.Trimesh(v, np.asarray(m.faces), process=False)
    try:
        low = full.simplify_quadric_decimation(face_count=2000)
    except (ImportError, ModuleNotFoundError) as err:
        sys.exit(f"mesh_invariance: quadric decimation needs the optional package "
                 f"fast-simplification (pip install fast-simplification): {err}")
    vf, ff = np.asarray(full.vertices), np.asarray(full.faces)
    vl, fl = np.asarray(low.vertices), np.asarray(low.faces)
    t = lambda a: torch.tensor(a, dtype=torch.float64 if a.dtype.kind == "f" else torch.long)  # noqa: E731
    lines = ["# Varifold mesh invariance (face-reference.ply, diameter 1)", "",
             f"Full mesh: {len(ff)} faces, mean triangle diameter {mean_triangle_diameter(vf, ff):.2e}; "
             f"decimated (quadric, fast-simplification): {len(fl)} faces, mean triangle diameter "
             f"{mean_triangle_diameter(vl, fl):.2e}. Binet kernel, float64.", "",
             "| sigma | d_Var(q, q') / ‖q'‖_Var | backend | seconds |", "|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    rel, rows = [], []
    with torch.no_grad():
        ql = V.varifold_measure(t(vl), t(fl))
        for sigma in SIGMAS:
            start = time.perf_counter()
            loss = V.VarifoldLoss(t(vl), t(fl), sigma)
            d2 = loss(t(vf), t(ff))
            norm2 = V.varifold_inner(*ql, *ql, sigma, backend="dense")
            rel.append(float(d2.clamp_min(0)) ** 0.5 / float(norm2) ** 0.5)
            rows.append([float(sigma), rel[-1], loss.stats["backend"], time.perf_counter() - start])
            lines.append(f"| {sigma:.4f} | {rel[-1]:.2e} | {loss.stats['backend']} | {rows[-1][-1]:.1f} |")
            print(lines[-1], flush=True)
    out = ROOT / "bench" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "mesh_invariance.md").write_text("\n".join(lines) + "\n")
    figures = {"full_faces": len(ff), "decimated_faces": len(fl), "rel_error_min": min(rel), "rel_error_max": max(rel)}
    figures |= {f"rel_error_sigma_{s:.3g}": r for s, r in zip(SIGMAS[::3], rel[::3])}
    write_results("mesh_invariance", figures,
                  [table(f"d_Var(q, q') / ||q'||_Var, {len(ff)} vs {len(fl)} faces, diameter 1",
                         ["sigma", "relative error", "backend", "seconds"], rows)])
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: PNG plot skipped (pip install matplotlib)")
        return
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    ax.semilogx(SIGMAS, rel, "o-")
    ax.set_xlabel("kernel scale sigma (diameter = 1)")
    ax.set_ylabel("d_Var(q, q') / ||q'||_Var")
    ax.set_title(f"{len(ff)} vs {len(fl)} faces")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "mesh_invariance.png", dpi=150)
    print(f"plot written to {out / 'mesh_invariance.png'}")


if __name__ == "__main__":
    main()
