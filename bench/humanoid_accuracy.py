"""Accuracy of the ``humanoid`` mannequin basis (retired from the bundle) on data never used to build it.

Held-out body types (``bases.build.humanoid.identity_sets()[1]``) performing held-out
motions (``TEST_MOTIONS``) are regenerated with the Blender generator (needs ``bpy``).

1. Registration: simulated scans (``bareesa.scan_simulator``: voxel remesh, noise, holes,
   random rigid motion and scale) registered with ``bareesa.registration.register``; vertex
   error against the true correspondence (mean, p95; mm and % of body height), Chamfer,
   Hausdorff and squared varifold distance to the scan (scan units, scaled back to metres).
2. Interpolation / extrapolation (the paper's Tables 3-4 protocol in miniature): held-out
   motions baked at every frame are cut into monotone mini-sequences; endpoints are projected
   onto the basis; the H2 geodesic (as solved, and anchored as the CLI and add-on output it),
   the straight line in latent space and the linear vertex blend of the true endpoints are
   compared with the true in-between (resp. following) frames.
3. Basis-size ablation (paper Table 3 style): projection error of held-out frames for
   prefixes of the pose and shape groups.
4. A contact sheet PNG (template, identities, a motion).

Usage: python -m bench.humanoid_accuracy --basis DIR/humanoid.npz [--scans N] [--full NPZ] [--card] [--out bench/out]
(build the mannequin first: python -m bases.build humanoid -o DIR)
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _table(rows, cols, title):
    print(f"\n{title}")
    widths = [max(len(c), *(len(f"{r[c]}") for r in rows)) for c in cols]
    print("  ".join(c.rjust(w) for c, w in zip(cols, widths)))
    for r in rows:
        print("  ".join(f"{r[c]}".rjust(w) for c, w in zip(cols, widths)), flush=True)


def held_out_data(log=print):
    """Held-out identities: rest meshes and held-out motions baked at every frame (T, N, 3), from
    the Blender generator. Every ``humanoid.BAKE_STEP``-th frame is what a basis build bakes."""
    from bases.build import humanoid

    gen = humanoid.Generator(log)
    _, test = humanoid.identity_sets()
    faces = gen.faces
    rests = [gen.rest_mesh(p)[0] for p in test]
    seqs = {(i, m): gen.motion(p, m, step=1) for i, p in enumerate(test) for m in humanoid.TEST_MOTIONS}
    return gen, faces, rests, seqs


# --------------------------------------------------------------------------- registration


def registration_rows(basis, faces, seqs, n_scans, seed=0):
    from bareesa.evaluation import chamfer, hausdorff, varifold, vertex_error
    from bareesa.registration import register
    from bareesa.scan_simulator import apply_similarity, simulate_scan

    keys = sorted(seqs)
    rows = []
    for k in range(n_scans):
        key = keys[k % len(keys)]
        seq = seqs[key]
        frame = [len(seq) // 2, len(seq) // 4, 3 * len(seq) // 4][(k // len(keys)) % 3]
        true = seq[frame].astype(np.float64)
        height = float(true[:, 2].max() - true[:, 2].min())
        scan_v, scan_f, info = simulate_scan(true, faces, seed=seed + k, remesh="voxel", noise=0.001, holes=3,
                                             scale=0.1)
        t0 = time.perf_counter()
        res = register(basis, scan_v, scan_f)
        seconds = time.perf_counter() - t0
        truth = apply_similarity(info, true)
        err = vertex_error(res.vertices, truth)
        s = info["scale"]
        sigma = 0.025 * height * s  # the finest level of the paper's body schedule
        rows.append({"scan": f"id{key[0]}/{key[1]}/f{frame}", "scan_verts": len(scan_v),
                     "mean_mm": round(1e3 * err["mean"] / s, 1), "p95_mm": round(1e3 * err["p95"] / s, 1),
                     "mean_%h": round(100 * err["mean"] / s / height, 3),
                     "p95_%h": round(100 * err["p95"] / s / height, 3),
                     "chamfer_mm": round(1e3 * chamfer(res.vertices, scan_v) / s, 1),
                     "hausdorff_mm": round(1e3 * hausdorff(res.vertices, scan_v) / s, 1),
                     "varifold": float(f"{varifold(res.vertices, basis.faces, scan_v, scan_f, sigma) / s**4:.3g}"),
                     "residual": None if res.residual is None else round(float(res.residual), 6),
                     "poor_fit": res.poor_fit, "retried": int(res.retried_alignments),
                     "seconds": round(seconds, 1)})
        _table(rows[-1:], list(rows[-1]), "") if k == 0 else print(
            "  ".join(str(v) for v in rows[-1].values()), flush=True)
    return rows


def _mean_row(rows):
    """Column means of registration rows (the numeric columns), and how many fits were flagged poor."""
    numeric = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
    out = {k: round(float(np.mean([r[k] for r in rows])), 6 if k == "residual" else 3) for k in rows[0]
           if all(numeric(r.get(k)) for r in rows)}
    if "poor_fit" in rows[0]:
        out["poor_fits"] = sum(bool(r["poor_fit"]) for r in rows)
    return out


# ---------------------------------------------------------------------- interpolation


def _distances(pred, true, faces, sigma):
    from bareesa.evaluation import chamfer, hausdorff, varifold

    return np.array([hausdorff(pred, true), chamfer(pred, true), varifold(pred, faces, true, faces, sigma)])


def monotone_segments(seq, min_frames=8, reverse=0.5):
    """Mini-sequences of a motion (T, N, 3): frame ranges [(a, b)] in which it does not turn back.

    A turn is a frame where the share of the vertices' motion that reverses (negative dot
    product of consecutive frame steps, summed per vertex) exceeds ``reverse`` times the share
    that goes on. Across a turn the end frames do not determine the in-betweens (a window
    symmetric about the top of a raise has two equal ends), so no method can interpolate it.
    """
    steps = np.diff(seq, axis=0)
    dots = np.einsum("tnc,tnc->tn", steps[:-1], steps[1:])
    ratio = np.maximum(-dots, 0).sum(1) / np.maximum(np.maximum(dots, 0).sum(1), 1e-30)
    cuts = [0] + [j + 1 for j in np.flatnonzero(ratio > reverse)] + [len(seq) - 1]
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b - a >= min_frames]


#: the methods ``interpolation_window`` and ``extrapolation_window`` compare; "H2 anchored + detail" is the CLI's
METHODS = ("H2 geodesic", "H2 anchored", "H2 anchored + detail", "latent line", "vertex blend")


def interpolation_window(basis, seq, codes, detail, k, half, sigma):
    """Every method's path k -> k + 2h against the true frames at a quarter, half and three quarters of
    the way: seq (T, N, 3), codes (T, P) and detail (T, N, 3) of its frames -> {method: (hausdorff,
    chamfer, varifold)} (``interpolation_rows`` explains the methods)."""
    from bareesa.geodesics import anchor_path, decode_path, geodesic, straight_path
    from bareesa.latent import detail_along

    t, f, h = basis.tensors()
    n = 2 * half + 1
    line = straight_path(codes[k], codes[k + 2 * half], n)
    g = geodesic(t, f, h, codes[k], codes[k + 2 * half], basis.weights, steps=n, metric=basis.template_metric()).path
    lam = np.linspace(0, 1, n)[:, None, None]
    blend = (1 - lam) * seq[k] + lam * seq[k + 2 * half]
    carried = detail_along(detail[k], detail[k + 2 * half], lam)
    anchored, on_line = decode_path(t, h, anchor_path(t, h, g, line)), decode_path(t, h, line)
    paths = (decode_path(t, h, g), anchored, anchored + carried, on_line, blend)
    assert np.allclose(on_line + carried, blend, atol=1e-9)
    probe = sorted({round(q * 2 * half) for q in (0.25, 0.5, 0.75)})
    return {name: np.mean([_distances(path[j], seq[k + j], basis.faces, sigma) for j in probe], axis=0)
            for name, path in zip(METHODS, paths)}


def extrapolation_window(basis, seq, codes, detail, k, half, targets, sigma):
    """Every method's continuation of (k, k + h) against the true frames ``targets`` (k + 2h, k + 3h,
    ...): -> {method: (hausdorff, chamfer, varifold)}; raises ShootingFailed when the shot does not
    converge."""
    from bareesa.geodesics import decode_path
    from bareesa.latent import detail_along
    from bareesa.shooting import anchor_extrapolation, extrapolate

    t, f, h = basis.tensors()
    ex = extrapolate(t, f, h, codes[k], codes[k + half], basis.weights, len(targets), substeps=min(half, 5))
    steps = np.arange(len(targets) + 2)[:, None]
    line = codes[k] + steps * (codes[k + half] - codes[k])
    blend = seq[k] + steps[:, :, None] * (seq[k + half] - seq[k])
    anchored = decode_path(t, h, anchor_extrapolation(t, h, ex))
    carried = detail_along(detail[k], detail[k + half], steps)
    paths = (decode_path(t, h, ex), anchored, anchored + carried, decode_path(t, h, line), blend)
    return {name: np.mean([_distances(path[2 + i], seq[m], basis.faces, sigma) for i, m in enumerate(targets)],
                          axis=0) for name, path in zip(METHODS, paths)}


def interpolation_rows(basis, seqs, halves=(5, 10), stride=6):
    """The paper's Tables 3-4 protocol in miniature, on the monotone mini-sequences of held-out motions.

    seqs are baked at every frame (24 fps). In every mini-sequence (``monotone_segments``), for
    each half span h (frames) and start k (every ``stride`` frames): interpolation k -> k + 2h,
    compared with the true frames at a quarter, half and three quarters of the way; from the
    mini-sequence's first frame a (as the paper, which starts from the first two meshes),
    extrapolation from (a, a + h) to a + 2h and a + 3h where they lie in the mini-sequence.
    Endpoint codes are projections of the true frames (``project_to_basis``); the vertex
    baselines use the true frames themselves. "H2 anchored" is the geodesic with the body's
    unmoving part kept in place (``bareesa.geodesics.anchor_path``, what the CLI and the add-on
    output); "+ detail" also carries the end frames' off-basis detail (``bareesa.latent.detail_along``,
    what the CLI writes for template-topology inputs), so it passes through the true end frames
    as the vertex blend does: the latent line plus the same detail IS the vertex blend (F is
    affine; checked below), so that pair differs only in the path between the same ends.
    Rows per half span, and "all": the mean over every window of the task. A shot that does not
    converge is counted and left out for every method.
    """
    from bareesa.errors import ShootingFailed
    from bareesa.latent import off_basis_detail, project_to_basis

    out = {(task, hf): {m: [] for m in METHODS} for task in ("interpolation", "extrapolation") for hf in halves}
    failures = []
    for n_done, key in enumerate(sorted(seqs)):
        seq = seqs[key].astype(np.float64)
        segments = monotone_segments(seq)
        print(f"  sequence {n_done + 1}/{len(seqs)}: identity {key[0]}, {key[1]}, mini-sequences {segments}",
              flush=True)
        sigma = 0.025 * float(seq[0][:, 2].max() - seq[0][:, 2].min())
        codes = project_to_basis(basis, seq)[0]
        detail = off_basis_detail(basis, seq, codes)
        for half in halves:
            for a, b in segments:
                for k in range(a, b - 2 * half + 1, stride):
                    for name, d in interpolation_window(basis, seq, codes, detail, k, half, sigma).items():
                        out[("interpolation", half)][name].append(d)
                    print(f"    interpolation {k} -> {k + 2 * half}: " + ", ".join(
                        f"{m} {1e3 * out[('interpolation', half)][m][-1][1]:.1f}" for m in METHODS) + " mm Chamfer",
                        flush=True)
                if b - a < 2 * half:
                    continue
                k = a
                targets = [m for m in (k + 2 * half, k + 3 * half) if m <= b]
                try:
                    found = extrapolation_window(basis, seq, codes, detail, k, half, targets, sigma)
                except ShootingFailed as err:
                    failures.append(f"{key}/k{k}/h{half}: {err}")
                    continue
                for name, d in found.items():
                    out[("extrapolation", half)][name].append(d)
                print(f"    extrapolation {k}, {k + half} -> {targets}: " + ", ".join(
                    f"{m} {1e3 * out[('extrapolation', half)][m][-1][1]:.1f}" for m in METHODS) + " mm Chamfer",
                    flush=True)
    for task in ("interpolation", "extrapolation"):
        out[(task, "all")] = {m: [d for hf in halves for d in out[(task, hf)][m]] for m in METHODS}
    rows = []
    for (task, half), per_method in out.items():
        for name, ds in per_method.items():
            if not ds:
                continue
            m = np.mean(ds, axis=0)
            rows.append({"task": task, "half span": half, "method": name, "hausdorff_mm": round(1e3 * m[0], 1),
                         "chamfer_mm": round(1e3 * m[1], 2), "varifold": float(f"{m[2]:.3g}"), "n": len(ds)})
    for line in failures:
        print(f"extrapolation failed (H2 shooting did not converge): {line}")
    return rows


#: ``METHODS``' name of the CLI's default path (anchored geodesic + the ends' off-basis detail)
CLI = "H2 anchored + detail"


def interpolation_figures(rows):
    """Headline figures of interpolation / extrapolation rows (their "all" windows): the CLI default's,
    the latent line's and the vertex blend's Chamfer and Hausdorff, and on how many of the three
    measures (Hausdorff, Chamfer, varifold) the CLI default beats both."""
    figures = {}
    keys = {CLI: "cli", "latent line": "latent_line", "vertex blend": "vertex_blend"}
    for task in ("interpolation", "extrapolation"):
        found = {r["method"]: r for r in rows if r["task"] == task and r["half span"] == "all"}
        for method, key in keys.items():
            if method in found:
                figures[f"{task}_{key}_chamfer_mm"] = found[method]["chamfer_mm"]
                figures[f"{task}_{key}_hausdorff_mm"] = found[method]["hausdorff_mm"]
        if all(m in found for m in keys):
            figures[f"{task}_cli_beats_both_measures"] = sum(
                all(found[CLI][k] < found[m][k] for m in ("latent line", "vertex blend"))
                for k in ("hausdorff_mm", "chamfer_mm", "varifold"))
    return figures


# ---------------------------------------------------------------------------- ablation


def ablation_rows(basis, rests, seqs, pose_sizes, shape_sizes):
    """RMS projection error (mm) of held-out frames onto prefixes of the pose and shape groups."""
    frames = np.concatenate([np.stack(rests)] + [s[1::2] for s in seqs.values()]).astype(np.float64)
    ps, ss = basis.group_slice("pose"), basis.group_slice("shape")
    rows = []
    for kp in pose_sizes:
        row = {"pose \\ shape": kp}
        for ks in shape_sizes:
            idx = np.r_[ps.start:ps.start + min(kp, ps.stop - ps.start), ss.start:ss.start + min(ks, ss.stop - ss.start)]
            a = basis.fields[idx].reshape(len(idx), -1).T
            x = (frames - basis.template).reshape(len(frames), -1).T
            coef, *_ = np.linalg.lstsq(a, x, rcond=None)
            r = (x - a @ coef).T.reshape(len(frames), -1, 3)
            row[str(ks)] = round(1e3 * float(np.sqrt((r ** 2).sum(-1).mean())), 2)
        rows.append(row)
    return rows


# ------------------------------------------------------------------------- contact sheet


def render(ax, verts, faces, elev=8, azim=-90, color=(0.75, 0.78, 0.85)):
    """Flat-shaded matplotlib rendering of a mesh into a 3D axis."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from bareesa.mesh import face_geometry

    p = verts[faces]
    n = face_geometry(verts, faces)[0]
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    light = np.array([0.35, -0.85, 0.4])
    shade = 0.25 + 0.75 * np.clip(n @ (light / np.linalg.norm(light)), 0, 1)
    ax.add_collection3d(Poly3DCollection(p, facecolors=np.clip(shade[:, None] * color, 0, 1), edgecolor="none"))
    c = 0.5 * (verts.max(0) + verts.min(0))
    r = 0.5 * (verts.max(0) - verts.min(0)).max()
    ax.set_xlim(c[0] - r, c[0] + r), ax.set_ylim(c[1] - r, c[1] + r), ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev, azim)
    ax.axis("off")


def contact_sheet(path, basis, gen, seqs):
    from bases.build import humanoid

    train, test = humanoid.identity_sets()
    rows = [("template + training identities", [basis.template] + [gen.rest_mesh(p)[0] for p in train[:5]]),
            ("held-out identities", [gen.rest_mesh(p)[0] for p in test] + [None, None]),
            ("training motion 'squat' (template body)", list(gen.motion({}, "squat")[::3])[:6]),
            ("held-out motion 'lunge' (held-out identity 0)", list(seqs[(0, "lunge")][::3])[:6])]
    sheet(path, rows, basis.faces, height=9.5)


def sheet(path, rows, faces, height):
    """A PNG of titled rows of up to six meshes (None leaves a gap): rows [(title, [(N, 3), ...])]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(12, height))
    for i, (title, meshes) in enumerate(rows):
        for j, v in enumerate(meshes[:6]):
            if v is None:
                continue
            ax = fig.add_subplot(len(rows), 6, 6 * i + j + 1, projection="3d")
            render(ax, np.asarray(v, dtype=np.float64), faces, color=(0.85, 0.75, 0.65) if i % 2 else
                   (0.7, 0.78, 0.9))
            if j == 0:
                ax.set_title(title, loc="left", fontsize=9)
    fig.subplots_adjust(0, 0, 1, 0.97, 0, 0.08)
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ------------------------------------------------------------------------------- main


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--basis", help="a build of the mannequin: python -m bases.build humanoid -o DIR, then "
                                        "DIR/humanoid.npz (it is no longer bundled)")
    parser.add_argument("--scans", type=int, default=8, help="number of simulated scans to register")
    parser.add_argument("--skip", nargs="*", default=[], choices=["registration", "interpolation", "ablation",
                                                                   "sheet"])
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "out")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--full", type=Path, metavar="NPZ",
                        help="a float64 build of the same basis (python -m bases.build --keep-full DIR): the scans "
                             "are registered with both, to show the shipped precision changes nothing")
    parser.add_argument("--card", action="store_true",
                        help="write the measured accuracy into the basis' card (the .json beside the .npz)")
    args = parser.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    if args.basis is None:
        parser.error("the humanoid mannequin is no longer bundled: build it with python -m bases.build humanoid "
                     "-o DIR and give --basis DIR/humanoid.npz")
    import torch

    from bench.common import variant_of

    torch.set_num_threads(args.threads)
    from bareesa.basis_io import load_basis

    basis = load_basis(args.basis)
    args.out.mkdir(parents=True, exist_ok=True)
    height = float(basis.template[:, 2].max() - basis.template[:, 2].min())
    print(f"basis {basis.name}: {len(basis.template)} vertices, groups {basis.groups}, height {height:.3f} m")
    from bases.build.humanoid import BAKE_STEP

    gen, faces, rests, every_frame = held_out_data(log=lambda *_: None)
    if not np.array_equal(faces, basis.faces):
        sys.exit("the generator's topology differs from the bundled basis: rebuild with python -m bases.build")
    seqs = {key: seq[::BAKE_STEP] for key, seq in every_frame.items()}  # the frames a build bakes
    results = {}
    if "ablation" not in args.skip:
        ps, ss = basis.group_slice("pose"), basis.group_slice("shape")
        np_, ns = ps.stop - ps.start, ss.stop - ss.start
        rows = ablation_rows(basis, rests, seqs, sorted({10, 20, 40, 60, np_} & set(range(1, np_ + 1))),
                             sorted({2, 4, 8, ns} & set(range(1, ns + 1))))
        _table(rows, list(rows[0]), "Ablation: RMS projection error (mm) of held-out frames, pose rows x shape columns")
        results["ablation"] = rows
    if "sheet" not in args.skip:
        contact_sheet(args.out / "humanoid_contact_sheet.png", basis, gen, seqs)
        print(f"\nwrote {args.out / 'humanoid_contact_sheet.png'}")
    if "interpolation" not in args.skip:
        rows = interpolation_rows(basis, every_frame)
        _table(rows, list(rows[0]), "Interpolation (frames k -> k+2h, in-betweens) and extrapolation (k, k+h -> "
               "k+2h, k+3h) in the monotone mini-sequences of held-out motions of held-out identities (24 fps)")
        results["interpolation"] = rows
    if "registration" not in args.skip and args.scans > 0:
        print("\nRegistration of simulated scans of held-out identities in held-out motions")
        rows = registration_rows(basis, faces, seqs, args.scans)
        mean = _mean_row(rows)
        print("mean  " + "  ".join(f"{k}={v}" for k, v in mean.items()))
        results["registration"] = {"rows": rows, "mean": mean}
        if args.full is not None:
            print(f"\nThe same scans registered with the float64 fields of {args.full}")
            full = registration_rows(load_basis(args.full), faces, seqs, args.scans)
            diff = [abs(a["mean_mm"] - b["mean_mm"]) for a, b in zip(rows, full)]
            full_mean = _mean_row(full)
            print("mean  " + "  ".join(f"{k}={v}" for k, v in full_mean.items()))
            print(f"shipped ({basis.fields.dtype} on load, stored {basis.provenance.get('fields_dtype', '?')}) vs "
                  f"float64 fields: mean vertex error {mean['mean_mm']} vs {full_mean['mean_mm']} mm; largest "
                  f"per-scan difference {max(diff):.2f} mm")
            results["registration_full_precision"] = {"rows": full, "mean": full_mean,
                                                      "max_abs_diff_mean_mm": max(diff)}
    (args.out / "humanoid_accuracy.json").write_text(json.dumps(results, indent=2) + "\n")
    write_humanoid_results(results, variant_of(parser, args, ("basis", "card", "out", "full")), argv)
    if args.card:
        write_card_accuracy(args.basis, results)


def write_humanoid_results(results, variant, argv):
    """bench/results/humanoid_accuracy[--variant].json from the parts measured."""
    from bench.common import dict_table, write_results

    figures, tables = {}, []
    if "registration" in results:
        mean = results["registration"]["mean"]
        figures |= {"registration_error_mean_pct_height": mean["mean_%h"],
                    "registration_error_p95_pct_height": mean["p95_%h"],
                    "registration_error_mean_mm": mean["mean_mm"], "registration_error_p95_mm": mean["p95_mm"],
                    "registration_wall_s": mean["seconds"], "registration_poor_fits": mean.get("poor_fits", 0)}
        tables.append(dict_table("Registration of simulated scans of held-out body types in held-out motions",
                                 results["registration"]["rows"]))
    if "registration_full_precision" in results:
        full = results["registration_full_precision"]
        figures["float64_fields_max_abs_diff_mean_mm"] = full["max_abs_diff_mean_mm"]
        tables.append(dict_table("The same scans registered with float64 fields", full["rows"]))
    if "ablation" in results:
        figures["ablation_full_rms_mm"] = list(results["ablation"][-1].values())[-1]
        tables.append(dict_table("Ablation: RMS projection error (mm) of held-out frames, pose rows x shape columns",
                                 results["ablation"]))
    if "interpolation" in results:
        figures |= interpolation_figures(results["interpolation"])
        tables.append(dict_table("Interpolation / extrapolation in monotone mini-sequences of held-out motions",
                                 results["interpolation"]))
    write_results("humanoid_accuracy", figures, tables, variant=variant, argv=argv)


def write_card_accuracy(name, results, measured_by="python -m bench.humanoid_accuracy --card"):
    """Record the measured accuracy in a basis' JSON card (the .json beside the basis' .npz)."""
    from bareesa.basis_io import resolve_basis_path

    path = resolve_basis_path(name).with_suffix(".json")
    card = json.loads(path.read_text())
    # parts skipped in this run (--skip) keep their last measurement
    summary = dict(card.get("accuracy", {}))
    summary |= {"measured_by": measured_by, "date": time.strftime("%Y-%m-%d"),
               "data": "simulated scans / frames of held-out identities in held-out motions"}
    if "registration" in results:
        summary["registration_mean"] = results["registration"]["mean"]
        summary["registration_rows"] = [{k: r[k] for k in ("scan", "mean_mm", "p95_mm", "mean_%h", "chamfer_mm")}
                                        for r in results["registration"]["rows"]]
    if "registration_full_precision" in results:
        summary["float64_fields_max_abs_diff_mean_mm"] = results["registration_full_precision"][
            "max_abs_diff_mean_mm"]
    if "interpolation" in results:
        summary["interpolation"] = results["interpolation"]
    if "ablation" in results:
        summary["ablation_rms_projection_mm"] = results["ablation"]
    card["accuracy"] = summary
    path.write_text(json.dumps(card, indent=2) + "\n")
    print(f"wrote the accuracy into {path}")


if __name__ == "__main__":
    main()
