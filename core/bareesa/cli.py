"""The ``bareesa`` command line.

Each verb is a small function: parse, load, call the core (``bareesa.workflows`` for
everything the Blender add-on does too), write, print. Errors the
user can act on (``BareEsaError``) print one line on stderr and exit with 2;
anything else is a bug and keeps its traceback.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .basis_building import build_basis, fits_metric
from .basis_io import DEFAULT_BASIS, load_basis, save_basis
from .cli_inputs import load_input, load_path, parse_components, parse_sequences, registration_overrides
from .errors import BareEsaError, InputError, ShootingFailed
from .evaluation import mesh_metrics, vertex_error
from .geodesics import decode_path
from .h2_metric import H2Weights, path_energy
from .landmarks import read_scan_landmarks, read_template_landmarks
from .masks import read_face_weights
from .mesh import load_mesh, save_mesh, validate_mesh
from .progress import tqdm_callback
from .registration import prepare_basis
from .scan_simulator import add_simulate_scan_arguments, apply_similarity, simulate_scan, simulate_scan_cli
from .statistics import fit_training_distribution, pose_prototypes, sample_velocities
from .workflows import (KnownCode, Options, Scan, check_device, code_of, extrapolate, geodesic_between, path_between,
                        random_bodies, stored_distribution, transfer)


def _options(args, **kwargs):
    """The workflows.Options of a verb: its --device (checked), its registration settings (--config, --set;
    --no-detail turns the detail layer of raw scans off) and the given fields."""
    settings = registration_overrides(args)
    if getattr(args, "no_detail", False):
        settings = {**settings, "detail.enabled": False}
    return Options(device=check_device(args.device), registration=settings, **kwargs)


def _add_device(p):
    p.add_argument("--device", default="cpu", help="where the solver runs: cpu (default), cuda or cuda:N")
    _add_settings(p)


def _add_settings(p):
    p.add_argument("--config", type=Path, metavar="FILE",
                   help="registration settings: a JSON object of RegistrationConfig settings, e.g. "
                        '{"retry": false, "poses": {"finalists": 3}} (bareesa register --show-config lists them)')
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                   help="one registration setting, after --config's (repeatable): e.g. --set poses.finalists=3 "
                        "--set retry=false")


def _print(result, as_json, title=None):
    if as_json:
        print(json.dumps(result, indent=2, sort_keys=True))
        return
    if title:
        print(title)
    width = max(len(k) for k in result)
    for key, value in result.items():
        text = f"{value:.6g}" if isinstance(value, float) else str(value)
        print(f"  {key:<{width}}  {text}")


def cmd_metrics(args):
    """Chamfer, Hausdorff and varifold between two meshes of any topology."""
    (va, fa), (vb, fb) = load_mesh(args.a), load_mesh(args.b)
    validate_mesh(va, fa, name=str(args.a))
    validate_mesh(vb, fb, name=str(args.b))
    if args.sigma is not None and not args.sigma > 0:
        raise InputError(f"--sigma must be positive, got {args.sigma}")
    result = mesh_metrics(va, fa, vb, fb, sigma=args.sigma, kernel=args.kernel)
    _print({k: float(v) for k, v in result.items()}, args.json, f"{args.a}  vs  {args.b}")


def cmd_path_energy(args):
    """H2 path energy of the path through the given same-topology meshes."""
    if len(args.frames) < 2:
        raise InputError("path-energy needs at least two meshes")
    weights = H2Weights.parse(args.metric)
    path, faces = load_path(args.frames)
    steps = path_energy(torch.from_numpy(path), torch.from_numpy(faces), weights, per_step=True)
    result = {"energy": float(steps.sum()), "steps": [float(s) for s in steps],
              "frames": len(args.frames), "metric": list(weights.as_tuple())}
    if args.json:
        _print(result, True)
    else:
        _print({"energy": result["energy"], "frames": result["frames"],
                "metric": ",".join(f"{w:g}" for w in weights.as_tuple())}, False, "H2 path energy")


def cmd_build_basis(args):
    """PCA basis from registered 4D sequences (differences of consecutive frames per group)."""
    template, faces = load_mesh(args.template)
    validate_mesh(template, faces, name=str(args.template))
    groups = parse_sequences(args.sequence)
    components = parse_components(args.components, groups)
    sequences = {}
    for group, seqs in groups.items():
        sequences[group] = []
        for files in seqs:
            frames = []
            for p in files:
                v, f = load_mesh(p)
                if v.shape != template.shape or not np.array_equal(f, faces):
                    raise InputError(f"{p} is not in the template's topology ({v.shape[0]} vertices, "
                                     f"template {template.shape[0]}): frames must be registered meshes")
                frames.append(v)
            sequences[group].append(np.stack(frames))
    provenance = {"template": str(args.template),
                  "sequences": {g: [[str(p) for p in files] for files in s] for g, s in groups.items()}}
    landmarks = read_template_landmarks(args.landmarks, len(template)) if args.landmarks else None
    metric = args.metric or ("fit" if fits_metric(sequences) else "body")
    callback, close = tqdm_callback("build basis")
    try:
        basis = build_basis(template, faces, sequences, components, weights=metric,
                            name=args.name or args.output.stem, units=args.units, provenance=provenance,
                            elastic=tuple(args.elastic or ()), landmarks=landmarks, callback=callback)
    finally:
        close()
    if not args.no_distribution:

        basis.extras.update(fit_training_distribution(basis, [f for s in sequences.values() for f in s]))
    if "pose" in sequences:  # starting poses tried by registration (core.registration, pose candidates)

        basis.extras["pose_prototypes"] = pose_prototypes(basis, np.concatenate(sequences["pose"]))
    save_basis(args.output, prepare_basis(basis))  # (with the constants every registration would compute)
    rows = {g: f"{b - a} fields, explained variance {basis.provenance['groups'][g]['explained_variance']:.4f}"
            for g, (a, b) in basis.groups.items()}
    fit = basis.provenance.get("metric_fit")
    rows["metric"] = ",".join(f"{w:.4g}" for w in basis.weights.as_tuple()) + (
        "" if fit is None else f" ({fit['chosen']}; held-out frame error " + ", ".join(
            f"{k} {v:.4g}" for k, v in fit["held_out_frame_error"].items()) + ")")
    _print(rows, False, f"wrote {args.output} ({basis.n_fields} fields)")


def _basis_and_pair(args, min_steps=None):
    """The verbs on two meshes A, B: check --steps, load the basis and both inputs (raw scans with their
    --landmarks-a/-b, --ignore-a/-b) -> (basis, a, b)."""
    if min_steps is not None and args.steps < min_steps:
        raise InputError(f"--steps must be at least {min_steps}, got {args.steps}")
    basis = load_basis(args.basis)
    return basis, *(load_input(basis, getattr(args, end), getattr(args, f"landmarks_{end}"),
                                getattr(args, f"ignore_{end}"), (f"--landmarks-{end}", f"--ignore-{end}"))
                    for end in ("a", "b"))


def cmd_distance(args):
    """Geodesic distance between two meshes in the latent space of a basis."""
    start = time.perf_counter()
    options = _options(args, steps=10)
    basis, a, b = _basis_and_pair(args)
    found = geodesic_between(basis, a, b, options)
    _print({"distance": found.distance, "seconds": time.perf_counter() - start}, args.json)


def _detail_report(ends, detail):
    """RMS off-basis detail of the two inputs (what the basis misses; only when both are in template
    topology) and whether the frames keep it: ends (workflows.Code, Code), detail (T, N, 3) or None."""
    details = [end.detail for end in ends]
    if any(d is None for d in details):
        return {}
    rms = float(np.sqrt(np.mean([np.sum(d ** 2, axis=1).mean() for d in details])))
    return {"off_basis_rms": rms, "detail_kept": detail is not None}


def cmd_interpolate(args):
    """Evenly paced geodesic in-betweens of two meshes, written as T meshes and their codes."""
    start = time.perf_counter()
    options = _options(args)
    basis, a, b = _basis_and_pair(args, min_steps=2)
    found = path_between(basis, a, b, args.steps, options, anchor=not args.no_anchor,
                         keep_detail=not args.no_detail)
    seconds = time.perf_counter() - start
    _write_frames(args.output, basis, found.frames, detail=found.detail)
    result = {"distance": found.distance, "seconds": seconds, "frames": args.steps, "output": str(args.output),
              **_detail_report(found.ends, found.detail)}
    _print(result, args.json, "geodesic interpolation")


def _write_frames(output, basis, codes, prefix="frame", detail=None):
    """Frames F(codes) (+ detail (T, N, 3) if given) as PLY meshes, and codes.npy."""
    t, _, h = basis.tensors()
    output.mkdir(parents=True, exist_ok=True)
    width = len(str(len(codes) - 1))
    frames = decode_path(t, h, codes)
    if detail is not None:
        frames = frames + detail
    for k, v in enumerate(frames):
        save_mesh(output / f"{prefix}_{k:0{width}d}.ply", v, basis.faces)
    np.save(output / "codes.npy", np.asarray(codes))


def cmd_extrapolate(args):
    """Continue the motion A -> B along the latent geodesic by T frames."""
    start = time.perf_counter()
    options = _options(args)
    basis, a, b = _basis_and_pair(args, min_steps=1)
    try:
        motion = extrapolate(basis, a, b, args.steps, options, anchor=not args.no_anchor,
                             keep_detail=not args.no_detail)
    except ShootingFailed as err:
        reached = err.reached
        if reached is None or len(reached.path) <= 2:
            raise
        _write_frames(args.output, basis, reached.path, detail=reached.detail)  # what was reached is kept
        raise ShootingFailed(f"{err} (the inputs and the {len(reached.path) - 2} frames before it are written to "
                             f"{args.output})", frames=err.frames) from None
    _write_frames(args.output, basis, motion.path, detail=motion.detail)
    # where a step did not converge, shooting refined time (shooting.ShootingReport): say where
    refined = {"shooting": motion.shooting.to_json()} if args.json else {
        "steps per frame": ",".join(str(k) for k in motion.shooting.substeps)}
    if motion.shooting.speed_relaxed and not args.json:
        refined["speed varied at frames"] = ",".join(str(k) for k in motion.shooting.speed_relaxed) + \
            " (the body passes a creased, almost flat joint there; kept at the finest step)"
    if motion.same_frame is not None:  # two scans: was the second registered in the first's frame?
        refined["same_frame" if args.json else "second scan in the first's frame"] = (
            motion.same_frame if args.json else "yes" if motion.same_frame else
            "no (fitted there it was far from the scan: registered apart)")
    if motion.shooting.frozen and not args.json:
        refined["continued at frames"] = ",".join(str(k) for k in motion.shooting.frozen) + \
            " (no geodesic step converged there: finished in the metric of its last point)"
    _print({"frames": len(motion.path), "seconds": time.perf_counter() - start, "output": str(args.output),
            **refined, **_detail_report(motion.ends, motion.detail)}, args.json,
           "geodesic extrapolation (frames 0 and 1 are the inputs)")


def cmd_transfer(args):
    """Put the motion of the given frames on another identity (swap the identity group)."""
    options = _options(args)
    basis = load_basis(args.basis)
    frames = [load_input(basis, p) for p in args.frames]
    moved = transfer(basis, frames, load_input(basis, args.identity), args.group, options)
    detail = None if args.no_detail else moved.detail
    _write_frames(args.output, basis, moved.motion, detail=detail)
    _print({"frames": len(moved.motion), "output": str(args.output), "identity_detail_kept": detail is not None},
           args.json, "motion transfer")


def cmd_sample(args):
    """Random shapes: Gaussian mixture on initial velocities at the template, then shoot."""
    if args.n < 1:
        raise InputError(f"-n must be at least 1, got {args.n}")
    options = _options(args)
    basis = load_basis(args.basis)
    fit = [load_input(basis, p) for p in args.fit] if args.fit else None
    if fit is None and not stored_distribution(basis):
        raise InputError(f"basis '{basis.name}' carries no fitted distribution: give --fit FILES")
    bodies = random_bodies(basis, args.n, args.seed, options, fit=fit, components=args.components)
    _write_frames(args.output, basis, bodies.codes, prefix="sample")
    # draws that could not be shot or creased a joint flat were replaced by further draws (workflows.sample_bodies)
    _print({"samples": args.n, "seed": args.seed, "replaced": bodies.replaced, "output": str(args.output)},
           args.json, "random shapes")


def cmd_register(args):
    """Latent code of a raw scan; writes the registered mesh (template topology, scan's frame)."""
    options = _options(args, kernel=args.kernel)
    basis = load_basis(args.basis)
    config = options.registration_config(basis)  # (unknown or bad settings refused before the scan is read)
    if args.show_config:
        print(config.describe())
        return
    if args.output is None:
        raise InputError("register: -o/--output is required (the registered mesh to write)")
    verts, faces = load_mesh(args.scan)
    validate_mesh(verts, faces, name=str(args.scan))
    landmarks = read_scan_landmarks(args.landmarks, basis) if args.landmarks else None
    weights = read_face_weights(args.ignore, faces, len(verts)) if args.ignore else None
    callback, close = tqdm_callback("register", disable=args.json or None)
    try:
        res = code_of(basis, Scan(verts, faces, face_weights=weights, landmarks=landmarks), options,
                      callback=callback).registration
    finally:
        close()
    output = Path(args.output)
    save_mesh(output, res.output_vertices, basis.faces)
    np.save(output.with_suffix(".code.npy"), res.code)
    out = res.to_json()
    if res.detail is not None:  # the basis fit beside the detailed mesh, and the layer itself (template frame)
        basis_fit = output.with_name(output.stem + ".basis" + output.suffix)
        save_mesh(basis_fit, res.vertices, basis.faces)
        np.save(output.with_suffix(".detail.npy"), res.detail)
        out["basis_fit_output"] = str(basis_fit)
    if args.json:
        _print(out, True)
    else:
        report = res.detail_report or {}
        shown = {"output": str(args.output), "varifold": out["varifold"], "basis fit chamfer": out["chamfer"],
                 "basis fit residual": out["residual"]}
        if res.detail is not None:
            shown.update({"detailed chamfer": report["chamfer"], "detailed residual": report["residual"],
                          "scan noise (estimated)": report.get("noise"), "basis fit output": out["basis_fit_output"]})
        elif report.get("skipped") and report["skipped"] != "turned off":
            shown["detail"] = f"none ({report['skipped']})"
        _print({**shown, "seconds": out["seconds"]}, False, f"registered {args.scan} onto basis '{basis.name}'")
    if res.retried_alignments and not args.json:
        print(f"the first fit was poor: registered again from {res.retried_alignments} other alignments, "
              "kept the better")
    if res.poor_fit:
        print(f"bareesa register: warning: poor fit: the scan is {res.residual:.3g} of the basis' size from the "
              f"registered surface, above the {basis.fit_check['poor_fit_above']:.3g} the basis reaches on its own "
              "held-out scans: is it a shape of this basis? (check the selection, mask floors, add landmarks)",
              file=sys.stderr)


def cmd_register_batch(args):
    """Register many scans (or the frames of one 4D capture) on a Dask cluster; resumable."""
    from .batch import MISSING_DASK, register_batch

    try:
        import distributed  # noqa: F401
    except ImportError:
        raise InputError(MISSING_DASK) from None
    scans = list(args.scans)
    if args.list is not None:
        if not args.list.is_file():
            raise InputError(f"--list file {args.list} does not exist")
        lines = [ln.strip() for ln in args.list.read_text().splitlines()]
        # relative paths in the list are relative to the list file's folder
        scans += [p if p.is_absolute() else args.list.parent / p
                  for p in (Path(ln) for ln in lines if ln and not ln.startswith("#"))]
    if args.chunk is not None and not args.sequence:
        raise InputError("--chunk only applies with --sequence")
    # a remote cluster's workers may have GPUs this machine lacks: there the workers' torch decides
    device = args.device if args.scheduler else check_device(args.device)
    report = register_batch(args.basis, scans, args.output, workers=args.workers,
                            threads_per_worker=args.threads_per_worker, scheduler=args.scheduler,
                            options={**({} if device == "cpu" else {"device": device}),
                                     **_batch_settings(args)},
                            sequence=args.sequence, chunk=args.chunk, progress=not args.json,
                            log=lambda text: print(text, file=sys.stderr))
    if args.json:
        _print({"counts": report.counts, "seams": report.seams, "seconds": report.seconds,
                "output": str(report.output), "rows": report.rows}, True)
        return
    for row in report.rows:
        what = (f"varifold {row['varifold']:.3g}, chamfer {row['chamfer']:.3g}" + (", poor fit" * bool(row["poor_fit"]))
                if row["status"] == "ok" else row["error"] or "")
        print(f"  {row['name']:<24} {row['status']:<8} {what}")
    for seam in report.seams:
        if seam["flagged"]:
            print(f"  seam {seam['before']} -> {seam['after']}: jump {seam['jump']:.3g}, "
                  f"{seam['ratio']:.1f} x the median motion")
    _print({**report.counts, "seconds": report.seconds, "summary": str(report.output / "summary.csv")}, False,
           f"register-batch onto basis '{args.basis}'")


def _batch_settings(args):
    """register-batch's --config / --set as ``register`` keywords, checked against the basis first."""
    settings = registration_overrides(args)
    if settings:
        Options(registration=settings).registration_config(load_basis(args.basis))
    return settings


def cmd_simulate_scan(args):
    """A realistic unregistered scan of a mesh (remesh, noise, holes, crop, rigid motion, clutter)."""
    info = simulate_scan_cli(args)
    _print({"output": info["output"], "vertices": info["n_vertices"], "faces": info["n_faces"],
            "scale": float(info["scale"])}, args.json, "simulated scan")


def cmd_demo(args):
    """The solver end to end on a bundled basis: two simulated scans -> registration -> geodesic."""
    if args.steps < 2:
        raise InputError(f"--steps must be at least 2, got {args.steps}")
    start = time.perf_counter()
    basis = load_basis(args.basis)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    print(f"BaRe-ESA {__version__} demo on basis '{basis.name}': {basis.template.shape[0]} vertices, "
          f"{basis.n_fields} fields ({', '.join(f'{g} {b - a}' for g, (a, b) in basis.groups.items())})")
    dist = stored_distribution(basis)
    rng = np.random.default_rng(args.seed)
    truths = (sample_velocities(dist, basis.groups, 2, args.seed) if dist
              else rng.normal(scale=0.5, size=(2, basis.n_fields)))
    rows, codes = [], []
    for name, truth in zip("AB", truths):
        true_v = basis.template + np.tensordot(truth, basis.fields, axes=1)
        scan_v, scan_f, info = simulate_scan(true_v, basis.faces, seed=args.seed + ord(name))
        save_mesh(out / f"scan_{name}.ply", scan_v, scan_f)
        callback, close = tqdm_callback(f"register scan {name}")
        try:
            res = code_of(basis, Scan(scan_v, scan_f), callback=callback).registration
        finally:
            close()
        save_mesh(out / f"scan_{name}_registered.ply", res.vertices, basis.faces)
        err = vertex_error(res.vertices, apply_similarity(info, true_v))["mean"] / info["scale"]
        rows.append((f"scan_{name}.ply", f"{len(scan_v)} vertices, {len(scan_f)} faces", res.seconds,
                     f"vertex error {err:.4g} {basis.units} (mean, against the true correspondence)"))
        codes.append(res.code)
    t0 = time.perf_counter()
    found = path_between(basis, KnownCode(codes[0]), KnownCode(codes[1]), args.steps, Options())
    _write_frames(out / "geodesic", basis, found.frames)
    rows.append(("geodesic/", f"{args.steps} evenly paced frames A -> B", time.perf_counter() - t0,
                 "in the template frame"))
    print(f"\nwrote to {out}/ ({time.perf_counter() - start:.0f} s in all)")
    for name, what, seconds, note in rows:
        print(f"  {name:<24} {what:<36} {seconds:6.1f} s  {note}")
    print("\nThe same in Blender, with keyframes, motion transfer and random bodies: bareesa-demo --out DIR "
          "(needs the bpy module: pip install -e \".[blender]\")")


IGNORE_HELP = ("what registration should not fit (a floor, a wall): a .npy or text file of one weight per scan "
               "vertex, 1 = ignore, 0 = keep (as the add-on's Ignore Group; a face weighs 1 - its vertices' mean)")


def _pair_parser(sub, name, func, text, frames=None):
    """A verb on two meshes A, B and a basis; frames = (help of --steps, --no-anchor, --no-detail) for the
    verbs that write frames to -o."""
    p = sub.add_parser(name, help=text)
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--basis", default=DEFAULT_BASIS, help=f"bundled basis name or .npz path (default: {DEFAULT_BASIS})")
    for end in ("a", "b"):
        p.add_argument(f"--landmarks-{end}", type=Path, metavar="FILE",
                       help=f"where the basis' named landmarks are on {end.upper()}, a raw scan (as register --landmarks)")
        p.add_argument(f"--ignore-{end}", type=Path, metavar="MASK",
                       help=f"what to ignore of {end.upper()}, a raw scan (as register --ignore)")
    if frames is not None:
        steps, anchor, detail = frames
        p.add_argument("--steps", type=int, default=10, help=steps)
        p.add_argument("--no-anchor", action="store_true", help=anchor)
        p.add_argument("--no-detail", action="store_true", help=detail)
        p.add_argument("-o", "--output", type=Path, required=True)
    _add_device(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=func)


def build_parser():
    parser = argparse.ArgumentParser(prog="bareesa", description="Basis-restricted elastic shape analysis "
                                     "of surface meshes.")
    parser.add_argument("--version", action="version", version=f"bareesa {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("metrics", help="Chamfer, Hausdorff and varifold distance between two meshes")
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--sigma", type=float, default=None,
                   help="varifold kernel width in the meshes' units (default: see evaluation.default_sigma)")
    p.add_argument("--kernel", choices=("binet", "linear", "constant"), default="binet")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_metrics)

    p = sub.add_parser("path-energy", help="H2 energy of a path through same-topology meshes")
    p.add_argument("frames", nargs="+", type=Path)
    p.add_argument("--metric", default="body",
                   help="a0,a1,b1,c1,d1,a2 or a preset: body (1,1000,100,1,1,1), face (1,10,10,10,1,1)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_path_energy)

    p = sub.add_parser("register", help="register a raw scan onto a basis' template")
    p.add_argument("scan", type=Path)
    p.add_argument("--basis", default=DEFAULT_BASIS, help=f"bundled basis name or .npz path (default: {DEFAULT_BASIS})")
    p.add_argument("-o", "--output", type=Path, help="registered mesh (template topology; required unless "
                                                       "--show-config)")
    p.add_argument("--landmarks", type=Path,
                   help="where the basis' named landmarks are on the scan: JSON {name: [x, y, z]} or CSV lines "
                        "'name, x, y, z[, weight]' (a template vertex index may stand for a name)")
    p.add_argument("--ignore", type=Path, metavar="MASK", help=IGNORE_HELP)
    p.add_argument("--kernel", default="auto", choices=("auto", "binet", "linear"),
                   help="varifold kernel: auto (default) is binet, and linear at the finest level of a noisy scan "
                        "(its faces wound consistently first); binet or linear on every level")
    _add_device(p)
    p.add_argument("--show-config", action="store_true",
                   help="print the registration settings this command would use (basis card, --config, --set) and "
                        "exit")
    p.add_argument("--no-detail", action="store_true",
                   help="the pure basis fit: no detail layer (by default the registered mesh also takes the scan's own "
                        "detail, and the basis fit is written beside it as OUTPUT.basis.ply)")
    p.add_argument("--json", action="store_true", help="print JSON (code, varifold, chamfer, seconds, levels, detail)")
    p.set_defaults(func=cmd_register)

    p = sub.add_parser("register-batch", help="register many scans (or a 4D sequence) on a Dask cluster, resumably")
    p.add_argument("scans", nargs="*", type=Path, metavar="SCAN",
                   help="scan files; a scan's mask and landmarks are files next to it: SCAN.ignore.npy or .txt, "
                        "SCAN.landmarks.json or .csv (as register's --ignore and --landmarks)")
    p.add_argument("--list", type=Path, help="a file of scan paths, one a line (relative to the file's folder)")
    p.add_argument("--basis", default=DEFAULT_BASIS, help=f"bundled basis name or .npz path (default: {DEFAULT_BASIS})")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="folder of the registered meshes, JSON records and summary.csv/.json")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the local cluster (default 2)")
    p.add_argument("--threads-per-worker", type=int, default=1, help="torch threads per worker (default 1)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="use a running Dask scheduler (tcp://HOST:8786)")
    p.add_argument("--sequence", action="store_true",
                   help="the scans are the frames of one 4D capture, in order: warm start each from the previous")
    p.add_argument("--chunk", type=int, metavar="K", help="with --sequence: frames per chunk run in parallel")
    p.add_argument("--device", default="cpu",
                   help="where the workers solve: cpu (default), cuda or cuda:N (then one worker per GPU)")
    _add_settings(p)
    p.add_argument("--json", action="store_true", help="print JSON (counts, seams, a row per scan)")
    p.set_defaults(func=cmd_register_batch)

    p = sub.add_parser("build-basis", help="PCA basis from registered 4D sequences")
    p.add_argument("template", type=Path)
    p.add_argument("--sequence", action="append", required=True, metavar="GROUP:F1,F2,...",
                   help="frames of one registered sequence, in order (repeatable, several per group), or "
                   "GROUP:DIR with DIR a register-batch output folder (its registered meshes, in order)")
    p.add_argument("--components", action="append", metavar="GROUP=K", help="fields kept per group (default 10)")
    p.add_argument("--metric", default=None,
                   help="metric of motion paths: fit (default when a group has two or more sequences: the weights "
                        "that make the training motions closest to geodesics, if they predict held-out frames "
                        "better than the presets), body (default otherwise), face or six numbers a0,a1,b1,c1,d1,a2")
    p.add_argument("--elastic", action="append", metavar="GROUP",
                   help="build GROUP from elastic H2 geodesics between consecutive frames (paper's shape basis)")
    p.add_argument("--no-distribution", action="store_true",
                   help="do not fit the Gaussian mixture on the training frames used by 'sample'")
    p.add_argument("--landmarks", type=Path, metavar="FILE",
                   help="named landmarks of the template: JSON {name: vertex index} or CSV lines 'name, vertex'")
    p.add_argument("--name", default=None)
    p.add_argument("--units", default="m")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.set_defaults(func=cmd_build_basis)

    _pair_parser(sub, "distance", cmd_distance, "geodesic distance between two meshes")
    _pair_parser(sub, "interpolate", cmd_interpolate, "geodesic in-betweens of two meshes", frames=(
        "number of frames written, ends included",
        "write the geodesic as solved (by default the body's unmoving part is kept where the straight line "
        "between the ends puts it: the metric's L2 term lets it sink)",
        "write F(code) only: by default, when both inputs are in template topology, what their codes miss "
        "(off-basis detail) is carried along so the frames pass through the inputs exactly"))
    _pair_parser(sub, "extrapolate", cmd_extrapolate, "continue a motion A -> B along the geodesic", frames=(
        "number of new frames",
        "write the geodesic as shot (by default the body's unmoving part is kept where the straight latent "
        "line puts it)",
        "write F(code) only: by default, when both inputs are in template topology, what their codes miss "
        "(off-basis detail) is continued linearly, as the latent line is"))

    p = sub.add_parser("transfer", help="transfer the motion of FRAMES onto another identity")
    p.add_argument("frames", nargs="+", type=Path)
    p.add_argument("--identity", type=Path, required=True, help="a mesh (scan or registered) of the identity")
    p.add_argument("--group", default="shape", help="the identity group of the basis (default: shape)")
    p.add_argument("--basis", default=DEFAULT_BASIS, help=f"bundled basis name or .npz path (default: {DEFAULT_BASIS})")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--no-detail", action="store_true",
                   help="frames of the basis alone (by default the identity's off-basis detail, or the detail layer "
                        "of its scan, is on every frame)")
    _add_device(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_transfer)

    p = sub.add_parser("sample", help="random shapes from the basis' distribution (or one fitted to FILES)")
    p.add_argument("--basis", default=DEFAULT_BASIS, help=f"bundled basis name or .npz path (default: {DEFAULT_BASIS})")
    p.add_argument("-n", type=int, default=6, help="number of shapes")
    p.add_argument("--fit", nargs="+", type=Path, help="meshes to fit the distribution to")
    p.add_argument("--components", type=int, default=3, help="mixture components per group with --fit")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", type=Path, required=True)
    _add_device(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_sample)


    p = sub.add_parser("simulate-scan", help="turn a mesh into a realistic unregistered scan")
    add_simulate_scan_arguments(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_simulate_scan)

    p = sub.add_parser("demo", help="simulate two scans, register them and interpolate (bundled basis)")
    p.add_argument("-o", "--output", default="bareesa-demo", help="folder for the meshes it writes")
    p.add_argument("--basis", default=DEFAULT_BASIS, help=f"bundled basis name or .npz path (default: {DEFAULT_BASIS})")
    p.add_argument("--steps", type=int, default=8, help="frames of the geodesic (default 8)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except BareEsaError as err:
        print(f"bareesa {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bareesa {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
