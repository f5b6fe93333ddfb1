"""Steps shared by the basis builders (plain numpy + core; no bpy)."""

import numpy as np

from bareesa.geodesics import geodesic
from bareesa.h2_metric import H2Weights
from bareesa.latent import project_to_basis
from bareesa.shooting import initial_velocity
from bareesa.statistics import fit_distribution
from bareesa.basis_building import vertex_geodesic


def elastic_paths(pairs, faces, weights="body", steps=4, max_iter=60, log=None):
    """Parametrised H2 geodesics in vertex space between pairs of same-topology meshes.

    pairs: list of ((N, 3), (N, 3)) -> list of paths (steps, N, 3). Their
    consecutive differences are exactly ``bareesa.statistics.elastic_tangents``;
    ``max_iter`` bounds the L-BFGS iterations per geodesic (the build budget).
    """
    w = H2Weights.parse(weights)
    out = []
    for i, (a, b) in enumerate(pairs):
        out.append(vertex_geodesic(a, b, faces, w, steps=steps, max_iter=max_iter))
        if log:
            log(f"  elastic geodesic {i + 1}/{len(pairs)}")
    return out


def fit_basis_distribution(basis, frames, n_components, max_samples=120, steps=4, max_iter=40, seed=0):
    """Gaussian mixtures on the log maps (initial velocities at the template, in the basis'
    ``shape_metric``) of training frames.

    frames (M, N, 3) in template topology; at most ``max_samples`` (evenly chosen)
    are used; each log map is the initial velocity of a latent geodesic 0 -> code
    (``steps`` meshes, at most ``max_iter`` L-BFGS iterations). Returns the
    ``gmm_*`` arrays to store in ``basis.extras``.
    """
    frames = np.asarray(frames)
    pick = np.unique(np.linspace(0, len(frames) - 1, min(max_samples, len(frames))).round().astype(int))
    codes = project_to_basis(basis, frames[pick])[0]
    codes = codes[np.abs(codes).sum(1) > 1e-9]
    t, f, h = basis.tensors()
    weights = basis.shape_metric  # random bodies are shot from the template in it
    metric = basis.template_metric(weights)  # preconditioning once for all (5x faster than G-bar at each code)
    velocities = np.stack([initial_velocity(geodesic(t, f, h, np.zeros_like(c), c, weights, steps=steps,
                                                     max_iter=max_iter, metric=metric).path) for c in codes])
    dist = fit_distribution(velocities, basis.groups, n_components, seed=seed)
    dist["distribution_samples"] = np.asarray(len(codes))
    return dist


def checked_template(template, faces, name):
    """Refuse a template that is not a closed manifold (the H2 metric and the varifold need one)."""
    from bareesa.mesh import validate_mesh

    rep = validate_mesh(template, faces, name)
    if rep.n_boundary_edges or rep.n_nonmanifold_edges:
        raise RuntimeError(f"{name} template is not closed and manifold: {rep}")


def topology_signature(faces):
    """A short fingerprint of a face array (to compare topologies across builds)."""
    import hashlib

    return hashlib.sha1(np.ascontiguousarray(np.asarray(faces, dtype=np.int64)).tobytes()).hexdigest()[:16]


def reduced_precision(basis, dtype=np.float16):
    """A copy of a basis whose fields went through ``dtype`` (what ``save_basis(..., fields_dtype)`` ships).

    -> (basis copy, max absolute field error / max |field|).
    """
    import copy

    out = copy.copy(basis)
    out.fields = basis.fields.astype(dtype).astype(np.float64)
    return out, float(np.abs(out.fields - basis.fields).max() / np.abs(basis.fields).max())
