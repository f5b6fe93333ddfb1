"""Accuracy of the bundled ``human`` basis (Anny) on data never used to build it.

Held-out identities (``bases.build.human.identities()[1]``) performing held-out motions
(``HUMAN_TEST_MOTIONS``) are regenerated with Anny (needs the ``[bases]`` extra).

1. Registration of simulated scans (remeshed, noisy, holed, random rotation and scale) with
   the CLI's defaults: vertex error against the true correspondence (mean, p95; mm and % of
   height), as ``bench.humanoid_accuracy``.
2. A real body nobody in the project made, ``../shared/data/body/DFAUST_template.ply``, in
   random orientations: mean nearest-point distance both ways and Hausdorff, with ``human``
   and, given ``--old DIR/humanoid.npz`` (``python -m bases.build humanoid -o DIR``: the mannequin
   is no longer bundled), the old mannequin beside it.
3. Interpolation / extrapolation on held-out motions (the humanoid bench's protocol) of the first
   ``--identities`` held-out identities.
4. Random bodies: self-intersecting face pairs (non-adjacent faces, ``bareesa.mesh.self_intersections``)
   over ``--bodies`` random bodies; the share with none.
5. Ablation (projection error of held-out frames for prefixes of the groups) and a contact
   sheet PNG.

Usage: python -m bench.human_accuracy [--scans N] [--bodies N] [--skip ...] [--old NPZ] [--card] [--out bench/out]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import dict_table, variant_of, write_results  # noqa: E402
from bench.humanoid_accuracy import (_mean_row, _table, ablation_rows, interpolation_figures,  # noqa: E402
                                     interpolation_rows, registration_rows, sheet)

DFAUST = ROOT.parent / "shared" / "data" / "body" / "DFAUST_template.ply"


def held_out_data(log=print):
    """-> (Human, rests (20, N, 3), {(identity, motion): (T, N, 3) every frame})."""
    from bases.build import human as hb

    gen = hb.Human(log)
    _, test = hb.identities(model=gen.model)
    rests = gen.rest(test)
    seqs = {(i, m): gen.motion(hb._take(test, i), m, step=1) for i in range(len(rests)) for m in hb.HUMAN_TEST_MOTIONS}
    return gen, rests, seqs


def surface_distances(a_verts, a_faces, b_verts, b_faces, samples=20000, seed=0):
    """Mean nearest-point distance a->b and b->a (area samples of each onto the other surface), Hausdorff (over
    the samples and every vertex: a small part such as a toe tip can escape the samples)."""
    import bpy  # noqa: F401  (puts bpy's mathutils on the path: exact point-to-surface distances)
    import trimesh
    from mathutils.bvhtree import BVHTree

    def one_way(src_v, src_f, dst_v, dst_f):
        pts = trimesh.sample.sample_surface(trimesh.Trimesh(src_v, src_f, process=False), samples, seed=seed)[0]
        tree = BVHTree.FromPolygons(np.asarray(dst_v).tolist(), np.asarray(dst_f).tolist())
        near = lambda points: np.array([tree.find_nearest(p)[3] for p in points])  # noqa: E731
        return near(pts), near(np.asarray(src_v))

    (ab, ab_v), (ba, ba_v) = one_way(a_verts, a_faces, b_verts, b_faces), one_way(b_verts, b_faces, a_verts, a_faces)
    return float(ab.mean()), float(ba.mean()), float(max(ab.max(), ba.max(), ab_v.max(), ba_v.max()))


def real_body_rows(bases=("human",), n=3, seed=0):
    """Register the DFAUST template (rotated, shifted) with each basis: surface distances in mm."""
    import trimesh
    import bpy  # noqa: F401

    from bareesa.basis_io import load_basis
    from bareesa.registration import register
    from bareesa.transforms import Similarity, axis_angle_rotation

    if not DFAUST.exists():
        print(f"(no {DFAUST}: the real-body rows are skipped)")
        return []
    mesh = trimesh.load(DFAUST, process=False)
    body_v, body_f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    rng = np.random.default_rng(seed)
    rows = []
    for name in bases:
        basis = load_basis(name)
        for k in range(n):
            axis = rng.normal(size=3)
            rot = axis_angle_rotation(axis / np.linalg.norm(axis) * rng.uniform(0, np.pi))
            sim = Similarity(rotation=rot, scale=1.0, translation=rng.normal(size=3))
            scan = sim.apply(body_v)
            t0 = time.perf_counter()
            res = register(basis, scan, body_f)
            seconds = time.perf_counter() - t0
            fit = sim.invert(np.asarray(res.vertices, dtype=np.float64))
            d_rb, d_br, haus = surface_distances(fit, basis.faces, body_v, body_f)
            rows.append({"basis": basis.name, "trial": k, "reg->body_mm": round(1e3 * d_rb, 1),
                         "body->reg_mm": round(1e3 * d_br, 1), "hausdorff_mm": round(1e3 * haus, 1),
                         "poor_fit": bool(res.poor_fit), "seconds": round(seconds, 1)})
            print("  ".join(str(v) for v in rows[-1].values()), flush=True)
    return rows


def random_body_rows(basis, n, seed=0):
    from bareesa.mesh import self_intersections
    from bareesa.workflows import random_bodies

    bodies = random_bodies(basis, n, seed=seed)
    verts = basis.template[None] + np.tensordot(bodies.codes, basis.fields, axes=(1, 0))
    counts = [len(self_intersections(v, basis.faces)) for v in verts]
    return {"bodies": n, "seed": seed, "with_none": int(sum(c == 0 for c in counts)),
            "share_with_none": round(float(np.mean([c == 0 for c in counts])), 3),
            "median_pairs": float(np.median(counts)), "max_pairs": int(max(counts)), "replaced_draws": int(bodies.replaced),
            "counts": counts}, verts


def contact_sheet(path, basis, gen, seqs, bodies):
    from bases.build import human as hb

    train, test = hb.identities(model=gen.model)
    rows = [("template + training identities", [basis.template] + list(gen.rest({k: v[:5] for k, v in
                                                                                  train.items()}))),
            ("held-out identities", list(gen.rest({k: v[:6] for k, v in test.items()}))),
            ("training motion 'jump' (template body)", list(gen.motion({k: np.array([0.5]) for k in
                                                                         gen.model.phenotype_labels}, "jump")[1::3])),
            ("held-out motion 'lunge' (held-out identity 0)", list(seqs[(0, "lunge")][::9])),
            ("random bodies", list(bodies[:6]))]
    sheet(path, rows, basis.faces, height=12)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--basis", default="human", help="the basis to measure (a build of bases.build.human)")
    parser.add_argument("--scans", type=int, default=8, help="number of simulated scans to register")
    parser.add_argument("--bodies", type=int, default=50, help="random bodies checked for self-intersection")
    parser.add_argument("--identities", type=int, default=4,
                        help="held-out identities whose held-out motions the interpolation part cuts into windows "
                             "(4: 8 sequences, the humanoid bench's protocol; each costs minutes)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random bodies")
    parser.add_argument("--real", type=int, default=3, help="random orientations of the real body per basis")
    parser.add_argument("--old", nargs="*", default=[], metavar="NPZ",
                        help="other bases registered to the real body beside --basis (e.g. a build of the retired "
                             "humanoid mannequin)")
    parser.add_argument("--skip", nargs="*", default=[],
                        choices=["registration", "real", "interpolation", "random", "ablation", "sheet"])
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "out")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--card", action="store_true", help="write the measured accuracy into bases/human.json")
    args = parser.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    import torch

    torch.set_num_threads(args.threads)
    from bareesa.basis_io import load_basis
    from bases.build.human import BAKE_STEP

    basis = load_basis(args.basis)
    args.out.mkdir(parents=True, exist_ok=True)
    height = float(basis.template[:, 2].max() - basis.template[:, 2].min())
    print(f"basis {basis.name}: {len(basis.template)} vertices, groups {basis.groups}, height {height:.3f} m")
    results = {}
    if set(args.skip) >= {"registration", "interpolation", "random", "ablation", "sheet"}:  # the real body only
        results["real_body"] = real_body_rows((args.basis, *args.old), n=args.real)
        (args.out / "human_accuracy_real.json").write_text(json.dumps(results, indent=2) + "\n")
        write_human_results(results, basis.name, variant_of(parser, args, IGNORED), argv)
        if args.card:
            write_card(args.basis, results)
        return
    if set(args.skip) >= {"registration", "interpolation", "ablation", "sheet"}:  # random bodies: no Anny
        gen = rests = every_frame = seqs = None
    else:
        gen, rests, every_frame = held_out_data(log=lambda *_: None)
        if not np.array_equal(gen.faces, basis.faces):
            sys.exit("the generator's topology differs from the basis: rebuild with python -m bases.build human")
        seqs = {key: seq[::BAKE_STEP] for key, seq in every_frame.items()}
    bodies = None
    if "random" not in args.skip or "sheet" not in args.skip:
        summary, bodies = random_body_rows(basis, args.bodies, args.seed)
        if "random" not in args.skip:
            print(f"\nRandom bodies: {summary['with_none']} of {summary['bodies']} without self-intersection "
                  f"(median {summary['median_pairs']} intersecting face pairs, max {summary['max_pairs']})")
            results["random_bodies"] = summary
    if "ablation" not in args.skip:
        ps, ss = basis.group_slice("pose"), basis.group_slice("shape")
        np_, ns = ps.stop - ps.start, ss.stop - ss.start
        rows = ablation_rows(basis, list(rests), seqs, sorted({20, 40, 60, 80, np_} & set(range(1, np_ + 1))),
                             sorted({5, 10, 20, 30, ns} & set(range(1, ns + 1))))
        _table(rows, list(rows[0]), "Ablation: RMS projection error (mm) of held-out frames, pose rows x shape columns")
        results["ablation"] = rows
    if "sheet" not in args.skip:
        contact_sheet(args.out / "human_contact_sheet.png", basis, gen, every_frame, bodies)
        print(f"\nwrote {args.out / 'human_contact_sheet.png'}")
    if "registration" not in args.skip and args.scans > 0:
        print("\nRegistration of simulated scans of held-out identities in held-out motions")
        rows = registration_rows(basis, basis.faces, seqs, args.scans)
        results["registration"] = {"rows": rows, "mean": _mean_row(rows),
                                   "p95_of_p95_%h": round(float(np.percentile([r["p95_%h"] for r in rows], 95)), 3)}
        print("mean  " + "  ".join(f"{k}={v}" for k, v in results["registration"]["mean"].items()))
    if "real" not in args.skip and args.real > 0:
        print("\nThe DFAUST template (a real body, no correspondence), randomly oriented: surface distances")
        results["real_body"] = real_body_rows((args.basis, *args.old), n=args.real)
    if "interpolation" not in args.skip:
        rows = interpolation_rows(basis, {k: v for k, v in every_frame.items() if k[0] < args.identities})
        _table(rows, list(rows[0]), "Interpolation / extrapolation in monotone mini-sequences of held-out motions")
        results["interpolation"] = rows
    (args.out / "human_accuracy.json").write_text(json.dumps(results, indent=2) + "\n")
    write_human_results(results, basis.name, variant_of(parser, args, IGNORED), argv)
    if args.card:
        write_card(args.basis, results)


#: arguments that change where output goes or what else is registered beside, not the figures
IGNORED = ("card", "out", "old")
def write_human_results(results, basis_name, variant, argv):
    """bench/results/human_accuracy[--variant].json from the parts measured."""
    figures, tables = {}, []
    if "registration" in results:
        rows, mean = results["registration"]["rows"], results["registration"]["mean"]
        figures |= {"registration_error_mean_pct_height": mean["mean_%h"],
                    "registration_error_p95_pct_height": mean["p95_%h"],
                    "registration_error_mean_mm": mean["mean_mm"], "registration_error_p95_mm": mean["p95_mm"],
                    "registration_p95_of_p95_pct_height": results["registration"]["p95_of_p95_%h"],
                    "registration_wall_s": mean["seconds"], "registration_poor_fits": mean.get("poor_fits", 0),
                    "registration_scans": len(rows)}
        tables.append(dict_table("Registration of simulated scans of held-out identities in held-out motions", rows))
    if results.get("real_body"):
        rows = results["real_body"]
        own = [r for r in rows if r["basis"] == basis_name] or rows
        figures |= {"real_body_reg_to_body_mm": max(r["reg->body_mm"] for r in own),
                    "real_body_body_to_reg_mm": max(r["body->reg_mm"] for r in own),
                    "real_body_hausdorff_mm": max(r["hausdorff_mm"] for r in own),
                    "real_body_wall_s": float(np.mean([r["seconds"] for r in own]))}
        tables.append(dict_table("The DFAUST template (a real body), randomly oriented: surface distances", rows))
    if "random_bodies" in results:
        summary = {k: v for k, v in results["random_bodies"].items() if k != "counts"}
        figures |= {"random_bodies_without_crossings_pct": 100 * summary["share_with_none"],
                    "random_bodies_replaced_draws": summary["replaced_draws"]}
        tables.append(dict_table("Random bodies: self-intersecting face pairs", [summary]))
    if "ablation" in results:
        rows = results["ablation"]
        figures["ablation_full_rms_mm"] = list(rows[-1].values())[-1]
        tables.append(dict_table("Ablation: RMS projection error (mm) of held-out frames, pose rows x shape columns",
                                 rows))
    if "interpolation" in results:
        figures |= interpolation_figures(results["interpolation"])
        tables.append(dict_table("Interpolation / extrapolation in monotone mini-sequences of held-out motions",
                                 results["interpolation"]))
    targets = {"registration_error_mean_pct_height": {"target": 0.5, "better": "lower"},
               "registration_error_p95_pct_height": {"target": 1.5, "better": "lower"},
               "real_body_reg_to_body_mm": {"target": 5.0, "better": "lower"},
               "real_body_body_to_reg_mm": {"target": 5.0, "better": "lower"},
               "real_body_hausdorff_mm": {"target": 40.0, "better": "lower"},
               "interpolation_cli_beats_both_measures": {"target": 3, "better": "higher"},
               "extrapolation_cli_beats_both_measures": {"target": 3, "better": "higher"},
               "random_bodies_without_crossings_pct": {"target": 95.0, "better": "higher"}}
    labels = {"registration_error_mean_pct_height": "scans of held-out people: mean vertex error",
              "registration_error_p95_pct_height": "scans of held-out people: p95 vertex error",
              "real_body_reg_to_body_mm": "real body: registered -> body (worst orientation)",
              "real_body_body_to_reg_mm": "real body: body -> registered (worst orientation)",
              "real_body_hausdorff_mm": "real body: Hausdorff (worst orientation)",
              "interpolation_cli_beats_both_measures":
                  "held-out motions, interpolation: measures (of 3) won by the CLI default",
              "extrapolation_cli_beats_both_measures":
                  "held-out motions, extrapolation: measures (of 3) won by the CLI default",
              "random_bodies_without_crossings_pct": "random bodies without self-intersecting faces"}
    write_results("human_accuracy", figures, tables, {k: v for k, v in targets.items() if k in figures},
                  variant=variant, labels=labels, argv=argv)


def write_card(basis, results):
    """Write the parts measured (``results``' keys) into the basis' card, leaving the others as they were."""
    from bareesa.basis_io import resolve_basis_path
    from bench.humanoid_accuracy import write_card_accuracy

    write_card_accuracy(basis, {k: v for k, v in results.items() if k in ("registration", "interpolation", "ablation")},
                        measured_by="python -m bench.human_accuracy --card")
    path = resolve_basis_path(basis).with_suffix(".json")
    card = json.loads(path.read_text())
    for key in ("random_bodies", "real_body"):
        if key in results:
            card["accuracy"][key] = results[key]
    path.write_text(json.dumps(card, indent=2) + "\n")


if __name__ == "__main__":
    main()
