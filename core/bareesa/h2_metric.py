"""The six-weight invariant H2 (second-order Sobolev) metric on triangle meshes.

Discretisation of the paper's appendix "Discretization of invariant H2 metrics".
For a mesh ``q`` (verts (..., N, 3), faces (F, 3)) and vertex fields h, k:

    G_q(h, k) = sum_v  a0 * A_v <h_v, k_v>
              + sum_f  A_f * [ a1 * tr(g^-1 dg_h g^-1 dg_k)
                             + beta * tr(g^-1 dg_h) tr(g^-1 dg_k)      beta = (b1 - a1) / 8
                             + c1 * <dn_h, dn_k>
                             + d1 * tr(g^-1 xi_h g^-1 xi_k^T) ]
              + sum_v  a2 * <(L h)_v, (L k)_v> / (4 A_v)

with, on each face f (edges e01, e02, dq = [e01, e02] a 3x2 matrix):
  g = dq^T dq (the face metric), dg_h = dq^T dh + dh^T dq (its variation along h),
  dn_h the variation of the unit normal, xi_h = dq^T dh - dh^T dq, and
  L the un-normalised cotangent Laplacian of ``geometry.cotan_laplacian`` so that
  (L h)_v / (2 A_v) is the Laplace-Beltrami operator and the last sum is
  the integral of |Delta h|^2.  A_f are true face areas, A_v = (1/3) sum of the
  adjacent face areas.

Parameterisation of the first-order split (so that the paper's weights mean
what the paper meant): we follow the paper's reference implementation, in which
the user-facing b1 enters as the coefficient beta = (b1 - a1)/8 of the squared
trace term, next to a1 * tr((g^-1 dg)^2).  Since tr(M^2) >= tr(M)^2 / 2, the
form is positive semi-definite whenever a1, c1, d1 >= 0 and 3 a1 + b1 >= 0, which
holds for the paper's body (1, 1000, 100, 1, 1, 1) and face (1, 10, 10, 10, 1, 1)
weights.  The appendix writes face areas as |e01 x e02| (twice the area); that
multiplies every term by the same factor 2 and changes no geodesic, so we keep
true areas (the metric then converges to the continuous integral).

The variations are linear in h (the metric is evaluated exactly as a bilinear
form); on a path they are evaluated at the midpoints of the time steps, where
g(q + h/2) - g(q - h/2) = dg_h exactly.
"""

from dataclasses import astuple, dataclass

import torch

from . import geometry
from .errors import InputError


@dataclass(frozen=True)
class H2Weights:
    """The six non-negative weights (a0, a1, b1, c1, d1, a2) of the H2 metric."""

    a0: float = 1.0
    a1: float = 1000.0
    b1: float = 100.0
    c1: float = 1.0
    d1: float = 1.0
    a2: float = 1.0

    def __post_init__(self):
        values = astuple(self)
        if not all(isinstance(x, (int, float)) and x == x and abs(x) != float("inf") for x in values):
            raise InputError(f"H2 weights must be finite numbers, got {values}")
        if min(self.a0, self.a1, self.c1, self.d1, self.a2) < 0 or 3 * self.a1 + self.b1 < 0:
            raise InputError(f"H2 weights {values} do not give a positive metric: a0, a1, c1, d1, a2 "
                             "must be >= 0 and 3*a1 + b1 >= 0")

    @classmethod
    def parse(cls, value):
        """From an H2Weights, a preset name ('body', 'face'), a sequence or 'a0,a1,b1,c1,d1,a2'."""
        if isinstance(value, cls):
            return value
        if isinstance(value, str):
            if value in PRESETS:
                return PRESETS[value]
            try:
                value = [float(x) for x in value.split(",")]
            except ValueError:
                raise InputError(f"metric weights '{value}' are neither a preset ({', '.join(PRESETS)}) "
                                 "nor six comma-separated numbers a0,a1,b1,c1,d1,a2") from None
        value = list(value)
        if len(value) != 6:
            raise InputError(f"expected six metric weights a0,a1,b1,c1,d1,a2, got {len(value)}")
        return cls(*map(float, value))

    def as_tuple(self):
        """(a0, a1, b1, c1, d1, a2)."""
        return astuple(self)


#: The paper's weights (section "Parameter selection").
PRESETS = {"body": H2Weights(1, 1000, 100, 1, 1, 1), "face": H2Weights(1, 10, 10, 10, 1, 1)}


def _safe_inverse_2x2(g, valid):
    """Inverse of (..., 2, 2) SPD matrices; zero where ``valid`` (...) is False."""
    det = g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] * g[..., 1, 0]
    det = torch.where(valid, det, torch.ones_like(det))
    adj = torch.stack([torch.stack([g[..., 1, 1], -g[..., 0, 1]], -1),
                       torch.stack([-g[..., 1, 0], g[..., 0, 0]], -1)], -2)
    return torch.where(valid[..., None, None], adj / det[..., None, None], torch.zeros_like(adj))


class _FootPoint:
    """Geometry of the foot point q needed by the metric (all tensors batched like verts)."""

    def __init__(self, verts, faces):
        e01, e02 = geometry.face_edges(verts, faces)
        self.faces = faces
        self.dq = torch.stack([e01, e02], dim=-1)  # (..., F, 3, 2)
        self.g = self.dq.transpose(-1, -2) @ self.dq  # (..., F, 2, 2)
        cross = torch.linalg.cross(e01, e02, dim=-1)
        sq = (cross * cross).sum(-1)
        tiny = torch.finfo(verts.dtype).tiny
        valid = sq > tiny * 1e6
        norm = torch.sqrt(torch.where(valid, sq, torch.ones_like(sq)))
        self.face_area = torch.where(valid, norm / 2, torch.zeros_like(norm))  # (..., F)
        self.inv_cross_norm = torch.where(valid, 1 / norm, torch.zeros_like(norm))
        self.normal = cross * self.inv_cross_norm[..., None]
        self.ginv = _safe_inverse_2x2(self.g, valid)
        self.e01, self.e02 = e01, e02
        self.verts = verts
        self._vertex_area = None

    @property
    def vertex_area(self):
        if self._vertex_area is None:
            self._vertex_area = geometry.vertex_areas(self.verts, self.faces)
        return self._vertex_area


def _first_order_features(q, h):
    """Per-face quantities linear in h: (g^-1 dg, dn, xi) for h (..., N, 3)."""
    dh = torch.stack(geometry.face_edges(h, q.faces), dim=-1)  # (..., F, 3, 2)
    dqt_dh = q.dq.transpose(-1, -2) @ dh
    dg = dqt_dh + dqt_dh.transpose(-1, -2)
    xi = dqt_dh.transpose(-1, -2) - dqt_dh  # dh^T dq - dq^T dh
    dcross = (torch.linalg.cross(dh[..., 0], q.e02.expand_as(dh[..., 0]), dim=-1)
              + torch.linalg.cross(q.e01.expand_as(dh[..., 1]), dh[..., 1], dim=-1))
    dn = (dcross - q.normal * (q.normal * dcross).sum(-1, keepdim=True)) * q.inv_cross_norm[..., None]
    return q.ginv @ dg, dn, xi


def _features(q, h, w):
    """Left and right features (..., X) of a field h (..., N, 3): G_q(h, k) = <left(h), right(k)>.

    Every term of the metric is a weighted sum of products of quantities linear
    in the field, so the metric is a plain dot product of feature vectors; the
    Gram matrix of P fields is then a single (P, X) @ (X, P) product.
    """
    left, right = [], []

    def add(x, y, weight):  # x, y (..., M, C) per-face or per-vertex values; weight (..., M)
        left.append((x * weight[..., None]).flatten(-2))
        right.append(y.flatten(-2))

    if w.a0:
        add(h, h, w.a0 * q.vertex_area)
    if w.a1 or w.b1 or w.c1 or w.d1:
        a, dn, xi = _first_order_features(q, h)
        beta = (w.b1 - w.a1) / 8
        if w.a1:  # tr(A_h A_k) = sum_ab A_h[a, b] A_k[b, a]
            add(a.flatten(-2), a.transpose(-1, -2).flatten(-2), w.a1 * q.face_area)
        if beta:
            tr = _trace(a)[..., None]
            add(tr, tr, beta * q.face_area)
        if w.c1:
            add(dn, dn, w.c1 * q.face_area)
        if w.d1:  # tr(g^-1 xi_h g^-1 xi_k^T) = sum_ab (g^-1 xi_h)[a, b] (xi_k g^-1)[a, b]
            add((q.ginv @ xi).flatten(-2), (xi @ q.ginv).flatten(-2), w.d1 * q.face_area)
    if w.a2:
        area = q.vertex_area
        inv = torch.where(area > 0, 1 / (4 * torch.where(area > 0, area, torch.ones_like(area))),
                          torch.zeros_like(area))
        lap = geometry.cotan_laplacian(q.verts, q.faces, h)
        add(lap, lap, w.a2 * inv)
    shape = torch.broadcast_shapes(*[x.shape[:-1] for x in left])
    left = torch.cat([x.expand(shape + x.shape[-1:]) for x in left], -1)
    right = torch.cat([x.expand(shape + x.shape[-1:]) for x in right], -1)
    return left, right


def _bilinear(q, h, k, w):
    """G_q(h, k) for h, k (..., N, 3) broadcasting with the foot point -> (...)."""
    left, _ = _features(q, h, w)
    _, right = _features(q, k, w)
    return (left * right).sum(-1)


def _cross3(x, y):
    """Cross product of vectors given as 3-tuples of (..., F) components."""
    return (x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0])


def _dot3(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _corner_components(x, corners, n_faces):
    """x (..., N, 3) -> [corner][axis] nested lists of (..., F) tensors."""
    per_axis = [c[..., corners].unflatten(-1, (3, n_faces)).unbind(-2) for c in x.unbind(-1)]
    return [tuple(per_axis[axis][k] for axis in range(3)) for k in range(3)]


def _quadratic(verts, faces, h, w):
    """G_q(h, h) for verts, h (..., N, 3) -> (...), in closed form per face.

    The form of ``_features`` written out with 2 x 2 algebra on per-component
    (..., F) arrays (no small matrix products; several times faster, it is the
    inner loop of every latent solve). With e1, e2 the face edges, d1, d2 those of
    h, g the face metric and D = det g = |c|^2, c = e1 x e2:
      g^-1 dg = adj(g) S / D with S = [[2 e1.d1, e1.d2 + e2.d1], [., 2 e2.d2]],
      xi = s J with s = e2.d1 - e1.d2, so tr(g^-1 xi g^-1 xi^T) = 2 s^2 / D,
      |dn|^2 = (|dc|^2 - (c.dc)^2 / D) / D with dc = d1 x e2 + e1 x d2,
      cot of the angle at a corner = (dot of its two edges) / sqrt(D).
    """
    corners = faces.T.reshape(-1)  # (3F,) corner-major
    n_faces = faces.shape[0]
    p = _corner_components(verts, corners, n_faces)
    v = _corner_components(h, corners, n_faces)
    sub = lambda x, y: tuple(a - b for a, b in zip(x, y))  # noqa: E731
    e1, e2, d1, d2 = sub(p[1], p[0]), sub(p[2], p[0]), sub(v[1], v[0]), sub(v[2], v[0])
    c = _cross3(e1, e2)
    det = _dot3(c, c)
    valid = det > torch.finfo(verts.dtype).tiny * 1e6
    det = torch.where(valid, det, torch.ones_like(det))
    root = torch.sqrt(det)
    area = torch.where(valid, root / 2, torch.zeros_like(det))  # (..., F)
    g11, g12, g22 = _dot3(e1, e1), _dot3(e1, e2), _dot3(e2, e2)
    per_face = torch.zeros_like(det)
    if w.a1 or w.b1 or w.d1:
        m11, m12, m21, m22 = _dot3(e1, d1), _dot3(e1, d2), _dot3(e2, d1), _dot3(e2, d2)
        s11, s12, s22 = 2 * m11, m12 + m21, 2 * m22
        a, b = g22 * s11 - g12 * s12, g22 * s12 - g12 * s22  # adj(g) S = [[a, b], [c_, d]]
        c_, d = g11 * s12 - g12 * s11, g11 * s22 - g12 * s12
        beta = (w.b1 - w.a1) / 8
        per_face = per_face + (w.a1 * (a * a + 2 * b * c_ + d * d) + beta * (a + d) ** 2) / (det * det)
        per_face = per_face + w.d1 * 2 * (m21 - m12) ** 2 / det
    if w.c1:
        dc = tuple(x + y for x, y in zip(_cross3(d1, e2), _cross3(e1, d2)))
        per_face = per_face + w.c1 * (_dot3(dc, dc) - _dot3(c, dc) ** 2 / det) / det
    total = (area * per_face).sum(-1)
    if w.a0 or w.a2:
        vertex_area = area.new_zeros(area.shape[:-1] + verts.shape[-2:-1]).index_add(
            -1, corners, (area / 3).repeat((1,) * (area.dim() - 1) + (3,)))
    if w.a0:
        total = total + w.a0 * (vertex_area * _dot(h, h)).sum(-1)
    if w.a2:
        inv_root = torch.where(valid, 1 / root, torch.zeros_like(root))
        cot = (g12 * inv_root, (g11 - g12) * inv_root, (g22 - g12) * inv_root)  # angle at corner 0, 1, 2
        # (L h) at corner j: cot_{j+2} (h_j - h_{j+1}) + cot_{j+1} (h_j - h_{j+2}), summed over faces
        lap = torch.stack([torch.cat([cot[(j + 2) % 3] * (v[j][axis] - v[(j + 1) % 3][axis])
                                      + cot[(j + 1) % 3] * (v[j][axis] - v[(j + 2) % 3][axis]) for j in range(3)], -1)
                           for axis in range(3)], -2)  # (..., 3, 3F) corner-major like ``corners``
        lap = lap.new_zeros(lap.shape[:-1] + h.shape[-2:-1]).index_add(-1, corners, lap)  # (..., 3, N)
        inv = torch.where(vertex_area > 0, 1 / (4 * torch.where(vertex_area > 0, vertex_area,
                                                                    torch.ones_like(vertex_area))),
                          torch.zeros_like(vertex_area))
        total = total + w.a2 * (inv * (lap * lap).sum(-2)).sum(-1)
    return total


def _dot(x, y):
    return (x * y).sum(-1)


def _trace(m):
    return m[..., 0, 0] + m[..., 1, 1]


def _check(verts, faces, *fields):
    if verts.dim() < 2 or verts.shape[-1] != 3:
        raise InputError(f"vertices must have shape (..., N, 3), got {tuple(verts.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3 or faces.dtype not in (torch.int64, torch.int32):
        raise InputError(f"faces must be an integer tensor of shape (F, 3), got {tuple(faces.shape)} {faces.dtype}")
    for f in fields:
        if f.shape[-2:] != verts.shape[-2:]:
            raise InputError(f"vector field of shape {tuple(f.shape)} does not match the mesh's "
                             f"{verts.shape[-2]} vertices")


def inner_product(verts, faces, h, k, weights=PRESETS["body"]):
    """G_q(h, k): verts (..., N, 3), faces (F, 3), h, k (..., N, 3) -> (...)."""
    w = H2Weights.parse(weights)
    _check(verts, faces, h, k)
    return _bilinear(_FootPoint(verts, faces), h, k, w)


def squared_norm(verts, faces, h, weights=PRESETS["body"]):
    """G_q(h, h): verts (..., N, 3), faces (F, 3), h (..., N, 3) -> (...)."""
    return inner_product(verts, faces, h, h, weights)


def metric_matrix(verts, faces, fields, weights=PRESETS["body"]):
    """Gram matrix [G_q(h_i, h_j)]: verts (N, 3), fields (P, N, 3) -> (P, P).

    With verts = F(alpha) this is the latent metric G-bar(alpha) of the paper.
    """
    w = H2Weights.parse(weights)
    _check(verts, faces, fields)
    if fields.dim() != 3:
        raise InputError(f"fields must have shape (P, N, 3), got {tuple(fields.shape)}")
    left, right = _features(_FootPoint(verts, faces), fields, w)
    gram = left @ right.transpose(0, 1)
    return (gram + gram.transpose(0, 1)) / 2


def path_energy(path, faces, weights=PRESETS["body"], duration=1.0, per_step=False):
    """Discrete path energy of a path of meshes: path (..., T, N, 3) -> (...).

    E = sum_k G_{m_k}(q_{k+1} - q_k, q_{k+1} - q_k) / dt,  dt = duration / (T - 1),
    m_k the midpoint (q_k + q_{k+1}) / 2: the Riemann sum of int_0^duration G(q', q') dt.
    With per_step=True returns the (..., T - 1) terms of the sum instead.
    """
    w = H2Weights.parse(weights)
    _check(path, faces)
    if path.dim() < 3 or path.shape[-3] < 2:
        raise InputError(f"a path needs at least two meshes, got shape {tuple(path.shape)}")
    steps = path[..., 1:, :, :] - path[..., :-1, :, :]
    mids = (path[..., 1:, :, :] + path[..., :-1, :, :]) / 2
    dt = duration / (path.shape[-3] - 1)
    terms = _quadratic(mids, faces, steps, w) / dt
    return terms if per_step else terms.sum(-1)


def assembled_metric_matrix(verts, faces, fields, weights=PRESETS["body"], chunk=1024):
    """Latent metric matrix [G_q(h_i, h_j)] assembled face by face: (N, 3), (P, N, 3) -> (P, P).

    The same matrix as ``h2_metric.metric_matrix`` (to rounding; degenerate faces
    aside), several times faster at paper scale: the first-order terms are per-face
    quadratic forms of the two edge variations, so G = sum_f E_f^T M_f E_f with the
    6 x 6 blocks M_f read off ``path_energy`` on the face soup (one gradient of six
    probes), plus a0 sum_v A_v <h, k> and a2 sum_v <L h, L k> / (4 A_v) with a sparse
    cotangent Laplacian. Not differentiable in verts (use ``metric_matrix`` for that);
    used for preconditioners and the quasi-Newton Jacobian of the geodesic step.
    """
    w = H2Weights.parse(weights)
    verts = verts.detach()
    p, n = fields.shape[:2]
    n_faces = faces.shape[0]
    gram = fields.new_zeros(p, p)
    # fields as (N, 3P) columns (axis-major): a face's edge variations are (2, 3, P) -> (6, P)
    columns = fields.detach().permute(1, 2, 0).reshape(n, 3 * p)
    if w.a1 or w.b1 or w.c1 or w.d1:
        soup = verts[faces].reshape(-1, 3)
        soup_faces = torch.arange(3 * n_faces, device=verts.device).reshape(n_faces, 3)
        probes = verts.new_zeros(6, n_faces, 3, 3)
        for k in range(6):  # probe k moves corner 1 + k // 3 along axis k % 3 on every face
            probes[k, :, 1 + k // 3, k % 3] = 1
        probes = probes.reshape(6, 3 * n_faces, 3).requires_grad_(True)
        first = H2Weights(0.0, w.a1, w.b1, w.c1, w.d1, 0.0)
        with torch.enable_grad():  # path_energy([q - h/2, q + h/2]) = G_q(h, h); its gradient is 2 M h
            e = path_energy(torch.stack([soup - probes / 2, soup + probes / 2], -3), soup_faces, first).sum()
            (g,) = torch.autograd.grad(e, probes)
        blocks = g.reshape(6, n_faces, 3, 3)[:, :, 1:, :].reshape(6, n_faces, 6).transpose(0, 1) / 2
        blocks = (blocks + blocks.transpose(1, 2)) / 2  # (F, 6, 6)
        for s in range(0, n_faces, chunk):
            fc = faces[s:s + chunk]
            edges = (columns[fc[:, 1:]] - columns[fc[:, :1]]).reshape(-1, 6, p)  # (f, 6, P)
            gram += edges.reshape(-1, p).T @ torch.bmm(blocks[s:s + chunk], edges).reshape(-1, p)
    if w.a0 or w.a2:
        area = geometry.vertex_areas(verts, faces).repeat_interleave(3)  # (3N,) like columns.reshape(3N, P)
        flat = columns.reshape(3 * n, p)
        if w.a0:
            gram += w.a0 * (flat * area[:, None]).T @ flat
        if w.a2:
            cot = geometry.corner_cotangents(verts, faces)
            rows, cols, vals = [], [], []
            for k in range(3):  # edge (i, j) opposite corner k, weight cot_k
                i, j, c = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3], cot[:, k]
                rows += [i, j, i, j]
                cols += [j, i, i, j]
                vals += [-c, -c, c, c]
            lap = torch.sparse_coo_tensor(torch.stack([torch.cat(rows), torch.cat(cols)]), torch.cat(vals),
                                          (n, n), check_invariants=False).coalesce()
            lh = torch.sparse.mm(lap, columns).reshape(3 * n, p)
            inv = torch.where(area > 0, 1 / (4 * torch.where(area > 0, area, torch.ones_like(area))),
                              torch.zeros_like(area))
            gram += w.a2 * (lh * inv[:, None]).T @ lh
    return (gram + gram.T) / 2
