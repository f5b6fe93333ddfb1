"""What landmarks and ignore masks fix (issue: registration an artist can steer).

1. ``sphere``: the deformed-sphere held-out +-60 frames (``../shared/data``), simulated scans, registered
   without and with three landmarks (the template's two poles and a point of its equator, placed to
   ~1 % of the length as a hand would): the +60 frames register mirrored without help.
2. ``arm``: held-out human scans with an arm raised (Anny's held-out identities waving, middle frame;
   needs the ``[bases]`` extra, or ``--truths FILE`` written by an earlier run), without and with eight
   landmarks (nose tip, navel, wrists, elbows, ankles; 1 cm placement noise).
3. ``floor``: random bodies of the human basis scanned standing on a floor plate with a wall behind
   them (one mesh, in a random orientation and scale), registered clean, with the plate and wall in
   the ignore mask (face weight 0), and without the mask.
Vertex errors against the true correspondence, mm for the human, % of the length for the sphere.

Usage: python -m bench.landmarks_masks [--parts sphere arm floor] [--scans N] [--truths FILE]
"""

import argparse
import sys
import time

import numpy as np
import torch

import bench.common  # noqa: F401  (puts the repo on sys.path)
from bench.common import OUT, markdown_table, report, table, variant_of, write_results
from bareesa import evaluation
from bareesa.basis_io import load_basis
from bareesa.errors import BareEsaError
from bareesa.registration import register
from bareesa.scan_simulator import apply_similarity, simulate_scan
from bareesa.synthetic import random_rotation
from bareesa.transforms import Similarity

ARM_LANDMARKS = ("nose_tip", "navel", "wrist_l", "wrist_r", "elbow_l", "elbow_r", "ankle_l", "ankle_r")
HUMAN_SCAN = dict(remesh="voxel", noise=0.001, holes=3)  # the human benches' simulated scans


def placed(points, noise, rng):
    """Landmark points as a hand places them: -> [(vertex, xyz)] with Gaussian noise of std ``noise``."""
    return [(v, p + rng.normal(scale=noise, size=3)) for v, p in points]


MESHES = OUT / "landmarks_masks"
#: each part's cases: (name, column of its mean vertex error in the part's rows)
CASES = {"sphere": (("free", 1), ("landmarks", 4)), "arm": (("free", 2), ("landmarks", 5)),
         "floor": (("clean", 3), ("masked", 6), ("unmasked", 9))}
TITLES = {"sphere": "sphere: held-out frames without and with 3 landmarks (errors in % of the length)",
          "arm": f"arm: held-out human scans with an arm raised, without and with {len(ARM_LANDMARKS)} landmarks",
          "floor": "floor: random bodies on a floor plate with a wall behind, clean, masked and unmasked"}


def keep(name, verts, faces, weights=None):
    """Save a mesh of the first case of a part for the README pictures (tools/render_landmarks_masks.py;
    ``<part>_transform.npy`` is the 4x4 scan -> template frame map of the part's right registration)."""
    from bareesa.mesh import save_mesh

    MESHES.mkdir(parents=True, exist_ok=True)
    save_mesh(MESHES / f"{name}.ply", verts, faces)
    if weights is not None:
        np.save(MESHES / f"{name}.weights.npy", weights)


def solve(truth, unit, *args, **kwargs):
    """register(*args, **kwargs) timed: -> (result or None, [mean, p95 vertex error / unit, seconds]);
    a solver refusal is printed and counted as a failure (NaN errors), the bench goes on."""
    t0 = time.perf_counter()
    try:
        res = register(*args, **kwargs)
    except BareEsaError as err:
        print(f"   failed: {err}", flush=True)
        return None, [float("nan"), float("nan"), time.perf_counter() - t0]
    e = evaluation.vertex_error(res.vertices, truth)
    return res, [e["mean"] / unit, e["p95"] / unit, time.perf_counter() - t0]


def sphere_rows():
    from bench.sphere_data import FAMILIES, HELD_OUT, load_frames, sphere_basis

    frames, faces = load_frames("landmarks_masks")
    basis = sphere_basis(frames, faces)
    t = basis.template
    marks = [int(np.argmax(t[:, 2])), int(np.argmin(t[:, 2])), int(np.argmax(t[:, 0]))]
    rng = np.random.default_rng(0)
    rows = []
    for fam in FAMILIES:
        for angle in HELD_OUT:
            truth = frames[(fam, angle)]
            sv, sf, info = simulate_scan(truth, faces, seed=abs(angle) + len(fam), holes=0, scale=0.3,
                                         resolution=0.03)
            truth_scan = apply_similarity(info, truth)
            unit = info["scale"] * basis.scale / 100  # % of the length
            row = [f"{fam} {angle:+d}"]
            for use in (False, True):
                lm = placed([(v, truth_scan[v]) for v in marks], 0.01 * info["scale"] * basis.scale, rng)
                res, numbers = solve(truth_scan, unit, basis, sv, sf, landmarks=lm if use else None)
                row += numbers
                if (fam, angle) == (FAMILIES[0], HELD_OUT[-1]) and res is not None:
                    keep("sphere_scan", sv, sf)
                    keep(f"sphere_{'landmarks' if use else 'free'}", res.vertices, basis.faces)
                    np.save(MESHES / "sphere_transform.npy", res.transform.matrix())  # the last: with landmarks
            rows.append(row)
            print("  ", *(f"{x:.3g}" if isinstance(x, float) else x for x in row), flush=True)
    return ["held-out frame", "no landmarks: mean %L", "p95 %L", "s", "3 landmarks: mean %L", "p95 %L", "s"], rows


def held_out_frames(path, n, motion="wave"):
    """Middle frames of held-out identities in a held-out motion: {name: (N, 3)} (the first n by
    name), all motions' cached in ``path``."""
    if path is not None and path.exists():
        with np.load(path) as z:
            frames = {k: z[k] for k in z.files}
    else:
        from bench.human_accuracy import held_out_data
        from bases.build.human import BAKE_STEP

        _, _, seqs = held_out_data()
        frames = {}
        for (ident, motion), seq in sorted(seqs.items()):
            seq = seq[::BAKE_STEP]
            frames[f"id{ident}_{motion}_f{len(seq) // 2}"] = seq[len(seq) // 2].astype(np.float64)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(path, **frames)
    chosen = sorted(k for k in frames if f"_{motion}_" in k)
    return {k: frames[k] for k in chosen[:n]}


def arm_rows(basis, n, truths):
    rng = np.random.default_rng(1)
    rows = []
    for k, (name, truth) in enumerate(held_out_frames(truths, n).items()):
        sv, sf, info = simulate_scan(truth, basis.faces, seed=100 + k, scale=0.1, **HUMAN_SCAN)
        truth_scan = apply_similarity(info, truth)
        unit = info["scale"] / 1000  # mm
        row = [name, len(sf)]
        for use in (False, True):
            lm = placed([(basis.landmarks[m], truth_scan[basis.landmarks[m]]) for m in ARM_LANDMARKS],
                        0.01 * info["scale"], rng)
            res, numbers = solve(truth_scan, unit, basis, sv, sf, landmarks=lm if use else None)
            row += numbers
            if k == 0 and res is not None:
                keep("arm_scan", sv, sf)
                keep(f"arm_{'landmarks' if use else 'free'}", res.vertices, basis.faces)
                np.save(MESHES / "arm_transform.npy", res.transform.matrix())
        rows.append(row)
        print("  ", *(f"{x:.3g}" if isinstance(x, float) else x for x in row), flush=True)
    return ["held-out scan", "faces", "no landmarks: mean mm", "p95 mm", "s",
            f"{len(ARM_LANDMARKS)} landmarks: mean mm", "p95 mm", "s"], rows


def plate(corner, u, v, pitch):
    """A flat rectangle corner + [0, 1] u + [0, 1] v triangulated at ~pitch: -> verts, faces."""
    nu, nv = max(2, int(np.linalg.norm(u) / pitch) + 1), max(2, int(np.linalg.norm(v) / pitch) + 1)
    a, b = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    verts = corner + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    q = (np.arange(nu - 1)[:, None] * nv + np.arange(nv - 1)[None, :]).ravel()
    return verts, np.concatenate([np.stack([q, q + nv, q + nv + 1], 1), np.stack([q, q + nv + 1, q + 1], 1)])


def floor_and_wall(truth, pitch, rng, noise):
    """A 1.6 m floor plate just under the feet and a 2 m wall 15 cm behind the body: -> verts, faces."""
    lo, hi = truth.min(0), truth.max(0)
    cx = 0.5 * (lo[0] + hi[0])
    fv, ff = plate(np.array([cx - 0.8, lo[1] - 0.6, lo[2] - 0.002]), np.array([1.6, 0, 0]), np.array([0, 1.2, 0]),
                   pitch)
    wv, wf = plate(np.array([cx - 0.8, hi[1] + 0.15, lo[2]]), np.array([0, 0, 2.0]), np.array([1.6, 0, 0]), pitch)
    verts = np.concatenate([fv, wv])
    return verts + rng.normal(scale=noise, size=verts.shape), np.concatenate([ff, wf + len(fv)])


def floor_rows(basis, n):
    from bareesa.workflows import random_bodies

    bodies = random_bodies(basis, n, seed=23).codes
    rng = np.random.default_rng(2)
    rows = []
    for k, code in enumerate(bodies):
        truth = basis.template + np.tensordot(code, basis.fields, 1)
        sv, sf, info = simulate_scan(truth, basis.faces, seed=200 + k, rigid=False, scale=0.0, **HUMAN_SCAN)
        cv, cf = floor_and_wall(truth, info["pitch"], rng, 0.001 * info["size"])
        move = Similarity(random_rotation(300 + k), float(np.exp(rng.uniform(-0.1, 0.1))), rng.normal(size=3))
        cluttered_v = move.apply(np.concatenate([sv, cv]))
        cluttered_f = np.concatenate([sf, cf + len(sv)])
        mask = np.r_[np.ones(len(sf)), np.zeros(len(cf))]
        truth_scan, unit = move.apply(truth), move.scale / 1000
        row = [f"body {k}", len(sf), len(cf)]
        cases = {"clean": (move.apply(sv), sf, None), "masked": (cluttered_v, cluttered_f, mask),
                 "unmasked": (cluttered_v, cluttered_f, None)}
        for case, (v, f, w) in cases.items():
            res, numbers = solve(truth_scan, unit, basis, v, f, scan_face_weights=w)
            row += numbers
            if k == 0 and res is not None:
                keep(f"floor_{case}", res.vertices, basis.faces)
                if case == "masked":
                    np.save(MESHES / "floor_transform.npy", res.transform.matrix())
        if k == 0:
            keep("floor_scan", cluttered_v, cluttered_f, mask)
        rows.append(row)
        print("  ", *(f"{x:.3g}" if isinstance(x, float) else x for x in row), flush=True)
    return ["random body", "body faces", "floor+wall faces", "clean: mean mm", "p95 mm", "s",
            "masked: mean mm", "p95 mm", "s", "no mask: mean mm", "p95 mm", "s"], rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="+", default=["sphere", "arm", "floor"], choices=["sphere", "arm", "floor"])
    parser.add_argument("--scans", type=int, default=3, help="human scans per part (default 3)")
    parser.add_argument("--truths", type=lambda p: __import__("pathlib").Path(p),
                        default=OUT / "held_out_wave_frames.npz",
                        help="cache of the held-out Anny frames (written on the first run)")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    sections, tables, figures = [], [], {}
    human = load_basis("human") if {"arm", "floor"} & set(args.parts) else None
    for part in args.parts:
        print(f"{part}:", flush=True)
        header, rows = {"sphere": sphere_rows, "arm": lambda: arm_rows(human, args.scans, args.truths),
                        "floor": lambda: floor_rows(human, args.scans)}[part]()
        sections.append(f"### {part}\n\n{markdown_table(header, rows)}")
        report("landmarks_masks", "\n\n".join(sections))
        tables.append(table(TITLES[part], header, rows))
        for case, column in CASES[part]:  # mean over the part's scans of each case's mean vertex error
            values = np.array([r[column] for r in rows], dtype=float)
            figures[f"{part}_{case}_error_mean_{'pct_length' if part == 'sphere' else 'mm'}"] = (
                float(np.nanmean(values)) if np.isfinite(values).any() else float("nan"))
            figures[f"{part}_{case}_failures"] = int(np.isnan(values).sum())
    print("\n\n".join(sections))
    write_results("landmarks_masks", figures, tables, variant=variant_of(parser, args, ("truths",)),
                  argv=sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    main()
