"""The one similarity-transform type: x -> scale * R x + t, for numpy arrays and torch tensors."""

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .errors import InputError


def axis_angle_rotation(w):
    """Rotation matrix of an axis-angle vector (exact at 0): (3,) tensor -> (3, 3) tensor
    (differentiable), or (3,) array -> (3, 3) float64 array.

    On the CPU the exponential of the skew matrix and its derivative are Rodrigues' formula in float64
    numpy (``rodrigues``): the solves' similarity variables build one rotation an evaluation, ~1,000 a
    registration, and torch's matrix_exp with its backward is many small autograd ops (and ~1e-12 off at
    small angles). Elsewhere, and for a second derivative, torch's matrix_exp."""
    if not isinstance(w, torch.Tensor):
        return rodrigues(np.asarray(w, dtype=np.float64))[0]
    if w.device.type == "cpu":
        return _Rotation.apply(w)
    return _exp_skew(w)


def _exp_skew(w):
    """matrix_exp of the skew matrix of w (3,) tensor (differentiable to any order)."""
    z = torch.zeros((), dtype=w.dtype, device=w.device)
    skew = torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])
    return torch.linalg.matrix_exp(skew)


#: Below this squared angle ``rodrigues`` takes its coefficients from their Taylor series in t = angle^2
#: (to t^5: a remainder under 1e-17); above it the closed forms lose at most ~3e-14 to cancellation
SMALL_ANGLE_SQ = 1e-2


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


_SKEW_BASIS = np.stack([_skew(row) for row in np.eye(3)])  # dK/dw_i, (3, 3, 3)


def rodrigues(w):
    """exp of the skew matrix K of w (3,) float64 array, R = I + a K + b K^2 (a = sin(r) / r,
    b = (1 - cos r) / r^2, r = |w|), and its derivative: -> R (3, 3), dR/dw (3, 3, 3) with [i] = dR/dw_i."""
    t = float(w @ w)
    if t < SMALL_ANGLE_SQ:
        terms = range(6)
        a = sum((-t) ** k / math.factorial(2 * k + 1) for k in terms)
        b = sum((-t) ** k / math.factorial(2 * k + 2) for k in terms)
        da = sum(-k * (-t) ** (k - 1) / math.factorial(2 * k + 1) for k in terms if k)
        db = sum(-k * (-t) ** (k - 1) / math.factorial(2 * k + 2) for k in terms if k)
    else:
        r = math.sqrt(t)
        a, b = math.sin(r) / r, 0.5 * (math.sin(r / 2) / (r / 2)) ** 2
        da, db = (math.cos(r) - a) / (2 * t), (a - 2 * b) / (2 * t)
    k = _skew(w)
    k2 = k @ k
    rotation = np.eye(3) + a * k + b * k2
    e = _SKEW_BASIS
    grad = a * e + b * (e @ k + k @ e) + 2 * w[:, None, None] * (da * k + db * k2)
    return rotation, grad


class _Rotation(torch.autograd.Function):
    """``axis_angle_rotation`` on the CPU: Rodrigues' formula and its derivative in numpy; a second
    derivative (create_graph) goes through torch's matrix_exp."""

    @staticmethod
    def forward(ctx, w):
        rotation, grad = rodrigues(w.detach().numpy().astype(np.float64))
        ctx.save_for_backward(w)
        ctx.grad = grad
        return torch.as_tensor(rotation, dtype=w.dtype)

    @staticmethod
    def backward(ctx, upstream):
        (w,) = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: a differentiable gradient
            with torch.enable_grad():
                return torch.autograd.grad(_exp_skew(w), w, upstream, create_graph=True)
        return torch.einsum("ijk,jk->i", torch.as_tensor(ctx.grad, dtype=upstream.dtype), upstream)


def rotation_angle(a, b):
    """Angle in degrees between two rotation matrices (3, 3)."""
    return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(a @ b.T) - 1) / 2))))


@dataclass(frozen=True, eq=False)
class Similarity:
    """The map x -> scale * rotation @ x + translation (e.g. scan frame -> template frame).

    rotation (3, 3) proper orthogonal, scale > 0, translation (3,).
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    scale: float = 1.0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        r = np.array(self.rotation, dtype=np.float64).reshape(3, 3)
        t = np.array(self.translation, dtype=np.float64).reshape(3)
        s = float(self.scale)
        if not (np.isfinite(r).all() and np.isfinite(t).all() and math.isfinite(s) and s > 0):
            raise InputError(f"invalid similarity: scale {s}, rotation/translation finite: "
                             f"{bool(np.isfinite(r).all())}/{bool(np.isfinite(t).all())}")
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
            raise InputError("similarity rotation must be a proper rotation matrix (R R^T = I, det +1)")
        for a in (r, t):
            a.flags.writeable = False
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "scale", s)

    def _like(self, points):
        if isinstance(points, torch.Tensor):
            as_t = lambda a: torch.tensor(a.tolist(), dtype=points.dtype, device=points.device)  # noqa: E731
            return as_t(self.rotation), as_t(self.translation)
        return self.rotation, self.translation

    def apply(self, points):
        """x -> scale R x + t: (..., 3) ndarray or tensor -> same type."""
        r, t = self._like(points)
        return self.scale * points @ r.T + t

    def invert(self, points):
        """The inverse map: (..., 3) ndarray or tensor -> same type."""
        r, t = self._like(points)
        return ((points - t) / self.scale) @ r

    def invert_vectors(self, vectors):
        """The inverse map's linear part (displacements, no translation): (..., 3) -> same type."""
        r, _ = self._like(vectors)
        return (vectors / self.scale) @ r

    def compose(self, other):
        """The similarity ``self o other`` (apply ``other`` first)."""
        return Similarity(self.rotation @ other.rotation, self.scale * other.scale,
                          self.scale * self.rotation @ other.translation + self.translation)

    def inverse(self):
        """The inverse similarity."""
        return Similarity(self.rotation.T, 1.0 / self.scale, -(self.rotation.T @ self.translation) / self.scale)

    def matrix(self):
        """The (4, 4) float64 homogeneous matrix [[scale R, t], [0, 1]]."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.scale * self.rotation, self.translation
        return m

    def to_dict(self):
        """JSON-ready {"rotation": 3x3 list, "scale": s, "translation": [x, y, z]}."""
        return {"rotation": self.rotation.tolist(), "scale": self.scale,
                "translation": self.translation.tolist()}

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(d["rotation"], d["scale"], d["translation"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"not a similarity record: {d!r}") from exc
