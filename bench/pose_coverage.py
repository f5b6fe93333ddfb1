"""Pose coverage of the default ``human`` basis: held-out people in random and in extreme poses.

Data (regenerated with Anny: the ``[bases]`` extra; ``--truths FILE`` caches it): held-out Anny
identities (``bases.build.human.identities()[1]``, never in training) in anatomically valid random
poses drawn with ``--seed`` (training postures use seeds from ``bases.build.human.POSTURE_SEED``),
rejected while they cross themselves, and in every named extreme pose of
``bases.build.poses.EXTREME_POSES`` (T-pose, arms overhead, tree pose, deep squat, sitting, kneeling,
...); the same people at rest (Anny's A-pose) are the baseline, timed in the same run. Each body is a
simulated scan (voxel remesh, 1 mm noise, 3 holes, random rotation, +-10 % scale) registered as the CLI
does: no landmarks, the basis' card settings.

Reports: the share of scans registered within 1 % of height (mean vertex error against the true
correspondence; extreme poses also within 1.5 %), error and time distributions, the worst pose's time
over the A-pose's, poor-fit flags on fits that are right, and the self-intersecting frames of
geodesics between extreme poses against the share of training postures that cross themselves.

Usage: python -m bench.pose_coverage [--random N] [--extreme N] [--apose N] [--geodesics N] [--seed S]
       [--truths FILE] [--threads T]
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import dict_table, variant_of, write_results  # noqa: E402

#: held-out random poses: a seed no training posture uses (training: POSTURE_SEED + performer)
SEED = 424242
SCAN = dict(remesh="voxel", noise=0.001, holes=3, scale=0.1)
SUCCESS, EXTREME_SUCCESS = 1.0, 1.5  # % of height


def held_out_truths(n_random, n_apose, seed, log=print):
    """-> (faces, {name: body (N, 3)}): random poses, the extreme poses and rest bodies of held-out people."""
    from bases.build import human as hb
    from bases.build.poses import EXTREME_POSES, plausible, random_pose

    gen = hb.Human(log)
    _, test = hb.identities(model=gen.model)
    people = len(test["age"])
    rng = np.random.default_rng(seed)
    out = {}
    for k in range(n_random):
        person = hb._take(test, k % people)
        for _ in range(20):  # a draw whose limbs cross is drawn again
            body = gen.postures(person, [random_pose(rng)])[0]
            if plausible(body, gen.faces):
                break
        out[f"random{k:02d}/id{k % people}"] = body
    for k, (name, posture) in enumerate(EXTREME_POSES.items()):
        out[f"{name}/id{(k + 7) % people}"] = gen.postures(hb._take(test, (k + 7) % people), [posture])[0]
    for k in range(n_apose):
        out[f"apose/id{k % people}"] = gen.rest(hb._take(test, k % people))[0]
    return gen.faces, out


def cached_truths(path, basis, n_random, n_apose, seed=SEED):
    """``held_out_truths``' bodies {name: (N, 3)}, read from the cache ``path`` when it exists (else made, and
    written there unless path is None); exits when their topology is not the basis'."""
    if path is not None and path.exists():
        stored = np.load(path)
        faces, truths = stored["faces"], {k: stored[k] for k in stored.files if k != "faces"}
    else:
        faces, truths = held_out_truths(n_random, n_apose, seed, log=lambda *_: None)
        if path is not None:
            np.savez_compressed(path, faces=faces, **truths)
    if not np.array_equal(faces, basis.faces):
        sys.exit("the generator's topology differs from the basis: rebuild with python -m bases.build human")
    return truths


def registration_row(basis, name, true, seed, keep=None):
    """Register a simulated scan of ``true`` (N, 3): -> row dict (``keep``: a dict that gets the scan and the
    fit, both in the true body's frame, under ``name``)."""
    from bareesa.evaluation import vertex_error
    from bareesa.registration import register
    from bareesa.scan_simulator import apply_similarity, simulate_scan, undo_similarity

    height = float(np.ptp(true[:, 2]))
    scan_v, scan_f, info = simulate_scan(true, basis.faces, seed=seed, **SCAN)
    t0 = time.perf_counter()
    res = register(basis, scan_v, scan_f)
    seconds = time.perf_counter() - t0
    err = vertex_error(res.vertices, apply_similarity(info, true))
    s = info["scale"]
    if keep is not None:
        keep[name] = ((undo_similarity(info, scan_v), scan_f), (undo_similarity(info, res.vertices), basis.faces))
    return {"scan": name, "kind": name.split("/")[0] if not name.startswith("random") else "random",
            "mean_mm": round(1e3 * err["mean"] / s, 1), "p95_mm": round(1e3 * err["p95"] / s, 1),
            "mean_%h": round(100 * err["mean"] / s / height, 3), "p95_%h": round(100 * err["p95"] / s / height, 3),
            "poor_fit": res.poor_fit, "retried": int(res.retried_alignments),
            "articulated_s": None if res.articulated is None else round(res.articulated["seconds"], 1),
            "seconds": round(seconds, 1)}


def crossing_share(bodies, faces):
    """Share of bodies (K, N, 3) with self-intersecting faces, and the counts."""
    from bareesa.mesh import self_intersections

    counts = [len(self_intersections(v, faces)) for v in bodies]
    return float(np.mean([c > 0 for c in counts])), counts


def geodesic_rows(basis, truths, n_pairs, frames=9):
    """Geodesics between the codes of pairs of extreme poses (``workflows.path_between``): the frames that
    cross themselves, against the endpoints' own."""
    from bareesa.latent import project_to_basis
    from bareesa.workflows import KnownCode, Options, path_between

    names = [n for n in truths if not n.startswith(("random", "apose"))]
    pairs = [(names[i], names[(i + 3) % len(names)]) for i in range(min(n_pairs, len(names)))]
    rows = []
    for a, b in pairs:
        codes = project_to_basis(basis, np.stack([truths[a], truths[b]]))[0]
        found = path_between(basis, KnownCode(codes[0]), KnownCode(codes[1]), frames, Options())
        bodies = basis.template + np.tensordot(found.frames, basis.fields, axes=1)
        share, counts = crossing_share(bodies, basis.faces)
        rows.append({"from": a, "to": b, "frames": frames, "crossing_frames": int(sum(c > 0 for c in counts)),
                     "ends_crossing": int((counts[0] > 0) + (counts[-1] > 0)), "max_pairs": int(max(counts))})
        print("  ".join(str(v) for v in rows[-1].values()), flush=True)
    return rows


def training_crossing_share(log=print):
    """Share of the first performer's training postures (as the build keeps them,
    ``bases.build.human.training_postures``) that cross themselves."""
    from bases.build import human as hb

    gen = hb.Human(log)
    neutral = {k: np.array([0.5]) for k in gen.model.phenotype_labels}  # the build's first performer
    bodies = hb.training_postures(gen, neutral, hb.POSTURE_SEED)[1]
    return crossing_share(bodies, gen.faces)[0]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--random", type=int, default=20, help="random-pose scans (default 20)")
    parser.add_argument("--extreme", type=int, default=None, help="extreme poses registered (default: all)")
    parser.add_argument("--apose", type=int, default=4, help="A-pose scans, the baseline (default 4)")
    parser.add_argument("--geodesics", type=int, default=6, help="geodesics between extreme poses (default 6)")
    parser.add_argument("--seed", type=int, default=SEED, help="the random poses' seed")
    parser.add_argument("--basis", default="human")
    parser.add_argument("--truths", type=Path, help="cache of the held-out bodies (written when missing)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--sheet", type=Path, help="also render the extreme poses' scans and fits to this PNG")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    from bareesa.basis_io import load_basis

    basis = load_basis(args.basis)
    truths = cached_truths(args.truths, basis, args.random, args.apose, args.seed)
    extreme = [n for n in truths if not n.startswith(("random", "apose"))][:args.extreme]
    order = ([n for n in truths if n.startswith("apose")][:args.apose] + [n for n in truths if n.startswith("random")]
             [:args.random] + extreme)
    rows, kept = [], {}
    for k, name in enumerate(order):
        rows.append(registration_row(basis, name, truths[name].astype(np.float64), seed=1000 + k,
                                     keep=kept if name in extreme else None))
        print("  ".join(str(v) for v in rows[-1].values()), flush=True)
    geodesics = geodesic_rows(basis, {n: truths[n] for n in extreme}, args.geodesics) if args.geodesics else []
    training = training_crossing_share() if args.geodesics else None
    figures, tables = summary(rows, geodesics, training)
    write_results("pose_coverage", figures, tables, TARGETS,
                  variant=variant_of(parser, args, ("truths", "threads", "sheet")), labels=LABELS)
    if args.sheet is not None:
        sheet(args.sheet, kept, rows)
    for key, value in figures.items():
        print(f"{key}: {value}")


TARGETS = {"random_success_pct": {"target": 95.0, "better": "higher"},
           "extreme_success_pct": {"target": 100.0, "better": "higher"},
           "worst_over_apose_time": {"target": 2.0, "better": "lower"},
           "poor_flags_on_good_fits": {"target": 0, "better": "lower"}}
LABELS = {"random_success_pct": "held-out random poses within 1 % of height (no landmarks)",
          "extreme_success_pct": "extreme poses within 1.5 % of height (no landmarks)",
          "worst_over_apose_time": "worst pose's registration time over the A-pose's",
          "poor_flags_on_good_fits": "right fits flagged poor",
          "apose_wall_s": "A-pose registration, same run (s)"}


def sheet(path, kept, rows, columns=6):
    """Scans (top) and their registrations (below) of the extreme poses, in rows of ``columns``."""
    from bench.common import contact_sheet

    errors = {r["scan"]: r["mean_%h"] for r in rows}
    names = list(kept)
    meshes, titles = [], []
    for start in range(0, len(names), columns):
        part = names[start:start + columns]
        blank = [None] * (columns - len(part))  # a short last row keeps scans above their fits
        meshes += [kept[n][0] for n in part] + blank + [kept[n][1] for n in part] + blank
        titles += ([f"{n.split('/')[0]}: scan" for n in part] + [""] * len(blank)
                   + [f"fit, {errors[n]:.2f} % of height" for n in part] + [""] * len(blank))
    contact_sheet(path, meshes, titles, ncols=columns, elev=10, azim=-70)
    print(f"wrote {path}")


def summary(rows, geodesics, training):
    """Figures and tables of the run."""
    kinds = {"random": [r for r in rows if r["kind"] == "random"], "apose": [r for r in rows if r["kind"] == "apose"],
             "extreme": [r for r in rows if r["kind"] not in ("random", "apose")]}
    figures = {}
    for kind, some in kinds.items():
        if not some:
            continue
        errors = np.array([r["mean_%h"] for r in some])
        times = np.array([r["seconds"] for r in some])
        limit = EXTREME_SUCCESS if kind == "extreme" else SUCCESS
        figures |= {f"{kind}_success_pct": round(100 * float(np.mean(errors <= limit)), 1),
                    f"{kind}_error_median_pct_height": round(float(np.median(errors)), 3),
                    f"{kind}_error_max_pct_height": round(float(errors.max()), 3),
                    f"{kind}_wall_s": round(float(times.mean()), 1), f"{kind}_wall_max_s": round(float(times.max()), 1),
                    f"{kind}_scans": len(some)}
    if kinds["apose"]:
        worst = max(r["seconds"] for r in rows)
        figures["worst_over_apose_time"] = round(worst / figures["apose_wall_s"], 2)
    figures["poor_flags_on_good_fits"] = sum(bool(r["poor_fit"]) and r["mean_%h"] <= SUCCESS for r in rows)
    figures["poor_flags"] = sum(bool(r["poor_fit"]) for r in rows)
    tables = [dict_table("Registration of held-out people, no landmarks", rows)]
    if geodesics:
        frames = sum(g["frames"] for g in geodesics)
        figures["geodesic_crossing_frames_pct"] = round(100 * sum(g["crossing_frames"] for g in geodesics) / frames, 1)
        figures["training_crossing_pct"] = round(100 * training, 1)
        tables.append(dict_table("Geodesics between extreme poses: frames with self-intersecting faces", geodesics))
    return figures, tables


if __name__ == "__main__":
    main()
