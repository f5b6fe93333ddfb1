"""Extrapolation, motion transfer and random generation on the deformed-sphere data (issue: statistics).

(1) Extrapolate from the 30 and 60 frames (and -30, -60) to predict 90 and 120 of each
family: H2 shooting (discrete geodesic calculus, one step per 30 degrees as in the frames, and
refined in time with SUBSTEPS steps per frame interval) vs straight-line continuation in latent
space vs linear vertex extrapolation (the paper's Table 4 in miniature). A shooting step that
does not converge (too coarse for a strongly curved motion) is reported as failed.
(2) Motion transfer (bend_Y onto a procedurally generated 'fat' identity) and random
generation (Gaussian mixture on the log maps of the training frames): contact sheets.
(3) Speed: 10 extrapolation steps at the paper's scale (6,890 vertices, P = 170).
Run: python -m bench.sphere_motion   (writes bench/out/sphere_motion.{md,*.png})
"""

import time

import numpy as np
import torch

from bench.common import OUT, contact_sheet, markdown_table, report, table, write_results
from bench.sphere_data import FAMILIES, family_sequence, load_frames
from bareesa import evaluation
from bareesa.geodesics import decode_path
from bareesa.basis_building import build_basis
from bareesa.latent import project_to_basis
from bareesa.errors import BareEsaError
from bareesa.shooting import extrapolate
from bareesa.statistics import fit_training_distribution, sample_codes, transfer_motion

SUBSTEPS = 4
METHODS = ("H2 shooting", f"H2 shooting, {SUBSTEPS} substeps", "latent line", "vertex line")


def identities(template):
    """Procedural identities of the sphere: thicker, thinner, longer (same topology)."""
    c = template.mean(0)
    ext = template.max(0) - template.min(0)
    long_axis = int(np.argmax(ext))
    out = []
    for radial, axial in ((1.35, 1.0), (0.75, 1.0), (1.0, 1.25), (1.2, 0.85)):
        s = np.full(3, radial)
        s[long_axis] = axial
        out.append(c + (template - c) * s)
    return out


def main():
    torch.set_num_threads(1)
    frames, faces = load_frames("sphere_motion")
    template = frames[("template", 0)]
    ids = identities(template)
    seqs = {"pose": [family_sequence(frames, fam) for fam in FAMILIES], "shape": [np.stack([template] + ids)]}
    basis = build_basis(template, faces, seqs, {"pose": 64, "shape": 8}, weights="face", name="sphere_motion")
    t, f, h = basis.tensors()
    sigma = 0.015 * basis.scale
    rows, failures = [], []
    for fam in FAMILIES:
        for sign in (1, -1):
            a0, a1 = frames[(fam, 30 * sign)], frames[(fam, 60 * sign)]
            c0, c1 = project_to_basis(basis, a0)[0], project_to_basis(basis, a1)[0]
            shots = {}
            for name, sub in ((METHODS[0], 1), (METHODS[1], SUBSTEPS)):
                try:
                    shots[name] = decode_path(t, h, extrapolate(t, f, h, c0, c1, basis.weights, 2, substeps=sub))
                except BareEsaError as err:
                    failures.append(f"{fam} {60 * sign:+d} -> {90 * sign:+d}, {name}: {err}")
            for k, angle in ((2, 90), (3, 120)):
                truth = frames.get((fam, angle * sign))
                if truth is None:
                    continue
                preds = {name: shot[k] for name, shot in shots.items()}
                preds["latent line"] = decode_path(t, h, (c0 + k * (c1 - c0))[None])[0]
                preds["vertex line"] = a0 + k * (a1 - a0)
                for name in METHODS:
                    if name not in preds:
                        rows.append([f"{fam} {angle * sign:+d}", name, "failed", "", "", ""])
                        continue
                    v = preds[name]
                    rows.append([f"{fam} {angle * sign:+d}", name, evaluation.vertex_error(v, truth)["mean"],
                                 evaluation.chamfer(v, truth), evaluation.hausdorff(v, truth),
                                 evaluation.varifold(v, faces, truth, faces, sigma)])
    ok = {r[0] for r in rows} - {r[0] for r in rows if r[2] == "failed"}
    summary = [[f"mean over {len(ok)} targets all methods reached", m,
                *np.mean([r[2:] for r in rows if r[1] == m and r[0] in ok], axis=0)] for m in METHODS]
    targets = {r[0] for r in rows}
    summary += [[f"mean over all {len(targets)} targets", m, *np.mean([r[2:] for r in rows if r[1] == m], axis=0)]
                for m in METHODS if all(r[2] != "failed" for r in rows if r[1] == m)]
    head1 = ["target", "method", "vertex err", "Chamfer", "Hausdorff", "varifold"]
    part1 = markdown_table(head1, rows + summary)
    if failures:
        part1 += "\n\nFailed shooting steps:\n" + "\n".join(f"- {x}" for x in failures)

    # motion transfer: the bend_Y motion onto the thick identity
    motion = family_sequence(frames, "bend_Y", exclude=())
    codes = np.stack([project_to_basis(basis, v)[0] for v in motion])
    ident = project_to_basis(basis, ids[0])[0]
    moved = decode_path(t, h, transfer_motion(codes, ident, basis.group_slice("shape")))
    pick = np.linspace(0, len(motion) - 1, 5).round().astype(int)
    contact_sheet(OUT / "sphere_motion_transfer.png",
                  [(motion[i], faces) for i in pick] + [(moved[i], faces) for i in pick],
                  [f"source {i}" for i in pick] + [f"transferred {i}" for i in pick], ncols=5, elev=10, azim=-30)

    # random generation from the distribution fitted on the training frames
    dist = fit_training_distribution(basis, seqs["pose"] + seqs["shape"], {"pose": 4, "shape": 2})
    rand = decode_path(t, h, sample_codes(t, f, h, dist, basis.groups, basis.shape_metric, n=8, seed=1, steps=6))
    contact_sheet(OUT / "sphere_motion_random.png", [(v, faces) for v in rand], [f"sample {i}" for i in range(8)],
                  ncols=4, elev=10, azim=-30)

    # speed at the paper's scale
    from bench.body_data import body_basis

    body = body_basis("sphere_motion")
    bt, bf, bh = body.tensors()
    rng = np.random.default_rng(0)
    c0 = rng.normal(size=body.n_fields) * 0.5
    c1 = c0 + rng.normal(size=body.n_fields) * 0.05
    t0, cpu0 = time.perf_counter(), time.process_time()
    extrapolate(bt, bf, bh, c0, c1, body.weights, 10)
    secs, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    head3 = ["problem", "torch threads", "wall seconds (target <= 10 s)", "CPU seconds"]
    rows3 = [[f"10 extrapolation steps, {bt.shape[0]} vertices, P = {body.n_fields}", torch.get_num_threads(), secs,
              cpu]]
    part3 = markdown_table(head3, rows3)
    report("sphere_motion", "## Extrapolation from (30, 60) to 90 and 120\n\n" + part1
           + "\n\n## Speed\n\n" + part3
           + f"\n\nPNGs: {OUT / 'sphere_motion_transfer.png'}, {OUT / 'sphere_motion_random.png'}")
    slug = lambda m: m.replace(",", "").replace(" ", "_").lower()  # noqa: E731
    figures = {f"extrapolation_{slug(r[1])}_error_units": r[2] for r in summary if r[0].endswith("all methods reached")}
    figures |= {"extrapolation_shooting_failures": len(failures), "paper_scale_10_steps_wall_s": secs,
                "paper_scale_10_steps_cpu_s": cpu}
    write_results("sphere_motion", figures,
                  [table("Extrapolation from (30, 60) to 90 and 120 (shape units)", head1, rows + summary),
                   table("Speed", head3, rows3)],
                  {"paper_scale_10_steps_wall_s": {"target": 10.0, "better": "lower"}},
                  labels={"paper_scale_10_steps_wall_s": "10 extrapolation steps at the paper's scale"})


if __name__ == "__main__":
    main()
