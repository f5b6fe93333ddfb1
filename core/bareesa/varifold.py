r"""Varifold distance between triangle meshes (appendix "Mesh invariant similarity measures").

A mesh q is represented by its faces f: barycentres c_f, unit normals n_f, areas a_f.
With the kernel

    k(x, n, x', n') = exp(-|x - x'|^2 / sigma^2) * kappa(n . n'),
    kappa = "binet": (n.n')^2 (default, the paper's)  | "linear": n.n' (oriented)  | "constant": 1,

the inner product is <q, q'> = sum_{f, f'} k(c_f, n_f, c_f', n_f') a_f a_f' and the squared
distance is d^2(q, q') = <q, q> - 2 <q, q'> + <q', q'>. Meshes may have any sizes and
connectivities; d^2 is differentiable (autograd) in the vertices of both meshes.

Public API
----------
``varifold_distance(verts, faces, target_verts, target_faces, sigma, ...)`` one-shot d^2;
``VarifoldLoss(target_verts, target_faces, sigma, ...)`` the same for a fixed target, with the
target's representation, self term <q', q'> and spatial grid cached (``loss(verts, faces)``);
``binned_measure`` a measure summed over cubic cells (exact orientation kernel);
``varifold_inner`` the raw inner product of two (centres, normals, weights) measures;
``choose_backend`` the rule used by ``backend="auto"``; ``default_cutoff``.

Backends (same maths, different evaluation strategies, as in geomloss)
----------------------------------------------------------------------
* ``"dense"``: plain torch, all pairs, chunked over rows so that temporaries stay below
  ~256 MB. Exact differences x - x' (accurate in float32). For small problems.
* ``"keops"``: pykeops LazyTensor reduction over all pairs (CPU or CUDA). One formula for the
  three kernels (kappa(t) = c0 + c1 t + c2 t^2 with c and 1/sigma^2 passed as parameters), one
  reduction that returns the value *and* the gradient terms, so a new sigma or kernel never
  recompiles; a compile (~8 s on CPU, cached in ``pykeops.get_build_folder()``,
  typically ~/.cache/keops2.3/) happens once per dtype x {value, value+gradient} x {dense, ranges}.
* ``"truncated"``: ignores the pairs with |x - x'| >= cutoff. The second mesh is sorted into a
  uniform grid of cubic cells (size cutoff/4, cached by ``VarifoldLoss`` for the target); the
  first mesh is sorted into coarser clusters (size cutoff/2, rebuilt at every call since
  vertices move). For each cluster, the cells whose box lies within ``cutoff`` of the
  cluster's bounding box form at most one contiguous run of the sorted second mesh per (y, z)
  row of cells; these runs are the block-sparse ``ranges`` of a KeOps reduction (CPU or CUDA).
  Without pykeops the same runs are evaluated as padded torch tiles (slower on CPU).

Truncation error bound: every ignored pair has spatial kernel value exp(-|x-x'|^2/sigma^2) <=
tol := exp(-cutoff^2/sigma^2) and |kappa| <= 1 for unit normals, so for each inner product

    |<q, q'>_truncated - <q, q'>| <= tol * A * A',    A = sum_f a_f,  A' = sum_f' a'_f'  (weighted),

hence |d^2_truncated - d^2| <= tol * (A + A')^2. The default cutoff is
``sigma * sqrt(log(1 / tol))`` with tol = 1e-6 (3.72 sigma). The bound is pessimistic: on a
smooth surface the ignored mass of an inner product is ~tol times the inner product itself, and
the self and cross terms' errors largely cancel in d^2 when q and q' are close.

``backend="auto"`` (see ``choose_backend``): on CUDA, "keops" (or "dense" without pykeops);
on CPU, "dense" while max(n_source, n_target)^2 < 2e7 face pairs, else "truncated" when the
cutoff is below a quarter of the bounding-box diagonal of both meshes, else "keops" (or
"dense" without pykeops).
"""

import contextlib
import io
import math

import torch
from torch.autograd.function import once_differentiable

from .errors import InputError
from .geometry import face_centers, face_normals_areas

KERNELS = {"binet": (0.0, 0.0, 1.0), "linear": (0.0, 1.0, 0.0), "constant": (1.0, 0.0, 0.0)}
BACKENDS = ("auto", "dense", "keops", "truncated")
DEFAULT_TOL = 1e-6
DENSE_MAX_PAIRS = 2e7
DENSE_CHUNK_BYTES = 256 * 2**20
CELL_FRACTION = 0.25      # grid cell size of the second mesh, in units of the cutoff
CLUSTER_FRACTION = 0.5    # cluster size of the first mesh, in units of the cutoff
TARGET_BIN_GAIN = 0.75    # VarifoldLoss bins its target only when that leaves at most this share of points

_KEOPS = None


def keops_available():
    """True when pykeops imports (its LazyTensor is then used by "keops" and "truncated")."""
    global _KEOPS
    if _KEOPS is None:
        try:
            # KeOps prints its banner and compile messages on stdout, which would corrupt
            # the CLI's JSON output: keep its import quiet and turn its verbosity off.
            with contextlib.redirect_stdout(io.StringIO()):
                import pykeops
                import pykeops.torch  # noqa: F401
            pykeops.set_verbose(False)
            _KEOPS = True
        except Exception:  # ImportError, or a broken compiler setup at import time
            _KEOPS = False
    return _KEOPS


def default_cutoff(sigma, tol=DEFAULT_TOL):
    """Cutoff radius beyond which the spatial kernel is <= tol: sigma * sqrt(log(1/tol))."""
    return float(sigma) * math.sqrt(math.log(1.0 / tol))


def choose_backend(n_source, n_target, sigma, extent, device, cutoff=None):
    """Backend for "auto": see the module docstring. extent = bounding-box diagonal of both meshes."""
    device = torch.device(device)
    cutoff = default_cutoff(sigma) if cutoff is None else float(cutoff)
    if device.type == "cuda":
        return "keops" if keops_available() else "dense"
    if max(n_source, n_target) ** 2 < DENSE_MAX_PAIRS:
        return "dense"
    if cutoff < 0.25 * float(extent):
        return "truncated"
    return "keops" if keops_available() else "dense"


# --------------------------------------------------------------------------- checks

def _check_options(sigma, kernel, backend, cutoff):
    if kernel not in KERNELS:
        raise InputError(f"unknown varifold kernel {kernel!r}; choose one of {sorted(KERNELS)}")
    if backend not in BACKENDS:
        raise InputError(f"unknown varifold backend {backend!r}; choose one of {list(BACKENDS)}")
    if backend == "keops" and not keops_available():
        raise InputError("backend 'keops' needs pykeops, which is not importable here; "
                         "install pykeops or use backend='dense' / 'truncated' / 'auto'")
    try:
        sigma = float(sigma)
    except (TypeError, ValueError):
        raise InputError(f"sigma must be a positive number, got {sigma!r}") from None
    if not (sigma > 0 and math.isfinite(sigma)):
        raise InputError(f"sigma must be a positive finite number, got {sigma}")
    if cutoff is not None and not (float(cutoff) > 0 and math.isfinite(float(cutoff))):
        raise InputError(f"cutoff must be a positive finite number or None, got {cutoff}")
    return sigma


def _check_mesh(verts, faces, name):
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


def binned_measure(centers, normals, weights, cell, kernel="binet"):
    """A measure summed over cubic cells of size ``cell``, as a smaller measure of pseudo-faces.

    centers (F, 3), normals (F, 3), weights (F,) -> centers (C', 3), unit normals (C', 3),
    weights (C',) (not differentiable). Each cell's faces are moved to their weighted centroid
    and replaced by pseudo-faces that reproduce the cell's orientation kernel exactly:
    binet: the eigenpairs (lambda_k, e_k) of sum a n n^T (at most 3: n^T T n = sum lambda_k
    (n.e_k)^2; eigenvalues below 1e-12 of the trace are dropped); linear: one face of normal
    s/|s| and weight |s|, s = sum a n; constant: one face of weight sum a. Only positions are
    approximated: the kernel of a cell is off by O((cell / sigma)^2) relative, mostly a blur
    along the surface (a plane crossing a cell has no spread along its normal).
    """
    c, n, a = (t.detach() for t in (centers, normals, weights))
    keep = a > 0
    c, n, a = c[keep], n[keep], a[keep]
    _, groups = torch.unique(torch.floor(c / cell).long(), dim=0, return_inverse=True)
    k = int(groups.max()) + 1 if groups.numel() else 0
    total = a.new_zeros(k).index_add_(0, groups, a)
    x = c.new_zeros(k, 3).index_add_(0, groups, a[:, None] * c) / total[:, None]
    if kernel == "binet":
        t = a.new_zeros(k, 9).index_add_(0, groups, a[:, None] * (n[:, :, None] * n[:, None, :]).reshape(-1, 9))
        lam, vec = torch.linalg.eigh(t.reshape(k, 3, 3))                  # (C, 3), (C, 3, 3) columns
        ok = lam > 1e-12 * total[:, None]
        cell_of = torch.arange(k, device=c.device)[:, None].expand(k, 3)[ok]
        return x[cell_of], vec.transpose(1, 2)[ok], lam[ok]
    if kernel == "linear":
        s = c.new_zeros(k, 3).index_add_(0, groups, a[:, None] * n)
        norm = s.norm(dim=1)
        ok = norm > 1e-12 * total
        return x[ok], s[ok] / norm[ok, None], norm[ok]
    mean = c.new_zeros(k, 3).index_add_(0, groups, a[:, None] * n)
    mean = torch.where(mean.norm(dim=1, keepdim=True) > 0, mean, mean.new_tensor([0.0, 0.0, 1.0]))
    return x, mean / mean.norm(dim=1, keepdim=True), total


# --------------------------------------------------------------------------- pair sums
# Every backend computes, for each "i" face, the 7 sums over the "j" faces
#   F0_i = sum_j b_j k_ij,  Fx_i = sum_j b_j k_ij (x_i - y_j),  Fn_i = sum_j b_j K_ij kappa'_ij m_j
# (only F0 when no gradient is needed). Then <q, q'> = sum_i a_i F0_i and
#   d/dx_i = -2 g a_i Fx_i,  d/dn_i = a_i Fn_i,  d/da_i = F0_i      (g = 1 / sigma^2).

def _dense_sums(x, n, y, m, b, g, coef, grad, max_bytes=DENSE_CHUNK_BYTES):
    """All-pairs sums in torch, chunked over rows: (N,3),(N,3),(M,3),(M,3),(M,) -> (N, 1 or 7)."""
    c0, c1, c2 = coef
    rows = max(1, int(max_bytes // (12 * y.shape[0] * y.element_size())))
    out = []
    for s in range(0, x.shape[0], rows):
        d = x[s:s + rows, None, :] - y[None, :, :]               # (B, M, 3)
        K = torch.exp(-g * (d * d).sum(-1)) * b                  # (B, M)
        t = n[s:s + rows] @ m.T
        W = K * (c0 + t * (c1 + c2 * t))
        parts = [W.sum(1, keepdim=True)]
        if grad:
            parts += [torch.einsum("bm,bmk->bk", W, d), (K * (c1 + 2 * c2 * t)) @ m]
        out.append(torch.cat(parts, 1))
    return torch.cat(out, 0)


def _keops_sums(x, n, y, m, b, g, coef, grad, ranges=None):
    """All-pairs (or block-sparse with ``ranges``) sums with one KeOps reduction -> (N, 1 or 7)."""
    from pykeops.torch import LazyTensor
    xi, ni = LazyTensor(x[:, None, :].contiguous()), LazyTensor(n[:, None, :].contiguous())
    yj, mj = LazyTensor(y[None, :, :].contiguous()), LazyTensor(m[None, :, :].contiguous())
    bj = LazyTensor(b[None, :, None].contiguous())
    G = LazyTensor(torch.tensor([g], dtype=x.dtype, device=x.device))
    C = LazyTensor(torch.tensor(coef, dtype=x.dtype, device=x.device))
    d = xi - yj
    K = (-G * d.sqnorm2()).exp() * bj
    t = ni | mj
    kap = C.elem(0) + t * (C.elem(1) + C.elem(2) * t)
    if grad:
        F = K * kap.concat(kap * d).concat((C.elem(1) + 2 * C.elem(2) * t) * mj)
    else:
        F = K * kap
    return F.sum(dim=1, ranges=ranges)


def _tile_sums(x, n, y, m, b, g, coef, grad):
    """Batched tile sums (T,I,3),(T,I,3),(T,J,3),(T,J,3),(T,J) -> (T, I, 1 or 7); centred expansion."""
    c0, c1, c2 = coef
    o = x[:, :1, :]
    x, y = x - o, y - o
    d2 = (x * x).sum(-1)[:, :, None] + (y * y).sum(-1)[:, None, :] - 2 * x @ y.transpose(1, 2)
    K = torch.exp(d2.clamp_min(0) * -g) * b[:, None, :]
    t = n @ m.transpose(1, 2)
    W = K * (c0 + t * (c1 + c2 * t))
    F0 = W.sum(-1, keepdim=True)
    if not grad:
        return F0
    return torch.cat([F0, x * F0 - W @ y, (K * (c1 + 2 * c2 * t)) @ m], -1)


class _Grid:
    """Uniform grid of cells (size h) of the "j" points: sort permutation and sorted cell keys."""

    def __init__(self, y, cutoff):
        y = y.detach()
        self.h = CELL_FRACTION * cutoff
        self.origin = y.min(0).values
        ijk = torch.floor((y - self.origin) / self.h).long()
        self.dims = (ijk.max(0).values + 1).tolist()
        nx, ny, _ = self.dims
        keys = ijk[:, 0] + nx * (ijk[:, 1] + ny * ijk[:, 2])
        self.keys, self.perm = torch.sort(keys)
        self.size = y.shape[0]

    def ranges(self, x, cutoff, cluster_size):
        """Clusters of x (sort perm, (C,2) ranges) and, per cluster, the runs of sorted j points
        within ``cutoff`` of its bounding box: slices (C,), runs (R,2); and the pair count."""
        x = x.detach()
        dev = x.device
        cidx = torch.floor((x - x.min(0).values) / cluster_size).long()
        cd = (cidx.max(0).values + 1).tolist()
        ckeys = cidx[:, 0] + cd[0] * (cidx[:, 1] + cd[1] * cidx[:, 2])
        ckeys, perm_i = torch.sort(ckeys)
        _, counts = torch.unique_consecutive(ckeys, return_counts=True)
        C = counts.shape[0]
        ends = torch.cumsum(counts, 0)
        ranges_i = torch.stack([ends - counts, ends], 1)
        cid = torch.repeat_interleave(torch.arange(C, device=dev), counts)
        xs = x[perm_i]
        lo = torch.full((C, 3), float("inf"), dtype=x.dtype, device=dev)
        lo = lo.scatter_reduce(0, cid[:, None].expand(-1, 3), xs, "amin", include_self=True)
        hi = torch.full((C, 3), -float("inf"), dtype=x.dtype, device=dev)
        hi = hi.scatter_reduce(0, cid[:, None].expand(-1, 3), xs, "amax", include_self=True)

        h, o, (nx, ny, nz) = self.h, self.origin, self.dims
        a0 = torch.floor((lo - cutoff - o) / h).long().clamp_min(0)                 # (C, 3)
        a1 = torch.minimum(torch.floor((hi + cutoff - o) / h).long(),
                           torch.tensor([nx - 1, ny - 1, nz - 1], device=dev))
        ky = max(int((a1[:, 1] - a0[:, 1]).max()) + 1, 1)
        kz = max(int((a1[:, 2] - a0[:, 2]).max()) + 1, 1)
        iy = a0[:, 1, None, None] + torch.arange(ky, device=dev)[None, :, None]     # (C, ky, 1)
        iz = a0[:, 2, None, None] + torch.arange(kz, device=dev)[None, None, :]     # (C, 1, kz)

        def gap(i, k):  # distance from the cluster box to the cell slab i along axis k
            cl = o[k] + i.to(x.dtype) * h
            return torch.maximum(cl - hi[:, k, None, None], lo[:, k, None, None] - (cl + h)).clamp_min(0)

        rem = cutoff ** 2 - gap(iy, 1) ** 2 - gap(iz, 2) ** 2                       # (C, ky, kz)
        valid = (rem > 0) & (iy <= a1[:, 1, None, None]) & (iz <= a1[:, 2, None, None])
        rx = rem.clamp_min(0).sqrt()
        ix0 = torch.floor((lo[:, 0, None, None] - rx - o[0]) / h).long().clamp_min(0)
        ix1 = torch.floor((hi[:, 0, None, None] + rx - o[0]) / h).long().clamp_max(nx - 1)
        valid &= ix0 <= ix1
        row = nx * (iy + ny * iz)
        start = torch.searchsorted(self.keys, (ix0 + row).reshape(-1))
        end = torch.searchsorted(self.keys, (ix1 + row).reshape(-1), right=True)
        valid = valid.reshape(-1) & (end > start)
        runs = torch.stack([start[valid], end[valid]], 1)
        owner = torch.arange(C, device=dev)[:, None].expand(C, ky * kz).reshape(-1)[valid]
        slices = torch.cumsum(torch.bincount(owner, minlength=C), 0)
        pairs = int(((runs[:, 1] - runs[:, 0]) * counts[owner]).sum())
        return perm_i, ranges_i, slices, runs, owner, pairs


def _truncated_tiles(xs, ns, ys, ms, bs, g, coef, grad, ranges_i, runs, owner, ti=16, tj=512):
    """Torch fallback of the block-sparse sums: per cluster, its runs are concatenated into one
    list of j indices, and (cluster rows x list) is cut into padded (ti x tj) tiles."""
    dev = xs.device
    C = ranges_i.shape[0]
    rl = runs[:, 1] - runs[:, 0]
    total = int(rl.sum())
    first = torch.repeat_interleave(torch.cumsum(rl, 0) - rl, rl)
    jlist = torch.repeat_interleave(runs[:, 0], rl) + torch.arange(total, device=dev) - first
    L = torch.zeros(C, dtype=torch.long, device=dev).index_add_(0, owner, rl)   # list length per cluster
    off = torch.cumsum(L, 0) - L
    nI = (ranges_i[:, 1] - ranges_i[:, 0] + ti - 1) // ti
    nJ = (L + tj - 1) // tj
    nt = nI * nJ
    c = torch.repeat_interleave(torch.arange(C, device=dev), nt)
    k = torch.arange(c.shape[0], device=dev) - torch.repeat_interleave(torch.cumsum(nt, 0) - nt, nt)
    it, jt = k // nJ[c], k % nJ[c]
    i0 = ranges_i[c, 0] + it * ti
    i1 = torch.minimum(i0 + ti, ranges_i[c, 1])
    p0 = off[c] + jt * tj
    p1 = torch.minimum(p0 + tj, off[c] + L[c])
    out = xs.new_zeros(xs.shape[0], 7 if grad else 1)
    chunk = max(1, DENSE_CHUNK_BYTES // (12 * ti * tj * xs.element_size()))
    ai, aj = torch.arange(ti, device=dev), torch.arange(tj, device=dev)
    for s in range(0, c.shape[0], chunk):
        ii = i0[s:s + chunk, None] + ai
        mi = ii < i1[s:s + chunk, None]
        ii = torch.where(mi, ii, i0[s:s + chunk, None])
        pp = p0[s:s + chunk, None] + aj
        mj = pp < p1[s:s + chunk, None]
        jj = jlist[torch.where(mj, pp, p0[s:s + chunk, None])]
        F = _tile_sums(xs[ii], ns[ii], ys[jj], ms[jj], bs[jj] * mj, g, coef, grad)
        out.index_add_(0, ii[mi], F[mi])
    return out


# --------------------------------------------------------------------------- engine

class _Engine:
    """Evaluates the pair sums of a measure against a "j" measure with one backend."""

    def __init__(self, backend, sigma, kernel, cutoff, use_keops=None):
        self.backend, self.g, self.coef = backend, 1.0 / sigma ** 2, KERNELS[kernel]
        self.cutoff = default_cutoff(sigma) if cutoff is None else float(cutoff)
        self.use_keops = keops_available() if use_keops is None else use_keops
        self.pairs = 0            # pairs evaluated by the last calls (reset by the caller)

    def sums(self, x, n, y, m, b, grad, grid=None):
        """Pair sums (N, 1 or 7) of i = (x, n) against j = (y, m, b); grid: cached _Grid of y."""
        x, n, y, m, b = (t.detach() for t in (x, n, y, m, b))
        if self.backend == "dense":
            self.pairs += x.shape[0] * y.shape[0]
            return _dense_sums(x, n, y, m, b, self.g, self.coef, grad)
        if self.backend == "keops":
            self.pairs += x.shape[0] * y.shape[0]
            return _keops_sums(x, n, y, m, b, self.g, self.coef, grad)
        grid = _Grid(y, self.cutoff) if grid is None else grid
        perm_i, ranges_i, slices, runs, owner, pairs = grid.ranges(
            x, self.cutoff, CLUSTER_FRACTION * self.cutoff)
        self.pairs += pairs
        xs, ns = x[perm_i], n[perm_i]
        ys, ms, bs = y[grid.perm], m[grid.perm], b[grid.perm]
        if self.use_keops:
            i32 = lambda t: t.to(torch.int32).contiguous()  # noqa: E731
            rng = (i32(ranges_i), i32(slices), i32(runs)) * 2   # axis-0 half unused (no KeOps autograd)
            F = _keops_sums(xs, ns, ys, ms, bs, self.g, self.coef, grad, ranges=rng)
        else:
            F = _truncated_tiles(xs, ns, ys, ms, bs, self.g, self.coef, grad, ranges_i, runs, owner)
        out = torch.empty_like(F)
        out[perm_i] = F
        return out


class _Inner(torch.autograd.Function):
    """<(x,n,a), (y,m,b)> with gradients from the fused pair sums (self term when ``symmetric``)."""

    @staticmethod
    def forward(ctx, x, n, a, y, m, b, engine, grid_j, grid_i, symmetric):
        need_i = any(ctx.needs_input_grad[:3])
        need_j = any(ctx.needs_input_grad[3:6]) and not symmetric
        F = engine.sums(x, n, y, m, b, need_i, grid_j)
        value = (a.detach() * F[:, 0]).sum()
        grads = []
        if need_i:
            f = 2.0 if symmetric else 1.0          # d/dq <q,q> = 2 x (i-side derivative), k symmetric
            ad = a.detach()[:, None]
            grads += [(-2 * f * engine.g) * ad * F[:, 1:4], f * ad * F[:, 4:7], f * F[:, 0]]
        if need_j:
            G = engine.sums(y, m, x, n, a, True, grid_i)
            bd = b.detach()[:, None]
            grads += [(-2 * engine.g) * bd * G[:, 1:4], bd * G[:, 4:7], G[:, 0]]
        ctx.need = (need_i, need_j)
        ctx.save_for_backward(*grads)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, go):
        grads = list(ctx.saved_tensors)
        out = [None] * 10
        if ctx.need[0]:
            out[0:3] = [go * t for t in grads[:3]]
            grads = grads[3:]
        if ctx.need[1]:
            out[3:6] = [go * t for t in grads[:3]]
        return tuple(out)


def varifold_inner(centers, normals, weights, other_centers, other_normals, other_weights,
                   sigma, kernel="binet", backend="dense", cutoff=None):
    """<q, q'> of two measures: (F,3),(F,3),(F,) and (F',3),(F',3),(F',) -> scalar (differentiable)."""
    sigma = _check_options(sigma, kernel, backend, cutoff)
    if backend == "auto":
        ext = torch.cat([centers, other_centers]).detach()
        ext = float((ext.max(0).values - ext.min(0).values).norm())
        backend = choose_backend(centers.shape[0], other_centers.shape[0], sigma, ext,
                                 centers.device, cutoff)
    engine = _Engine(backend, sigma, kernel, cutoff)
    return _Inner.apply(centers, normals, weights, other_centers, other_normals, other_weights,
                        engine, None, None, False)


class VarifoldLoss:
    """Squared varifold distance to a fixed target: ``loss(verts (N,3), faces (F,3)) -> scalar``.

    Caches the target's centres/normals/weighted areas, its self term <q', q'> (unless the target
    requires grad) and, for "truncated", its grid. ``stats`` holds the backend and the number of
    face pairs evaluated by the last call (``pairs``) next to the all-pairs count (``all_pairs``).

    ``target_cell`` (a length, e.g. sigma / 2): the target measure is replaced by its
    ``binned_measure`` on cells of that size when this has at most TARGET_BIN_GAIN times as
    many points as the target has faces (a scan much finer than sigma: otherwise the small
    saving is not worth the approximation and its dependence on the cell grid); the source
    stays exact. Not for a target that
    requires grad. ``target_points`` is the number of target points used.
    """

    def __init__(self, target_verts, target_faces, sigma, kernel="binet", backend="auto",
                 target_weights=None, cutoff=None, target_cell=None):
        self.sigma = _check_options(sigma, kernel, backend, cutoff)
        if target_cell is not None and not (float(target_cell) > 0 and math.isfinite(float(target_cell))):
            raise InputError(f"target_cell must be a positive finite length or None, got {target_cell}")
        _check_mesh(target_verts, target_faces, "target")
        if target_weights is not None:
            if not torch.is_tensor(target_weights) or target_weights.shape != target_faces.shape[:1]:
                raise InputError(f"target_weights must be a tensor of shape ({target_faces.shape[0]},)")
            if not bool(torch.isfinite(target_weights).all()) or bool((target_weights < 0).any()):
                raise InputError("target_weights must be finite and nonnegative")
            target_weights = target_weights.to(target_verts)
        self.kernel, self.backend, self.cutoff = kernel, backend, cutoff
        self._target_mesh = (target_verts, target_faces.long(), target_weights)
        self._measure = varifold_measure(*self._target_mesh)
        self.target_requires_grad = any(t.requires_grad for t in self._measure)
        if target_cell is not None:
            if self.target_requires_grad:
                raise InputError("target_cell bins the target, which then cannot require grad")
            binned = binned_measure(*self._measure, float(target_cell), kernel)
            if binned[0].shape[0] <= TARGET_BIN_GAIN * self._measure[0].shape[0]:
                self._measure = binned
        self.target_points = self._measure[0].shape[0]
        self._grid = None
        self._self = {}
        self.stats = {}

    @property
    def target(self):
        """Target centres (F',3), normals (F',3), weighted areas (F',); rebuilt if it requires grad."""
        return varifold_measure(*self._target_mesh) if self.target_requires_grad else self._measure

    def _target_grid(self, engine):
        if self._grid is None or self._grid[0] != engine.cutoff:
            self._grid = (engine.cutoff, _Grid(self._measure[0].detach(), engine.cutoff))
        return self._grid[1]

    def _target_self(self, engine, backend, target):
        """<q', q'>, computed once per backend (every call if the target requires grad)."""
        grid = self._target_grid(engine) if backend == "truncated" else None
        if self.target_requires_grad:
            return self._term(engine, backend, target, target, True, grid)
        if backend not in self._self:
            with torch.no_grad():
                self._self[backend] = self._term(engine, backend, target, target, True, grid)
        return self._self[backend]

    def _term(self, engine, backend, q, qt, symmetric, grid_j=None):
        if backend == "truncated" and grid_j is None:
            grid_j = _Grid(qt[0], engine.cutoff)
        if symmetric:
            qt = tuple(t.detach() for t in qt)
        return _Inner.apply(*q, *qt, engine, grid_j, None, symmetric)

    def __call__(self, verts, faces):
        """Squared distance d^2(q, q_target) of the mesh (verts (N,3), faces (F,3)) -> scalar."""
        _check_mesh(verts, faces, "source")
        tc = self._measure[0]
        if verts.dtype != tc.dtype or verts.device != tc.device:
            raise InputError(f"source is {verts.dtype} on {verts.device} but the target is "
                             f"{tc.dtype} on {tc.device}; convert one of them")
        q = varifold_measure(verts, faces.long())
        target = self.target
        backend = self.backend
        if backend == "auto":
            pts = torch.cat([q[0], tc]).detach()
            ext = float((pts.max(0).values - pts.min(0).values).norm())
            backend = choose_backend(q[0].shape[0], tc.shape[0], self.sigma, ext, verts.device,
                                     self.cutoff)
        engine = _Engine(backend, self.sigma, self.kernel, self.cutoff)
        grid_t = self._target_grid(engine) if backend == "truncated" else None
        self_s = self._term(engine, backend, q, q, True)
        cross = self._term(engine, backend, q, target, False, grid_t)
        pairs = engine.pairs
        self_t = self._target_self(engine, backend, target)
        n, nt = q[0].shape[0], tc.shape[0]
        self.stats = {"backend": backend, "pairs": pairs, "all_pairs": n * n + n * nt}
        return self_s - 2 * cross + self_t


def varifold_distance(verts, faces, target_verts, target_faces, sigma, kernel="binet",
                      backend="auto", target_weights=None, cutoff=None):
    """Squared varifold distance d^2(q, q') of two meshes (N,3),(F,3) and (N',3),(F',3) -> scalar."""
    return VarifoldLoss(target_verts, target_faces, sigma, kernel, backend, target_weights,
                        cutoff)(verts, faces)
