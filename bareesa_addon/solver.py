"""Access to the solver package ``bareesa`` from the add-on (no bpy here).

Inside the installable extension the solver is vendored as ``<extension>/bareesa``
(relative imports, bundled bases in ``<extension>/bareesa/bases``); otherwise the
installed ``bareesa`` package is used. The solver is imported lazily so that the
add-on registers (and can offer to install dependencies) even when torch is missing.
"""

import dataclasses
import importlib
from pathlib import Path

SCHEDULE_PRESETS = (
    ("PAPER", "Paper", "The basis' own multiscale schedule (the paper's, tuned to the basis)"),
    ("FAST", "Fast", "A shortened schedule: at most 2 time steps and 40 iterations per level"),
)
FAST_STEPS, FAST_ITER = 2, 40


class DependencyError(ImportError):
    """The solver's Python dependencies are missing (message tells the user what to do)."""


def module(name):
    """The solver submodule ``name`` (e.g. "latent"), vendored copy first."""
    package = __package__ or "bareesa_addon"
    try:
        return importlib.import_module(f"{package}.bareesa.{name}")
    except ModuleNotFoundError as err:
        if err.name not in (f"{package}.bareesa", f"{package}.bareesa.{name}"):
            raise DependencyError(f"the solver needs the Python module '{err.name}': open Preferences > "
                                  "Add-ons > BaRe-ESA and press 'Install dependencies'") from None
    try:
        return importlib.import_module(f"bareesa.{name}")
    except ModuleNotFoundError as err:
        if err.name in ("bareesa", f"bareesa.{name}"):
            raise DependencyError(f"the BaRe-ESA solver ({name}) is not installed with the add-on") from None
        raise DependencyError(f"the solver needs the Python module '{err.name}': open Preferences > "
                              "Add-ons > BaRe-ESA and press 'Install dependencies'") from None


_BASIS_CACHE = {}


def resolve_basis(reference, user_dir=None):
    """A bundled name, a name saved in ``user_dir`` or a path -> the string bareesa.basis_io.load_basis takes."""
    reference = (reference or "").strip()
    if not reference:
        raise module("errors").InputError("no basis chosen: set one in the Basis section (a bundled name "
                                          "such as 'human' or a path to an .npz file)")
    p = Path(reference)
    if p.suffix != ".npz" and p.parent == Path(".") and user_dir is not None:
        candidate = Path(user_dir) / f"{reference}.npz"
        if candidate.exists():
            return str(candidate)
    return reference


def card_summary(card):
    """One line saying what a basis is, from its card (dict): e.g. '6276 vertices, 140 fields (pose 100,
    shape 40), 21 landmarks'."""
    groups = ", ".join(f"{g} {b - a}" for g, (a, b) in card.get("groups", {}).items())
    text = f"{card.get('n_vertices', '?')} vertices, {card.get('n_fields', '?')} fields"
    text += f" ({groups})" if groups else ""
    n_marks = len(card.get("landmarks", {}))
    return text + (f", {n_marks} landmarks" if n_marks else "")


_CATALOGUE_CACHE = {}


def basis_catalogue(user_dir=None):
    """The bases a user can pick by name, bundled ones first then those saved in ``user_dir``:
    -> [(name, one-line summary)] (summaries from the .json cards beside the files; no basis is loaded).

    The panel asks on every redraw: the list is read again only when a folder changed (its mtime)."""
    import json

    folders = module("basis_io").basis_search_path() + ([Path(user_dir)] if user_dir else [])
    key = tuple((str(f), f.stat().st_mtime_ns if f.is_dir() else None) for f in folders)
    if key not in _CATALOGUE_CACHE:
        found = {}
        for folder in folders:
            for npz in sorted(Path(folder).glob("*.npz")):
                if npz.stem in found:
                    continue
                try:
                    summary = card_summary(json.loads(npz.with_suffix(".json").read_text()))
                except (OSError, ValueError):
                    summary = str(npz)
                found[npz.stem] = summary
        _CATALOGUE_CACHE.clear()
        _CATALOGUE_CACHE[key] = list(found.items())
    return _CATALOGUE_CACHE[key]


def load_basis(reference, user_dir=None):
    """Load (cached by file and modification time) a basis: -> (Basis, resolved path string)."""
    basis_io = module("basis_io")
    path = basis_io.resolve_basis_path(resolve_basis(reference, user_dir))
    key = (str(path.resolve()), path.stat().st_mtime_ns)
    if key not in _BASIS_CACHE:
        _BASIS_CACHE.clear()  # one basis at a time: bodies are large
        _BASIS_CACHE[key] = basis_io.load_basis(path)
    return _BASIS_CACHE[key], str(path.resolve())


def schedule(basis, preset):
    """The registration schedule for a preset name (see SCHEDULE_PRESETS): -> tuple of Level."""
    if preset == "PAPER":
        return basis.schedule
    if preset == "FAST":
        return tuple(dataclasses.replace(lv, steps=min(lv.steps, FAST_STEPS), max_iter=min(lv.max_iter, FAST_ITER))
                     for lv in basis.schedule)
    raise module("errors").InputError(f"unknown schedule preset {preset!r}")


def metric(basis, preset, custom=""):
    """H2 weights: "BASIS" -> None (the basis' own: its ``weights`` for paths, its ``shape_metric``
    for registration and random bodies), "BODY", "FACE" or "CUSTOM" (a0,a1,b1,c1,d1,a2 in ``custom``)."""
    h2 = module("h2_metric")
    if preset == "BASIS":
        return None
    if preset == "CUSTOM":
        return h2.H2Weights.parse(custom)
    return h2.H2Weights.parse(preset.lower())


def field_names(basis):
    """Shape-key name of every field, in field order: '<group>_<index:03d>'."""
    names = [None] * basis.n_fields
    for group, (start, stop) in basis.groups.items():
        for i in range(start, stop):
            names[i] = f"{group}_{i - start:03d}"
    return names
