r"""Varifold distance between triangle meshes (appendix "Mesh invariant similarity measures").

A mesh q is represented by its faces f: barycentres c_f, unit normals n_f, areas a_f.
With the kernel

    k(x, n, x', n') = exp(-|x - x'|^2 / sigma^2) * kappa(n . n'),
    kappa = "binet": (n.n')^2 (default, the paper's)  | "linear": n.n' (oriented)  | "constant": 1,

the inner product is <q, q'> = sum_{f, f'} k(c_f, n_f, c_f', n_f') a_f a_f' and the squared
distance is d^2(q, q') = <q, q> - 2 <q, q'> + <q', q'>. Meshes may have any sizes and
connectivities; d^2 is differentiable (autograd) in the vertices of both meshes.

Modules: ``kernels`` (KERNELS, option checks, ``default_cutoff``, ``choose_backend``),
``measure`` (face measures and the binned measure), ``backends`` (the pair sums),
``loss`` (inner products and distances).

Binned measures
---------------
For sigma much larger than the faces, faces are summed over cells (``measure.group_features``,
``measure.cell_features``): each cell keeps its weighted centroid and the sum of its faces'
features, which make kappa a dot product (binet: sum a n n^T, 9 numbers; linear: sum a n, 3;
constant: sum a, 1), so that the kernel of two cells is exp(-|x - x'|^2 / sigma^2) <f, f'>,
exact in the orientations. ``BinnedVarifoldLoss`` (a moving mesh against a binned target) and
``BinnedMeasureLoss`` (a binned measure, e.g. moved by a similarity, against a binned target)
evaluate these cell pairs with the same backends as faces. ``binned_measure`` turns a binned
measure into at most 3 pseudo-faces per cell, for a fixed target of the face path
(``VarifoldLoss(target_cell=)``).

Public API
----------
``varifold_distance(verts, faces, target_verts, target_faces, sigma, ...)`` one-shot d^2;
``VarifoldLoss(target_verts, target_faces, sigma, ...)`` the same for a fixed target, with the
target's representation, self term <q', q'> and spatial grid cached (``loss(verts, faces)``);
``binned_measure`` a measure summed over cubic cells (exact orientation kernel);
``varifold_inner`` the raw inner product of two (centres, normals, weights) measures;
``BinnedVarifoldLoss``, ``BinnedMeasureLoss`` distances of binned measures;
``choose_backend`` the rule used by ``backend="auto"``; ``default_cutoff``.
``kernels._KEOPS = False`` forces the torch code paths (as if pykeops were missing).

Backends (same maths, different evaluation strategies, as in geomloss)
----------------------------------------------------------------------
* ``"dense"``: plain torch, all pairs, chunked over rows so that temporaries stay below
  ~256 MB. Exact differences x - x' (accurate in float32). For small problems.
* ``"keops"``: pykeops LazyTensor reduction over all pairs (CPU or CUDA). One formula for the
  three kernels (kappa(t) = c0 + c1 t + c2 t^2 with c and 1/sigma^2 passed as parameters), one
  reduction that returns the value *and* the gradient terms, so a new sigma or kernel never
  recompiles; a compile (once per machine, cached in ``pykeops.get_build_folder()``,
  typically ~/.cache/keops2.3/) happens once per dtype x {value, value+gradient} x {dense, ranges}
  (binned measures: also once per feature dimension).
* ``"truncated"``: ignores the pairs with |x - x'| >= cutoff. The second mesh is sorted into a
  uniform grid of cubic cells (size cutoff/4, cached by ``VarifoldLoss`` for the target); the
  first mesh is sorted into coarser clusters (size cutoff/2). For each cluster, the cells whose
  box lies within ``ranges_reach(cutoff)`` (the cutoff and a margin of 2 x RANGES_MARGIN x cutoff)
  of the cluster's bounding box form at most one contiguous run of the sorted second mesh per
  (y, z) row of cells; these runs are the block-sparse ``ranges`` of a KeOps reduction (CPU or
  CUDA). A loss keeps each moving term's clusters and runs (``backends.KeptRanges``) until a vertex
  has moved more than RANGES_MARGIN x cutoff. Without pykeops the same runs are evaluated as padded
  torch tiles (slower on CPU).

Truncation error bound: every ignored pair has spatial kernel value exp(-|x-x'|^2/sigma^2) <=
tol := exp(-cutoff^2/sigma^2) and |kappa| <= 1 for unit normals, so for each inner product

    |<q, q'>_truncated - <q, q'>| <= tol * A * A',    A = sum_f a_f,  A' = sum_f' a'_f'  (weighted),

hence |d^2_truncated - d^2| <= tol * (A + A')^2 (binned measures: the same with A = sum |f|,
since |<f, f'>| <= |f| |f'|, and |f| <= the cell's area). The default cutoff is
``sigma * sqrt(log(1 / tol))`` with tol = 1e-6 (3.72 sigma). The bound is pessimistic: on a
smooth surface the ignored mass of an inner product is ~tol times the inner product itself, and
the self and cross terms' errors largely cancel in d^2 when q and q' are close.

``backend="auto"`` (see ``choose_backend``): on CUDA, "keops" (or "dense" without pykeops);
on CPU, "truncated" when the cutoff is below a quarter of the bounding-box diagonal of both meshes,
pykeops imports and max(n_source, n_target)^2 >= 1.5e6 face (or cell) pairs; else "dense" while that
is < 2e7, else "truncated" when the cutoff is short, else "keops" (or "dense" without pykeops).
"""

from . import kernels
from .backends import build_keops_kernels
from .kernels import (BACKENDS, DEFAULT_TOL, KERNELS, choose_backend, default_cutoff, is_oriented,
                      keops_available)
from .loss import BIN_CELL, BinnedMeasureLoss, BinnedVarifoldLoss, VarifoldLoss, varifold_distance, varifold_inner
from .measure import binned_measure, cell_features, group_features, moved_measure, varifold_measure

__all__ = ["BACKENDS", "BIN_CELL", "BinnedMeasureLoss", "BinnedVarifoldLoss", "DEFAULT_TOL", "KERNELS",
           "VarifoldLoss", "binned_measure", "build_keops_kernels", "cell_features", "choose_backend",
           "default_cutoff", "group_features", "is_oriented", "keops_available", "kernels", "moved_measure",
           "varifold_distance", "varifold_inner", "varifold_measure"]
