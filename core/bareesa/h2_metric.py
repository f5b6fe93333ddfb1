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


def _quadratic(verts, faces, h, w, compute=None):
    """G_q(h, h) for verts, h (..., N, 3) -> (...), in closed form per face.

    The form of ``_features`` written out with 2 x 2 algebra on per-component
    (..., F) arrays (no small matrix products; several times faster, it is the
    inner loop of every latent solve). With e1, e2 the face edges, d1, d2 those of
    h, g the face metric and D = det g = |c|^2, c = e1 x e2:
      g^-1 dg = adj(g) S / D with S = [[2 e1.d1, e1.d2 + e2.d1], [., 2 e2.d2]],
      xi = s J with s = e2.d1 - e1.d2, so tr(g^-1 xi g^-1 xi^T) = 2 s^2 / D,
      |dn|^2 = (|dc|^2 - (c.dc)^2 / D) / D with dc = d1 x e2 + e1 x d2,
      cot of the angle at a corner = (dot of its two edges) / sqrt(D).
    compute: the dtype of the per-face algebra (default verts'): the edges are taken in verts' dtype
    and the sums accumulated in it. Differentiated by ``_quadratic_gradient``, written out.
    """
    compute = verts.dtype if compute is None else compute
    if torch.is_grad_enabled() and (verts.requires_grad or h.requires_grad):
        verts, h = torch.broadcast_tensors(verts, h)
        return _QuadraticForm.apply(verts, h, faces, w, compute)
    return _robust_parts(verts, faces, h, w, compute)[0]


#: ``compute`` algebra is redone in verts' dtype when no face has det = |e1 x e2|^2 above this (faces of
#: ~1e-5 units and smaller, where float32 products of edges underflow)
SMALL_FACES_DET = 1e-20


def _robust_parts(verts, faces, h, w, compute):
    """``_quadratic_parts`` in ``compute``, or in verts' dtype where that is not finite (a face crushed
    by a line search's trial step: its det underflows float32) or every face is tiny (SMALL_FACES_DET)
    -> (total, parts, dtype used)."""
    total, parts = _quadratic_parts(verts, faces, h, w, compute)
    if compute != verts.dtype and (not bool(torch.isfinite(total).all())
                                   or float(torch.where(parts["valid"], parts["det"], 0.0).max()) < SMALL_FACES_DET):
        compute = verts.dtype
        total, parts = _quadratic_parts(verts, faces, h, w, compute)
    return total, parts, compute


def _quadratic_parts(verts, faces, h, w, compute):
    """``_quadratic``'s value (...) and the per-face and per-vertex parts its gradient reuses (a dict)."""
    corners = faces.T.reshape(-1)  # (3F,) corner-major
    n_faces = faces.shape[0]
    p = _corner_components(verts, corners, n_faces)
    v = _corner_components(h, corners, n_faces)
    sub = lambda x, y: tuple(a - b for a, b in zip(x, y))  # noqa: E731
    e1, e2, d1, d2 = sub(p[1], p[0]), sub(p[2], p[0]), sub(v[1], v[0]), sub(v[2], v[0])
    c = _cross3(e1, e2)
    det = _dot3(c, c)
    # which faces are degenerate is decided in verts' dtype: a face valid there whose det underflows
    # ``compute`` makes the sums non-finite, and ``_robust_parts`` redoes them in verts' dtype
    valid = det > torch.finfo(verts.dtype).tiny * 1e6
    cast = lambda x: tuple(a.to(compute) for a in x)  # noqa: E731
    e1, e2, d1, d2, c, det = cast(e1), cast(e2), cast(d1), cast(d2), cast(c), det.to(compute)
    det = torch.where(valid, det, torch.ones_like(det))
    root = torch.sqrt(det)
    area = torch.where(valid, root / 2, torch.zeros_like(det))  # (..., F)
    g11, g12, g22 = _dot3(e1, e1), _dot3(e1, e2), _dot3(e2, e2)
    parts = dict(e1=e1, e2=e2, d1=d1, d2=d2, c=c, det=det, valid=valid, root=root, area=area,
                 g11=g11, g12=g12, g22=g22)
    per_face = torch.zeros_like(det)
    if w.a1 or w.b1 or w.d1:
        m11, m12, m21, m22 = _dot3(e1, d1), _dot3(e1, d2), _dot3(e2, d1), _dot3(e2, d2)
        s11, s12, s22 = 2 * m11, m12 + m21, 2 * m22
        a, b = g22 * s11 - g12 * s12, g22 * s12 - g12 * s22  # adj(g) S = [[a, b], [c_, d]]
        c_, d = g11 * s12 - g12 * s11, g11 * s22 - g12 * s12
        beta = (w.b1 - w.a1) / 8
        # divided by det twice, never by det^2 or det^3 (their range ends at faces of ~1 mm in float32)
        first = (w.a1 * (a * a + 2 * b * c_ + d * d) + beta * (a + d) ** 2) / det / det
        per_face = per_face + first + w.d1 * 2 * (m21 - m12) ** 2 / det
        parts.update(m12=m12, m21=m21, s11=s11, s12=s12, s22=s22, a=a, b=b, c_=c_, d=d, first=first)
    if w.c1:
        dc = tuple(x + y for x, y in zip(_cross3(d1, e2), _cross3(e1, d2)))
        per_face = per_face + w.c1 * (_dot3(dc, dc) - _dot3(c, dc) ** 2 / det) / det
        parts.update(dc=dc)
    parts.update(per_face=per_face)
    total = (area * per_face).sum(-1, dtype=verts.dtype)
    if w.a0 or w.a2:
        vertex_area = area.new_zeros(area.shape[:-1] + verts.shape[-2:-1]).index_add(
            -1, corners, (area / 3).repeat((1,) * (area.dim() - 1) + (3,)))
        parts.update(vertex_area=vertex_area)
    if w.a0:
        total = total + w.a0 * (vertex_area.to(h.dtype) * _dot(h, h)).sum(-1)
    if w.a2:
        inv_root = torch.where(valid, 1 / root, torch.zeros_like(root))
        cot = (g12 * inv_root, (g11 - g12) * inv_root, (g22 - g12) * inv_root)  # angle at corner 0, 1, 2
        # (L h) at corner j: cot_{j+2} (h_j - h_{j+1}) + cot_{j+1} (h_j - h_{j+2}), summed over faces; in
        # the edges d1 = h_1 - h_0, d2 = h_2 - h_0:
        lap = torch.stack([torch.cat([-cot[2] * d1[k] - cot[1] * d2[k],
                                      cot[0] * (d1[k] - d2[k]) + cot[2] * d1[k],
                                      cot[1] * d2[k] + cot[0] * (d2[k] - d1[k])], -1)
                           for k in range(3)], -2)  # (..., 3, 3F) corner-major like ``corners``
        lap = lap.new_zeros(lap.shape[:-1] + h.shape[-2:-1]).index_add(-1, corners, lap)  # (..., 3, N)
        inv = torch.where(vertex_area > 0, 1 / (4 * torch.where(vertex_area > 0, vertex_area,
                                                                    torch.ones_like(vertex_area))),
                          torch.zeros_like(vertex_area))
        total = total + w.a2 * (inv * (lap * lap).sum(-2)).sum(-1, dtype=verts.dtype)
        parts.update(inv_root=inv_root, cot=cot, lap=lap, inv=inv)
    return total, parts


def _quadratic_gradient(parts, h, faces, w, grad):
    """The gradient of ``_quadratic`` in verts and h (..., N, 3) from its parts, times grad (...).

    Reverse mode written out on the per-component (..., F) arrays of ``_quadratic_parts``: the
    vertex terms give the gradients of the vertex areas and of the Laplacian, which flow back to
    the faces' areas and cotangents; every per-face quantity then back to the edges e1, e2, d1, d2
    (the cotangent weights and the areas through the face metric and c), and the edges to the
    vertices."""
    P = parts
    n_faces = faces.shape[0]
    e1, e2, d1, d2, c, det, root, area = (P[k] for k in ("e1", "e2", "d1", "d2", "c", "det", "root", "area"))
    zero = torch.zeros_like(det)
    g_area = P["per_face"]
    g_per_face = area
    g_det, g_root, g11_g, g12_g, g22_g = zero, zero, zero, zero, zero
    ge1, ge2, gd1, gd2 = [zero] * 3, [zero] * 3, [zero] * 3, [zero] * 3
    add3 = lambda x, y: tuple(a + b for a, b in zip(x, y))  # noqa: E731
    scale3 = lambda x, s: tuple(a * s for a in x)  # noqa: E731
    corners = faces.T.reshape(-1)
    gather = lambda t: t[..., corners].unflatten(-1, (3, n_faces))  # (..., N) -> (..., 3, F)  # noqa: E731
    g_h = None
    if w.a0 or w.a2:
        g_va = w.a0 * _dot(h, h).to(det.dtype) if w.a0 else 0.0
        if w.a0:
            g_h = 2 * w.a0 * P["vertex_area"].to(h.dtype)[..., None] * h
        if w.a2:
            inv, lap, cot = P["inv"], P["lap"], P["cot"]
            g_va = g_va - 4 * w.a2 * inv * inv * (lap * lap).sum(-2)
            g_lap = gather(2 * w.a2 * inv[..., None, :] * lap)  # (..., 3 axes, 3 corners, F)
            # the edge opposite corner k joins k+1 and k+2 with weight cot_k: w_k to corner k+1, -w_k to k+2
            diff = [g_lap[..., :, (k + 1) % 3, :] - g_lap[..., :, (k + 2) % 3, :] for k in range(3)]  # (..., 3, F)
            edge = [tuple(x - y for x, y in zip(d1, d2)), d2, scale3(d1, -1.0)]  # h_{k+1} - h_{k+2}
            g_cot = [sum(diff[k][..., axis, :] * edge[k][axis] for axis in range(3)) for k in range(3)]
            flow = [diff[k] * cot[k][..., None, :] for k in range(3)]
            gd1 = add3(gd1, (flow[0] - flow[2]).unbind(-2))  # corner 1 gets w_0 - w_2, corner 2 w_1 - w_0
            gd2 = add3(gd2, (flow[1] - flow[0]).unbind(-2))
            inv_root = P["inv_root"]
            g11_g = g11_g + g_cot[1] * inv_root
            g22_g = g22_g + g_cot[2] * inv_root
            g12_g = g12_g + (g_cot[0] - g_cot[1] - g_cot[2]) * inv_root
            g_root = g_root - (g_cot[0] * cot[0] + g_cot[1] * cot[1] + g_cot[2] * cot[2]) * inv_root
        g_area = g_area + gather(g_va).sum(-2) / 3
    g_root = g_root + torch.where(P["valid"], g_area / 2, zero)
    if w.a1 or w.b1 or w.d1:
        m12, m21, s11, s12, s22 = (P[k] for k in ("m12", "m21", "s11", "s12", "s22"))
        a, b, c_, d = P["a"], P["b"], P["c_"], P["d"]
        g11, g12, g22 = P["g11"], P["g12"], P["g22"]
        beta = (w.b1 - w.a1) / 8
        q = g_per_face / det / det
        trace = 2 * beta * (a + d)
        ga, gd = q * (2 * w.a1 * a + trace), q * (2 * w.a1 * d + trace)
        gb, gc_ = q * (2 * w.a1 * c_), q * (2 * w.a1 * b)
        g_det = g_det - 2 * g_per_face * P["first"] / det
        s = m21 - m12
        g_s = g_per_face * 4 * w.d1 * s / det
        g_det = g_det - g_per_face * 2 * w.d1 * (s * s / det) / det
        gs11, gs22 = ga * g22 - gc_ * g12, gd * g11 - gb * g12
        gs12 = gb * g22 + gc_ * g11 - (ga + gd) * g12
        g22_g = g22_g + ga * s11 + gb * s12
        g11_g = g11_g + gc_ * s12 + gd * s22
        g12_g = g12_g - ga * s12 - gb * s22 - gc_ * s11 - gd * s12
        gm11, gm22 = 2 * gs11, 2 * gs22
        gm12, gm21 = gs12 - g_s, gs12 + g_s
        ge1 = add3(ge1, add3(scale3(d1, gm11), scale3(d2, gm12)))
        ge2 = add3(ge2, add3(scale3(d1, gm21), scale3(d2, gm22)))
        gd1 = add3(gd1, add3(scale3(e1, gm11), scale3(e2, gm21)))
        gd2 = add3(gd2, add3(scale3(e1, gm12), scale3(e2, gm22)))
    g_c = [zero] * 3
    if w.c1:
        dc = P["dc"]
        cdc, dcdc = _dot3(c, dc), _dot3(dc, dc)
        k = g_per_face * w.c1 / det
        g_dc = add3(scale3(dc, 2 * k), scale3(c, -2 * k * cdc / det))
        g_c = scale3(dc, -2 * k * cdc / det)
        g_det = g_det + k * (-dcdc + 2 * cdc * cdc / det) / det
        gd1 = add3(gd1, _cross3(e2, g_dc))
        ge2 = add3(ge2, _cross3(g_dc, d1))
        ge1 = add3(ge1, _cross3(d2, g_dc))
        gd2 = add3(gd2, _cross3(g_dc, e1))
    g_det = torch.where(P["valid"], g_det + g_root / (2 * root), zero)
    g_c = add3(g_c, scale3(c, 2 * g_det))
    ge1 = add3(ge1, add3(_cross3(e2, g_c), add3(scale3(e1, 2 * g11_g), scale3(e2, g12_g))))
    ge2 = add3(ge2, add3(_cross3(g_c, e1), add3(scale3(e2, 2 * g22_g), scale3(e1, g12_g))))

    def to_vertices(g1, g2):  # edge gradients (3 x (..., F)) -> vertex gradients (..., N, 3) times grad
        g1, g2 = torch.stack(g1, -2), torch.stack(g2, -2)  # (..., 3, F)
        out = g1.new_zeros(g1.shape[:-1] + h.shape[-2:-1])
        out.index_add_(-1, faces[:, 1], g1).index_add_(-1, faces[:, 2], g2).index_add_(-1, faces[:, 0], -(g1 + g2))
        return out.transpose(-1, -2).to(h.dtype) * grad[..., None, None]

    g_verts, g_field = to_vertices(ge1, ge2), to_vertices(gd1, gd2)
    if g_h is not None:
        g_field = g_field + grad[..., None, None] * g_h
    return g_verts, g_field


class _QuadraticForm(torch.autograd.Function):
    """``_quadratic`` with its gradient written out (``_quadratic_gradient``); a second derivative
    (create_graph, e.g. the shooting step's Jacobian) goes through autograd on the closed form."""

    @staticmethod
    def forward(ctx, verts, h, faces, w, compute):
        total, parts, compute = _robust_parts(verts, faces, h, w, compute)
        ctx.save_for_backward(verts, h, faces)
        ctx.parts, ctx.w, ctx.compute = parts, w, compute
        return total

    @staticmethod
    def backward(ctx, grad):
        verts, h, faces = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: a differentiable gradient
            with torch.enable_grad():
                total = _quadratic_parts(verts, faces, h, ctx.w, ctx.compute)[0]
                return (*torch.autograd.grad(total, (verts, h), grad, create_graph=True, allow_unused=True),
                        None, None, None)
        grads = _quadratic_gradient(ctx.parts, h, faces, ctx.w, grad)
        if ctx.compute != verts.dtype and not all(bool(torch.isfinite(g).all()) for g in grads):
            # as in the forward: a crushed face's terms overflow float32; its own dtype has the range
            parts = _quadratic_parts(verts, faces, h, ctx.w, verts.dtype)[1]
            grads = _quadratic_gradient(parts, h, faces, ctx.w, grad)
        return (*grads, None, None, None)


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


def path_energy(path, faces, weights=PRESETS["body"], duration=1.0, per_step=False, compute_dtype=None):
    """Discrete path energy of a path of meshes: path (..., T, N, 3) -> (...).

    E = sum_k G_{m_k}(q_{k+1} - q_k, q_{k+1} - q_k) / dt,  dt = duration / (T - 1),
    m_k the midpoint (q_k + q_{k+1}) / 2: the Riemann sum of int_0^duration G(q', q') dt.
    With per_step=True returns the (..., T - 1) terms of the sum instead. compute_dtype: the dtype
    of the per-face algebra (default the path's; the face edges are taken and the sums accumulated
    in the path's dtype, so float32 algebra on a float64 path loses ~1e-6 relative, not the
    coordinates' digits).
    """
    w = H2Weights.parse(weights)
    _check(path, faces)
    if path.dim() < 3 or path.shape[-3] < 2:
        raise InputError(f"a path needs at least two meshes, got shape {tuple(path.shape)}")
    steps = path[..., 1:, :, :] - path[..., :-1, :, :]
    mids = (path[..., 1:, :, :] + path[..., :-1, :, :]) / 2
    dt = duration / (path.shape[-3] - 1)
    terms = _quadratic(mids, faces, steps, w, compute_dtype) / dt
    return terms if per_step else terms.sum(-1)


def _first_order_blocks(verts, faces, w):
    """The first-order terms of G_q face by face: (N, 3), (F, 3) -> (F, 6, 6) symmetric blocks M_f with
    G_q(h, h) = sum_f e_f^T M_f e_f + (zeroth and second order), e_f = (h_1 - h_0, h_2 - h_0) (6,)."""
    n_faces = faces.shape[0]
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
    return (blocks + blocks.transpose(1, 2)) / 2


def _cotan_matrix(verts, faces):
    """The un-normalised cotangent Laplacian L (``geometry.cotan_laplacian``) as a torch sparse (N, N)."""
    n = verts.shape[0]
    cot = geometry.corner_cotangents(verts, faces)
    rows, cols, vals = [], [], []
    for k in range(3):  # edge (i, j) opposite corner k, weight cot_k
        i, j, c = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3], cot[:, k]
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        vals += [-c, -c, c, c]
    return torch.sparse_coo_tensor(torch.stack([torch.cat(rows), torch.cat(cols)]), torch.cat(vals),
                                   (n, n), check_invariants=False).coalesce()


def _inverse_quarter_areas(area):
    """1 / (4 A_v) where A_v > 0, else 0."""
    return torch.where(area > 0, 1 / (4 * torch.where(area > 0, area, torch.ones_like(area))), torch.zeros_like(area))


def sparse_metric(verts, faces, weights=PRESETS["body"]):
    """G_q as a sparse matrix on vertex fields flattened vertex-major (h.reshape(-1)): (N, 3), (F, 3) ->
    scipy.sparse csr (3N, 3N) float64 with h^T G h = G_q(h, h). Not differentiable in verts; what a
    solver over free vertex displacements preconditions with (``registration.detail``)."""
    import scipy.sparse as sp

    w = H2Weights.parse(weights)
    verts = verts.detach().to(torch.float64)
    faces = faces.long()
    n = verts.shape[0]
    out = sp.csr_matrix((3 * n, 3 * n))
    if w.a1 or w.b1 or w.c1 or w.d1:
        blocks = _first_order_blocks(verts, faces, w)  # (F, 6, 6) on (h1 - h0, h2 - h0)
        select = torch.zeros(6, 9, dtype=torch.float64)  # corner coordinates (3 corners x 3 axes) -> edges
        for e in range(2):
            for a in range(3):
                select[3 * e + a, 3 * (e + 1) + a], select[3 * e + a, a] = 1.0, -1.0
        local = select.T @ blocks @ select  # (F, 9, 9)
        index = (3 * faces[:, :, None] + torch.arange(3)).reshape(-1, 9)  # (F, 9) global rows
        rows = index[:, :, None].expand(-1, 9, 9).reshape(-1).numpy()
        cols = index[:, None, :].expand(-1, 9, 9).reshape(-1).numpy()
        out = out + sp.csr_matrix((local.reshape(-1).numpy(), (rows, cols)), shape=(3 * n, 3 * n))
    if w.a0 or w.a2:
        area = geometry.vertex_areas(verts, faces)
        eye = sp.identity(3, format="csr")
        if w.a0:
            out = out + w.a0 * sp.kron(sp.diags(area.numpy()), eye, format="csr")
        if w.a2:
            lap = _cotan_matrix(verts, faces)
            idx = lap.indices().numpy()
            lap = sp.csr_matrix((lap.values().numpy(), (idx[0], idx[1])), shape=(n, n))
            out = out + w.a2 * sp.kron(lap.T @ sp.diags(_inverse_quarter_areas(area).numpy()) @ lap, eye, format="csr")
    return ((out + out.T) / 2).tocsr()


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
        blocks = _first_order_blocks(verts, faces, w)
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
            lh = torch.sparse.mm(_cotan_matrix(verts, faces), columns).reshape(3 * n, p)
            inv = _inverse_quarter_areas(area)
            gram += w.a2 * (lh * inv[:, None]).T @ lh
    return (gram + gram.T) / 2
