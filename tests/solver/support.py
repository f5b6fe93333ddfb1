"""Helpers shared by the solver's tests (plain functions and data, not fixtures; those are in conftest.py)."""

import numpy as np

from bareesa import latent, synthetic

#: two codes of the 4-field smooth sphere basis (the ``sphere`` fixture)
A = np.array([0.2, -0.3, 0.4, 0.1])
B = np.array([-0.5, 0.6, 0.1, 0.7])


def small_basis(p=4, subdivisions=2, seed=0):
    """A template blob and p smooth fields (functions of position)."""
    v, f = synthetic.blob_mesh(subdivisions, seed=seed)
    rng = np.random.default_rng(seed)
    fields = np.stack([0.2 * np.sin(v @ rng.normal(size=(3, 3))) for _ in range(p)])
    return latent.Basis(template=v, faces=f, fields=fields, groups={"pose": (0, p - 1), "shape": (p - 1, p)},
                        weights="face", scale=2.0, name="small")


def limb_basis():
    """A blob whose fields bend a 'limb' (the vertices with x > 0.5, under a third), push it
    sideways and up (y, z) and lift the whole body (z): the basis spans the z translation only."""
    v, f = synthetic.blob_mesh(3)
    limb = (v[:, 0] > 0.5).astype(float)[:, None]
    bend = limb * np.array([0.0, 0.0, 1.0]) * (v[:, :1] - 0.5)
    push = limb * np.array([0.0, 1.0, 0.5])
    lift = np.broadcast_to([0.0, 0.0, 1.0], v.shape)
    b = latent.Basis(template=v, faces=f, fields=np.stack([bend, push, lift]), groups={}, weights="body")
    return b, limb[:, 0] > 0
