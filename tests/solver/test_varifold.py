"""Tests of bareesa.varifold: the three backends agree, metric properties, invariances, options."""

import numpy as np
import pytest
import torch

from bareesa import varifold as V
from bareesa.errors import InputError
from bareesa.synthetic import blob_mesh, random_rotation
from bareesa.varifold import VarifoldLoss, choose_backend, varifold_distance

SIGMA = 0.1          # blobs have diameter ~2-3: truncation removes most pairs at this scale
DT = torch.float64


def mesh(subdivisions=3, seed=0, requires_grad=False):
    v, f = blob_mesh(subdivisions, seed=seed)
    return torch.tensor(v, dtype=DT).requires_grad_(requires_grad), torch.tensor(f)


@pytest.fixture(scope="module")
def keops_ok():
    """Skip when pykeops is missing or cannot compile here."""
    if not V.keops_available():
        pytest.skip("pykeops is not importable")
    try:
        v, f = mesh(1)
        varifold_distance(v, f, v + 0.1, f, SIGMA, backend="keops")
    except Exception as err:  # compiler missing, etc.
        pytest.skip(f"KeOps does not compile here: {err}")
    return True


BACKENDS = ["dense", "keops", "truncated", "truncated-torch"]


@pytest.fixture
def use_backend(request, monkeypatch):
    """Returns the backend name to pass; 'truncated-torch' = truncated without KeOps ranges."""
    def setup(name):
        if name in ("keops", "truncated"):
            request.getfixturevalue("keops_ok")
        if name == "truncated-torch":
            monkeypatch.setattr(V.kernels, "_KEOPS", False)
            return "truncated"
        return name
    return setup


def value_and_grads(backend, kernel="binet", sigma=SIGMA):
    v, f = mesh(3, 0, True)
    w, g = mesh(2, 1, True)
    loss = VarifoldLoss(w, g, sigma, kernel=kernel, backend=backend)
    d = loss(v, f)
    gv, gw = torch.autograd.grad(d, (v, w))
    return d.detach(), gv, gw, loss.stats


@pytest.mark.parametrize("kernel", ["binet", "linear", "constant"])
@pytest.mark.parametrize("backend", BACKENDS[1:])
def test_backends_agree_with_dense_values_and_gradients(backend, kernel, use_backend):
    ref = value_and_grads("dense", kernel)
    out = value_and_grads(use_backend(backend), kernel)
    assert torch.isclose(out[0], ref[0], rtol=1e-5, atol=0)
    for a, b in zip(out[1:3], ref[1:3]):
        assert float((a - b).norm() / b.norm()) < 1e-5
    if backend.startswith("truncated"):
        assert out[3]["pairs"] < 0.5 * out[3]["all_pairs"], "truncation removed no pairs"


@pytest.mark.parametrize("backend", ["truncated", "truncated-torch"])
def test_a_loss_keeps_its_ranges_while_the_source_moves_less_than_the_margin(backend, use_backend, monkeypatch):
    # a source moved by half the margin: no new ranges, and the value and gradient a fresh loss (new ranges)
    # gives; moved by twice the margin: new ranges; both within the truncation bound of dense
    from bareesa.varifold import backends

    v, f = mesh(3, 0)
    w, g = mesh(2, 1)
    cut = 2.5 * SIGMA
    margin = backends.RANGES_MARGIN * cut
    found = []
    ranges = backends.Grid.ranges
    monkeypatch.setattr(backends.Grid, "ranges", lambda *a, **k: found.append(1) or ranges(*a, **k))
    loss = VarifoldLoss(w, g, SIGMA, backend=use_backend(backend), cutoff=cut)
    loss(v, f)
    first = len(found)
    assert first == 3  # the target's self term (once), the source's self and cross terms
    direction = torch.tensor(np.random.default_rng(0).normal(size=v.shape))
    direction /= direction.norm(dim=1).max()
    A = float(V.varifold_measure(v, f)[2].sum() + V.varifold_measure(w, g)[2].sum())
    for shift, new in ((0.5 * margin, 0), (2.0 * margin, 2)):
        moved = (v + shift * direction).requires_grad_(True)
        value = loss(moved, f)
        assert len(found) - first == new
        (grad,) = torch.autograd.grad(value, moved)
        fresh_moved = moved.detach().clone().requires_grad_(True)
        fresh = VarifoldLoss(w, g, SIGMA, backend=use_backend(backend), cutoff=cut)(fresh_moved, f)
        (fresh_grad,) = torch.autograd.grad(fresh, fresh_moved)
        dense_moved = moved.detach().clone().requires_grad_(True)
        dense = varifold_distance(dense_moved, f, w, g, SIGMA, backend="dense")
        (dense_grad,) = torch.autograd.grad(dense, dense_moved)
        # kept and fresh ranges differ only in pairs beyond the cutoff: less than the truncation's own error
        assert abs(float(value - fresh)) <= 1e-5 * abs(float(fresh))
        assert float((grad - fresh_grad).norm()) <= 0.5 * float((fresh_grad - dense_grad).norm())
        assert abs(float(value - dense)) <= np.exp(-(cut / SIGMA) ** 2) * A ** 2
        first = len(found)


def test_truncation_error_within_documented_bound():
    v, f = mesh(3, 0)
    w, g = mesh(2, 1)
    exact = varifold_distance(v, f, w, g, SIGMA, backend="dense")
    cut = 2.0 * SIGMA                       # loose cutoff: tol = exp(-4)
    approx = varifold_distance(v, f, w, g, SIGMA, backend="truncated", cutoff=cut)
    A = V.varifold_measure(v, f)[2].sum() + V.varifold_measure(w, g)[2].sum()
    assert 0 < abs(float(approx - exact)) <= np.exp(-(cut / SIGMA) ** 2) * float(A) ** 2


@pytest.mark.parametrize("backend", BACKENDS)
def test_varifold_loss_equals_varifold_distance(backend, use_backend):
    name = use_backend(backend)
    v, f = mesh(3, 0)
    w, g = mesh(2, 1)
    loss = VarifoldLoss(w, g, SIGMA, backend=name)
    d1, d2 = loss(v, f), loss(v, f)           # second call uses the cached target self term
    ref = varifold_distance(v, f, w, g, SIGMA, backend=name)
    assert torch.allclose(d1, ref, rtol=1e-12) and torch.allclose(d2, ref, rtol=1e-12)


def test_distance_to_itself_is_zero_and_symmetric_positive():
    v, f = mesh(3, 0)
    w, g = mesh(2, 1)
    norm2 = varifold_distance(v, f, v + 1e3, f, SIGMA) / 2         # far apart: d^2 = |q|^2 + |q'|^2
    assert abs(float(varifold_distance(v, f, v, f, SIGMA))) < 1e-12 * float(norm2)
    d12 = varifold_distance(v, f, w, g, SIGMA)
    d21 = varifold_distance(w, g, v, f, SIGMA)
    assert torch.isclose(d12, d21, rtol=1e-12)
    assert float(d12) > 1e-3 * float(norm2)


def test_gradient_matches_finite_differences():
    v, f = blob_mesh(1, seed=0)
    w, g = blob_mesh(1, seed=1)
    v = torch.tensor(v, dtype=DT, requires_grad=True)
    w = torch.tensor(w, dtype=DT, requires_grad=True)
    f, g = torch.tensor(f), torch.tensor(g)
    fn = lambda a, b: varifold_distance(a, f, b, g, 0.5, backend="dense")  # noqa: E731
    assert torch.autograd.gradcheck(fn, (v, w), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


def test_rigid_motion_of_both_meshes_leaves_distance_unchanged():
    v, f = mesh(3, 0)
    w, g = mesh(2, 1)
    R = torch.tensor(random_rotation(3), dtype=DT)
    t = torch.tensor([0.3, -2.0, 5.0], dtype=DT)
    for backend in ("dense", "truncated-torch"):
        name = "truncated" if backend == "truncated-torch" else backend
        d = varifold_distance(v, f, w, g, SIGMA, backend=name)
        dm = varifold_distance(v @ R.T + t, f, w @ R.T + t, g, SIGMA, backend=name)
        assert torch.isclose(d, dm, rtol=1e-6), backend


def test_same_surface_at_two_resolutions_is_close():
    coarse, fine, other = mesh(4, 0), mesh(5, 0), mesh(5, 4)     # same seed = same smooth surface
    sigma = 0.3
    qf = V.varifold_measure(*fine)
    norm = float(V.varifold_inner(*qf, *qf, sigma, backend="truncated")) ** 0.5
    same = float(varifold_distance(*coarse, *fine, sigma, backend="truncated")) ** 0.5 / norm
    diff = float(varifold_distance(*coarse, *other, sigma, backend="truncated")) ** 0.5 / norm
    assert same < 1e-2
    assert diff > 30 * same


def test_linear_kernel_sees_orientation_binet_does_not():
    v, f = mesh(3, 0)
    w, g = mesh(2, 1)
    flipped = g[:, [0, 2, 1]]
    for kernel, sign in (("linear", -1.0), ("binet", 1.0)):
        qv, qw, qf = V.varifold_measure(v, f), V.varifold_measure(w, g), V.varifold_measure(w, flipped)
        a = V.varifold_inner(*qv, *qw, SIGMA, kernel=kernel)
        b = V.varifold_inner(*qv, *qf, SIGMA, kernel=kernel)
        assert torch.isclose(b, sign * a, rtol=1e-12), kernel
    assert not torch.isclose(varifold_distance(v, f, w, g, SIGMA, "linear"),
                             varifold_distance(v, f, w, flipped, SIGMA, "linear"))


@pytest.mark.parametrize("backend", ["dense", "truncated-torch"])
def test_target_weights_ones_and_zero_weighted_clutter(backend, use_backend):
    name = use_backend(backend)
    v, f = mesh(3, 0)
    w, g = mesh(3, 0)
    w = w * 1.05
    ones = torch.ones(g.shape[0], dtype=DT)
    plain = varifold_distance(v, f, w, g, SIGMA, backend=name)
    assert torch.allclose(varifold_distance(v, f, w, g, SIGMA, backend=name, target_weights=ones),
                          plain, rtol=1e-12)
    clutter_v, clutter_f = mesh(2, 3)
    scan_v = torch.cat([w, clutter_v * 0.5 + torch.tensor([3.0, 0.0, 0.0], dtype=DT)])
    scan_f = torch.cat([g, clutter_f + w.shape[0]])
    weights = torch.cat([ones, torch.zeros(clutter_f.shape[0], dtype=DT)])
    cluttered = varifold_distance(v, f, scan_v, scan_f, SIGMA, backend=name)
    ignored = varifold_distance(v, f, scan_v, scan_f, SIGMA, backend=name, target_weights=weights)
    assert torch.allclose(ignored, plain, rtol=1e-10)
    assert float(cluttered) > 1.5 * float(plain)


def test_float32_and_auto_choice():
    v, f = mesh(3, 0)
    w, g = mesh(2, 1)
    d64 = varifold_distance(v, f, w, g, SIGMA, backend="dense")
    d32 = varifold_distance(v.float(), f, w.float(), g, SIGMA, backend="dense")
    assert d32.dtype == torch.float32 and abs(float(d32) - float(d64)) < 1e-4 * float(d64)
    assert choose_backend(1000, 1000, 0.1, 2.0, "cpu") == "dense"
    assert choose_backend(14000, 55000, 0.025, 2.0, "cpu") == "truncated"
    assert choose_backend(14000, 55000, 1.0, 2.0, "cpu") in ("keops", "dense")


@pytest.mark.parametrize("kwargs, match", [
    ({"kernel": "gauss"}, "kernel"), ({"backend": "gpu"}, "backend"), ({"sigma": 0.0}, "sigma"),
    ({"sigma": -1.0}, "sigma"), ({"cutoff": -1.0}, "cutoff")])
def test_bad_options_raise_input_error(kwargs, match):
    v, f = mesh(1, 0)
    args = {"sigma": SIGMA, **kwargs}
    with pytest.raises(InputError, match=match):
        varifold_distance(v, f, v, f, **args)


def test_bad_meshes_raise_input_error(monkeypatch):
    v, f = mesh(1, 0)
    bad = v.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        varifold_distance(bad, f, v, f, SIGMA)
    with pytest.raises(InputError, match="shape"):
        varifold_distance(v[:, :2], f, v, f, SIGMA)
    with pytest.raises(InputError, match="outside"):
        varifold_distance(v, f + 1000, v, f, SIGMA)
    with pytest.raises(InputError, match="target_weights"):
        varifold_distance(v, f, v, f, SIGMA, target_weights=torch.ones(3, dtype=DT))
    monkeypatch.setattr(V.kernels, "_KEOPS", False)
    with pytest.raises(InputError, match="pykeops"):
        varifold_distance(v, f, v, f, SIGMA, backend="keops")
    assert choose_backend(14000, 55000, 1.0, 2.0, "cpu") == "dense"


def _cell_centroids(c, a, cell):
    """Each face's centre moved to the area-weighted centroid of its cubic cell (F, 3)."""
    _, groups = torch.unique(torch.floor(c / cell).long(), dim=0, return_inverse=True)
    k = int(groups.max()) + 1
    x = c.new_zeros(k, 3).index_add_(0, groups, a[:, None] * c) / a.new_zeros(k).index_add_(0, groups, a)[:, None]
    return x[groups]


BIN_SIGMA = 0.2      # faces of mesh(4) are ~sigma/2 wide: cells of sigma/2 hold a few faces


@pytest.mark.parametrize("kernel", ["binet", "linear", "constant"])
def test_binned_measure_is_exact_for_the_orientation_kernel(kernel):
    # pseudo-faces reproduce <probe, target> exactly once each face sits at its cell's centroid
    c, n, a = V.varifold_measure(*mesh(4, 0))
    cell = 0.5 * BIN_SIGMA
    xb, nb, ab = V.binned_measure(c, n, a, cell, kernel)
    assert xb.shape[0] < 0.7 * c.shape[0] and torch.allclose(nb.norm(dim=1), torch.ones_like(ab))
    if kernel != "linear":                   # binet: sum of eigenvalues = trace = sum of areas
        assert float(ab.sum()) == pytest.approx(float(a.sum()), rel=1e-12)
    p, m = mesh(3, 1, True)
    probe = V.varifold_measure(p, m)
    moved = (_cell_centroids(c, a, cell), n, a)
    for sigma in (BIN_SIGMA, 3 * BIN_SIGMA):
        ref = V.varifold_inner(*probe, *moved, sigma, kernel=kernel)
        out = V.varifold_inner(*probe, xb, nb, ab, sigma, kernel=kernel)
        assert torch.isclose(out, ref, rtol=1e-10, atol=0)
        (g_ref,) = torch.autograd.grad(ref, p, retain_graph=True)
        (g_out,) = torch.autograd.grad(out, p, retain_graph=True)
        assert float((g_out - g_ref).norm() / g_ref.norm()) < 1e-10


@pytest.mark.parametrize("backend", ["dense", "truncated"])
def test_binned_target_close_to_exact_loss(backend, use_backend):
    # cells of sigma/2: d^2 of two different blobs within 2%, its gradient within 3% (relative);
    # the error is that of moving each face to its cell's centroid, O((cell/sigma)^2)
    name = use_backend(backend)
    v, f = mesh(3, 0, True)
    w, g = mesh(4, 1)
    exact = VarifoldLoss(w, g, BIN_SIGMA, backend=name)
    binned = VarifoldLoss(w, g, BIN_SIGMA, backend=name, target_cell=BIN_SIGMA / 2)
    assert binned.target_points < 0.6 * g.shape[0]
    d0, d1 = exact(v, f), binned(v, f)
    (g0,), (g1,) = torch.autograd.grad(d0, v), torch.autograd.grad(d1, v)
    assert float(abs(d1 - d0).detach() / d0.detach()) < 0.02
    assert float((g1 - g0).norm() / g0.norm()) < 0.03
    coarse = VarifoldLoss(w, g, BIN_SIGMA, backend=name, target_cell=BIN_SIGMA)   # larger cells, larger error
    gc, = torch.autograd.grad(coarse(v, f), v)
    assert float((gc - g0).norm()) > 2 * float((g1 - g0).norm())


def test_binned_target_gradient_matches_finite_differences():
    v, f = blob_mesh(1, seed=0)
    w, g = blob_mesh(2, seed=1)
    v = torch.tensor(v, dtype=DT, requires_grad=True)
    loss = VarifoldLoss(torch.tensor(w, dtype=DT), torch.tensor(g), 0.5, backend="dense", target_cell=0.4)
    assert loss.target_points < g.shape[0]
    f = torch.tensor(f)
    assert torch.autograd.gradcheck(lambda a: loss(a, f), (v,), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


def test_binned_target_options():
    w, g = mesh(2, 1)
    few = VarifoldLoss(w, g, SIGMA, target_cell=1e-6)          # no cell holds 2 faces: faces kept
    assert few.target_points == g.shape[0]
    few = VarifoldLoss(w, g, SIGMA, target_cell=0.25)   # a few cells hold several faces: not worth it
    assert few.target_points == g.shape[0] > V.binned_measure(*V.varifold_measure(w, g), 0.25)[0].shape[0]
    with pytest.raises(InputError, match="target_cell"):
        VarifoldLoss(w, g, SIGMA, target_cell=0.0)
    with pytest.raises(InputError, match="require grad"):
        VarifoldLoss(w.clone().requires_grad_(True), g, SIGMA, target_cell=SIGMA)


# ------------------------------------------------------------------ binned measures (centroids, features)

def binned_value_and_grads(backend, kernel):
    v, f = mesh(3, 0, True)
    w, g = mesh(3, 1)
    loss = V.BinnedVarifoldLoss(v, f, w, g, SIGMA, kernel=kernel, cell=SIGMA / 2, backend=backend)
    d = loss(v, f)
    (gv,) = torch.autograd.grad(d, v)
    return d.detach(), gv, loss.stats


@pytest.mark.parametrize("kernel", ["binet", "linear", "constant"])
@pytest.mark.parametrize("backend", BACKENDS[1:])
def test_binned_loss_backends_agree_with_dense_values_and_gradients(backend, kernel, use_backend):
    # the cell pairs of binned measures go through the same backends as faces
    ref = binned_value_and_grads("dense", kernel)
    out = binned_value_and_grads(use_backend(backend), kernel)
    assert out[2]["backend"] == backend.split("-")[0] and ref[2]["backend"] == "dense"
    assert torch.isclose(out[0], ref[0], rtol=1e-5, atol=0)
    assert float((out[1] - ref[1]).norm() / ref[1].norm()) < 1e-5
    if backend.startswith("truncated"):
        assert out[2]["pairs"] < 0.5 * out[2]["all_pairs"], "truncation removed no pairs"


def test_binned_measure_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    x, f = (torch.tensor(rng.normal(size=s), dtype=DT, requires_grad=True) for s in ((7, 3), (7, 9)))
    loss = V.BinnedMeasureLoss(torch.tensor(rng.normal(size=(5, 3)), dtype=DT),
                               torch.tensor(rng.normal(size=(5, 9)), dtype=DT), 0.8, backend="dense")
    assert torch.autograd.gradcheck(loss, (x, f), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_cell_groups_label_each_cell_once_in_lexicographic_order():
    rng = np.random.default_rng(3)
    points = torch.tensor(rng.normal(size=(2000, 3)) * [1.0, 5.0, 0.2] + 40.0, dtype=DT)
    groups, n = V.measure.cell_groups(points, 0.25)
    cells = torch.floor(points / 0.25).long()
    expected_cells, expected = torch.unique(cells, dim=0, return_inverse=True)
    assert n == len(expected_cells) and torch.equal(groups, expected)
    assert V.measure.cell_groups(points[:0], 0.25)[1] == 0


@pytest.mark.parametrize("kernel", ["binet", "linear", "constant"])
def test_moved_binned_measure_is_the_binned_measure_of_the_moved_mesh(kernel):
    v, f = mesh(3, 0)
    groups, n = V.measure.cell_groups(V.varifold_measure(v, f)[0], 0.3)
    R, s = torch.tensor(random_rotation(2), dtype=DT), torch.tensor(1.7, dtype=DT)
    t = torch.tensor([0.3, -1.0, 2.0], dtype=DT)
    x, feat, _ = V.group_features(*V.varifold_measure(v, f), groups, n, kernel)
    xm, fm, _ = V.group_features(*V.varifold_measure(s * v @ R.T + t, f), groups, n, kernel)
    x2, f2 = V.moved_measure(x, feat, R, s, t, kernel)
    assert torch.allclose(x2, xm, rtol=0, atol=1e-12) and torch.allclose(f2, fm, rtol=0, atol=1e-12)


@pytest.mark.parametrize("kernel", ["binet", "linear", "constant"])
def test_binned_loss_with_one_face_per_cell_is_the_face_loss(kernel):
    # features <f, f'> reproduce kappa(n.n') a a' exactly: cells too small to hold two faces give d^2
    v, f = mesh(2, 0, True)
    w, g = mesh(2, 1)
    binned = V.BinnedVarifoldLoss(v, f, w, g, SIGMA, kernel=kernel, cell=1e-6, backend="dense")
    assert binned.n_groups == f.shape[0] and binned.n_target == g.shape[0]
    d0, d1 = VarifoldLoss(w, g, SIGMA, kernel=kernel, backend="dense")(v, f), binned(v, f)
    (g0,), (g1,) = torch.autograd.grad(d0, v), torch.autograd.grad(d1, v)
    assert torch.isclose(d1, d0, rtol=1e-10, atol=0) and float((g1 - g0).norm() / g0.norm()) < 1e-10


def test_keops_can_be_turned_off_from_the_environment(monkeypatch):
    """BAREESA_NO_KEOPS=1 (for a GPU where KeOps' compiled code crashes): "auto" never picks KeOps."""
    monkeypatch.setattr(V.kernels, "_KEOPS", None)
    monkeypatch.setenv(V.kernels.NO_KEOPS_ENV, "1")
    assert not V.keops_available()
    assert V.kernels.choose_backend(100, 100, SIGMA, 1.0, "cuda") == "dense"


def test_auto_truncates_a_short_cutoff_from_fewer_pairs_with_keops_only(monkeypatch):
    """With pykeops, "auto" truncates a cutoff below a quarter of the extent from TRUNCATE_MIN_PAIRS
    (max(n)^2) on, where dense was chosen up to DENSE_MAX_PAIRS; without it dense stays the choice there."""
    n = int((V.kernels.TRUNCATE_MIN_PAIRS ** 0.5 + V.kernels.DENSE_MAX_PAIRS ** 0.5) / 2)  # between the two
    monkeypatch.setattr(V.kernels, "_KEOPS", True)
    assert V.kernels.choose_backend(n, n, 0.01, 2.0, "cpu") == "truncated"
    assert V.kernels.choose_backend(n, n, 1.0, 2.0, "cpu") == "dense"  # a cutoff as long as the body
    small = int(V.kernels.TRUNCATE_MIN_PAIRS ** 0.5) - 1
    assert V.kernels.choose_backend(small, small, 0.01, 2.0, "cpu") == "dense"
    monkeypatch.setattr(V.kernels, "_KEOPS", False)
    assert V.kernels.choose_backend(n, n, 0.01, 2.0, "cpu") == "dense"


def test_keops_cpu_flags_are_set_only_while_pykeops_imports_and_never_over_the_users(monkeypatch):
    """On Linux x86_64 KeOps' CPU kernels get KEOPS_CPU_FLAGS through CXXFLAGS while pykeops imports (it
    reads them then), and the environment is as it was after; a user's CXXFLAGS, or another platform,
    are left alone."""
    monkeypatch.delenv("CXXFLAGS", raising=False)
    monkeypatch.setattr(V.kernels.platform, "system", lambda: "Linux")
    monkeypatch.setattr(V.kernels.platform, "machine", lambda: "x86_64")
    with V.kernels._keops_cpu_flags():
        assert V.kernels.os.environ["CXXFLAGS"] == V.kernels.KEOPS_CPU_FLAGS
    assert "CXXFLAGS" not in V.kernels.os.environ
    monkeypatch.setenv("CXXFLAGS", "-O1")
    with V.kernels._keops_cpu_flags():
        assert V.kernels.os.environ["CXXFLAGS"] == "-O1"
    assert V.kernels.os.environ["CXXFLAGS"] == "-O1"
    monkeypatch.delenv("CXXFLAGS")
    monkeypatch.setattr(V.kernels.platform, "system", lambda: "Darwin")
    with V.kernels._keops_cpu_flags():
        assert "CXXFLAGS" not in V.kernels.os.environ


def test_keops_kernels_leave_the_process_ieee_and_agree_with_torch(keops_ok):
    """KEOPS_CPU_FLAGS vectorise KeOps' sums without -ffast-math, which would link crtfastmath into each
    kernel: loading one would then flush denormals to zero in the whole process (Blender's too). After the
    truncated KeOps sums with gradients ran, a denormal survives; and they agree with torch's dense sums."""
    v, f = mesh(3, requires_grad=True)
    w, g = mesh(3, seed=1)
    values, grads = [], []
    for backend in ("truncated", "dense"):
        d = varifold_distance(v, f, w + 0.05, g, SIGMA, backend=backend, cutoff=12 * SIGMA)
        values.append(float(d.detach()))
        grads.append(torch.autograd.grad(d, v)[0])
    assert values[0] == pytest.approx(values[1], rel=1e-12)
    assert float((grads[0] - grads[1]).norm() / grads[1].norm()) < 1e-12
    tiny64 = np.finfo(np.float64).tiny
    assert np.float64(tiny64) / np.float64(4.0) > 0  # not flushed to zero
    assert float(torch.tensor(1e-40, dtype=torch.float32) * 0.5) > 0


def test_grid_runs_looked_up_in_its_table_are_the_ones_binary_search_finds():
    """``Grid.ranges`` looks each cell's run of sorted points up in a table (``Grid.first``): the same
    clusters, runs and pair count as searching the sorted keys, for "i" points inside, around and far
    outside the grid; a grid with far more cells than points (far clutter) keeps no table."""
    from bareesa.varifold.backends import Grid

    rng = np.random.default_rng(4)
    on_ellipsoid = lambda n: torch.as_tensor((lambda u: u / np.linalg.norm(u, axis=1, keepdims=True))(  # noqa: E731
        rng.normal(size=(n, 3))) * [0.5, 0.3, 1.0])
    y = on_ellipsoid(3000)
    x = torch.cat([on_ellipsoid(2000) * 1.1, torch.as_tensor(rng.normal(size=(50, 3)) + [-30.0, 9.0, 40.0])])
    for cutoff in (0.15, 0.4, 1.5):
        grid = Grid(y, cutoff)
        assert grid.first is not None
        looked_up = grid.ranges(x, cutoff, 0.5 * cutoff)
        grid.first = None
        searched = grid.ranges(x, cutoff, 0.5 * cutoff)
        assert looked_up[-1] == searched[-1] > 0
        for a, b in zip(looked_up[:-1], searched[:-1]):
            assert torch.equal(a, b)
    assert Grid(torch.cat([y, torch.tensor([[500.0, 500.0, 500.0]], dtype=y.dtype)]), 0.05).first is None


def test_keops_kernels_are_built_once_when_two_solves_ask_at_once(monkeypatch, tmp_path):
    # the add-on runs solves side by side in threads: the second caller waits for the first's build (KeOps
    # would otherwise compile the same formula twice into the same files) and then finds it done
    import threading
    import time

    from bareesa.varifold import backends, kernels

    calls = []

    def slow(*args, **kwargs):
        calls.append(threading.get_ident())
        time.sleep(0.05)
        return torch.zeros(4, 12, dtype=DT)  # (any width: the engine only places the rows)

    monkeypatch.setattr(kernels, "_KEOPS", True)
    monkeypatch.setattr(backends, "_keops_sums", slow)
    monkeypatch.setattr(backends, "_built", set())
    monkeypatch.setattr(backends, "_built_marker", lambda dtype, device, formulas: tmp_path / "built")
    results = []
    threads = [threading.Thread(target=lambda: results.append(V.build_keops_kernels(DT))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(results) == [False, True] and len(calls) == len(backends.keops_formulas())
    assert len(set(calls)) == 1 and (tmp_path / "built").exists()


def test_the_keops_formulas_built_follow_the_kernels_of_the_levels():
    # binet's cells carry 9 numbers, linear's 3 (a noisy scan's finest level): both are built when both are used;
    # the face sums take a kernel's coefficients as arguments, so one pair serves every kernel
    from bareesa.varifold import backends

    names = lambda kernels: backends._formula_names(backends.keops_formulas(kernels))  # noqa: E731
    assert names(("binet",)) == ("FacePairs+grad", "FeaturePairs9", "FeaturePairs9+grad")
    both = names(("binet", "binet", "binet", "linear"))
    assert both == names(("binet+linear",)) and set(both) - set(names(("binet",))) == {"FeaturePairs3",
                                                                                        "FeaturePairs3+grad"}


@pytest.mark.parametrize("kind", ["faces", "cells"])
def test_keops_face_values_come_from_the_gradient_formula_and_every_sum_equals_torchs(kind):
    # KeOps builds each formula at its first use on a machine (~5 s): the faces' values alone (a fixed target's
    # self term, once a level) are the leading sums of the formula with the gradient's, so no second binary is
    # built for them; the cells' values alone (screening scores, many) keep their own, cheaper formula
    from bareesa.varifold import backends, keops_available

    if not keops_available():
        pytest.skip("pykeops does not import here")
    gen = torch.Generator().manual_seed(3)
    x, y = torch.rand(40, 3, generator=gen, dtype=DT), torch.rand(50, 3, generator=gen, dtype=DT)
    if kind == "faces":
        pairs = backends.FacePairs("binet")
        u = torch.nn.functional.normalize(torch.randn(40, 3, generator=gen, dtype=DT), dim=1)
        v = (torch.nn.functional.normalize(torch.randn(50, 3, generator=gen, dtype=DT), dim=1),
             torch.rand(50, generator=gen, dtype=DT))
    else:
        pairs = backends.FeaturePairs(9)
        u, v = torch.randn(40, 9, generator=gen, dtype=DT), (torch.randn(50, 9, generator=gen, dtype=DT),)
    seen = []
    real = backends._keops_sums

    def spy(*args, **kwargs):
        seen.append(args[6])
        return real(*args, **kwargs)

    dense = backends.Engine("dense", 0.3, pairs, 10.0)
    for backend in ("keops", "truncated"):
        engine = backends.Engine(backend, 0.3, pairs, 10.0, use_keops=True)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(backends, "_keops_sums", spy)
            values, both = engine.sums(x, u, y, v, False), engine.sums(x, u, y, v, True)
        assert values.shape == (40, pairs.width(False)) and both.shape == (40, pairs.width(True))
        assert torch.allclose(values, both[:, :pairs.width(False)], rtol=1e-12, atol=1e-15)
        assert torch.allclose(values, dense.sums(x, u, y, v, False), rtol=1e-10, atol=1e-12)
    assert seen == ([True] * 4 if kind == "faces" else [False, True] * 2)
