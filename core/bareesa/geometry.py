"""Discrete differential geometry of triangle meshes (appendix of the paper).

All functions are batched over leading dimensions of ``verts`` (..., N, 3),
take ``faces`` as an (F, 3) long tensor shared by the batch, are autograd
differentiable and take device/dtype from their inputs.

Areas are true triangle areas |e01 x e02| / 2 (the paper writes |e01 x e02|;
that global factor 2 is discussed in ``h2_metric``).
"""

import torch


def face_edges(verts, faces):
    """Edge vectors e01, e02 of each face: (..., N, 3), (F, 3) -> 2 x (..., F, 3)."""
    v0 = verts[..., faces[:, 0], :]
    return verts[..., faces[:, 1], :] - v0, verts[..., faces[:, 2], :] - v0


def face_centers(verts, faces):
    """Barycentres of the faces: (..., N, 3) -> (..., F, 3)."""
    return verts[..., faces, :].mean(dim=-2)


def face_normals_areas(verts, faces):
    """Unit normals (..., F, 3) and true areas (..., F) of the faces.

    Degenerate faces get a zero normal and zero area (no NaN, also in the gradient).
    """
    e01, e02 = face_edges(verts, faces)
    cross = torch.linalg.cross(e01, e02, dim=-1)
    sq = (cross * cross).sum(-1)
    tiny = torch.finfo(verts.dtype).tiny
    norm = torch.sqrt(sq.clamp_min(tiny))
    areas = torch.where(sq > tiny, norm, torch.zeros_like(norm)) / 2
    normals = torch.where((sq > tiny)[..., None], cross / norm[..., None], torch.zeros_like(cross))
    return normals, areas


def face_areas(verts, faces):
    """True face areas: (..., N, 3) -> (..., F)."""
    return face_normals_areas(verts, faces)[1]


def vertex_areas(verts, faces):
    """Barycentric vertex areas, 1/3 of the adjacent face areas: (..., N, 3) -> (..., N)."""
    a = (face_areas(verts, faces) / 3)[..., None].expand(verts.shape[:-2] + faces.shape)
    out = verts.new_zeros(verts.shape[:-1])
    return out.index_add(-1, faces.reshape(-1), a.reshape(verts.shape[:-2] + (-1,)))


def corner_cotangents(verts, faces):
    """Cotangent of the angle at each face corner: (..., N, 3) -> (..., F, 3).

    Column k is the angle at vertex faces[:, k]; it weighs the opposite edge.
    """
    p = verts[..., faces, :]  # (..., F, 3, 3)
    cots = []
    for k in range(3):
        a = p[..., (k + 1) % 3, :] - p[..., k, :]
        b = p[..., (k + 2) % 3, :] - p[..., k, :]
        dot = (a * b).sum(-1)
        cross = torch.linalg.norm(torch.linalg.cross(a, b, dim=-1), dim=-1)
        cots.append(dot / cross.clamp_min(torch.finfo(verts.dtype).eps * (dot.abs() + 1e-30)))
    return torch.stack(cots, dim=-1)


def cotan_laplacian(verts, faces, field):
    """Un-normalised cotangent Laplacian of a vertex field (appendix formula).

    (L h)_i = sum_j (cot a_ij + cot b_ij) (h_i - h_j);  verts (..., N, 3),
    field (..., N, C) -> (..., N, C). Divide by 2 * vertex area for the
    pointwise Laplace-Beltrami operator.
    """
    cot = corner_cotangents(verts, faces)  # (..., F, 3)
    shape = torch.broadcast_shapes(verts.shape[:-1], field.shape[:-1]) + field.shape[-1:]
    out = field.new_zeros(shape)
    for k in range(3):
        i = faces[:, (k + 1) % 3]
        j = faces[:, (k + 2) % 3]
        w = cot[..., k][..., None]  # weight of edge (i, j), opposite corner k
        d = w * (field[..., i, :] - field[..., j, :])
        out = out.index_add(-2, i, d).index_add(-2, j, -d)
    return out
