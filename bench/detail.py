"""The detail layer of the default ``human`` basis: the scan's own detail on the registered mesh.

Data: the real body ``../shared/data/body/DFAUST_template.ply`` (a clean mesh of a real person, another
triangulation), randomly oriented; held-out Anny people (``bench.pose_coverage.held_out_truths``, never in
training; ``--truths FILE`` caches them) at rest and in random poses, as
  clean   the clean body's surface triangulated anew (every face split in four at random points along
          its edges, vertex and face orders shuffled): no noise, no holes;
  noisy   the same with ~2 mm Gaussian noise (``--noise``, metres on a 1.7 m body);
  holes   noisy, with 3 holes of 4 % of the size.
Each is registered as the CLI does (no landmarks, the card's settings) with the detail layer on, and the
basis fit and the detailed mesh are compared with the TRUE clean surface (the body before noise and holes):
mean distance each way and Hausdorff (BVH, surface to surface), the detail layer's flipped or collapsed faces
against the basis fit, surface self-intersections added, the largest spike into a hole (template vertices
over a hole: their distance to the true surface, detailed minus basis fit, % of height) and the layer's time
over the basis fit's.

Usage: python -m bench.detail [--people N] [--real N] [--truths FILE] [--threads T] [--figure PNG]
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import dict_table, variant_of, write_results  # noqa: E402
from bench.human_accuracy import DFAUST, surface_distances  # noqa: E402

KINDS = ("clean", "noisy", "holes")


def _over_holes(fit, scan, reach=0.01):
    """Vertices of a fit (N, 3) farther than ``reach`` from every scan vertex: the parts over holes."""
    from scipy.spatial import cKDTree

    return cKDTree(scan).query(fit, k=1)[0] > reach


def row(basis, name, kind, truth, truth_faces, scan, scan_faces, height):
    """Register one scan (its frame = the truth's) with the detail layer; compare both fits with the truth."""
    from scipy.spatial import cKDTree

    from bareesa.mesh import self_intersections
    from bareesa.registration import register
    from bareesa.registration.detail import bad_faces

    t0 = time.perf_counter()
    res = register(basis, scan, scan_faces)
    seconds = time.perf_counter() - t0
    report = res.detail_report
    detail_s = report["seconds"] if report["levels"] else 0.0
    out = {"body": name, "kind": kind, "poor_fit": bool(res.poor_fit)}
    b = surface_distances(res.vertices, basis.faces, truth, truth_faces)
    out |= {"basis_fit_mm": round(1e3 * b[0], 2), "basis_truth_mm": round(1e3 * b[1], 2),
            "basis_hausdorff_mm": round(1e3 * b[2], 1)}
    detailed = res.output_vertices
    d = surface_distances(detailed, basis.faces, truth, truth_faces)
    out |= {"detail_fit_mm": round(1e3 * d[0], 2), "detail_truth_mm": round(1e3 * d[1], 2),
            "detail_hausdorff_mm": round(1e3 * d[2], 1), "kept": report["kept"], "skipped": report["skipped"]}
    if truth.shape == detailed.shape and truth_faces is basis.faces:  # a held-out body: its true correspondence
        out["basis_vertex_mm"] = round(1e3 * float(np.linalg.norm(res.vertices - truth, axis=1).mean()), 2)
        out["detail_vertex_mm"] = round(1e3 * float(np.linalg.norm(detailed - truth, axis=1).mean()), 2)
    else:
        out["basis_vertex_mm"] = out["detail_vertex_mm"] = None
    out["bad_faces"] = int(bad_faces(detailed, basis.faces, res.vertices).sum())
    out["crossings_added"] = len(self_intersections(detailed, basis.faces)) - len(self_intersections(res.vertices,
                                                                                                    basis.faces))
    holes = _over_holes(res.vertices, scan) if kind == "holes" else np.zeros(len(detailed), bool)
    if holes.any():
        tree = cKDTree(truth)  # (the truth's vertices: the true surface, densely enough at these lengths)
        spike = tree.query(detailed[holes])[0] - tree.query(res.vertices[holes])[0]
        out["hole_spike_pct_height"] = round(100 * float(max(spike.max(), 0.0)) / height, 3)
    else:
        out["hole_spike_pct_height"] = None
    out |= {"basis_fit_s": round(seconds - detail_s, 1), "detail_s": round(detail_s, 1),
            "detail_over_basis_pct": round(100 * detail_s / max(seconds - detail_s, 1e-9), 1)}
    return out, res


def real_rows(basis, n, seed=0):
    """The DFAUST template, randomly oriented: the registered meshes against it."""
    import trimesh

    from bareesa.transforms import Similarity, axis_angle_rotation

    if not DFAUST.exists():
        print(f"(no {DFAUST}: the real-body rows are skipped)")
        return [], None
    mesh = trimesh.load(DFAUST, process=False)
    body_v, body_f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    rng = np.random.default_rng(seed)
    rows, shown = [], None
    for k in range(n):
        axis = rng.normal(size=3)
        sim = Similarity(rotation=axis_angle_rotation(axis / np.linalg.norm(axis) * rng.uniform(0, np.pi)),
                         scale=1.0, translation=rng.normal(size=3))
        scan = sim.apply(body_v)
        out, res = row(basis, f"DFAUST #{k}", "real", scan, body_f, scan, body_f, np.ptp(body_v[:, 2]))
        rows.append(out)
        print("  ".join(str(v) for v in out.values()), flush=True)
        if shown is None:
            shown = (scan, body_f, res)
    return rows, shown


def people_rows(basis, truths, names, noise, seed=0):
    """Held-out Anny people as clean, noisy and holed scans: the body's surface exactly, triangulated anew
    (``synthetic.remesh_same_surface``: no face or vertex of the template's), then noise and holes; the
    registered meshes against the clean body."""
    from bareesa.scan_simulator import simulate_scan
    from bareesa.synthetic import remesh_same_surface

    rows = []
    for k, name in enumerate(names):
        body = truths[name].astype(np.float64)
        height = float(np.ptp(body[:, 2]))
        size = 2 * float(np.sqrt(((body - body.mean(0)) ** 2).sum(1).mean()))
        fine, fine_faces = remesh_same_surface(body, basis.faces, seed=seed + k)
        for kind in KINDS:
            scan, scan_faces, info = simulate_scan(fine, fine_faces, seed=seed + k, remesh=None,
                                                   noise=0.0 if kind == "clean" else noise / size,
                                                   holes=3 if kind == "holes" else 0, rigid=False)
            out, _ = row(basis, name, kind, body, basis.faces, scan, scan_faces, height)
            rows.append(out)
            print("  ".join(str(v) for v in out.values()), flush=True)
    return rows


def summary(rows):
    """Figures of the run, by kind of scan."""
    figures = {}
    for kind in ("real",) + KINDS:
        some = [r for r in rows if r["kind"] == kind]
        if not some:
            continue
        figures |= {f"{kind}_basis_mean_mm": round(max(max(r["basis_fit_mm"], r["basis_truth_mm"]) for r in some), 2),
                    f"{kind}_detail_mean_mm": round(max(max(r["detail_fit_mm"], r["detail_truth_mm"]) for r in some), 2),
                    f"{kind}_basis_hausdorff_mm": max(r["basis_hausdorff_mm"] for r in some),
                    f"{kind}_detail_hausdorff_mm": max(r["detail_hausdorff_mm"] for r in some),
                    f"{kind}_detail_kept": sum(bool(r["kept"]) for r in some), f"{kind}_scans": len(some)}
    noisy = [r for r in rows if r["kind"] in ("noisy", "holes")]
    if noisy:
        figures["noisy_closer_to_truth_pct"] = round(100 * float(np.mean(
            [r["detail_fit_mm"] + r["detail_truth_mm"] < r["basis_fit_mm"] + r["basis_truth_mm"] for r in noisy])), 1)
    spikes = [r["hole_spike_pct_height"] for r in rows if r["hole_spike_pct_height"] is not None]
    if spikes:
        figures["hole_spike_max_pct_height"] = max(spikes)
    figures["bad_faces"] = sum(r["bad_faces"] for r in rows)
    figures["crossings_added_max"] = max(r["crossings_added"] for r in rows)
    figures["detail_over_basis_median_pct"] = round(float(np.median([r["detail_over_basis_pct"] for r in rows])), 1)
    figures["detail_over_basis_max_pct"] = max(r["detail_over_basis_pct"] for r in rows)
    return figures


def figure(path, shown, top=5.0):
    """Scan, basis fit and detailed fit of the real body, the fits' faces coloured by their distance to the
    scan's surface (mm, 0 to ``top``)."""
    import bpy  # noqa: F401  (puts bpy's mathutils on the path)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mathutils.bvhtree import BVHTree
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from bareesa.basis_io import load_basis

    scan, scan_faces, res = shown
    frame = res.transform  # shown upright, in the template frame
    upright = frame.apply(scan)
    tree = BVHTree.FromPolygons(upright.tolist(), np.asarray(scan_faces).tolist())
    faces = load_basis("human").faces
    panels = [("scan", upright, scan_faces, None)]
    for title, verts in (("basis fit", res.vertices), ("detailed fit", res.output_vertices)):
        v = frame.apply(verts)
        dist = 1e3 * np.array([tree.find_nearest(p)[3] for p in v[faces].mean(1)]) / frame.scale
        panels.append((title, v, faces, dist))
    fig = plt.figure(figsize=(11, 7))
    lo, hi = upright.min(0), upright.max(0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    for k, (title, v, f, dist) in enumerate(panels):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        colours = "lightgray" if dist is None else plt.cm.viridis(np.clip(dist / top, 0, 1))
        ax.add_collection3d(Poly3DCollection(v[f], facecolors=colours, edgecolor="none"))
        ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
               zlim=(centre[2] - half, centre[2] + half))
        ax.set_box_aspect((1, 1, 1), zoom=1.5)
        ax.view_init(elev=5, azim=-90)
        ax.set_axis_off()
        ax.set_title(title, fontsize=10)
    bar = fig.colorbar(plt.cm.ScalarMappable(norm=plt.Normalize(0, top), cmap="viridis"), ax=fig.axes,
                       orientation="horizontal", fraction=0.04, pad=0.02)
    bar.set_label(f"distance to the scan's surface (mm; {top:g} and more alike)")
    fig.savefig(path, dpi=90, bbox_inches="tight")
    print(f"figure written to {path}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--people", type=int, default=6, help="held-out Anny people (each clean, noisy, holes)")
    parser.add_argument("--real", type=int, default=2, help="random orientations of the real body")
    parser.add_argument("--noise", type=float, default=0.002, help="the noisy scans' noise (m)")
    parser.add_argument("--basis", default="human")
    parser.add_argument("--truths", type=Path, help="cache of the held-out bodies (as bench.pose_coverage's)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--figure", type=Path, help="also render the real body's scan, basis and detailed fits")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    from bareesa.basis_io import load_basis

    basis = load_basis(args.basis)
    rows, shown = real_rows(basis, args.real)
    if args.people:
        from bench.pose_coverage import cached_truths

        truths = cached_truths(args.truths, basis, args.people, args.people)
        names = ([n for n in truths if n.startswith("apose")][:(args.people + 1) // 2]
                 + [n for n in truths if n.startswith("random")][:args.people // 2])
        rows += people_rows(basis, truths, names, args.noise)
    figures = summary(rows)
    write_results("detail", figures, [dict_table("Basis fit and detailed fit against the true surface", rows)],
                  TARGETS, variant=variant_of(parser, args, ("truths", "threads", "figure")), labels=LABELS)
    if args.figure is not None and shown is not None:
        figure(args.figure, shown)
    for key, value in figures.items():
        print(f"{key}: {value}")
    import os

    sys.stdout.flush()
    os._exit(0)  # bpy (the BVH distances) can hang in its exit handlers


TARGETS = {"real_detail_mean_mm": {"target": 1.0, "better": "lower"},
           "real_detail_hausdorff_mm": {"target": 10.0, "better": "lower"},
           "clean_detail_mean_mm": {"target": 1.0, "better": "lower"},
           "clean_detail_hausdorff_mm": {"target": 10.0, "better": "lower"},
           "noisy_closer_to_truth_pct": {"target": 100.0, "better": "higher"},
           "bad_faces": {"target": 0, "better": "lower"},
           "crossings_added_max": {"target": 0, "better": "lower"},
           "hole_spike_max_pct_height": {"target": 1.0, "better": "lower"},
           "detail_over_basis_max_pct": {"target": 50.0, "better": "lower"}}
LABELS = {"real_detail_mean_mm": "real body (DFAUST): detailed fit, mean distance each way, worst",
          "real_detail_hausdorff_mm": "real body: detailed fit, Hausdorff",
          "real_basis_mean_mm": "real body: basis fit, mean distance each way, worst",
          "clean_detail_mean_mm": "clean held-out people: detailed fit, mean distance each way, worst",
          "clean_detail_hausdorff_mm": "clean held-out people: detailed fit, Hausdorff",
          "noisy_closer_to_truth_pct": "noisy scans (2 mm): detailed fits closer to the true surface than the basis fit",
          "bad_faces": "flipped or collapsed faces added by the detail layer",
          "crossings_added_max": "surface self-intersections added by the detail layer (worst scan)",
          "hole_spike_max_pct_height": "largest spike into a hole",
          "detail_over_basis_max_pct": "detail layer's time over the basis fit's, worst"}


if __name__ == "__main__":
    main()
