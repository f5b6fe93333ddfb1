"""How well geodesics reproduce motions they were not shown: the fitted metric against the paper's.

The deformed-capsule families of ``../shared/data/deformed_sphere`` (bend_X, bend_Y, twist_X, each a
sequence through the template) build a basis the way a user would, ``build-basis`` defaults (10 fields,
``--metric fit``), without the +-60 frames. Then, for each family and sign:

- midpoint: the frames 30 and 90 -> the held-out 60 frame (the middle of the geodesic);
- ahead: the frames 30 and 60 -> 90, 120 (and 150 where the family has it), by shooting.

Methods: geodesics of the fitted metric, of the paper's weights (``body``, what the CLI used before)
and of the ``face`` preset; the straight line in latent space; the vertex blend (linear in vertex
space). Errors are mean vertex distances to the true frame, in % of the capsule's length, and the
Chamfer distance of the issue's measurement; failed shootings are counted, never dropped silently.

With ``--human`` (needs the ``[bases]`` extra: Anny), the shipped ``human`` basis too: held-out
identities (``--people``) in the held-out motions (wave, lunge), baked at every frame (24 fps); in
windows starting at the frames ``HUMAN_STARTS``: the midpoint of (k, k + 10) -> k + 5, and from (k, k + 1)
the frames 1, 5, 10 and 20 ahead, as ``bareesa interpolate`` / ``extrapolate`` make them (anchored, the
inputs' off-basis detail carried), with the basis' metric (the card says whether it was fitted) and the
paper's weights, against the latent line (with the same detail) and the vertex blend; mean vertex error
in mm.

Run: python -m bench.motion_fidelity --human   (writes bench/results/motion_fidelity.json; without
--human, the capsule part alone, motion_fidelity--capsule-only.json)
"""

import argparse
import sys
import time

import numpy as np
import torch

from bench.common import dict_table, variant_of, write_results
from bench.sphere_data import FAMILIES, family_sequence, load_frames
from bareesa import evaluation, workflows
from bareesa.basis_building import build_basis
from bareesa.errors import BareEsaError
from bareesa.geodesics import decode_path, geodesic
from bareesa.h2_metric import PRESETS, H2Weights
from bareesa.latent import project_to_basis

#: build-basis' default number of fields per group.
COMPONENTS = 10
#: Time points of the geodesic whose middle predicts the held-out frame.
STEPS = 9
GEODESIC_METHODS = ("fitted metric", "paper weights", "face preset")
METHODS = (*GEODESIC_METHODS, "latent line", "vertex blend")


def predictions(basis, c0, c1, v0, v1, metrics, ahead, frozen):
    """{method: (len(ahead), N, 3) or an error message}: the frames at times ``ahead`` (in units of the
    step c0 -> c1; 0.5 is the midpoint) by each method; extrapolation as ``bareesa extrapolate`` does it
    (``workflows.extrapolate``, unanchored, no detail); frozen: {method: frames continued in the frozen
    metric} is filled in."""
    t, f, h = basis.tensors()
    out = {}
    for name, w in metrics.items():
        try:
            if ahead == [0.5]:
                path = geodesic(t, f, h, c0, c1, w, steps=STEPS).path[STEPS // 2][None]
            else:
                motion = workflows.extrapolate(basis, workflows.KnownCode(c0), workflows.KnownCode(c1),
                                               int(max(ahead)) - 1, workflows.Options(weights=w), anchor=False,
                                               keep_detail=False)
                frozen[name] = motion.shooting.frozen
                path = motion.path[[int(k) for k in ahead]]
            out[name] = decode_path(t, h, path)
        except BareEsaError as err:
            out[name] = str(err).splitlines()[0]
    out["latent line"] = decode_path(t, h, np.stack([c0 + k * (c1 - c0) for k in ahead]))
    out["vertex blend"] = np.stack([v0 + k * (v1 - v0) for k in ahead])
    return out


#: First frames of the human windows (the sequences have 49 frames).
HUMAN_STARTS = (4, 20)
HUMAN_HALF = 5
HUMAN_AHEAD = (1, 5, 10, 20)
HUMAN_METHODS = ("basis metric", "paper weights", "latent line", "vertex blend")


def human_sequences(people):
    """{(identity, motion): (49, N, 3)}: held-out identities of the ``human`` build in its held-out motions."""
    from bases.build import human as hb
    from bases.build.motions import HUMAN_TEST_MOTIONS

    gen = hb.Human(lambda *_: None)
    _, test = hb.identities(model=gen.model)
    return {(i, m): gen.motion(hb._take(test, i), m, step=1).astype(np.float64)
            for i in range(people) for m in HUMAN_TEST_MOTIONS}


def human_rows(basis, seqs, failures, also=None):
    """One row per window and target: the mean vertex error (mm) of each of HUMAN_METHODS (and of the
    metrics ``also``, {label: weights})."""
    t, f, h = basis.tensors()
    metrics = {"basis metric": basis.weights, "paper weights": PRESETS["body"], **(also or {})}
    methods = (*metrics, "latent line", "vertex blend")
    rows = []
    for (ident, motion), seq in seqs.items():
        for k in HUMAN_STARTS:
            a, b, m = seq[k], seq[k + 2 * HUMAN_HALF], seq[k + HUMAN_HALF]
            ends = [workflows.TemplateMesh(a), workflows.TemplateMesh(b)]
            got = {}
            for name, w in metrics.items():
                found = workflows.path_between(basis, *ends, 3, workflows.Options(weights=w))
                got[name] = decode_path(t, h, found.frames[1:2])[0] + found.detail[1]
            got["latent line"] = got["vertex blend"] = (a + b) / 2  # (the line plus the carried detail is the blend)
            row = {"window": f"id{ident} {motion} {k}-{k + 2 * HUMAN_HALF}", "task": "midpoint",
                   "target": k + HUMAN_HALF}
            rows.append(row | {n: 1e3 * float(np.linalg.norm(got[n] - m, axis=1).mean()) for n in methods})
            n_new = max(HUMAN_AHEAD)
            shots = {}
            given = workflows.codes_of(basis, [workflows.TemplateMesh(seq[j]) for j in (k, k + 1)])
            for name, w in metrics.items():
                try:
                    found = workflows.extrapolate(basis, *(workflows.KnownCode(c.code, c.detail) for c in given),
                                                  n_new, workflows.Options(weights=w))
                except BareEsaError as err:  # the frames before the failure, as asking for fewer would give them
                    failures.append(f"id{ident} {motion} from {k}, {name}: {str(err).splitlines()[0]}")
                    found = getattr(err, "reached", None)
                if found is not None:
                    shots[name] = (decode_path(t, h, found.path) + found.detail, found.shooting)
            (c0, d0), (c1, d1) = ((c.code, c.detail) for c in given)
            for ahead in HUMAN_AHEAD:
                truth = seq[k + 1 + ahead]
                line = decode_path(t, h, (c1 + ahead * (c1 - c0))[None])[0]
                got = {"latent line": line + d1 + ahead * (d1 - d0),
                       "vertex blend": seq[k + 1] + ahead * (seq[k + 1] - seq[k])}
                got |= {n: shot[0][1 + ahead] for n, shot in shots.items() if 1 + ahead < len(shot[0])}
                row = {"window": f"id{ident} {motion} {k}, {k + 1}", "task": f"{ahead} ahead", "target": k + 1 + ahead}
                row |= {n: (1e3 * float(np.linalg.norm(got[n] - truth, axis=1).mean()) if n in got else None)
                        for n in methods}
                report = shots.get("basis metric", (None, None))[1]
                row["frozen frames (basis metric)"] = None if report is None else len(report.frozen)
                rows.append(row)
    return rows


#: Frames of the BVP geodesics that shooting is checked against (the CLI's geodesic time points).
AGREEMENT_STEPS = 10
#: Simulated scans for the registered inputs (as bench.pose_coverage makes them).
SCAN = dict(remesh="voxel", noise=0.001, holes=3, scale=0.1)


def agreement_rows(basis, seqs, scans):
    """IVP against BVP: the geodesic (as ``bareesa interpolate`` solves it) between frames 4 and 44 of each
    sequence, and, for the first ``scans`` sequences, between registered simulated scans of them; shot from
    its first two points by AGREEMENT_STEPS - 2 steps: -> rows with the largest and the last frame's mean
    vertex distance (mm) between the shot and the geodesic. Also extrapolation 10 frames ahead from registered
    scans of frames 20 and 22 (``workflows.extrapolate``: the second registered in the first's frame): finished
    or not, and its error at 10 ahead against the true frame (in the registrations' frame), beside the vertex blend
    of the true frames 20 and 22."""
    from bareesa.scan_simulator import simulate_scan
    from bareesa.registration.prealign import landmark_alignment
    from bareesa.shooting import extrapolate

    t, f, h = basis.tensors()
    rows = []
    options = workflows.Options(steps=AGREEMENT_STEPS)
    for n, ((ident, motion), seq) in enumerate(seqs.items()):
        inputs = {"template bodies": [workflows.TemplateMesh(seq[j]) for j in (4, 44)]}
        if n < scans:
            # (one capture: the same scanner pose and scale for both frames)
            inputs["registered scans"] = [workflows.Scan(*simulate_scan(seq[j], basis.faces, seed=n, **SCAN)[:2])
                                          for j in (4, 44)]
        for kind, ends in inputs.items():
            codes = [c.code for c in workflows.codes_of(basis, ends, options)]
            path = workflows.geodesic_between(basis, *(workflows.KnownCode(c) for c in codes), options).path
            row = {"sequence": f"id{ident} {motion}", "inputs": kind, "frames": "4 -> 44"}
            try:
                shot = extrapolate(t, f, h, path[0], path[1], basis.weights, AGREEMENT_STEPS - 2)
                gap = np.linalg.norm(decode_path(t, h, shot[2:]) - decode_path(t, h, path[2:]), axis=-1).mean(-1)
                row |= {"shot vs geodesic, worst frame (mm)": 1e3 * float(gap.max()),
                        "last frame (mm)": 1e3 * float(gap[-1])}
            except BareEsaError as err:
                row |= {"shot vs geodesic, worst frame (mm)": None, "failed": str(err).splitlines()[0]}
            rows.append(row)
        if n < scans:
            ends = [workflows.Scan(*simulate_scan(seq[j], basis.faces, seed=100 + n, **SCAN)[:2]) for j in (20, 22)]
            row = {"sequence": f"id{ident} {motion}", "inputs": "registered scans", "frames": "20, 22 -> 10 ahead"}
            try:
                found = workflows.extrapolate(basis, *ends, 10, workflows.Options(), keep_detail=False)
                first, pred = decode_path(t, h, found.path[[0, -1]])
                # the registrations' frame is the scans' alignment to the template, not the sequence's own: the
                # true frames are compared in it (the similarity taking the true first frame onto its fit)
                gauge = landmark_alignment(first, seq[20])
                blend = seq[22] + 10 * (seq[22] - seq[20])
                row |= {"finished": True, "same frame": found.same_frame, "frozen frames": len(found.shooting.frozen),
                        "error at 10 ahead (mm)": 1e3 * float(np.linalg.norm(pred - gauge.apply(seq[42]), axis=1).mean()),
                        "true frames' vertex blend (mm)": 1e3 * float(np.linalg.norm(blend - seq[42], axis=1).mean())}
            except BareEsaError as err:
                reached = getattr(err, "frames", None)
                row |= {"finished": False, "frames reached": 0 if reached is None else len(reached),
                        "failed": str(err).splitlines()[0]}
            rows.append(row)
    return rows


def human_figures(rows, also=()):
    """Summary figures of ``human_rows``: per task, the share of windows each metric wins against the
    latent line and the vertex blend, mean errors, failures."""
    out = {}
    for task in ["midpoint", *(f"{a} ahead" for a in HUMAN_AHEAD)]:
        picked = [r for r in rows if r["task"] == task]
        key = task.replace(" ", "_")
        for m in (*HUMAN_METHODS, *also):
            errs = [r[m] for r in picked if r[m] is not None]
            out[f"human_{key}_{m.replace(' ', '_')}_mean_mm"] = float(np.mean(errs)) if errs else None
        for m in ("basis metric", "paper weights", *also):
            wins = [r[m] is not None and r[m] < min(r["latent line"], r["vertex blend"]) for r in picked]
            out[f"human_{key}_{m.replace(' ', '_')}_beats_line_and_blend_pct"] = 100.0 * np.mean(wins)
            out[f"human_{key}_{m.replace(' ', '_')}_failed"] = sum(r[m] is None for r in picked)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--components", type=int, default=COMPONENTS)
    parser.add_argument("--human", action="store_true", help="also the human basis on held-out people (needs Anny)")
    parser.add_argument("--people", type=int, default=3, help="held-out identities of the human part")
    parser.add_argument("--scans", type=int, default=6,
                        help="human part: sequences whose frames are also given as registered simulated scans")
    parser.add_argument("--also", action="append", default=[], metavar="LABEL=W",
                        help="human part: also a metric LABEL with the weights W (six numbers), for comparison")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    frames, faces = load_frames("motion_fidelity")
    template = frames[("template", 0)]
    length = float(np.ptp(template, axis=0).max())
    t0 = time.perf_counter()
    basis = build_basis(template, faces, {"pose": [family_sequence(frames, fam) for fam in FAMILIES]},
                        {"pose": args.components}, weights="fit", name="deformed_capsule")
    fit_s = time.perf_counter() - t0
    fit = basis.provenance["metric_fit"]
    metrics = {"fitted metric": basis.weights, "paper weights": PRESETS["body"], "face preset": PRESETS["face"]}
    rows, failures, continued = [], [], []
    for fam in FAMILIES:
        for sign in (1, -1):
            code = {a: project_to_basis(basis, frames[(fam, a * sign)])[0] for a in (30, 60, 90)}
            tasks = [("midpoint", 30, 90, [0.5])]
            ahead = [k for k in (2, 3, 4) if (fam, (30 + 30 * k) * sign) in frames]
            tasks.append(("ahead", 30, 60, ahead))
            for task, a, b, when in tasks:
                frozen = {}
                got = predictions(basis, code[a], code[b], frames[(fam, a * sign)], frames[(fam, b * sign)],
                                  metrics, when, frozen)
                continued.extend(f"{fam} {a * sign:+d}, {b * sign:+d}, {m}: frames {v}" for m, v in frozen.items() if v)
                for i, k in enumerate(when):
                    angle = int(round(a + k * (b - a))) * sign
                    truth = frames[(fam, angle)]
                    row = {"family": fam, "task": task, "inputs": f"{a * sign:+d}, {b * sign:+d}",
                           "target": f"{angle:+d}"}
                    for m in METHODS:
                        if isinstance(got[m], str):
                            row[m] = None
                            if i == 0:
                                failures.append(f"{fam} {row['inputs']} -> {row['target']}, {m}: {got[m]}")
                        else:
                            row[m] = 100 * evaluation.vertex_error(got[m][i], truth)["mean"] / length
                            row[m + " Chamfer"] = evaluation.chamfer(got[m][i], truth)
                    rows.append(row)
    figures = {"fit_seconds": fit_s, "fit_chosen_is_fit": fit["chosen"] == "fit",
               "ahead_fitted_metric_frozen_runs": sum(": fitted metric:" in x for x in continued)}
    for task in ("midpoint", "ahead"):
        picked = [r for r in rows if r["task"] == task]
        for m in METHODS:
            errs = [r[m] for r in picked if r[m] is not None]
            key = m.replace(" ", "_")
            figures[f"{task}_{key}_mean_pct_length"] = float(np.mean(errs)) if errs else None
            figures[f"{task}_{key}_failed"] = sum(r[m] is None for r in picked)
        for m in GEODESIC_METHODS:
            key = m.replace(" ", "_")
            beats = [r[m] is not None and r[m] < min(r["latent line"], r["vertex blend"]) for r in picked]
            figures[f"{task}_{key}_beats_line_and_blend_pct"] = 100.0 * np.mean(beats)
        figures[f"{task}_families_fitted_beats_both"] = sum(
            all(r["fitted metric"] is not None and r["fitted metric"] < min(r["latent line"], r["vertex blend"])
                for r in picked if r["family"] == fam) for fam in FAMILIES)
    tables = []
    if args.human:
        from bareesa.basis_io import load_basis

        human = load_basis("human")
        start = time.perf_counter()
        also = dict(spec.split("=", 1) for spec in args.also)
        also = {label: H2Weights.parse(w) for label, w in also.items()}
        seqs = human_sequences(args.people)
        hrows = human_rows(human, seqs, failures, also)
        figures |= human_figures(hrows, tuple(also)) | {"human_seconds": time.perf_counter() - start}
        chosen = human.provenance.get("metric_fit", {}).get("chosen", "set by hand")
        tables.append(dict_table("human: mean vertex error (mm) of held-out people in held-out motions; basis metric "
                                 + ", ".join(f"{w:.4g}" for w in human.weights.as_tuple()) + f" ({chosen})", hrows))
        start = time.perf_counter()
        arows = agreement_rows(human, seqs, args.scans)
        gaps = [r["shot vs geodesic, worst frame (mm)"] for r in arows if "shot vs geodesic, worst frame (mm)" in r]
        shots = [r for r in arows if "finished" in r]
        figures |= {"human_ivp_bvp_gap_max_mm": max((g for g in gaps if g is not None), default=None),
                    "human_ivp_bvp_failed": sum(g is None for g in gaps),
                    "human_scan_extrapolation_finished_pct": 100.0 * np.mean([r["finished"] for r in shots])
                    if shots else None, "human_agreement_seconds": time.perf_counter() - start}
        tables.append(dict_table("human: shooting from a geodesic's first two points against the geodesic (IVP vs "
                                 "BVP), and extrapolation from registered scans", arows))
    # the full run (--human) is the default results file the README shows; the capsule alone is a variant
    variant = "_".join(filter(None, [variant_of(parser, args, ("human", "also")),
                                     None if args.human else "capsule-only"]))
    header = ["family", "task", "inputs", "target", *METHODS]
    table_rows = [{k: r.get(k) for k in header} for r in rows]
    chamfer = [{"family": r["family"], "task": r["task"], "target": r["target"],
                **{m: r.get(m + " Chamfer") for m in METHODS}} for r in rows]
    scores = [{"candidate": k, "held-out training frame error (units)": v}
              for k, v in fit["held_out_frame_error"].items()]
    write_results("motion_fidelity", figures,
                  [dict_table("Mean vertex error, % of the capsule's length (empty: shooting failed)", table_rows),
                   dict_table("Chamfer distance (shape units)", chamfer),
                   dict_table(f"Metric fit (chosen: {fit['chosen']}, weights "
                              + ", ".join(f"{w:.4g}" for w in fit["weights"]) + ")", scores), *tables],
                  TARGETS, labels=LABELS, variant=variant, argv=sys.argv[1:] if argv is None else argv)
    for line in failures:
        print("failed:", line)
    for line in continued:
        print("continued in the frozen metric:", line)
    for key, value in figures.items():
        print(f"{key}: {value}")


TARGETS = {"midpoint_families_fitted_beats_both": {"target": len(FAMILIES), "better": "higher"},
           "human_midpoint_basis_metric_beats_line_and_blend_pct": {"target": 80.0, "better": "higher"},
           "human_10_ahead_basis_metric_beats_line_and_blend_pct": {"target": 80.0, "better": "higher"},
           "human_10_ahead_basis_metric_failed": {"target": 0, "better": "lower"},
           "human_ivp_bvp_gap_max_mm": {"target": 2.0, "better": "lower"},
           "human_scan_extrapolation_finished_pct": {"target": 100.0, "better": "higher"},
           "midpoint_fitted_metric_beats_line_and_blend_pct": {"target": 100.0, "better": "higher"},
           "ahead_fitted_metric_failed": {"target": 0, "better": "lower"}}
LABELS = {"midpoint_families_fitted_beats_both": "capsule families whose held-out midpoints the fitted metric "
                                                 "predicts better than the latent line and the vertex blend",
          "midpoint_fitted_metric_beats_line_and_blend_pct": "held-out capsule midpoints: fitted metric beats line "
                                                             "and blend",
          "ahead_fitted_metric_failed": "capsule extrapolations (30, 60 -> 90 ...) that failed, fitted metric",
          "human_midpoint_basis_metric_beats_line_and_blend_pct": "human held-out windows: geodesic midpoint beats "
                                                                  "line and blend",
          "human_10_ahead_basis_metric_beats_line_and_blend_pct": "human held-out windows: 10 frames ahead beats "
                                                                  "line and blend",
          "human_10_ahead_basis_metric_failed": "human held-out windows: extrapolations 10 frames ahead that failed",
          "human_ivp_bvp_gap_max_mm": "human: shooting from a geodesic's first two points against the geodesic, worst "
                                      "frame's mean vertex distance",
          "human_scan_extrapolation_finished_pct": "human: extrapolations from registered scans of held-out people "
                                                   "that finished"}

if __name__ == "__main__":
    main()
