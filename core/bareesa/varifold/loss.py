"""Varifold inner products and squared distances: of face measures and of binned measures."""

import math

import torch
from torch.autograd.function import once_differentiable

from ..errors import InputError
from ..geometry import face_centers
from .backends import RANGES_MARGIN, Engine, FacePairs, FeaturePairs, Grid, KeptRanges
from .kernels import check_options, resolve_backend
from .measure import binned_measure, cell_features, cell_groups, check_mesh, group_features, varifold_measure

TARGET_BIN_GAIN = 0.75    # VarifoldLoss bins its target only when that leaves at most this share of points
#: Default cell size of ``BinnedVarifoldLoss``, in units of sigma (relative kernel error ~ (cell/sigma)^2 / 4)
BIN_CELL = 0.4


#: arguments of ``_Inner.apply`` before the measures
_LEAD = 5


class _Inner(torch.autograd.Function):
    """<q, q'> of two measures (x, u, ...) of the engine's kind, with gradients from the fused pair
    sums (the self term <q, q> when ``symmetric``); kept: the term's ``KeptRanges`` or None."""

    @staticmethod
    def forward(ctx, engine, grid_j, grid_i, symmetric, kept, *measures):
        k = len(measures) // 2
        q, qt = measures[:k], measures[k:]
        need_i = any(ctx.needs_input_grad[_LEAD:_LEAD + k])
        need_j = any(ctx.needs_input_grad[_LEAD + k:]) and not symmetric
        kind = engine.kind
        F = engine.sums(q[0], q[1], qt[0], qt[1:], need_i, grid_j, kept)
        value = kind.value(q[1:], F)
        grads = []
        if need_i:  # d/dq <q,q> = 2 x (i-side derivative), k symmetric
            grads += kind.grads(q[1:], F, engine.g, 2.0 if symmetric else 1.0)
        if need_j:
            G = engine.sums(qt[0], qt[1], q[0], q[1:], True, grid_i)
            grads += kind.grads(qt[1:], G, engine.g, 1.0)
        ctx.need, ctx.k = (need_i, need_j), k
        ctx.save_for_backward(*grads)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, go):
        grads, k = list(ctx.saved_tensors), ctx.k
        out = [None] * (_LEAD + 2 * k)
        if ctx.need[0]:
            out[_LEAD:_LEAD + k] = [go * t for t in grads[:k]]
            grads = grads[k:]
        if ctx.need[1]:
            out[_LEAD + k:] = [go * t for t in grads[:k]]
        return tuple(out)


def varifold_inner(centers, normals, weights, other_centers, other_normals, other_weights,
                   sigma, kernel="binet", backend="dense", cutoff=None):
    """<q, q'> of two measures: (F,3),(F,3),(F,) and (F',3),(F',3),(F',) -> scalar (differentiable)."""
    sigma = check_options(sigma, kernel, backend, cutoff)
    backend = resolve_backend(backend, centers, other_centers, sigma, cutoff)
    engine = Engine(backend, sigma, FacePairs(kernel), cutoff)
    return _Inner.apply(engine, None, None, False, None, centers, normals, weights,
                        other_centers, other_normals, other_weights)


class _FixedTarget:
    """What a squared distance to a fixed target measure caches: the target's grid and self term."""

    def _start(self, measure, requires_grad, ranges_margin=RANGES_MARGIN):
        self._measure, self.target_requires_grad = measure, requires_grad
        self._grid = None
        self._self = {}
        # the moving source's terms' ranges
        self._kept = {"self": KeptRanges(ranges_margin), "cross": KeptRanges(ranges_margin)}
        self.stats = {}

    def _target_grid(self, engine):
        if self._grid is None or self._grid[0] != engine.cutoff:
            self._grid = (engine.cutoff, Grid(self._measure[0].detach(), engine.cutoff))
        return self._grid[1]

    def _target_self(self, engine, target):
        """<q', q'>, computed once per backend (every call if the target requires grad)."""
        backend = engine.backend
        grid = self._target_grid(engine) if backend == "truncated" else None
        if self.target_requires_grad:
            return self._term(engine, target, target, True, grid)
        if backend not in self._self:
            with torch.no_grad():
                self._self[backend] = self._term(engine, target, target, True, grid)
        return self._self[backend]

    def _term(self, engine, q, qt, symmetric, grid_j=None, kept=None):
        if engine.backend == "truncated" and grid_j is None and kept is None:
            grid_j = Grid(qt[0], engine.cutoff)
        if symmetric:
            qt = tuple(t.detach() for t in qt)
        return _Inner.apply(engine, grid_j, None, symmetric, kept, *q, *qt)

    def _distance(self, engine, q, target):
        """<q, q> - 2 <q, q'> + <q', q'> -> scalar; records ``stats``."""
        grid_t = self._target_grid(engine) if engine.backend == "truncated" else None
        self_s = self._term(engine, q, q, True, kept=self._kept["self"])
        cross = self._term(engine, q, target, False, grid_t,
                           kept=None if self.target_requires_grad else self._kept["cross"])
        pairs = engine.pairs
        self_t = self._target_self(engine, target)
        n, nt = q[0].shape[0], target[0].shape[0]
        self.stats = {"backend": engine.backend, "pairs": pairs, "all_pairs": n * n + n * nt}
        return self_s - 2 * cross + self_t


class VarifoldLoss(_FixedTarget):
    """Squared varifold distance to a fixed target: ``loss(verts (N,3), faces (F,3)) -> scalar``.

    Caches the target's centres/normals/weighted areas, its self term <q', q'> (unless the target
    requires grad) and, for "truncated", its grid. ``stats`` holds the backend and the number of
    face pairs evaluated by the last call (``pairs``) next to the all-pairs count (``all_pairs``).

    ``target_cell`` (a length, e.g. sigma / 2): the target measure is replaced by its
    ``binned_measure`` on cells of that size when this has at most TARGET_BIN_GAIN times as
    many points as the target has faces (a scan much finer than sigma: otherwise the small
    saving is not worth the approximation and its dependence on the cell grid); the source
    stays exact. Not for a target that
    requires grad. ``target_points`` is the number of target points used. ``ranges_margin`` (a share of
    the cutoff): how far the truncated backend's kept block-sparse
    ranges reach beyond the cutoff, and so how far the source may move before they are found again (a
    solve whose steps move points further, e.g. free vertex displacements, keeps them with a wider one).
    """

    def __init__(self, target_verts, target_faces, sigma, kernel="binet", backend="auto",
                 target_weights=None, cutoff=None, target_cell=None, ranges_margin=RANGES_MARGIN):
        self.sigma = check_options(sigma, kernel, backend, cutoff)
        if target_cell is not None and not (float(target_cell) > 0 and math.isfinite(float(target_cell))):
            raise InputError(f"target_cell must be a positive finite length or None, got {target_cell}")
        check_mesh(target_verts, target_faces, "target")
        if target_weights is not None:
            if not torch.is_tensor(target_weights) or target_weights.shape != target_faces.shape[:1]:
                raise InputError(f"target_weights must be a tensor of shape ({target_faces.shape[0]},)")
            if not bool(torch.isfinite(target_weights).all()) or bool((target_weights < 0).any()):
                raise InputError("target_weights must be finite and nonnegative")
            target_weights = target_weights.to(target_verts)
        self.kernel, self.backend, self.cutoff = kernel, backend, cutoff
        self._target_mesh = (target_verts, target_faces.long(), target_weights)
        measure = varifold_measure(*self._target_mesh)
        requires_grad = any(t.requires_grad for t in measure)
        if target_cell is not None:
            if requires_grad:
                raise InputError("target_cell bins the target, which then cannot require grad")
            binned = binned_measure(*measure, float(target_cell), kernel)
            if binned[0].shape[0] <= TARGET_BIN_GAIN * measure[0].shape[0]:
                measure = binned
        self._start(measure, requires_grad, ranges_margin)
        self.target_points = measure[0].shape[0]

    @property
    def target(self):
        """Target centres (F',3), normals (F',3), weighted areas (F',); rebuilt if it requires grad."""
        return varifold_measure(*self._target_mesh) if self.target_requires_grad else self._measure

    def __call__(self, verts, faces, weights=None):
        """Squared distance d^2(q, q_target) of the mesh (verts (N,3), faces (F,3); its faces' weights (F,) or
        None: each face counted by its area times its weight) -> scalar."""
        check_mesh(verts, faces, "source")
        tc = self._measure[0]
        if verts.dtype != tc.dtype or verts.device != tc.device:
            raise InputError(f"source is {verts.dtype} on {verts.device} but the target is "
                             f"{tc.dtype} on {tc.device}; convert one of them")
        q = varifold_measure(verts, faces.long(), weights)
        backend = resolve_backend(self.backend, q[0], tc, self.sigma, self.cutoff)
        return self._distance(Engine(backend, self.sigma, FacePairs(self.kernel), self.cutoff), q, self.target)


def varifold_distance(verts, faces, target_verts, target_faces, sigma, kernel="binet",
                      backend="auto", target_weights=None, cutoff=None):
    """Squared varifold distance d^2(q, q') of two meshes (N,3),(F,3) and (N',3),(F',3) -> scalar."""
    return VarifoldLoss(target_verts, target_faces, sigma, kernel, backend, target_weights,
                        cutoff)(verts, faces)


class BinnedMeasureLoss(_FixedTarget):
    """Squared varifold distance of binned measures to a fixed one:
    ``loss(centroids (C,3), features (C,K)) -> scalar`` (differentiable in both).

    target_centers (D, 3), target_features (D, K) (``measure.cell_features``; detached). Caches
    the target's self term (``self_t``) and grid; ``stats`` as for ``VarifoldLoss``.
    """

    def __init__(self, target_centers, target_features, sigma, backend="auto", cutoff=None):
        self.sigma = check_options(sigma, None, backend, cutoff)
        self.backend, self.cutoff = backend, cutoff
        self._start((target_centers.detach(), target_features.detach()), False)

    @property
    def target(self):
        """Target centroids (D, 3) and features (D, K)."""
        return self._measure

    def _engine(self, centers):
        backend = resolve_backend(self.backend, centers, self._measure[0], self.sigma, self.cutoff)
        return Engine(backend, self.sigma, FeaturePairs(self._measure[1].shape[1]), self.cutoff)

    @property
    def self_t(self):
        """<q', q'> (scalar tensor) with the backend chosen for the target against itself."""
        return self._target_self(self._engine(self._measure[0]), self._measure)

    def __call__(self, centers, features):
        """d^2 of the binned measure (C, 3), (C, K) to the target -> scalar."""
        return self._distance(self._engine(centers), (centers, features), self._measure)


class BinnedVarifoldLoss:
    """Squared varifold distance with both measures summed over cubic cells (default BIN_CELL x sigma).

    For sigma much larger than the faces (the coarse levels of a schedule) this replaces
    F x (F + G) face pairs by C x (C + D) cell pairs. The target (scan) is binned once; the
    source's faces are grouped once (by their cells at construction) and each call sums the
    moving faces over these fixed groups (differentiable). Orientation is exact; positions are
    approximated by each group's centroid (relative kernel error ~ (cell / sigma)^2 / 4). The
    cell pairs are summed by ``backend`` ("auto" chooses as for faces).
    """

    def __init__(self, source_verts, faces, target_verts, target_faces, sigma, kernel="binet",
                 target_weights=None, cell=None, backend="auto", cutoff=None):
        sigma = check_options(sigma, kernel, backend, cutoff)
        self.kernel = kernel
        cell = BIN_CELL * sigma if cell is None else cell
        self.groups, self.n_groups = cell_groups(face_centers(source_verts.detach(), faces), cell)
        x, feat, _ = cell_features(*varifold_measure(target_verts, target_faces, target_weights), cell, kernel)
        self.n_target = x.shape[0]
        self._loss = BinnedMeasureLoss(x, feat, sigma, backend, cutoff)

    @property
    def target(self):
        """Binned target: centroids (D, 3), features (D, K)."""
        return self._loss.target

    @property
    def self_t(self):
        """|target|^2 (computed on first use: callers may first only look at the sizes)."""
        return self._loss.self_t

    @property
    def stats(self):
        """Backend and pair counts of the last call."""
        return self._loss.stats

    def __call__(self, verts, faces):
        """Squared binned distance of the mesh (verts (N, 3), faces (F, 3)) to the target -> scalar."""
        x, feat, _ = group_features(*varifold_measure(verts, faces), self.groups, self.n_groups, self.kernel)
        return self._loss(x, feat)
