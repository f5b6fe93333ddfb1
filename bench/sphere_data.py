"""The deformed-sphere 4D data of ../shared/data/deformed_sphere, and the basis built from it.

27 registered meshes (422 vertices, one topology): the template and bend_X, bend_Y,
twist_X at +-30 ... +-150 degrees. Each family is read as one sequence through the
template (ordered by angle); the +-60 frames are held out of the basis.
"""

import re

import numpy as np

from bench.common import shared_data
from bareesa.latent import Level
from bareesa.basis_building import build_basis
from bareesa.mesh import load_mesh

FAMILIES = ("bend_X", "bend_Y", "twist_X")
HELD_OUT = (-60, 60)
#: Registration schedule relative to the length of the shape (12.7 units).
SCHEDULE = (Level(0.1, 1e2, 2, 150), Level(0.04, 1e4, 3, 150), Level(0.015, 1e6, 4, 200))


def load_frames(script):
    """{(family, angle): verts (N, 3)} with ('template', 0) and the faces (F, 3)."""
    folder = shared_data(script) / "deformed_sphere"
    template, faces = load_mesh(folder / "template.ply")
    frames = {("template", 0): template}
    for path in sorted(folder.glob("*.ply")):
        m = re.fullmatch(r"(.+)_(-?\d+)", path.stem)
        if m:
            v, f = load_mesh(path)
            assert np.array_equal(f, faces), f"{path} is not in the template topology"
            frames[(m.group(1), int(m.group(2)))] = v
    return frames, faces


def family_sequence(frames, family, exclude=HELD_OUT):
    """The frames of a family ordered by angle through the template: (T, N, 3)."""
    angles = sorted({a for f, a in frames if f == family} | {0})
    return np.stack([frames[("template", 0)] if a == 0 else frames[(family, a)]
                     for a in angles if a not in exclude])


def sphere_basis(frames, faces, metric="face", elastic=False):
    """Pose basis from the three families without the held-out frames."""
    seqs = {"pose": [family_sequence(frames, fam) for fam in FAMILIES]}
    return build_basis(frames[("template", 0)], faces, seqs, {"pose": 64}, weights=metric,
                       name="deformed_sphere", schedule=SCHEDULE, units="",
                       elastic=("pose",) if elastic else ())
