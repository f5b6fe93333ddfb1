r"""Articulated pre-fit: the basis' skeleton posed to the scan, then projected into the latent space.

A pose far from rest (arms overhead, a knee bent up and turned out, a crouch) is a local minimum the
latent levels cannot leave: at a coarse sigma folding a leg costs more path energy than it gains in
data term. A basis may carry a skeleton (``Skeleton.of_basis``: joint centres of the template, parents,
skinning weights, optionally a library of typical poses as joint rotations). Before the first level the
template is posed by linear blend skinning from rest and from the library's poses; the best starts are
fitted (every joint's rotation and a similarity) to the scan by L-BFGS on a coarse varifold, with a soft
penalty on rotations past each joint's range, coarse then finer; the best fit's skinned template is
projected into the latent space (``latent.project_to_basis``) and the registration starts from that code.
"""

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..latent import project_to_basis
from ..optimize import minimize_lbfgs
from ..transforms import Similarity, axis_angle_rotation
from ..varifold import BinnedMeasureLoss, cell_features, varifold_measure
from .prealign import bounded_log_scale, coarse_measure, surface_centroid

#: ``Basis.extras`` keys of a skeleton (``Skeleton.of_basis``)
SKELETON_KEYS = ("skeleton_joints", "skeleton_parents", "skinning_weights")
#: ... and the optional ones: joint names (as a "|"-joined string array), each joint's range (J, 3, 2): the
#: least and largest rotation-vector component about each rest axis (radians), and a library of poses
#: (K, J, 3) rotation vectors tried as starts
SKELETON_OPTIONAL = ("skeleton_names", "skeleton_limits", "skeleton_pose_library")


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A template's skeleton: joints (J, 3) rest centres in the template frame, parents (J,) int (-1 for the
    root; every parent listed before its children), weights (N, J) skinning weights (rows sum to 1),
    limits (J, 3, 2) each joint's range: least and largest rotation-vector component about each rest axis
    (radians; a knee bends one way), library (K, J, 3) rotation vectors of typical poses (K may be 0),
    names (J,)."""

    joints: np.ndarray
    parents: np.ndarray
    weights: np.ndarray
    limits: np.ndarray
    library: np.ndarray
    names: tuple

    @classmethod
    def of_basis(cls, basis):
        """The basis' skeleton from its extras, or None when it has none (or a damaged one)."""
        extras = basis.extras
        if any(extras.get(k) is None for k in SKELETON_KEYS):
            return None
        joints = np.asarray(extras["skeleton_joints"], dtype=np.float64)
        parents = np.asarray(extras["skeleton_parents"], dtype=np.int64).ravel()
        weights = np.asarray(extras["skinning_weights"], dtype=np.float64)
        n_joints = len(joints)
        if (joints.shape != (n_joints, 3) or parents.shape != (n_joints,) or weights.shape != (len(basis.template), n_joints)
                or not (parents < np.arange(n_joints)).all() or not np.isfinite(weights).all()):
            return None
        weights = weights / np.maximum(weights.sum(1, keepdims=True), 1e-12)
        free = np.tile([-math.pi, math.pi], (n_joints, 3, 1))
        limits = np.asarray(extras.get("skeleton_limits", free), dtype=np.float64)
        library = np.asarray(extras.get("skeleton_pose_library", np.zeros((0, n_joints, 3))), dtype=np.float64)
        if (limits.shape != (n_joints, 3, 2) or (limits[..., 0] > limits[..., 1]).any() or library.ndim != 3
                or library.shape[1:] != (n_joints, 3)):
            return None
        names = extras.get("skeleton_names")
        names = tuple(str(np.asarray(names).ravel()[0]).split("|")) if names is not None else ()
        return cls(joints, parents, weights, limits, library, names if len(names) == n_joints else ())

    def tensors(self, dtype=torch.float64, device="cpu"):
        """(joints (J, 3), weights (N, J), limits (J, 3, 2)) as tensors."""
        as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        return as_t(self.joints), as_t(self.weights), as_t(self.limits)

    def within(self, j, rotvec, slack=1e-9):
        """Whether rotation vector (3,) lies in joint j's range."""
        return bool(((rotvec >= self.limits[j, :, 0] - slack) & (rotvec <= self.limits[j, :, 1] + slack)).all())


def batch_rotations(rotvecs):
    """Rotation matrices of rotation vectors: (J, 3) tensor -> (J, 3, 3) (differentiable)."""
    w = rotvecs
    z = torch.zeros_like(w[:, 0])
    skew = torch.stack([torch.stack([z, -w[:, 2], w[:, 1]], -1), torch.stack([w[:, 2], z, -w[:, 0]], -1),
                        torch.stack([-w[:, 1], w[:, 0], z], -1)], 1)
    return torch.linalg.matrix_exp(skew)


def skin(skeleton, verts, rotvecs, tensors=None):
    """The template posed by linear blend skinning: verts (N, 3) tensor at rest, rotvecs (J, 3) tensor (each
    joint's rotation about its centre, in the rest frame's axes; the root's included) -> (N, 3) tensor."""
    joints, weights, _ = tensors or skeleton.tensors(verts.dtype, verts.device)
    local = batch_rotations(rotvecs)
    rot, shift = [None] * len(joints), [None] * len(joints)
    for j, p in enumerate(skeleton.parents):
        r_local, t_local = local[j], joints[j] - local[j] @ joints[j]  # x -> R (x - c) + c
        if p < 0:
            rot[j], shift[j] = r_local, t_local
        else:
            rot[j], shift[j] = rot[p] @ r_local, rot[p] @ t_local + shift[p]
    rot, shift = torch.stack(rot), torch.stack(shift)
    moved = torch.einsum("jab,nb->nja", rot, verts) + shift[None]
    return (weights[:, :, None] * moved).sum(1)


def _directions():
    """The 26 unit directions to the faces, edges and corners of a cube: (26, 3)."""
    grid = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)],
                    dtype=np.float64)
    return grid / np.linalg.norm(grid, axis=1, keepdims=True)


def _turning(a, b):
    """The rotation vector (3,) of the smallest rotation taking unit vector a to unit vector b."""
    axis, cos = np.cross(a, b), float(np.clip(a @ b, -1.0, 1.0))
    if np.linalg.norm(axis) < 1e-9:
        if cos > 0:
            return np.zeros(3)
        other = np.eye(3)[int(np.argmin(np.abs(a)))]
        axis = np.cross(a, other)
    return axis / np.linalg.norm(axis) * math.acos(cos)


def searched_joints(skeleton, template):
    """The joints whose direction the discrete search tries (a wide range, not the root), heaviest subtree
    first, and the rest direction (3,) of each: from its centre to its subtree's skinned centroid."""
    n_joints = len(skeleton.joints)
    subtree = np.eye(n_joints, dtype=bool)
    for j in range(n_joints - 1, 0, -1):  # parents come before their children
        p = skeleton.parents[j]
        if p >= 0:
            subtree[p] |= subtree[j]
    out = []
    for j in range(n_joints):
        if skeleton.parents[j] < 0 or np.ptp(skeleton.limits[j], axis=1).max() < math.radians(90):
            continue
        mass = skeleton.weights[:, subtree[j]].sum(1)
        if mass.sum() <= 0:
            continue
        arm = (mass[:, None] * template).sum(0) / mass.sum() - skeleton.joints[j]
        if np.linalg.norm(arm) > 1e-9:
            out.append((float(mass.sum()), j, arm / np.linalg.norm(arm)))
    return [(j, arm) for _, j, arm in sorted(out, key=lambda item: -item[0])]


def direction_search(objective, x0, skeleton, template, passes=2):
    """Joint by joint (``searched_joints``), the rotation of its rest direction onto each of 26 directions
    within the joint's range, kept where the objective (of the variables x (n,) tensor) is lowest; ``passes``
    sweeps: -> variables (n,) numpy."""
    x = np.array(x0, dtype=np.float64)
    best = float(objective(torch.as_tensor(x)))
    for _ in range(passes):
        for j, arm in searched_joints(skeleton, template):
            for d in _directions():
                turn = _turning(arm, d)
                if not skeleton.within(j, turn):
                    continue
                trial = x.copy()
                trial[3 * j:3 * j + 3] = turn
                value = float(objective(torch.as_tensor(trial)))
                if value < best:
                    best, x = value, trial
    return x


@dataclass
class PoseFit:
    """The articulated fit: rotvecs (J, 3), the similarity scan -> template frame, the posed template
    (N, 3) in the template frame, its score (squared varifold over the scan's self term at the finer
    sigma), the start it came from (-1: rest, the library's index, or the library's size: the direction
    search's)."""

    rotvecs: np.ndarray
    transform: Similarity
    posed: np.ndarray
    score: float
    start: int


class PoseProblem:
    """The articulated fit against one alignment of the scan: variables x = (rotation vectors (J, 3), the
    template's rotation (3), translation (3), log-scale (1)) of the posed template moved toward the scan
    (M, 3), (G, 3), which ``transform`` puts in the template frame; ``objective(sigma)`` the coarse varifold
    over the scan's self term plus the range penalty and the prior."""

    def __init__(self, skeleton, basis, scan_verts, scan_faces, transform, settings, face_weights=None):
        self.skeleton, self.basis, self.settings, self.transform = skeleton, basis, settings, transform
        self.template = torch.as_tensor(basis.template, dtype=torch.float64)
        self.tensors = skeleton.tensors(torch.float64)
        self.faces = torch.as_tensor(basis.faces, dtype=torch.long)
        self.scan = (transform.apply(np.asarray(scan_verts, dtype=np.float64)), scan_faces, face_weights)
        self.center = surface_centroid(basis.template, basis.faces)[1]
        self.shift = surface_centroid(*self.scan)[1] - self.center
        self.n_joints, self.limit = len(skeleton.joints), math.log(settings.scale_limit)
        self.free = torch.as_tensor(skeleton.parents >= 0)  # the root's rotation is the similarity's
        self.sigmas = [s * basis.scale for s in settings.sigmas]
        self._objectives = {}

    def variables(self, rotvecs):
        """Rotation vectors (J, 3) -> variables (n,) numpy, the centroids matched."""
        return np.concatenate([np.asarray(rotvecs).ravel(), np.zeros(3), self.shift, np.zeros(1)])

    def rotations(self, x):
        """The joints' rotation vectors (J, 3) numpy of variables x (the root's zero)."""
        return np.asarray(x[:3 * self.n_joints]).reshape(self.n_joints, 3) * (self.skeleton.parents >= 0)[:, None]

    def objective(self, sigma):
        """objective(x (n,) tensor) -> scalar tensor at ``sigma`` (built once per sigma)."""
        if sigma in self._objectives:
            return self._objectives[sigma]
        cell, settings, n = self.settings.cell * sigma, self.settings, self.n_joints
        scan = BinnedMeasureLoss(*coarse_measure(self.scan[0] - self.center, self.scan[1], self.scan[2], cell), sigma)
        self_t, center_t = float(scan.self_t), torch.as_tensor(self.center, dtype=torch.float64)
        limits = self.tensors[2]

        def objective(x):
            rot = x[:3 * n].reshape(n, 3) * self.free[:, None]
            posed = skin(self.skeleton, self.template, rot, self.tensors)
            scale = torch.exp(bounded_log_scale(x[-1:], self.limit))[0]
            posed = scale * (posed - center_t) @ axis_angle_rotation(x[3 * n:3 * n + 3]).T + x[3 * n + 3:3 * n + 6]
            # binned afresh each evaluation (the cells follow the pose; the sums are differentiable)
            gamma = scan(*cell_features(*varifold_measure(posed, self.faces), cell)[:2]) / self_t
            excess = torch.relu(limits[..., 0] - rot) + torch.relu(rot - limits[..., 1])
            return gamma + settings.limit_weight * (excess ** 2).sum() + settings.prior * (rot ** 2).sum()

        self._objectives[sigma] = objective
        return objective

    def search(self):
        """The starts (rest, the library's poses and, from the best of them, the joints' directions searched)
        scored at the coarse sigma: -> [(score, start index, variables)], best first (index -1: rest, the
        library's size: the direction search's)."""
        coarse, library = self.objective(self.sigmas[0]), self.skeleton.library
        starts = [self.variables(r) for r in np.concatenate([np.zeros((1, self.n_joints, 3)), library])]
        with torch.no_grad():
            scores = [float(coarse(torch.as_tensor(x))) for x in starts]
            # each limb's direction searched in turn: the coarse varifold has no slope toward an arm raised
            # overhead from one hanging down (the torso lies between)
            starts.append(direction_search(coarse, starts[int(np.argmin(scores))], self.skeleton, self.basis.template))
            scores.append(float(coarse(torch.as_tensor(starts[-1]))))
        return sorted(((score, k - 1, x) for k, (score, x) in enumerate(zip(scores, starts))), key=lambda t: t[0])

    def refine(self, x, sigmas, monitor=None):
        """L-BFGS from variables x at each of ``sigmas`` in turn -> (variables, objective at the last)."""
        value = None
        for sigma in sigmas:
            x, value, _ = minimize_lbfgs(self.objective(sigma), x, monitor, max_iter=self.settings.max_iter,
                                         gtol=1e-9, ftol=1e-10)
        return x, value

    def result(self, x, score, start):
        """The PoseFit of variables x."""
        n, rot = self.n_joints, self.rotations(x)
        with torch.no_grad():
            posed = skin(self.skeleton, self.template, torch.as_tensor(rot), self.tensors).numpy()
        scale = math.exp(float(bounded_log_scale(float(x[-1]), self.limit)))
        r = axis_angle_rotation(x[3 * n:3 * n + 3])
        # the template moved by x -> s R (x - c) + tau + c; the scan moves by the inverse instead
        move = Similarity(r, scale, x[3 * n + 3:3 * n + 6] + self.center - scale * r @ self.center)
        return PoseFit(rot, move.inverse().compose(self.transform), posed, float(score), start)


def fit_pose(skeleton, basis, scan_verts, scan_faces, transforms, settings, face_weights=None, monitor=None):
    """The skeleton's pose and a similarity fitted to a scan (M, 3), (G, 3) from the best of candidate
    alignments ``transforms`` [Similarity scan -> template frame], as ``settings`` (a
    ``config.ArticulatedFit``) says: every alignment's starts searched at the coarse sigma, the best
    ``settings.starts`` of all fitted there, the best of those at the finer sigmas -> PoseFit."""
    problems = [PoseProblem(skeleton, basis, scan_verts, scan_faces, t, settings, face_weights) for t in transforms]
    found = []
    for problem in problems:
        if monitor is not None:
            monitor.check()
        found += [(score, start, x, problem) for score, start, x in problem.search()]
    fits = []
    for _, start, x, problem in sorted(found, key=lambda f: f[0])[:settings.starts]:
        x, value = problem.refine(x, problem.sigmas[:1], monitor)
        fits.append((value, start, x, problem))
    value, start, x, problem = min(fits, key=lambda f: f[0])
    x, value = problem.refine(x, problem.sigmas[1:], monitor)
    return problem.result(x, value, start)


def articulated_start(basis, skeleton, scan_verts, scan_faces, transforms, settings, face_weights=None,
                      monitor=None):
    """The code (P,) and alignment a registration starts from after the articulated fit (``fit_pose``) from
    candidate alignments [Similarity], and the fit: -> (code, Similarity, PoseFit)."""
    fit = fit_pose(skeleton, basis, scan_verts, scan_faces, transforms, settings, face_weights, monitor)
    code = project_to_basis(basis, fit.posed, ridge=settings.projection_ridge)[0]
    return code, fit.transform, fit
