"""Elastic vs plain-difference shape bases on the deformed-sphere data (issue: statistics).

Both bases are built from the same training frames (the three families without the
held-out +-60 frames; then, sparser, without +-60 and +-90) with the same number P of
fields: 'plain' from differences of consecutive frames, 'elastic' from the steps of
parametrised H2 geodesics between them
(``build_basis(elastic=...)``, the paper's shape-basis construction). Each held-out
frame is projected onto each basis (L2 least squares, ``project_to_basis``) and the
reconstruction error is measured: mean vertex error, Chamfer, Hausdorff.
Run: python -m bench.elastic_basis   (writes bench/out/elastic_basis.md)
"""

import time

import numpy as np
import torch

from bench.common import markdown_table, report, table, write_results
from bench.sphere_data import FAMILIES, HELD_OUT, family_sequence, load_frames
from bareesa import evaluation
from bareesa.latent import Basis, project_to_basis
from bareesa.basis_building import build_basis

P_VALUES = (2, 4, 6, 8, 12)
ELASTIC_STEPS = 5  # time points of each elastic geodesic: 4 tangent vectors per pair of frames
WIDE_GAP = (-90, -60, 60, 90)  # a sparser training set: the elastic paths must bridge 30 -> 120 degrees


def reconstruction(basis, verts, faces):
    """Errors of the L2 projection of a registered mesh onto a basis: vertex, Chamfer, Hausdorff."""
    code, _ = project_to_basis(basis, verts, ridge=0)
    rec = basis.template + np.tensordot(code, basis.fields, axes=1)
    return [evaluation.vertex_error(rec, verts)["mean"], evaluation.chamfer(rec, verts),
            evaluation.hausdorff(rec, verts)]


def compare(frames, faces, held):
    """Summary and per-frame rows of both constructions with the frames at angles ``held`` held out."""
    template = frames[("template", 0)]
    seqs = {"pose": [family_sequence(frames, fam, exclude=held) for fam in FAMILIES]}
    held_out = [(fam, a) for fam in FAMILIES for a in held if (fam, a) in frames]
    rows, summary = [], []
    for kind in ("plain", "elastic"):
        t0 = time.perf_counter()
        full = build_basis(template, faces, seqs, {"pose": max(P_VALUES)}, weights="face", name=kind,
                           elastic=("pose",) if kind == "elastic" else (), elastic_steps=ELASTIC_STEPS)
        secs = time.perf_counter() - t0
        for p in P_VALUES:  # principal fields are ordered: the first p fields are the P = p basis
            basis = Basis(template=full.template, faces=full.faces, fields=full.fields[:p], groups={},
                          weights=full.weights, name=f"{kind}_{p}")
            errs = np.array([reconstruction(basis, frames[k], faces) for k in held_out])
            for k, e in zip(held_out, errs):
                rows.append([f"{k[0]} {k[1]:+d}", kind, p, *e])
            summary.append([f"mean of {len(held_out)} held-out frames", kind, p, *errs.mean(0), secs])
    summary.sort(key=lambda r: (r[2], r[1] != "plain"))
    return summary, sorted(rows, key=lambda r: (r[2], r[0], r[1]))


def main():
    torch.set_num_threads(1)
    frames, faces = load_frames("elastic_basis")
    head = ["held-out frame", "basis", "P", "vertex err", "Chamfer", "Hausdorff"]
    parts = [f"Reconstruction (L2 projection) error of held-out frames; shape length 12.7 units, face metric, "
             f"elastic geodesics with {ELASTIC_STEPS} time points, {torch.get_num_threads()} torch thread."]
    figures, tables = {}, []
    for held, key in ((HELD_OUT, "held60"), (WIDE_GAP, "held60_90")):
        summary, rows = compare(frames, faces, held)
        title = ", ".join(f"{a:+d}" for a in held)
        parts += [f"## Held out: {title}", markdown_table(head + ["build seconds (all P)"], summary),
                  f"### Per frame (held out: {title})", markdown_table(head, rows)]
        tables += [table(f"Held out: {title}", head + ["build seconds (all P)"], summary),
                   table(f"Per frame (held out: {title})", head, rows)]
        for r in summary:
            if r[2] in (4, max(P_VALUES)):
                figures[f"{key}_{r[1]}_p{r[2]}_vertex_error_units"] = r[3]
            figures[f"{key}_{r[1]}_build_s"] = r[-1]
    report("elastic_basis", "# Elastic vs plain-difference basis\n\n" + "\n\n".join(parts))
    write_results("elastic_basis", figures, tables)


if __name__ == "__main__":
    main()
