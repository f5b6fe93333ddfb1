r"""Measures of a mesh for the varifold: its faces, and their sums over cells (the binned measure).

A face measure is (centres (F, 3), unit normals (F, 3), weights (F,)). A binned measure is
(centroids (C, 3), features (C, K)): each group of faces is moved to its weighted centroid and
keeps the sum of its faces' kernel features, which make the orientation kernel a dot product,
so that a group is exact for it: binet (n.n')^2 = <n n^T, n' n'^T>: sum a n n^T (K = 9); linear
n.n': sum a n (3); constant: sum a (1). Only positions are approximated: the kernel of a cell is
off by O((cell / sigma)^2) relative, mostly a blur along the surface.
"""

import torch

from ..errors import InputError
from ..geometry import face_centers, face_normals_areas


def check_mesh(verts, faces, name):
    """InputError unless verts (N, 3) float and faces (F, 3) int tensors form a valid finite mesh."""
    if not torch.is_tensor(verts) or not torch.is_floating_point(verts):
        raise InputError(f"{name} vertices must be a floating point torch tensor (N, 3)")
    if verts.ndim != 2 or verts.shape[1] != 3 or verts.shape[0] == 0:
        raise InputError(f"{name} vertices must have shape (N, 3) with N > 0, got {tuple(verts.shape)}")
    if not torch.is_tensor(faces) or faces.dtype not in (torch.int64, torch.int32):
        raise InputError(f"{name} faces must be an integer torch tensor (F, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise InputError(f"{name} faces must have shape (F, 3) with F > 0, got {tuple(faces.shape)}")
    if faces.device != verts.device:
        raise InputError(f"{name} faces are on {faces.device} but its vertices on {verts.device}")
    if int(faces.min()) < 0 or int(faces.max()) >= verts.shape[0]:
        raise InputError(f"{name} faces index vertices outside [0, {verts.shape[0]})")
    if not bool(torch.isfinite(verts).all()):
        raise InputError(f"{name} vertices contain NaN or infinite values")


def varifold_measure(verts, faces, weights=None):
    """Face barycentres (F, 3), unit normals (F, 3), areas (F,) (times optional weights (F,))."""
    normals, areas = face_normals_areas(verts, faces)
    if weights is not None:
        areas = areas * weights
    return face_centers(verts, faces), normals, areas


def cell_groups(points, cell):
    """Index of the cubic cell (of size ``cell``) of each point: (F, 3) -> groups (F,) int64, number of cells."""
    ijk = torch.floor(points.detach() / cell).long()
    if not ijk.numel():
        return ijk.new_zeros(0), 0
    ijk = ijk - ijk.min(0).values
    dims = [int(d) + 1 for d in ijk.max(0).values]
    if dims[0] * dims[1] * dims[2] < 2 ** 62:  # one integer key per cell, ordered like (i, j, k): a 1-D
        #                                         unique is far cheaper than torch.unique(dim=0)
        key = ijk[:, 2] + dims[2] * (ijk[:, 1] + dims[1] * ijk[:, 0])
        _, groups = torch.unique(key, return_inverse=True)
    else:
        _, groups = torch.unique(ijk, dim=0, return_inverse=True)
    return groups, int(groups.max()) + 1


def face_features(normals, weights, kernel):
    """Weighted kernel features of faces: normals (F, 3), weights (F,) -> (F, K) (see the module docstring)."""
    if kernel == "binet":
        per_face = (normals[:, :, None] * normals[:, None, :]).reshape(-1, 9)
    elif kernel == "linear":
        per_face = normals
    else:
        per_face = torch.ones_like(weights)[:, None]
    return weights[:, None] * per_face


def group_features(centers, normals, weights, groups, n_groups, kernel):
    """The binned measure: a face measure (F, 3), (F, 3), (F,) summed over groups (F,) ->
    centroids (C, 3), features (C, K), masses (C,); differentiable (a massless group sits at 0)."""
    mass = weights.new_zeros(n_groups).index_add(0, groups, weights)
    moment = centers.new_zeros(n_groups, 3).index_add(0, groups, weights[:, None] * centers)
    x = moment / mass.clamp_min(torch.finfo(mass.dtype).tiny)[:, None]
    per_face = face_features(normals, weights, kernel)
    feat = per_face.new_zeros(n_groups, per_face.shape[1]).index_add(0, groups, per_face)
    return x, feat, mass


def cell_features(centers, normals, weights, cell, kernel="binet"):
    """The binned measure on cubic cells of size ``cell``: (F, 3), (F, 3), (F,) -> centroids (C, 3),
    features (C, K), masses (C,); cells whose features vanish are left out."""
    groups, n_groups = cell_groups(centers, cell)
    x, feat, mass = group_features(centers, normals, weights, groups, n_groups, kernel)
    keep = feat.abs().sum(1) > 0
    return x[keep], feat[keep], mass[keep]


def pseudo_faces(centroids, features, masses, kernel):
    """A binned measure (C, 3), (C, K), (C,) as at most 3 pseudo-faces per cell that reproduce its
    orientation kernel exactly -> centres (C', 3), unit normals (C', 3), weights (C',).

    binet: the eigenpairs (lambda_k, e_k) of sum a n n^T (n^T T n = sum lambda_k (n.e_k)^2;
    eigenvalues below 1e-12 of the mass are dropped); linear: one face of normal s/|s| and weight
    |s|, s = sum a n; constant: one face of weight sum a (its normal, e_z, does not matter).
    """
    k = centroids.shape[0]
    if kernel == "binet":
        lam, vec = torch.linalg.eigh(features.reshape(k, 3, 3))           # (C, 3), (C, 3, 3) columns
        ok = lam > 1e-12 * masses[:, None]
        cell_of = torch.arange(k, device=centroids.device)[:, None].expand(k, 3)[ok]
        return centroids[cell_of], vec.transpose(1, 2)[ok], lam[ok]
    if kernel == "linear":
        norm = features.norm(dim=1)
        ok = norm > 1e-12 * masses
        return centroids[ok], features[ok] / norm[ok, None], norm[ok]
    return centroids, centroids.new_tensor([0.0, 0.0, 1.0]).expand(k, 3), features[:, 0]


def binned_measure(centers, normals, weights, cell, kernel="binet"):
    """A face measure summed over cubic cells of size ``cell``, as a smaller measure of pseudo-faces:
    (F, 3), (F, 3), (F,) -> (C', 3), unit normals (C', 3), weights (C',) (not differentiable; see
    ``pseudo_faces``), for the face backends against a fixed target."""
    centers, normals, weights = (t.detach() for t in (centers, normals, weights))
    return pseudo_faces(*cell_features(centers, normals, weights, cell, kernel), kernel)


def moved_measure(centroids, features, rotation, scale, shift, kernel):
    """A binned measure (C, 3), (C, K) moved by x -> scale R x + shift (R (3, 3), scale and shift
    tensors): areas grow by scale^2 and normals rotate -> centroids (C, 3), features (C, K)."""
    x = scale * centroids @ rotation.T + shift
    if kernel == "binet":
        return x, (scale**2 * (rotation @ features.reshape(-1, 3, 3) @ rotation.T)).reshape(-1, 9)
    if kernel == "linear":
        return x, scale**2 * features @ rotation.T
    return x, scale**2 * features
