"""The one similarity-transform type: x -> scale * R x + t, for numpy arrays and torch tensors."""

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .errors import InputError


def axis_angle_rotation(w):
    """Rotation matrix of an axis-angle vector (exact at 0): (3,) tensor -> (3, 3) tensor
    (differentiable), or (3,) array -> (3, 3) float64 array."""
    if not isinstance(w, torch.Tensor):
        return axis_angle_rotation(torch.as_tensor(np.asarray(w, dtype=np.float64))).numpy()
    z = torch.zeros((), dtype=w.dtype, device=w.device)
    skew = torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])
    return torch.linalg.matrix_exp(skew)


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
