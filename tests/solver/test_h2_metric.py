import math

import numpy as np
import pytest
import torch

from bareesa import h2_metric as H
from bareesa import synthetic
from bareesa.errors import InputError

BODY = H.PRESETS["body"]
FACE = H.PRESETS["face"]


def _mesh(subdivisions=2, seed=0, dtype=torch.float64):
    v, f = synthetic.blob_mesh(subdivisions, seed=seed)
    return torch.tensor(v, dtype=dtype), torch.tensor(f)


def _fields(p, verts, seed=0, scale=0.1):
    g = torch.Generator().manual_seed(seed)
    return scale * torch.randn((p,) + verts.shape, generator=g, dtype=verts.dtype)


def _smooth_path(verts, t=4, seed=0):
    """A curved path of meshes (t, N, 3) through smooth deformations."""
    rng = np.random.default_rng(seed)
    a = torch.tensor(rng.normal(size=(3, 3)) * 0.2, dtype=verts.dtype)
    b = torch.tensor(rng.normal(size=(3, 3)) * 0.2, dtype=verts.dtype)
    s = torch.linspace(0, 1, t, dtype=verts.dtype)[:, None, None]
    return verts + s * (verts @ a.T) + s**2 * torch.sin(verts @ b.T)


def test_metric_matrix_matches_pairwise_inner_products():
    v, f = _mesh()
    fields = _fields(4, v)
    gram = H.metric_matrix(v, f, fields, BODY)
    direct = torch.stack([torch.stack([H.inner_product(v, f, fields[i], fields[j], BODY) for j in range(4)])
                          for i in range(4)])
    assert torch.allclose(gram, direct, rtol=1e-12, atol=0)


def test_metric_matrix_symmetric_positive_definite_for_independent_fields():
    v, f = _mesh()
    for w in (BODY, FACE, H.H2Weights(0, 1, 1, 1, 1, 0)):
        gram = H.metric_matrix(v, f, _fields(6, v, seed=3), w)
        assert torch.equal(gram, gram.T)
        assert torch.linalg.eigvalsh(gram).min() > 0


def test_inner_product_is_symmetric_and_bilinear():
    v, f = _mesh()
    h, k, m = _fields(3, v, seed=1)
    assert torch.isclose(H.inner_product(v, f, h, k, FACE), H.inner_product(v, f, k, h, FACE), rtol=1e-12)
    lhs = H.inner_product(v, f, 2 * h - 3 * m, k, FACE)
    rhs = 2 * H.inner_product(v, f, h, k, FACE) - 3 * H.inner_product(v, f, m, k, FACE)
    assert torch.isclose(lhs, rhs, rtol=1e-10)


def test_squared_norm_is_quadratic_in_speed():
    v, f = _mesh()
    h = _fields(1, v)[0]
    for s in (0.5, 3.0):
        assert torch.isclose(H.squared_norm(v, f, s * h, BODY), s**2 * H.squared_norm(v, f, h, BODY), rtol=1e-12)


def test_translation_field_has_zero_first_order_and_laplacian_terms():
    v, f = _mesh()
    t = torch.tensor([0.3, -1.0, 2.0], dtype=v.dtype).expand_as(v)
    scale = H.squared_norm(v, f, _fields(1, v)[0], H.H2Weights(0, 1, 1, 1, 1, 1))
    assert H.squared_norm(v, f, t, H.H2Weights(0, 1, 1, 1, 1, 0)).abs() < 1e-12 * scale
    assert H.squared_norm(v, f, t, H.H2Weights(0, 0, 0, 0, 0, 1)).abs() < 1e-12 * scale
    # the L2 term is area * |t|^2 exactly
    area = torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]).norm(dim=1).sum() / 2
    l2 = H.squared_norm(v, f, t, H.H2Weights(2, 0, 0, 0, 0, 0))
    assert torch.isclose(l2, 2 * area * (t[0] ** 2).sum(), rtol=1e-12)


def test_infinitesimal_rotation_does_not_change_metric_or_area():
    v, f = _mesh()
    omega = torch.tensor([[0, -1, 0.5], [1, 0, -0.2], [-0.5, 0.2, 0]], dtype=v.dtype)
    r = v @ omega.T
    ref = H.squared_norm(v, f, r, H.H2Weights(0, 0, 0, 1, 0, 0))
    assert ref > 0  # normals rotate
    assert H.squared_norm(v, f, r, H.H2Weights(0, 1, 1, 0, 0, 0)).abs() < 1e-12 * ref
    assert H.squared_norm(v, f, r, H.H2Weights(0, 1, 9, 0, 0, 0)).abs() < 1e-12 * ref


def test_scaling_field_on_sphere_matches_continuous_values():
    """h = x on the unit sphere: g^-1 dg = 2 I, dn = 0, xi = 0, Delta x = -2 n."""
    v, f = synthetic.icosphere(5)
    v, f = torch.tensor(v), torch.tensor(f)
    area = 4 * math.pi
    # a1 tr(A^2) + (b1 - a1)/8 tr(A)^2 = 8 a1 + 2 (b1 - a1) = 6 a1 + 2 b1 per unit area
    for a1, b1 in ((1.0, 1.0), (1.0, 9.0), (2.0, 0.0)):
        val = H.squared_norm(v, f, v, H.H2Weights(0, a1, b1, 0, 0, 0))
        assert val.item() == pytest.approx((6 * a1 + 2 * b1) * area, rel=2e-3)
    assert H.squared_norm(v, f, v, H.H2Weights(0, 0, 0, 1, 1, 0)).abs() < 1e-10
    lap = H.squared_norm(v, f, v, H.H2Weights(0, 0, 0, 0, 0, 1))  # int |2 n|^2 = 16 pi
    assert lap.item() == pytest.approx(16 * math.pi, rel=1e-2)


def test_constant_path_has_zero_energy():
    v, f = _mesh()
    path = v.expand(5, -1, -1)
    assert H.path_energy(path, f, BODY) == 0


def test_path_energy_invariant_under_rigid_motion_of_whole_path():
    v, f = _mesh()
    path = _smooth_path(v)
    rot = torch.tensor(synthetic.random_rotation(7), dtype=v.dtype)
    moved = path @ rot.T + torch.tensor([1.0, -2.0, 0.5], dtype=v.dtype)
    for w in (BODY, FACE):
        e0, e1 = H.path_energy(path, f, w), H.path_energy(moved, f, w)
        assert torch.isclose(e0, e1, rtol=1e-10)


def test_path_energy_invariant_under_vertex_and_face_permutation():
    v, f = _mesh()
    path = _smooth_path(v)
    rng = np.random.default_rng(1)
    perm = torch.tensor(rng.permutation(v.shape[0]))
    inverse = torch.argsort(perm)
    faces = inverse[f][torch.tensor(rng.permutation(f.shape[0]))]
    faces = faces.roll(1, dims=1)  # also cycle the corners of every face
    e0, e1 = H.path_energy(path, f, BODY), H.path_energy(path[:, perm], faces, BODY)
    assert torch.isclose(e0, e1, rtol=1e-10)


def test_path_energy_scales_quadratically_with_speed():
    v, f = _mesh()
    path = _smooth_path(v)
    e = H.path_energy(path, f, BODY)
    # the same path traversed in half the time: speed x2, energy x2 (= 4 x speed^2 over half the time)
    assert torch.isclose(H.path_energy(path, f, BODY, duration=0.5), 2 * e, rtol=1e-12)
    # a translation path at speed s: every step is the same rigid step, energy exactly s^2 * E_1
    t = torch.tensor([0.2, 0.1, -0.3], dtype=v.dtype)
    steps = torch.arange(4, dtype=v.dtype)[:, None, None]
    e1 = H.path_energy(v + steps * t, f, BODY)
    assert e1 > 0
    assert torch.isclose(H.path_energy(v + steps * 3 * t, f, BODY), 9 * e1, rtol=1e-12)


def test_path_energy_per_step_sums_to_total_and_uses_midpoints():
    v, f = _mesh()
    path = _smooth_path(v, t=3)
    steps = H.path_energy(path, f, FACE, per_step=True)
    assert steps.shape == (2,)
    assert torch.isclose(steps.sum(), H.path_energy(path, f, FACE), rtol=1e-12)
    mid = (path[0] + path[1]) / 2
    assert torch.isclose(steps[0], 2 * H.squared_norm(mid, f, path[1] - path[0], FACE), rtol=1e-12)


@pytest.mark.parametrize("weights", [(1, 0, 0, 0, 0, 0), (0, 1, 0, 0, 0, 0), (0, 0, 5, 0, 0, 0), (0, 0, 0, 1, 0, 0),
                                     (0, 0, 0, 0, 1, 0), (0, 0, 0, 0, 0, 1), (1, 1000, 100, 1, 1, 1)])
def test_closed_form_path_energy_matches_the_feature_form_term_by_term(weights):
    # path_energy uses a closed per-face formula; squared_norm the feature vectors of the Gram matrix
    v, f = _mesh(seed=3)
    path = _smooth_path(v, t=3, seed=2)
    w = H.H2Weights(*weights)
    steps = H.path_energy(path, f, w, per_step=True)
    for k in range(2):
        mid, step = (path[k] + path[k + 1]) / 2, path[k + 1] - path[k]
        assert torch.isclose(steps[k], 2 * H.squared_norm(mid, f, step, w), rtol=1e-11)


def test_path_energy_is_batched():
    v, f = _mesh()
    paths = torch.stack([_smooth_path(v, seed=0), _smooth_path(v, seed=1)])
    batched = H.path_energy(paths, f, BODY)
    assert batched.shape == (2,)
    for i in range(2):
        assert torch.isclose(batched[i], H.path_energy(paths[i], f, BODY), rtol=1e-12)


def test_path_energy_gradient_matches_finite_differences():
    v, f = _mesh(subdivisions=1)
    path = _smooth_path(v, t=3).clone().requires_grad_(True)
    w = H.H2Weights(1, 10, 5, 2, 1, 1)
    assert torch.autograd.gradcheck(lambda p: H.path_energy(p, f, w), (path,), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("weights", [(1, 0, 0, 0, 0, 0), (0, 1, 0, 0, 0, 0), (0, 0, 5, 0, 0, 0), (0, 0, 0, 1, 0, 0),
                                     (0, 0, 0, 0, 1, 0), (0, 0, 0, 0, 0, 1), (1, 1000, 100, 1, 1, 1)])
def test_written_out_gradient_matches_autograd_of_the_closed_form_term_by_term(weights):
    # path_energy's backward is written out by hand; autograd through the same closed form is the reference
    v, f = _mesh(seed=4)
    v = v.clone()
    v[f[0, 1]] = v[f[0, 0]]  # a degenerate face on the way
    w = H.H2Weights(*weights)
    paths = torch.stack([_smooth_path(v, t=3, seed=1), _smooth_path(v, t=3, seed=2)])
    steps, mids = paths[:, 1:] - paths[:, :-1], (paths[:, 1:] + paths[:, :-1]) / 2
    upstream = torch.tensor([[0.3, -1.2], [2.0, 0.7]], dtype=v.dtype)
    grads = []
    for closed in (H._quadratic, lambda q, f, h, w: H._quadratic_parts(q, f, h, w, q.dtype)[0]):
        q, h = mids.clone().requires_grad_(True), steps.clone().requires_grad_(True)
        grads.append(torch.autograd.grad((closed(q, f, h, w) * upstream).sum(), (q, h)))
    for written, reference in zip(*grads):
        assert torch.allclose(written, reference, rtol=1e-10, atol=1e-12 * reference.abs().max())


def test_path_energy_has_a_second_derivative():
    # the shooting step differentiates the energy's gradient (create_graph)
    v, f = _mesh(subdivisions=1)
    path = _smooth_path(v, t=3).clone().requires_grad_(True)
    w = H.H2Weights(1, 10, 5, 2, 1, 1)
    assert torch.autograd.gradgradcheck(lambda p: H.path_energy(p, f, w), (path,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_float32_algebra_on_a_float64_path_stays_close_to_float64():
    v, f = _mesh(subdivisions=3)
    path = (_smooth_path(v, t=5) + 50.0).requires_grad_(True)  # far off the origin: edges taken in float64
    e64 = H.path_energy(path, f, BODY)
    (g64,) = torch.autograd.grad(e64, path)
    e32 = H.path_energy(path, f, BODY, compute_dtype=torch.float32)
    (g32,) = torch.autograd.grad(e32, path)
    assert e32.dtype == g32.dtype == torch.float64
    assert e32.item() == pytest.approx(e64.item(), rel=1e-6)
    assert float((g32 - g64).norm() / g64.norm()) < 1e-5
    # float32 coordinates instead lose the edges' digits
    e_coords = H.path_energy(path.detach().float(), f, BODY).double()
    assert abs(e_coords.item() - e64.item()) > 10 * abs(e32.item() - e64.item())


def test_float32_algebra_falls_back_to_float64_where_a_crushed_face_or_tiny_faces_overflow_it():
    # a line search's trial step can crush a face: its det underflows float32 (not float64) and the
    # gradient is not finite there; on a mesh of tiny faces the products of edges underflow. path_energy
    # then redoes the algebra in the path's own dtype
    v, f = _mesh()
    rng = np.random.default_rng(0)
    crushed = v.clone()
    a, b, c = f[0]
    crushed[c] = crushed[a] + 0.3 * (crushed[b] - crushed[a]) + 1e-24 * (crushed[c] - crushed[a])
    for verts in (crushed, v * 1e-6):
        step = 1e-3 * float(verts.abs().max()) * torch.tensor(rng.normal(size=v.shape))
        step[f[0]] = 0.0  # the crushed face stays crushed at the midpoint
        path = torch.stack([verts, verts + step]).requires_grad_(True)
        mids, steps = (path[1:] + path[:-1]).detach() / 2, (path[1:] - path[:-1]).detach()
        total, parts = H._quadratic_parts(mids, f, steps, BODY, torch.float32)
        raw = H._quadratic_gradient(parts, steps, f, BODY, torch.ones(1, dtype=v.dtype))
        finite = bool(torch.isfinite(total).all()) and all(bool(torch.isfinite(g).all()) for g in raw)
        assert not finite or float(parts["det"].max()) < H.SMALL_FACES_DET  # the hazard is real here
        e64 = H.path_energy(path, f, BODY)
        (g64,) = torch.autograd.grad(e64, path)
        e32 = H.path_energy(path, f, BODY, compute_dtype=torch.float32)
        (g32,) = torch.autograd.grad(e32, path)
        assert torch.isfinite(g32).all()
        assert e32.item() == pytest.approx(e64.item(), rel=1e-6)
        assert torch.allclose(g32, g64, rtol=1e-6, atol=1e-6 * float(g64.abs().max()))


def test_metric_matrix_gradient_matches_finite_differences():
    v, f = _mesh(subdivisions=1)
    fields = _fields(3, v)
    w = H.H2Weights(1, 10, 5, 2, 1, 1)
    v = v.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: H.metric_matrix(x, f, fields, w), (v,), eps=1e-6, atol=1e-6,
                                    rtol=1e-5)


def test_float32_agrees_with_float64():
    v, f = _mesh()
    path = _smooth_path(v)
    e64 = H.path_energy(path, f, BODY)
    e32 = H.path_energy(path.float(), f, BODY)
    assert e32.dtype == torch.float32
    assert e32.item() == pytest.approx(e64.item(), rel=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_agrees_with_cpu():
    v, f = _mesh()
    path = _smooth_path(v)
    e = H.path_energy(path.cuda(), f.cuda(), BODY)
    assert e.device.type == "cuda"
    assert e.item() == pytest.approx(H.path_energy(path, f, BODY).item(), rel=1e-10)


def test_degenerate_face_gives_finite_energy():
    v, f = _mesh()
    v = v.clone()
    v[f[0, 1]] = v[f[0, 0]]  # collapse an edge of face 0
    path = _smooth_path(v)
    assert torch.isfinite(H.path_energy(path, f, BODY))


def test_bad_inputs_raise_clear_errors():
    v, f = _mesh()
    with pytest.raises(InputError, match="does not match"):
        H.squared_norm(v, f, v[:-1], BODY)
    with pytest.raises(InputError, match="at least two meshes"):
        H.path_energy(v[None], f, BODY)
    with pytest.raises(InputError, match="positive metric"):
        H.H2Weights(1, -1, 0, 0, 0, 0)
    with pytest.raises(InputError, match="six"):
        H.H2Weights.parse("1,2,3")
    assert H.H2Weights.parse("body") == BODY
    assert H.H2Weights.parse("1,10,10,10,1,1") == FACE
