"""Registration and interpolation on the deformed-sphere data (issue: latent space).

(1) Simulated scans (voxel remesh, noise, random rigid motion and scale) of the
held-out +-60 frames are registered; errors against the true correspondence.
(2) Interpolation 30 -> 90 (and -30 -> -90) of each family; the midpoint is
compared with the true 60 frame for the H2 latent geodesic, the straight line in
latent space and the linear vertex blend (the paper's Table 5 ablation).
Run: python -m bench.sphere_registration   (writes bench/out/sphere_registration.{md,png})
"""

import time

import numpy as np
import torch

import bench.common  # noqa: F401  (puts the repo on sys.path)
from bench.common import OUT, contact_sheet, markdown_table, report, table, write_results
from bench.sphere_data import FAMILIES, HELD_OUT, load_frames, sphere_basis
from bareesa import evaluation
from bareesa.geodesics import decode_path, geodesic, resample_path
from bareesa.latent import project_to_basis
from bareesa.registration import register
from bareesa.scan_simulator import apply_similarity, simulate_scan


def shape_metrics(verts, faces, truth, sigma):
    """Vertex error (truth correspondence), Chamfer, Hausdorff, varifold against the true mesh."""
    err = evaluation.vertex_error(verts, truth)
    return [err["mean"], err["p95"], evaluation.chamfer(verts, truth), evaluation.hausdorff(verts, truth),
            evaluation.varifold(verts, faces, truth, faces, sigma)]


def main():
    torch.set_num_threads(2)
    frames, faces = load_frames("sphere_registration")
    basis = sphere_basis(frames, faces)
    length = basis.scale
    sigma = basis.schedule[-1].sigma * basis.scale
    print(f"basis: {basis.n_fields} fields from {basis.provenance['groups']['pose']['tangent_vectors']} "
          f"tangent vectors; shape length {length:.2f}; finest sigma {sigma:.3f}")

    rows = []
    for fam in FAMILIES:
        for angle in HELD_OUT:
            truth = frames[(fam, angle)]
            sv, sf, info = simulate_scan(truth, faces, seed=abs(angle) + len(fam), holes=0, scale=0.3, resolution=0.03)
            t0 = time.perf_counter()
            res = register(basis, sv, sf)
            secs = time.perf_counter() - t0
            truth_scan = apply_similarity(info, truth)  # the truth in the scan's frame
            err = evaluation.vertex_error(res.vertices, truth_scan)
            scale = info["scale"]
            rows.append([f"{fam} {angle:+d}", len(sf), err["mean"] / scale / length * 100,
                         err["p95"] / scale / length * 100,
                         evaluation.chamfer(res.vertices, sv) / scale / length * 100,
                         evaluation.hausdorff(res.vertices, sv) / scale / length * 100, res.varifold, secs])
            print("  ", *(f"{x:.4g}" if isinstance(x, float) else x for x in rows[-1]), flush=True)
    mean = ["mean", "", *np.mean([r[2:] for r in rows], axis=0)]
    head1 = ["held-out frame", "scan faces", "vertex err mean %L", "vertex err p95 %L", "Chamfer %L", "Hausdorff %L",
             "varifold (template frame)", "seconds"]
    part1 = markdown_table(head1, rows + [mean])

    t, f, h = basis.tensors()
    rows2, sheet, titles = [], [], []
    for fam in FAMILIES:
        for sign in (1, -1):
            a, b, mid = frames[(fam, 30 * sign)], frames[(fam, 90 * sign)], frames[(fam, 60 * sign)]
            ca, cb = project_to_basis(basis, a)[0], project_to_basis(basis, b)[0]
            g = geodesic(t, f, h, ca, cb, basis.weights, steps=9, metric=basis.template_metric())
            h2_mid = decode_path(t, h, resample_path(t, f, h, g.path, basis.weights, 3))[1]
            lat_mid = decode_path(t, h, ((ca + cb) / 2)[None])[0]
            lin_mid = (a + b) / 2
            for name, v in (("H2 geodesic", h2_mid), ("latent line", lat_mid), ("vertex blend", lin_mid)):
                rows2.append([f"{fam} {30 * sign:+d}->{90 * sign:+d}", name,
                              *shape_metrics(v, faces, mid, sigma)])
            if fam == "bend_Y" and sign == 1:
                sheet = [(a, faces), (mid, faces), (h2_mid, faces), (lat_mid, faces), (lin_mid, faces), (b, faces)]
                titles = ["30", "true 60", "H2 geodesic", "latent line", "vertex blend", "90"]
    summary = []
    for name in ("H2 geodesic", "latent line", "vertex blend"):
        vals = np.array([r[2:] for r in rows2 if r[1] == name])
        summary.append(["mean", name, *vals.mean(0)])
    head2 = ["interpolation", "method", "vertex err mean", "vertex err p95", "Chamfer", "Hausdorff", "varifold"]
    part2 = markdown_table(head2, rows2 + summary)
    contact_sheet(OUT / "sphere_registration.png", sheet, titles, elev=10, azim=-30)
    report("sphere_registration",
           "## Registration of simulated scans of held-out frames (errors in % of the shape length L)\n\n"
           + part1 + "\n\n## Interpolation midpoints against the true 60 frame\n\n" + part2
           + f"\n\nPNG: {OUT / 'sphere_registration.png'}")
    figures = {"registration_error_mean_pct_length": mean[2], "registration_error_p95_pct_length": mean[3],
               "registration_wall_s": mean[-1]}
    figures |= {f"interpolation_{r[1].replace(' ', '_').lower()}_error_mean_units": r[2] for r in summary}
    write_results("sphere_registration", figures,
                  [table("Registration of simulated scans of held-out frames (errors in % of the shape length L)",
                         head1, rows + [mean]),
                   table("Interpolation midpoints against the true 60 frame (shape units)", head2, rows2 + summary)])


if __name__ == "__main__":
    main()
