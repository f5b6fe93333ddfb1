"""Rebuild the bundled bases from nothing: ``python -m bases.build [human] [deformables] [humanoid] [-o DIR]``.

Deterministic (fixed seeds, single-threaded torch); needs the ``bpy`` module and,
for ``human``, the Anny body model (``pip install -e ".[bases]"``; Anny's first
model build takes minutes and writes its cache to ``ANNY_CACHE_DIR``). Each written
basis then gets its derived constants (``store_derived``); ``--derived`` recomputes
only those, in the bases already in the output folder.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

BASES_DIR = Path(__file__).resolve().parents[1]
#: Bundled fields are stored in float16 (bench/humanoid_accuracy.py compares against float64).
FIELDS_DTYPE = np.float16
BUILDERS = ("human", "deformables", "humanoid")
#: What ``python -m bases.build`` rebuilds: the bundled bases (``humanoid``, the retired mannequin, on request).
DEFAULT = ("human", "deformables")


def _log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def store_derived(path):
    """Add to a saved basis file the per-basis constants a registration would compute in every process
    (``bareesa.registration.prepare_basis``), computed afresh from its fields as stored."""
    from bareesa.basis_io import add_extras, load_basis, update_card
    from bareesa.registration import PREPARED_EXTRAS, prepare_basis

    basis = load_basis(path)
    for key in PREPARED_EXTRAS:
        basis.extras.pop(key, None)
    prepare_basis(basis)
    derived = {k: basis.extras[k] for k in PREPARED_EXTRAS if k in basis.extras}
    if derived:  # (a basis without shape weights or pose prototypes has none)
        add_extras(path, **derived)
        names = ", ".join(k for k in derived if not k.endswith(("_weights", "_codes")))
        update_card(path, provenance=basis.provenance | {"derived": f"{names}: {DERIVED_NOTE}"})
    return list(derived)


def refit_motion_metric(path):
    """Refit the motion metric of a built human basis (``human.fit_motion_metric``) and store it with its
    template metric; the fields and everything else stay as they are."""
    import torch

    from bareesa.basis_io import add_extras, load_basis, update_card

    from bases.build import human

    torch.set_num_threads(1)
    start = time.perf_counter()
    sequences = human.motion_sequences(_log)
    _log(f"baked {len(sequences)} training motions ({time.perf_counter() - start:.0f} s)")
    basis = load_basis(path)
    fit = human.fit_motion_metric(basis, sequences, _log)
    basis.extras.pop("template_metric", None)
    add_extras(path, template_metric=basis.template_metric(), template_metric_weights=np.array(fit.weights.as_tuple()))
    update_card(path, metric=list(fit.weights.as_tuple()),
                provenance=basis.provenance | {"metrics": human.METRICS_NOTE})
    _log(f"{path}: motion metric {fit.chosen} ({time.perf_counter() - start:.0f} s)")


DERIVED_NOTE = ("computed from the stored fields by bareesa.registration.prepare_basis (python -m bases.build "
                "--derived): G-bar(0) in the shape weights, the decoded pose prototypes' surface moments")


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m bases.build", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="NAME", help="bases to build: human, deformables, humanoid (default: human and deformables)")
    parser.add_argument("-o", "--output", type=Path, default=BASES_DIR, help="folder to write <name>.npz/.json")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (default 1: deterministic and fastest on a shared machine)")
    parser.add_argument("--full-precision", action="store_true", help="store fields in float64")
    parser.add_argument("--keep-full", type=Path, metavar="DIR",
                        help="also write float64 copies to DIR (to compare accuracy with the shipped precision)")
    parser.add_argument("--derived", action="store_true",
                        help="only recompute the derived constants of bases already built (no bpy, no Anny)")
    parser.add_argument("--motion-metric", action="store_true",
                        help="human only: refit the motion metric of the basis already built to its training motions "
                             "(fields unchanged; needs Anny)")
    args = parser.parse_args(argv)
    unknown = set(args.names) - set(BUILDERS)
    if unknown:
        parser.error(f"unknown basis {', '.join(sorted(unknown))}; choose from {', '.join(BUILDERS)}")

    if args.motion_metric:
        path = args.output / "human.npz"
        if set(args.names) - {"human"} or not path.exists():
            sys.exit(f"error: --motion-metric refits {path}, the human basis; build it first")
        refit_motion_metric(path)
        return

    if args.derived:
        for name in dict.fromkeys(args.names or DEFAULT):
            path = args.output / f"{name}.npz"
            if not path.exists():
                sys.exit(f"error: no basis {path} to add derived constants to; build it first")
            start = time.perf_counter()
            stored = store_derived(path)
            _log(f"{path}: {', '.join(stored) or 'no derived constants'} ({time.perf_counter() - start:.1f} s)")
        return

    import torch

    torch.set_num_threads(args.threads)
    try:
        import bpy  # noqa: F401
    except ImportError:
        sys.exit("building the bases needs the bpy module: pip install -e '.[bases]' (Python 3.11)")
    from bareesa.basis_io import save_basis

    import importlib

    builders = {n: importlib.import_module(f"bases.build.{n}").build for n in dict.fromkeys(args.names or DEFAULT)}
    dtype = None if args.full_precision else FIELDS_DTYPE
    total = time.perf_counter()
    for name in builders:
        start = time.perf_counter()
        _log(f"building {name}")
        basis, _ = builders[name](log=_log)
        basis.provenance["fields_dtype"] = np.dtype(dtype or np.float64).name
        path = args.output / f"{name}.npz"
        save_basis(path, basis, fields_dtype=dtype)
        store_derived(path)
        if args.keep_full is not None and dtype is not None:
            args.keep_full.mkdir(parents=True, exist_ok=True)
            save_basis(args.keep_full / f"{name}.npz", basis)
        _log(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB, {basis.n_fields} fields, "
             f"{time.perf_counter() - start:.0f} s)")
        _log(json.dumps({g: list(r) for g, r in basis.groups.items()}))
    _log(f"all done in {time.perf_counter() - total:.0f} s")


if __name__ == "__main__":
    main()
