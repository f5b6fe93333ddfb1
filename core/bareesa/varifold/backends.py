r"""Pair sums of a measure against a "j" measure: dense torch, KeOps, and truncated (grid + runs).

A measure is (x, u, *rest): centres x (N, 3), the data u the "i" side needs and, on the "j"
side, v = (u, *rest). Every backend computes, for each "i" point, sums over the "j" points of
the Gaussian K_ij = exp(-g |x_i - y_j|^2) (g = 1 / sigma^2) times what the kind of measure
puts on a pair (``FacePairs``, ``FeaturePairs``), with the sums that the gradient needs.
"""

import hashlib
import os
import sys
import threading
import warnings
from pathlib import Path

import torch

from .kernels import KEOPS_CPU_FLAGS, KERNELS, default_cutoff, disable_keops, keops_available
from .measure import face_features

DENSE_CHUNK_BYTES = 256 * 2**20
CELL_FRACTION = 0.25      # grid cell size of the "j" measure, in units of the cutoff
CLUSTER_FRACTION = 0.5    # cluster size of the "i" measure, in units of the cutoff
TABLE_CELLS_PER_POINT = 16  # a grid keeps a table of where each cell's points begin up to this many cells a point
#: Block-sparse ranges reach RANGES_MARGIN x the cutoff beyond it on either side (every term alike, so that a
#: measure's distance to itself stays zero), and a term's ``KeptRanges`` are reused while no point has moved
#: more than that margin since they were found
RANGES_MARGIN = 0.025


def ranges_reach(cutoff, margin=RANGES_MARGIN):
    """How far block-sparse ranges reach for a cutoff: cutoff (1 + 2 margin)."""
    return cutoff * (1 + 2 * margin)


# --------------------------------------------------------------------------- kinds of measures

class FacePairs:
    r"""Faces (x, n, a) against faces (y, m, b): k_ij = K_ij kappa(n_i . m_j) b_j (times a_i).

    Sums (N, 1 or 7): F0_i = sum_j k_ij, Fx_i = sum_j k_ij (x_i - y_j), Fn_i = sum_j b_j K_ij
    kappa'_ij m_j. Then <q, q'> = sum_i a_i F0_i and d/dx_i = -2 g a_i Fx_i, d/dn_i = a_i Fn_i,
    d/da_i = F0_i. kappa(t) = c0 + c1 t + c2 t^2 (``KERNELS``).
    """

    exact_differences = True   # the dense backend forms x_i - y_j (accurate in float32)
    #: KeOps sums the values alone (a fixed target's self term, once a level) with the gradient's formula and
    #: keeps their column: each formula is a compile at its first use on a machine
    #: (docs/decisions/004-keops-kernels-at-first-use.md)
    values_formula = False

    def __init__(self, kernel):
        self.params = KERNELS[kernel]

    def width(self, grad):
        """Number of sums per "i" point."""
        return 7 if grad else 1

    def masked(self, v, mask):
        """The "j" data (m, b) of padded tiles with the padding (mask 0) weightless."""
        m, b = v
        return m, b * mask

    def sums(self, K, fx, n, v, grad):
        """Sums from the Gaussian K (..., I, J) (overwritten), n (..., I, 3), v = (m (..., J, 3),
        b (..., J)); fx(W, sum_j W) -> sum_j W_ij (x_i - y_j) (..., I, 3)."""
        c0, c1, c2 = self.params
        m, b = v
        K = K.mul_(b.unsqueeze(-2))
        t = n @ m.transpose(-1, -2)
        W = K * (c0 + t * (c1 + c2 * t))
        F0 = W.sum(-1, keepdim=True)
        if not grad:
            return F0
        return torch.cat([F0, fx(W, F0), (K * (c1 + 2 * c2 * t)) @ m], -1)

    def keops(self, K, d, n, v, C, grad):
        """The same sums as a KeOps formula of LazyTensors (C: the kernel's coefficients)."""
        m, b = v
        K = K * b
        t = n | m
        kap = C.elem(0) + t * (C.elem(1) + C.elem(2) * t)
        if grad:
            return K * kap.concat(kap * d).concat((C.elem(1) + 2 * C.elem(2) * t) * m)
        return K * kap

    def value(self, data, F):
        """<q, q'> from the sums (data = (n, a) of the "i" measure) -> scalar."""
        return (data[1].detach() * F[:, 0]).sum()

    def grads(self, data, F, g, f):
        """f x the gradients of <q, q'> in (x, n, a) of the "i" measure."""
        a = data[1].detach()[:, None]
        return [(-2 * f * g) * a * F[:, 1:4], f * a * F[:, 4:7], f * F[:, 0]]


class FeaturePairs:
    r"""Binned measures (x, f) against (y, h): k_ij = K_ij <f_i, h_j> on K-dim features (``measure``).

    Sums (N, K or K+3): Fh_i = sum_j K_ij h_j, Fx_i = sum_j k_ij (x_i - y_j). Then
    <q, q'> = sum_i <f_i, Fh_i> and d/dx_i = -2 g Fx_i, d/df_i = Fh_i.
    """

    params = ()
    exact_differences = False  # coarse sigma: the dense backend expands |x - y|^2 (matrix products)
    #: the values alone have their own KeOps formula: the screening scores sum them on fine cells, where the
    #: gradient's formula is dearer (docs/decisions/004-keops-kernels-at-first-use.md)
    values_formula = True

    def __init__(self, dim):
        self.dim = dim

    def width(self, grad):
        """Number of sums per "i" point."""
        return self.dim + 3 if grad else self.dim

    def masked(self, v, mask):
        """The "j" features of padded tiles with the padding (mask 0) zero."""
        return (v[0] * mask.unsqueeze(-1),)

    def sums(self, K, fx, f, v, grad):
        """Sums from the Gaussian K (..., I, J) (overwritten), f (..., I, K), v = (h (..., J, K),); fx as for faces."""
        h = v[0]
        Fh = K @ h
        if not grad:
            return Fh
        return torch.cat([Fh, fx(K.mul_(f @ h.transpose(-1, -2)), None)], -1)

    def keops(self, K, d, f, v, C, grad):
        """The same sums as a KeOps formula of LazyTensors."""
        h = v[0]
        if grad:
            return (K * h).concat(K * (f | h) * d)
        return K * h

    def value(self, data, F):
        """<q, q'> from the sums (data = (f,) of the "i" measure) -> scalar."""
        return (data[0].detach() * F[:, :self.dim]).sum()

    def grads(self, data, F, g, f):
        """f x the gradients of <q, q'> in (x, f) of the "i" measure."""
        return [(-2 * f * g) * F[:, self.dim:], f * F[:, :self.dim]]


# --------------------------------------------------------------------------- pair sums

def _dense_sums(x, u, y, v, g, kind, grad, max_bytes=DENSE_CHUNK_BYTES):
    """All-pairs sums in torch, chunked over rows: faces with exact differences x - y (accurate in
    float32), binned measures (coarse sigma) as one tile per chunk (a few matrix products)."""
    rows = max(1, int(max_bytes // (12 * y.shape[0] * y.element_size())))
    out = []
    for s in range(0, x.shape[0], rows):
        if not kind.exact_differences:
            out.append(_tile_sums(x[None, s:s + rows], u[None, s:s + rows], y[None], tuple(t[None] for t in v),
                                  g, kind, grad)[0])
            continue
        d = x[s:s + rows, None, :] - y[None, :, :]               # (B, M, 3)
        K = torch.exp(-g * (d * d).sum(-1))                      # (B, M)
        out.append(kind.sums(K, lambda W, _, d=d: torch.einsum("bm,bmk->bk", W, d), u[s:s + rows], v, grad))
    return torch.cat(out, 0)


def _lazy(t, side):
    """A tensor (P, D) or (P,) as a KeOps LazyTensor of the "i" or "j" side."""
    from pykeops.torch import LazyTensor
    t = t if t.ndim == 2 else t[:, None]
    return LazyTensor((t[:, None, :] if side == "i" else t[None, :, :]).contiguous())


def _keops_sums(x, u, y, v, g, kind, grad, ranges=None):
    """All-pairs (or block-sparse with ``ranges``) sums with one KeOps reduction."""
    from pykeops.torch import LazyTensor
    xi, ui = _lazy(x, "i"), _lazy(u, "i")
    yj, vj = _lazy(y, "j"), [_lazy(t, "j") for t in v]
    G = LazyTensor(torch.tensor([g], dtype=x.dtype, device=x.device))
    C = LazyTensor(torch.tensor(kind.params, dtype=x.dtype, device=x.device)) if kind.params else None
    d = xi - yj
    K = (-G * d.sqnorm2()).exp()
    return kind.keops(K, d, ui, vj, C, grad).sum(dim=1, ranges=ranges)


def keops_formulas(kernels=("binet",)):
    """The KeOps formulas the losses use with these kernels (names, or names joined by "+"): face sums, and
    cell-feature sums of each kernel's features (binet's 9 numbers a cell, linear's 3, constant's 1), each
    with the gradient's sums and, where the kind has one (``values_formula``), without; a kernel's
    coefficients are arguments, not part of a formula, so the face sums of every kernel share one
    -> [(kind, grad)]."""
    probe = torch.ones(1, 3, dtype=torch.float64), torch.ones(1, dtype=torch.float64)
    dims = sorted({face_features(*probe, name).shape[1] for k in kernels for name in k.split("+")}, reverse=True)
    kinds = [FacePairs("binet")] + [FeaturePairs(dim) for dim in dims]
    return [(kind, grad) for kind in kinds for grad in ((False, True) if kind.values_formula else (True,))]


_built = set()  # (dtype, device, formulas) this process has evaluated or found built
_building = threading.Lock()  # solves side by side in threads (the add-on's) build them once, one at a time


def _formula_names(formulas):
    """Names of formulas [(kind, grad)], e.g. ("FacePairs", "FeaturePairs9+grad")."""
    return tuple(f"{type(kind).__name__}{getattr(kind, 'dim', '')}{'+grad' if grad else ''}"
                 for kind, grad in formulas)


def _built_marker(dtype, device, formulas):
    """The file in KeOps' build folder that says these formulas were built for this environment (its
    Python, KeOps' flags, dtype and device): KeOps' binaries are per environment."""
    import pykeops

    tag = hashlib.sha1(repr((sys.prefix, sys.version, pykeops.__version__, os.environ.get("CXXFLAGS"),
                             KEOPS_CPU_FLAGS, _formula_names(formulas), str(dtype),
                             device.type)).encode()).hexdigest()[:16]
    return Path(pykeops.get_build_folder()) / f"bareesa_kernels_{tag}.built"


def build_keops_kernels(dtype=torch.float64, device="cpu", kernels=("binet",), announce=None):
    """Evaluate each of ``keops_formulas(kernels)`` once on a few points of ``dtype`` on ``device``, as the
    losses sum them there (block-sparse on the CPU, "truncated"; whole on a GPU, "keops"), so that KeOps
    compiles now what it has not built for this environment yet (3 formulas for binet levels, at their first
    use on a machine) instead of in the middle of a solve; then leaves a marker in KeOps' build folder, and
    later processes find it and do nothing. announce: called first when they are to be evaluated (e.g. to say so on a
    progress bar). Where KeOps cannot build them (no C++ compiler, a broken toolchain) it is turned off for
    the process with a warning, and the solvers use their torch sums. -> whether this call evaluated them
    (False: KeOps unavailable or turned off, or built before)."""
    device = torch.device(device)
    formulas = keops_formulas(kernels)
    key = (dtype, str(device), _formula_names(formulas))
    if key in _built or not keops_available():
        return False
    with _building:  # a second caller waits for the first and then finds them built
        return _build(key, dtype, device, formulas, announce)


def _build(key, dtype, device, formulas, announce):
    """``build_keops_kernels`` once the lock is held."""
    if key in _built or not keops_available():
        return False
    marker = _built_marker(dtype, device, formulas)
    if marker.exists():
        _built.add(key)
        return False
    if announce is not None:
        announce()
    x = torch.linspace(0, 1, 12, dtype=dtype, device=device).reshape(4, 3)
    normals = torch.nn.functional.normalize(x + 0.5, dim=1)
    weights = torch.ones(4, dtype=dtype, device=device)
    features = torch.cat([x, x, x], 1)
    try:
        for kind, grad in formulas:
            engine = Engine("keops" if device.type == "cuda" else "truncated", 1.0, kind, 10.0, use_keops=True)
            cells = features[:, :getattr(kind, "dim", 0)]
            u, v = (normals, (normals, weights)) if isinstance(kind, FacePairs) else (cells, (cells,))
            engine.sums(x, u, x, v, grad)
    except Exception as err:  # noqa: BLE001  (KeOps' compiler errors have no common type)
        disable_keops()
        message = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        warnings.warn(f"KeOps cannot build its kernels here ({message[:200]}); using torch's sums instead "
                      "(slower)", RuntimeWarning, stacklevel=3)
        return False
    _built.add(key)
    try:
        marker.write_text("built by bareesa.varifold.build_keops_kernels\n")
    except OSError:  # a read-only cache: the next process evaluates them again (a few ms each)
        pass
    return True


def _tile_sums(x, u, y, v, g, kind, grad):
    """Batched tile sums: x (T, I, 3), u (T, I, D), y (T, J, 3), v (T, J, ...) -> (T, I, width);
    centred expansion of |x - y|^2."""
    o = x[:, :1, :]
    x, y = x - o, y - o
    # |x|^2 + |y|^2 - 2 x.y in one product, then the Gaussian in place: each pass over the (T, I, J) tiles
    # counts (the pre-alignment's and pose stage's coarse sums are made of them; the same digits)
    d2 = torch.baddbmm((x * x).sum(-1)[:, :, None] + (y * y).sum(-1)[:, None, :], x, y.transpose(1, 2), alpha=-2)
    K = d2.clamp_min_(0).mul_(-g).exp_()

    def fx(W, row_sums):
        return x * (W.sum(-1, keepdim=True) if row_sums is None else row_sums) - W @ y

    return kind.sums(K, fx, u, v, grad)


class Grid:
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
        # where each cell's run of sorted points begins (runs are then looked up, not searched for), unless
        # the grid has far more cells than points (a scan with far clutter)
        n_cells = nx * ny * self.dims[2]
        self.first = None
        if n_cells <= TABLE_CELLS_PER_POINT * max(self.size, 1024):
            counts = torch.bincount(self.keys, minlength=n_cells)
            self.first = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])

    def run_bounds(self, lo, hi):
        """The sorted points' index ranges [start, end) of the runs of cell keys lo..hi (both (R,) >= 0,
        inclusive): as ``searchsorted`` finds them, by table when the grid has one."""
        if self.first is None:
            return torch.searchsorted(self.keys, lo), torch.searchsorted(self.keys, hi, right=True)
        top = self.first.shape[0] - 1
        return self.first[lo.clamp(0, top)], self.first[(hi + 1).clamp(0, top)]

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
        start, end = self.run_bounds((ix0 + row).reshape(-1), (ix1 + row).reshape(-1))
        valid = valid.reshape(-1) & (end > start)
        runs = torch.stack([start[valid], end[valid]], 1)
        owner = torch.arange(C, device=dev)[:, None].expand(C, ky * kz).reshape(-1)[valid]
        slices = torch.cumsum(torch.bincount(owner, minlength=C), 0)
        pairs = int(((runs[:, 1] - runs[:, 0]) * counts[owner]).sum())
        return perm_i, ranges_i, slices, runs, owner, pairs


def _moved(x, x0):
    """The largest distance a point moved: x, x0 (N, 3) -> float."""
    return float(((x - x0) ** 2).sum(1).max()) ** 0.5


class KeptRanges:
    """The block-sparse ranges of one term (a loss' self or cross term), kept across calls.

    They reach RANGES_MARGIN x cutoff beyond it on either side (``ranges_reach``) and are reused while no
    point of either side has moved more than that margin since: every pair within the cutoff is still
    among them. The pairs summed are then the same from call to call while the surface moves a little (an
    optimiser's late steps and line searches), instead of changing with every call's clusters; finding
    the ranges cost as much as a third of a finest-level evaluation.
    """

    def __init__(self, margin=RANGES_MARGIN):
        self._kept = None
        self.margin = margin

    def get(self, x, y, cutoff, grid=None):
        """(grid of y, ``Grid.ranges``' output) for the i points x (N, 3) and the j points y (M, 3):
        ``grid`` is y's when y is fixed (kept by the caller), None when y moves (a grid is then kept here).
        They reach ``margin`` x cutoff beyond it (the KeptRanges' margin, RANGES_MARGIN by default)."""
        margin = self.margin * cutoff
        if self._kept is not None:
            x0, y0, given, kept_cutoff, kept_grid, out = self._kept
            if (given is grid and kept_cutoff == cutoff and x0.shape == x.shape and _moved(x, x0) <= margin
                    and (grid is not None or (y0.shape == y.shape and _moved(y, y0) <= margin))):
                return kept_grid, out
        moving = grid is None
        kept_grid = Grid(y, cutoff) if moving else grid
        out = kept_grid.ranges(x, ranges_reach(cutoff, self.margin), CLUSTER_FRACTION * cutoff)
        self._kept = (x.clone(), y.clone() if moving else None, grid, cutoff, kept_grid, out)
        return kept_grid, out


def _truncated_tiles(xs, us, ys, vs, g, kind, grad, ranges_i, runs, owner, ti=16, tj=512):
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
    out = xs.new_zeros(xs.shape[0], kind.width(grad))
    chunk = max(1, DENSE_CHUNK_BYTES // (12 * ti * tj * xs.element_size()))
    ai, aj = torch.arange(ti, device=dev), torch.arange(tj, device=dev)
    for s in range(0, c.shape[0], chunk):
        ii = i0[s:s + chunk, None] + ai
        mi = ii < i1[s:s + chunk, None]
        ii = torch.where(mi, ii, i0[s:s + chunk, None])
        pp = p0[s:s + chunk, None] + aj
        mj = pp < p1[s:s + chunk, None]
        jj = jlist[torch.where(mj, pp, p0[s:s + chunk, None])]
        F = _tile_sums(xs[ii], us[ii], ys[jj], kind.masked(tuple(t[jj] for t in vs), mj), g, kind, grad)
        out.index_add_(0, ii[mi], F[mi])
    return out


# --------------------------------------------------------------------------- engine

class Engine:
    """Evaluates the pair sums of a measure against a "j" measure with one backend."""

    def __init__(self, backend, sigma, kind, cutoff, use_keops=None):
        self.backend, self.g, self.kind = backend, 1.0 / sigma ** 2, kind
        self.cutoff = default_cutoff(sigma) if cutoff is None else float(cutoff)
        self.use_keops = keops_available() if use_keops is None else use_keops
        self.pairs = 0            # pairs evaluated by the last calls (reset by the caller)

    def sums(self, x, u, y, v, grad, grid=None, kept=None):
        """Pair sums (N, width) of i = (x (N, 3), u (N, D)) against j = (y (M, 3), v (tuple of
        (M, ...))); grid: cached Grid of y; kept: the term's ``KeptRanges`` (truncated), or None."""
        x, u, y = x.detach(), u.detach(), y.detach()
        v = tuple(t.detach() for t in v)
        if self.backend == "dense":
            self.pairs += x.shape[0] * y.shape[0]
            return _dense_sums(x, u, y, v, self.g, self.kind, grad)
        # KeOps' formula: with the gradient's sums where the kind has no values-only one (their first columns)
        width, keops_grad = self.kind.width(grad), grad or not self.kind.values_formula
        if self.backend == "keops":
            self.pairs += x.shape[0] * y.shape[0]
            return _keops_sums(x, u, y, v, self.g, self.kind, keops_grad)[:, :width]
        if kept is not None:
            grid, (perm_i, ranges_i, slices, runs, owner, pairs) = kept.get(x, y, self.cutoff, grid)
        else:
            grid = Grid(y, self.cutoff) if grid is None else grid
            perm_i, ranges_i, slices, runs, owner, pairs = grid.ranges(
                x, ranges_reach(self.cutoff), CLUSTER_FRACTION * self.cutoff)
        self.pairs += pairs
        xs, us = x[perm_i], u[perm_i]
        ys, vs = y[grid.perm], tuple(t[grid.perm] for t in v)
        if self.use_keops:
            i32 = lambda t: t.to(torch.int32).contiguous()  # noqa: E731
            rng = (i32(ranges_i), i32(slices), i32(runs)) * 2   # axis-0 half unused (no KeOps autograd)
            F = _keops_sums(xs, us, ys, vs, self.g, self.kind, keops_grad, ranges=rng)[:, :width]
        else:
            F = _truncated_tiles(xs, us, ys, vs, self.g, self.kind, grad, ranges_i, runs, owner)
        out = torch.empty_like(F)
        out[perm_i] = F
        return out

