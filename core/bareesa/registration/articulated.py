r"""Articulated pre-fit: the basis' skeleton posed to the scan, then projected into the latent space.

A pose far from rest (arms overhead, a knee bent up and turned out, a crouch) is a local minimum the
latent levels cannot leave: at a coarse sigma folding a leg costs more path energy than it gains in
data term. A basis may carry a skeleton (``Skeleton.of_basis``: joint centres of the template, parents,
skinning weights, optionally a library of typical poses as joint rotations). Before the first level the
template is posed by linear blend skinning from rest and from the library's poses; the best starts are
fitted (every joint's rotation and a similarity) to the scan by L-BFGS on a coarse varifold, with a soft
penalty on rotations past each joint's range, coarse then finer; the best fit's skinned template is
projected into the latent space (``latent.project_to_basis``) and the registration starts from that code
(docs/decisions/021-articulated-prefit.md).
"""

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..geometry import vertex_areas
from ..latent import project_to_basis
from ..mesh import face_geometry
from ..optimize import minimize_lbfgs
from ..transforms import Similarity, axis_angle_rotation
from ..varifold import BinnedMeasureLoss, cell_features
from .prealign import bounded_log_scale, coarse_measure, surface_centroid

#: ``Basis.extras`` keys of a skeleton (``Skeleton.of_basis``); optional beside them: "skeleton_names" (one
#: "|"-joined string), "skeleton_limits" (J, 3, 2) each joint's range (the least and largest rotation-vector
#: component about each rest axis, radians) and "skeleton_pose_library" (K, J, 3) rotation vectors of poses
#: tried as starts
SKELETON_KEYS = ("skeleton_joints", "skeleton_parents", "skinning_weights")


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
        if (joints.shape != (n_joints, 3) or parents.shape != (n_joints,)
                or weights.shape != (len(basis.template), n_joints)
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
    """Rotation matrices of rotation vectors: (J, 3) tensor -> (J, 3, 3) by Rodrigues' formula (differentiable;
    the coefficients from their series near 0)."""
    w = rotvecs
    z = torch.zeros_like(w[:, 0])
    skew = torch.stack([torch.stack([z, -w[:, 2], w[:, 1]], -1), torch.stack([w[:, 2], z, -w[:, 0]], -1),
                        torch.stack([-w[:, 1], w[:, 0], z], -1)], 1)
    t = (w * w).sum(1)
    small = t < 1e-6
    safe = torch.where(small, torch.ones_like(t), t)
    angle = torch.sqrt(safe)
    a = torch.where(small, 1 - t / 6, torch.sin(angle) / angle)
    b = torch.where(small, 0.5 - t / 24, (1 - torch.cos(angle)) / safe)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a[:, None, None] * skew + b[:, None, None] * (skew @ skew)


def _depth_levels(parents):
    """The joints grouped by depth, root first: [(joints (k,), their parents (k,))] as index arrays."""
    depth = np.zeros(len(parents), dtype=np.int64)
    for j, p in enumerate(parents):
        depth[j] = 0 if p < 0 else depth[p] + 1
    return [(np.flatnonzero(depth == d), np.asarray(parents)[depth == d]) for d in range(int(depth.max()) + 1)]


def joint_transforms(parents, joints, rotvecs):
    """Each joint's rigid motion x -> R x + t from rotation vectors (..., J, 3) tensor (each about its joint
    centre joints (J, 3), in the rest frame's axes, after its parent's): -> (R (..., J, 3, 3), t (..., J, 3)).
    One batched step per depth of the tree (a few dozen tensor operations, not a few per joint)."""
    batch = rotvecs.shape[:-2]
    local = batch_rotations(rotvecs.reshape(-1, 3)).reshape(*batch, -1, 3, 3)
    local_shift = joints - (local @ joints[:, :, None])[..., 0]  # x -> R (x - c) + c
    order, rots, shifts = [], [], []
    position = np.empty(len(parents), dtype=np.int64)  # each joint's column in the stacked results
    for idx, par in _depth_levels(parents):
        r_local, t_local = local[..., idx, :, :], local_shift[..., idx, :]
        if par[0] < 0:
            r, t = r_local, t_local
        else:
            cols = torch.as_tensor(position[par])
            r_parent, t_parent = torch.cat(rots, -3)[..., cols, :, :], torch.cat(shifts, -2)[..., cols, :]
            r = r_parent @ r_local
            t = (r_parent @ t_local[..., None])[..., 0] + t_parent
        position[idx] = len(order) + np.arange(len(idx))
        order += list(idx)
        rots.append(r)
        shifts.append(t)
    back = torch.as_tensor(np.argsort(order))
    return torch.cat(rots, -3)[..., back, :, :], torch.cat(shifts, -2)[..., back, :]


def skin(skeleton, verts, rotvecs, tensors=None):
    """The template posed by linear blend skinning: verts (N, 3) tensor at rest, rotvecs (J, 3) tensor (each
    joint's rotation about its centre, in the rest frame's axes; the root's included) -> (N, 3) tensor."""
    joints, weights, _ = tensors or skeleton.tensors(verts.dtype, verts.device)
    rot, shift = joint_transforms(skeleton.parents, joints, rotvecs)
    moved = torch.einsum("jab,nb->nja", rot, verts) + shift[None]
    return (weights[:, :, None] * moved).sum(1)


def surface_samples(verts, faces, weights, count, seed=0):
    """Points of a surface drawn in proportion to area (fixed seed), each standing for an equal share of it:
    verts (N, 3), faces (F, 3), skinning weights (N, J) -> centres (S, 3), unit normals (S, 3), the share
    (float), their skinning weights (S, J) (their face's vertices' mean)."""
    vectors, areas, _ = face_geometry(verts, faces)
    pick = np.random.default_rng(seed).choice(len(faces), count, p=areas / areas.sum())
    normals = vectors[pick] / np.maximum(areas[pick], 1e-300)[:, None]
    return (verts[faces[pick]].mean(1), normals, float(areas.sum() / count), weights[faces[pick]].mean(1))


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


def searched_joints(skeleton, template, faces, share=0.05):
    """The joints whose direction the discrete search tries, heaviest subtree first, and the rest direction
    (3,) of each (from its centre to its subtree's skinned centroid): not the root, a wide range (90 degrees
    or more), a subtree of at least ``share`` of the surface (template (N, 3), faces (F, 3): a limb, not a
    hand)."""
    n_joints = len(skeleton.joints)
    subtree = np.eye(n_joints, dtype=bool)
    for j in range(n_joints - 1, 0, -1):  # parents come before their children
        p = skeleton.parents[j]
        if p >= 0:
            subtree[p] |= subtree[j]
    vertex_area = vertex_areas(torch.as_tensor(template), torch.as_tensor(faces)).numpy()
    total = vertex_area.sum()
    out = {}
    for j in range(n_joints):
        mass = vertex_area * skeleton.weights[:, subtree[j]].sum(1)
        if (skeleton.parents[j] < 0 or np.ptp(skeleton.limits[j], axis=1).max() < math.radians(90)
                or mass.sum() < share * total):
            continue
        arm = (mass[:, None] * template).sum(0) / mass.sum() - skeleton.joints[j]
        if np.linalg.norm(arm) > 1e-9:
            out[j] = (float(mass.sum()), arm / np.linalg.norm(arm))
    return [(j, arm) for j, (_, arm) in sorted(out.items(), key=lambda item: -item[1][0])]


def direction_search(problem, sigma, x0, passes=1, roots=False):
    """Joint by joint (``searched_joints``; ``roots``: the limbs' roots only), its rotation set to each
    candidate and kept where ``problem.values`` at ``sigma`` is lowest: a limb's root (an upper arm, a
    thigh) the rotations taking its rest direction onto each of 26 directions and its rotations in the pose
    library, a bone below a searched one (a forearm, a shin) the library's rotations only; clipped into
    its range; ``passes`` sweeps: -> variables (n,) numpy."""
    skeleton, basis = problem.skeleton, problem.basis
    x = np.array(x0, dtype=np.float64)
    rot = problem.rotations(x)
    best = float(problem.values(sigma, x, rot[None])[0])
    limbs = searched_joints(skeleton, basis.template, basis.faces)
    below = {j for j, _ in limbs if skeleton.parents[j] in {k for k, _ in limbs}}
    for _ in range(passes):
        for j, arm in limbs:
            if roots and j in below:
                continue
            lo, hi = skeleton.limits[j, :, 0], skeleton.limits[j, :, 1]
            turns = list(skeleton.library[:, j])
            # a turn onto any direction is a rotation about any axis: for an elbow, which bends about one,
            # most are no pose (a forearm folded back through the upper arm) and the coarse varifold can
            # prefer them; the library's poses bend it as people do
            if j not in below or not turns:
                turns = [_turning(arm, d) for d in _directions()] + turns
            turns = np.unique(np.round(np.clip(turns, lo, hi), 6), axis=0)
            trials = np.repeat(rot[None], len(turns), 0)
            trials[:, j] = turns
            values = problem.values(sigma, x, trials)
            k = int(np.argmin(values))
            if values[k] < best:
                best, rot = float(values[k]), trials[k]
    x[:3 * len(rot)] = rot.ravel()
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
        # the template as area samples whose centres and normals move with their blended joints: an evaluation
        # costs a few thousand points, not the whole mesh
        centres, normals, share, weights = surface_samples(basis.template, basis.faces, skeleton.weights,
                                                           settings.samples)
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
        self.samples = (as_t(centres), as_t(normals), torch.full((len(centres),), share, dtype=torch.float64),
                        as_t(weights))
        self.scan = (transform.apply(np.asarray(scan_verts, dtype=np.float64)), scan_faces, face_weights)
        (template_area, self.center), (scan_area, scan_center) = (surface_centroid(basis.template, basis.faces),
                                                                  surface_centroid(*self.scan))
        self.shift = scan_center - self.center  # where the posed centroid goes
        # the scan's size over the template's by their areas (a pose does not change them)
        self.size = math.sqrt(scan_area / template_area)
        self.n_joints, self.limit = len(skeleton.joints), math.log(settings.scale_limit)
        self.free = torch.as_tensor(skeleton.parents >= 0)  # the root's rotation is the similarity's
        self.sigmas = [s * basis.scale for s in settings.sigmas]
        self._objectives = {}

    def variables(self, rotvecs):
        """Rotation vectors (J, 3) -> variables (n,) numpy, the centroids matched."""
        return np.concatenate([np.asarray(rotvecs).ravel(), np.zeros(3), self.shift, np.zeros(1)])

    def posed_samples(self, rot):
        """The area samples' centres (..., S, 3) and unit normals (..., S, 3) posed by joint rotations
        (..., J, 3) tensor (linear blend skinning of the samples)."""
        centres, normals, _, weights = self.samples
        joint_rot, joint_shift = joint_transforms(self.skeleton.parents, self.tensors[0], rot)
        batch = rot.shape[:-2]
        blend = (weights @ joint_rot.reshape(*batch, self.n_joints, 9)).reshape(*batch, -1, 3, 3)
        posed = (blend @ centres[:, :, None])[..., 0] + weights @ joint_shift
        turned = (blend @ normals[:, :, None])[..., 0]
        return posed, turned / turned.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def place(self, posed, turned, x):
        """Posed samples (..., S, 3) and their normals moved by variables x (n,) tensor: turned and scaled
        about their centroid, which x's translation places, the surface areas matched before x's scale (a
        raised arm moves the centroid and changes the second moments, the pre-alignment's scale, not the
        area, so every pose tried keeps the scan's centroid and size) -> (posed, normals, scale tensor)."""
        n = self.n_joints
        scale = torch.exp(bounded_log_scale(x[-1:], self.limit))[0] * self.size
        r = axis_angle_rotation(x[3 * n:3 * n + 3])
        return scale * (posed - posed.mean(-2, keepdim=True)) @ r.T + x[3 * n + 3:3 * n + 6], turned @ r.T, scale

    def penalty(self, rot):
        """The range penalty and the prior of joint rotations (..., J, 3) tensor -> (...)."""
        limits = self.tensors[2]
        excess = torch.relu(limits[..., 0] - rot) + torch.relu(rot - limits[..., 1])
        return (self.settings.limit_weight * (excess ** 2).sum((-2, -1))
                + self.settings.prior * (rot ** 2).sum((-2, -1)))

    def values(self, sigma, x, rotvecs):
        """The objective at ``sigma`` (cells of ``search_cell``) of variables x (n,) numpy with their joint
        rotations replaced by each of rotvecs (T, J, 3) -> (T,) numpy: one batched posing and binning for all
        (the discrete searches try dozens of rotations a joint)."""
        cell_size = self.settings.search_cell * sigma
        key = ("batch", sigma, cell_size)
        if key not in self._objectives:
            scan = BinnedMeasureLoss(*coarse_measure(self.scan[0] - self.center, self.scan[1], self.scan[2],
                                                     cell_size), sigma)
            self._objectives[key] = (scan.target, float(scan.self_t))
        (target_x, target_f), self_t = self._objectives[key]
        count = len(rotvecs)
        with torch.no_grad():
            rot = torch.as_tensor(rotvecs, dtype=torch.float64) * self.free[:, None]
            posed, turned, scale = self.place(*self.posed_samples(rot), torch.as_tensor(x))  # (T, S, 3)
            scale = float(scale)
            # every trial's samples binned at once: cells keyed by (trial, cell)
            ijk = torch.floor(posed / cell_size).long()
            ijk = ijk - ijk.reshape(-1, 3).min(0).values
            dims = ijk.reshape(-1, 3).max(0).values + 1
            trial = torch.arange(count)[:, None].expand(-1, posed.shape[1])
            cellkey = ((trial * dims[0] + ijk[..., 0]) * dims[1] + ijk[..., 1]) * dims[2] + ijk[..., 2]
            keys, groups = torch.unique(cellkey.reshape(-1), return_inverse=True)
            mass = torch.full((posed.shape[1],), float(self.samples[2][0]) * scale ** 2, dtype=torch.float64)
            feats = (mass[:, None] * (turned[..., :, None] * turned[..., None, :]).reshape(count, -1, 9)).reshape(-1, 9)
            weight = mass.repeat(count)
            total = weight.new_zeros(len(keys)).index_add(0, groups, weight)
            centroid = posed.new_zeros(len(keys), 3).index_add(0, groups, weight[:, None] * posed.reshape(-1, 3))
            centroid = centroid / total[:, None]
            feature = feats.new_zeros(len(keys), 9).index_add(0, groups, feats)
            owner = keys // (dims[0] * dims[1] * dims[2])
            sizes = torch.bincount(owner, minlength=count)
            slot = torch.arange(len(keys)) - torch.repeat_interleave(torch.cumsum(sizes, 0) - sizes, sizes)
            width = int(sizes.max())
            cx = posed.new_zeros(count, width, 3).index_put_((owner, slot), centroid)
            cf = posed.new_zeros(count, width, 9).index_put_((owner, slot), feature)  # empty slots weigh 0
            g = 1.0 / sigma ** 2
            own = torch.exp(-g * torch.cdist(cx, cx) ** 2) * (cf @ cf.transpose(1, 2))
            cross = torch.exp(-g * torch.cdist(cx, target_x[None]) ** 2) * (cf @ target_f.T[None])
            gamma = (own.sum((1, 2)) - 2 * cross.sum((1, 2)) + self_t) / self_t
        return (gamma + self.penalty(rot)).numpy()

    def rotations(self, x):
        """The joints' rotation vectors (J, 3) numpy of variables x (the root's zero)."""
        return np.asarray(x[:3 * self.n_joints]).reshape(self.n_joints, 3) * (self.skeleton.parents >= 0)[:, None]

    def objective(self, sigma, cell=None):
        """objective(x (n,) tensor) -> scalar tensor at ``sigma``, both surfaces binned on cells of ``cell`` x
        sigma (default the settings'; built once per sigma and cell)."""
        key = (sigma, self.settings.cell if cell is None else cell)
        if key in self._objectives:
            return self._objectives[key]
        cell, n = key[1] * sigma, self.n_joints
        scan = BinnedMeasureLoss(*coarse_measure(self.scan[0] - self.center, self.scan[1], self.scan[2], cell), sigma)
        self_t, masses = float(scan.self_t), self.samples[2]

        def objective(x):
            rot = x[:3 * n].reshape(n, 3) * self.free[:, None]
            posed, turned, scale = self.place(*self.posed_samples(rot), x)
            # binned afresh each evaluation (the cells follow the pose; the sums are differentiable)
            gamma = scan(*cell_features(posed, turned, masses * scale ** 2, cell)[:2]) / self_t
            return gamma + self.penalty(rot)

        self._objectives[key] = objective
        return objective

    def starts(self):
        """Rest and the library's poses scored at the coarse sigma: -> (score, index: -1 rest, else the
        library's, variables) of the best."""
        coarse, library = self.objective(self.sigmas[self.settings.search_sigma]), self.skeleton.library
        starts = [self.variables(r) for r in np.concatenate([np.zeros((1, self.n_joints, 3)), library])]
        with torch.no_grad():
            scores = [float(coarse(torch.as_tensor(x))) for x in starts]
        best = int(np.argmin(scores))
        return scores[best], best - 1, starts[best]

    def search(self, x):
        """Each joint's direction searched at the coarse sigma from variables x (``starts``), the alignment and
        size then settled for that pose (a person's size is known only roughly from the area, and a wrong one
        makes a raised arm overshoot), or the start settled if that ends lower -> (variables, objective there)."""
        # each limb's direction searched in turn: the coarse varifold has no slope toward an arm raised
        # overhead from one hanging down (the torso lies between)
        coarse, settle = [self.sigmas[self.settings.search_sigma]], self.settings.settle_iter
        found = self.refine(direction_search(self, coarse[0], x), coarse, max_iter=settle)
        # the start settled as it is too: near a library pose (a crouch) the joint-by-joint search can
        # leave it for a worse one
        kept = self.refine(x, coarse, max_iter=settle)
        return min(found, kept, key=lambda f: f[1])

    def search_finely(self, x):
        """The limbs' roots (an upper arm, a thigh) searched again at the finest sigma from variables x: at a
        coarser one both arms overhead and one folded by the head look alike -> variables."""
        return direction_search(self, self.sigmas[-1], x, roots=True)

    def refine(self, x, sigmas, monitor=None, max_iter=None):
        """L-BFGS from variables x at each of ``sigmas`` in turn (at most ``max_iter`` steps each, default the
        settings') -> (variables, objective at the last)."""
        value = None
        for sigma in sigmas:
            x, value, _ = minimize_lbfgs(self.objective(sigma), x, monitor, max_iter=max_iter or self.settings.max_iter,
                                         gtol=1e-9, ftol=1e-10)
        return x, value

    def result(self, x, score, start):
        """The PoseFit of variables x."""
        n, rot = self.n_joints, self.rotations(x)
        with torch.no_grad():
            posed = skin(self.skeleton, self.template, torch.as_tensor(rot), self.tensors).numpy()
            samples = self.posed_samples(torch.as_tensor(rot))[0].numpy()
        middle = samples.mean(0)
        scale = math.exp(float(bounded_log_scale(float(x[-1]), self.limit))) * self.size
        r = axis_angle_rotation(x[3 * n:3 * n + 3])
        # the posed template moved by y -> s R (y - m) + tau + c (m its samples' centroid, c the template's:
        # the scan's cells are about c); the scan moves by the inverse instead
        move = Similarity(r, scale, x[3 * n + 3:3 * n + 6] + self.center - scale * r @ middle)
        return PoseFit(rot, move.inverse().compose(self.transform), posed, float(score), start)


def fit_pose(skeleton, basis, scan_verts, scan_faces, transforms, settings, face_weights=None, monitor=None):
    """The skeleton's pose and a similarity fitted to a scan (M, 3), (G, 3) from the best of candidate
    alignments ``transforms`` [Similarity scan -> template frame], as ``settings`` (a
    ``config.ArticulatedFit``) says: from every alignment's best start (rest or the library's) the joints'
    directions searched at the coarse sigma (``PoseProblem.search``); the ``settings.searched`` that fit best
    there searched finely and fitted at every sigma in turn (the others too while the best scores above
    ``settings.poor_score``); the fit that ends lowest at the finest sigma
    -> PoseFit, or None when rest, at the alignment it fits best, is a better start than every pose of the
    library (a body near rest, which the latent levels find on their own: the search would only cost time)."""
    problems = [PoseProblem(skeleton, basis, scan_verts, scan_faces, t, settings, face_weights) for t in transforms]
    starts = [(*p.starts(), p) for p in problems]
    if len(skeleton.library) and min(starts, key=lambda s: s[0])[1] < 0:
        return None
    searched = []
    for _, start, x, problem in starts:
        if monitor is not None:
            monitor.check()
        searched.append((*problem.search(x)[::-1], start, problem))  # (value, x, start, problem)
    fits, ranked = [], sorted(searched, key=lambda f: f[0])
    for k, (_, x, start, problem) in enumerate(ranked):
        # the coarse search can rank a body turned the wrong way first: while the best fit is still poor,
        # the other alignments are fitted too
        if k >= settings.searched and min(f[0] for f in fits) <= settings.poor_score:
            break
        x, value = problem.refine(problem.search_finely(x), problem.sigmas, monitor)
        fits.append((value, start, x, problem))
    value, start, x, problem = min(fits, key=lambda f: f[0])
    return problem.result(x, value, start)


def articulated_start(basis, skeleton, scan_verts, scan_faces, transforms, settings, face_weights=None,
                      monitor=None, metric=None):
    """The code (P,) and alignment a registration may start from after the articulated fit (``fit_pose``) from
    candidate alignments [Similarity], and the fit: -> (code, Similarity, PoseFit), or None when the scan is
    near rest. metric: the H2 weights of the projection's ridge (``latent.project_to_basis``), the
    registration's own (its path energy's); None: the basis' motion metric."""
    fit = fit_pose(skeleton, basis, scan_verts, scan_faces, transforms, settings, face_weights, monitor)
    if fit is None:
        return None
    code = project_to_basis(basis, fit.posed, ridge=settings.projection_ridge, weights=metric)[0]
    return code, fit.transform, fit
