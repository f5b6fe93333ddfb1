"""Procedural test surfaces: smooth closed meshes the project generates itself.

Used by tests, the demo and benchmarks; no third-party meshes are shipped.
Returns numpy arrays ``verts (N, 3) float64`` and ``faces (F, 3) int64``.
"""

import numpy as np
import trimesh


def icosphere(subdivisions=3, radius=1.0):
    """Unit icosphere: -> verts (N, 3), faces (F, 3)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def blob(verts, amplitude=0.2, frequency=2.0, stretch=(1.0, 0.8, 0.6), seed=0):
    """Smooth star-shaped deformation of points on the unit sphere: (N, 3) -> (N, 3).

    The displacement is a deterministic function of position (so two meshes of
    the same sphere at different resolutions sample the *same* surface).
    """
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(4, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    phases = rng.uniform(0, 2 * np.pi, size=4)
    u = verts / np.linalg.norm(verts, axis=1, keepdims=True)
    r = 1.0 + amplitude * np.sin(frequency * u @ dirs.T + phases).mean(axis=1)
    return u * r[:, None] * np.asarray(stretch)


def blob_mesh(subdivisions=3, seed=0, **kwargs):
    """A smooth closed genus-0 surface (deformed, stretched icosphere)."""
    v, f = icosphere(subdivisions)
    return blob(v, seed=seed, **kwargs), f


def torus(n_major=32, n_minor=16, major=1.0, minor=0.35):
    """Regular torus grid mesh: -> verts (n_major*n_minor, 3), faces (2*n_major*n_minor, 3)."""
    u = np.linspace(0, 2 * np.pi, n_major, endpoint=False)
    v = np.linspace(0, 2 * np.pi, n_minor, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    verts = np.stack([(major + minor * np.cos(vv)) * np.cos(uu),
                      (major + minor * np.cos(vv)) * np.sin(uu),
                      minor * np.sin(vv)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    a = i * n_minor + j
    b = ((i + 1) % n_major) * n_minor + j
    c = ((i + 1) % n_major) * n_minor + (j + 1) % n_minor
    d = i * n_minor + (j + 1) % n_minor
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces.astype(np.int64)


def random_rotation(seed=0):
    """A uniformly random rotation matrix (3, 3) with det +1."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q
