"""Paper-scale test problems: the DFAUST template (6,890 vertices) with P synthetic smooth fields.

Used only for timing (the fields are smooth random deformations, not learned motions).
"""

import numpy as np
import trimesh

from bench.common import shared_data
from bareesa.latent import PAPER_BODY_SCHEDULE, Basis
from bareesa.mesh import load_mesh


def body_basis(script, n_fields=170, n_shape=40, seed=0, amplitude=0.02):
    """Basis with n_fields smooth fields on the template scaled to 1.7 m (pose + shape groups)."""
    v, f = load_mesh(shared_data(script) / "body" / "DFAUST_template.ply")
    ext = v.max(0) - v.min(0)
    v = (v - v.mean(0)) * (1.7 / ext.max())
    rng = np.random.default_rng(seed)
    freq = rng.uniform(1.0, 6.0, size=(n_fields, 1))
    dirs = rng.normal(size=(n_fields, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, size=(n_fields, 1))
    amp = rng.normal(size=(n_fields, 1, 3))
    fields = amplitude * np.sin(freq * (dirs @ v.T) + phase)[:, :, None] * amp
    return Basis(template=v, faces=f, fields=fields,
                 groups={"pose": (0, n_fields - n_shape), "shape": (n_fields - n_shape, n_fields)},
                 weights="body", schedule=PAPER_BODY_SCHEDULE, scale=1.7, units="m", name="synthetic_body")


def body_scan(basis, code, subdivisions=1, noise=0.002, seed=0):
    """F(code) subdivided (55,104 faces at 1), noisy, with vertex and face order shuffled."""
    v = basis.template + np.tensordot(code, basis.fields, axes=1)
    m = trimesh.Trimesh(v, basis.faces, process=False)
    for _ in range(subdivisions):
        m = m.subdivide()
    rng = np.random.default_rng(seed)
    verts = np.asarray(m.vertices) + noise * rng.normal(size=m.vertices.shape)
    perm = rng.permutation(len(verts))
    rank = np.empty_like(perm)
    rank[perm] = np.arange(len(perm))
    faces = rank[np.asarray(m.faces)][rng.permutation(len(m.faces))]
    return verts[perm], faces
