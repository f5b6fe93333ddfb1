"""Bases from registered 4D data (paper section 5.2): PCA of frame differences or of the steps of
elastic H2 geodesics (parametrised, in full vertex space) between consecutive meshes."""

import math

import numpy as np
import torch

from .errors import InputError
from .geodesics import geodesic
from .h2_metric import H2Weights, assembled_metric_matrix, path_energy
from .latent import PAPER_BODY_SCHEDULE, Basis
from .metric_fit import choose_motion_metric
from .optimize import minimize_lbfgs
from .progress import Monitor
from .threads import with_one_blas_thread

RANK_RTOL = 1e-6


#: Tangent sets with more vectors and coordinates than this use a randomised SVD.
RANDOMIZED_MIN = 2500


def principal_fields(tangents, n_components):
    """Leading principal directions of tangent vectors: (M, N, 3) -> fields (K, N, 3), variance ratios (K,).

    Uncentred PCA (SVD of the tangent vectors themselves): tangent vectors of
    motions are directions, their mean is meaningful and must stay in the span.
    Fields are scaled by singular value / sqrt(M) so that codes of the training
    data are of order one (well-conditioned optimisation).
    """
    m = tangents.reshape(tangents.shape[0], -1)
    if m.shape[0] == 0:
        raise InputError("no tangent vectors: a group needs at least one sequence of two frames")
    if min(m.shape) > RANDOMIZED_MIN and n_components < min(m.shape) // 8:
        # thousands of frames: a seeded randomised SVD of the leading directions (scikit-learn); the
        # variance ratios are still shares of the whole (squared Frobenius norm)
        from sklearn.utils.extmath import randomized_svd

        _, s, vt = randomized_svd(m, n_components, n_oversamples=max(20, n_components // 2), n_iter=6,
                                  random_state=0)
        total = float(np.einsum("ij,ij->", m, m))
    else:
        _, s, vt = np.linalg.svd(m, full_matrices=False)
        total = float((s**2).sum())
    # directions below RANK_RTOL x the leading singular value carry < 1e-12 of the variance: they
    # are rounding noise (Blender bakes float32 frames), not motion, and would make bad fields
    rank = int((s > s[0] * RANK_RTOL).sum()) if s[0] > 0 else 0
    if rank == 0:
        raise InputError("all tangent vectors are zero: the frames of a group do not move")
    k = min(n_components, rank)
    fields = (s[:k, None] / math.sqrt(m.shape[0])) * vt[:k]
    ratios = s[:k] ** 2 / total
    return fields.reshape(k, *tangents.shape[1:]), ratios


def sequence_tangents(sequences):
    """Differences of consecutive frames of each sequence: list of (T_i, N, 3) -> (sum(T_i - 1), N, 3)."""
    diffs = [np.diff(np.asarray(s, dtype=np.float64), axis=0) for s in sequences if len(s) >= 2]
    if not diffs:
        raise InputError("every sequence has fewer than two frames: nothing to learn a motion from")
    return np.concatenate(diffs)


@with_one_blas_thread
def build_basis(template, faces, groups, components, weights="body", scale=None, name="basis",
                units="", schedule=PAPER_BODY_SCHEDULE, provenance=None, elastic=(), elastic_steps=5,
                callback=None, cancel=None, landmarks=None):
    """PCA basis from registered 4D data (paper section 5.2).

    groups: {name: list of sequences (T_i, N, 3)} in template topology;
    components: {name: K} the number of fields kept per group; groups named in
    ``elastic`` use the steps of parametrised H2 geodesics between consecutive
    meshes instead of plain differences (the paper's shape basis); landmarks: {name: template vertex};
    weights: the metric of motion paths, a preset, six numbers or "fit" (``metric_fit.choose_motion_metric``
    on the sequences of the groups with two or more; the paper's body weights build elastic groups then).
    """
    template = np.asarray(template, dtype=np.float64)
    fit = isinstance(weights, str) and weights == "fit"
    construction_weights = H2Weights.parse("body" if fit else weights)
    unknown = set(elastic) - set(groups)
    if unknown:
        raise InputError(f"elastic construction asked for unknown groups {', '.join(sorted(unknown))}")
    blocks, ranges, report, start = [], {}, {}, 0
    for gname, seqs in groups.items():
        for s in seqs:
            if np.asarray(s).shape[1:] != template.shape:
                raise InputError(f"group '{gname}': a frame has shape {np.asarray(s).shape[1:]} but the template "
                                 f"has {template.shape}: frames must be registered to the template topology")
        k = int(components.get(gname, 10))
        if k < 1:
            raise InputError(f"group '{gname}': number of components must be >= 1, got {k}")
        if gname in elastic:
            tangents = elastic_tangents([np.asarray(x, dtype=np.float64) for x in seqs], faces,
                                        construction_weights, steps=elastic_steps, callback=callback,
                                        cancel=cancel)
        else:
            tangents = sequence_tangents(seqs)
        fields, ratios = principal_fields(tangents, k)
        blocks.append(fields)
        ranges[gname] = (start, start + fields.shape[0])
        start += fields.shape[0]
        report[gname] = {"tangent_vectors": int(tangents.shape[0]), "components": int(fields.shape[0]),
                         "construction": "elastic H2 geodesics" if gname in elastic else "frame differences",
                         "requested": k, "explained_variance": float(ratios.sum()),
                         "variance_ratios": [float(r) for r in ratios]}
    if scale is None:
        ext = template.max(0) - template.min(0)
        scale = float(ext.max())
    prov = dict(provenance or {})
    prov["groups"] = report
    basis = Basis(template=template, faces=np.asarray(faces), fields=np.concatenate(blocks), groups=ranges,
                  weights=construction_weights, schedule=schedule, scale=scale, name=name, units=units,
                  provenance=prov, landmarks=landmarks or {})
    if fit:
        motions = [s for seqs in groups.values() if len(seqs) >= 2 for s in seqs]
        chosen = choose_motion_metric(basis, motions, callback=callback, cancel=cancel)
        basis.weights, basis.shape_weights = chosen.weights, construction_weights
        basis.provenance["metric_fit"] = chosen.card()
    return basis


def fits_metric(groups):
    """Whether ``build_basis`` fits the motion metric by default: a group has two or more sequences."""
    return any(len(seqs) >= 2 for seqs in groups.values())


#: Meshes up to this many vertices get the metric-whitened solver (dense 3N x 3N metric matrix).
WHITENED_MAX_VERTICES = 1000


def vertex_geodesic(verts0, verts1, faces, weights, steps=5, max_iter=300, callback=None, cancel=None):
    """Parametrised H2 geodesic in full vertex space between same-topology meshes.

    verts0, verts1 (N, 3) numpy -> path (steps, N, 3) with the given ends. Up to
    WHITENED_MAX_VERTICES vertices it is the latent boundary value problem with one
    field per vertex coordinate, whitened by the H2 metric matrix at the mean mesh
    (converges in tens of iterations); larger meshes minimise the discrete path
    energy over the interior meshes with plain L-BFGS from the linear blend.
    """
    v0, v1 = (np.asarray(v, dtype=np.float64) for v in (verts0, verts1))
    if v0.shape != v1.shape:
        raise InputError(f"an elastic geodesic needs two meshes in one topology, got {v0.shape} and {v1.shape}")
    if steps < 3:
        return np.stack([v0, v1])
    faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.long)
    n = v0.shape[0]
    if n <= WHITENED_MAX_VERTICES:
        coords = torch.eye(3 * n, dtype=torch.float64).reshape(3 * n, n, 3)  # field i moves coordinate i
        metric = assembled_metric_matrix(torch.from_numpy((v0 + v1) / 2), faces_t, coords, weights).numpy()
        g = geodesic(torch.from_numpy(v0), faces_t, coords, np.zeros(3 * n), (v1 - v0).ravel(), weights,
                     steps=steps, max_iter=max_iter, metric=metric, callback=callback, cancel=cancel)
        path = v0 + g.path.reshape(steps, n, 3)
        path[0], path[-1] = v0, v1
        return path
    t = np.linspace(0, 1, steps)[:, None, None]
    path = (1 - t) * v0 + t * v1
    ends = torch.from_numpy(path[[0, -1]])
    shape = path[1:-1].shape

    def energy(x):
        return path_energy(torch.cat([ends[:1], x.reshape(shape), ends[1:]]), faces_t, weights)

    x, _, _ = minimize_lbfgs(energy, path[1:-1].ravel(), Monitor("elastic geodesic", callback, cancel),
                             max_iter=max_iter, message="elastic geodesic")
    path[1:-1] = x.reshape(shape)
    return path


@with_one_blas_thread
def elastic_tangents(sequences, faces, weights, steps=5, callback=None, cancel=None):
    """Tangent vectors of H2 geodesics between consecutive meshes of each sequence.

    sequences: list of (T_i, N, 3) -> (sum_i (T_i - 1) * (steps - 1), N, 3): the
    steps of each elastic geodesic (the paper's shape-basis construction).
    """
    out = []
    for seq in sequences:
        for a, b in zip(seq[:-1], seq[1:]):
            out.append(np.diff(vertex_geodesic(a, b, faces, weights, steps, callback=callback, cancel=cancel),
                               axis=0))
    if not out:
        raise InputError("elastic tangents need sequences of at least two meshes")
    return np.concatenate(out)
