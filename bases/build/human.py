"""The ``human`` basis: realistic people from the Anny body model (Anny: Apache-2.0; MakeHuman data: CC0).

Template. Anny's default body (all phenotypes 0.5) in its rest pose, topology
``anny-noeyes-notongue`` (13,348 vertices, one closed surface with internal
mouth and eye pockets). The pockets' faces (Anny's body-part segmentation:
``eye_cavity.L/R``, ``mouth_cavity``) are removed and the three holes closed
by a fan around each rim's mean; the closed body is then remeshed once, left-
right symmetric: Blender's symmetric collapse decimation (adaptive: hands and
face keep their detail), then rounds of edge flips (Blender's beautify, on one
half, mirrored) and tangential relaxation projected back onto the body. Each
template vertex lies on the closed body, so its barycentric coordinates give a
fixed sparse linear map Anny vertices -> template vertices: any Anny body lands
in template topology, vertex order fixed. Z-up, facing -Y, left = +X, metres,
feet on z = 0.

Identities. Anny's ``SimpleShapeDistribution`` (realistic height, weight,
muscle and proportions given age and sex), both sexes, morphological ages 13-85
(teenagers to old age); ``N_TRAIN_IDENTITIES`` for the shape group and
``N_TEST_IDENTITIES`` held out (drawn after, never seen by the build).

Motions. Joint-angle curves (``bases/build/motions.py``: the mannequin's
motions plus walk, run, sit down, crouch, reach, jump, dance, pick up) mapped
onto Anny's rig, posed in one batch per identity; every frame is put back on
the floor (its lowest point at z = 0, plus the motion's own flight height).

Basis. ``pose``: PCA of frame-to-frame tangents of the training motions of
``MOTION_IDENTITIES`` training identities; ``shape``: PCA of the steps of
elastic H2 geodesics template -> training identity in the rest pose (the
paper's construction). Group sizes are chosen by ``bench/human_ablation``.
"""

import math
import time
from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from bareesa.basis_building import build_basis
from bareesa.h2_metric import H2Weights
from bareesa.latent import PAPER_BODY_SCHEDULE, Level
from bareesa.statistics import pose_prototypes

from .common import checked_template, elastic_paths, fit_basis_distribution, topology_signature
from .landmarks import LANDMARK_NOTES, human_landmarks
from .parts import PARTS_NOTE, human_parts
from .motions import HUMAN_TEST_MOTIONS, HUMAN_TRAIN_MOTIONS, pose_at
from .poses import EXTREME_POSES, POSE_FAMILIES, plausible, pose_family, random_pose, vertex_segments

NAME = "human"
#: The basis' H2 metrics (a0, a1, b1, c1, d1, a2): motion paths in MOTION_WEIGHTS (with the paper's body
#: weights their geodesics bend the fingers), shapes measured from the template in the paper's
#: (``Basis.shape_weights``); see docs/decisions/101-human-motion-metric.md.
MOTION_WEIGHTS = (1e4, 1000.0, 100.0, 1.0, 1.0, 0.01)
#: The motion metric the basis keeps is fitted to the training motions of this many performers (the template
#: and the first training identities; ``bareesa.metric_fit``), against the presets and MOTION_WEIGHTS
#: (docs/decisions/023-motion-metric-fit.md).
METRIC_FIT_PERFORMERS = 5
SHAPE_WEIGHTS = (1.0, 1000.0, 100.0, 1.0, 1.0, 1.0)
SEED = 17
TOPOLOGY = "anny-noeyes-notongue"
CAVITIES = ("eye_cavity.L", "eye_cavity.R", "mouth_cavity")
DECIMATE_RATIO = 0.5        # of the closed body's faces: ~6.2k template vertices
REMESH_ROUNDS = 6           # flip + relax rounds
N_TRAIN_IDENTITIES = 200
N_TEST_IDENTITIES = 20
MOTION_IDENTITIES = 20      # training identities (the template and 19 others) that perform every training motion
AGE_RANGE = (13.0, 85.0)    # morphological age, years
FRAMES = 48                 # frames per motion at 24 fps
BAKE_STEP = 3               # a mesh every BAKE_STEP frames -> 17 meshes per motion
POSE_COMPONENTS = 100
SHAPE_COMPONENTS = 40
POSE_PROTOTYPES = 32
#: Static postures each motion performer takes besides the motions (``bases/build/poses.py``, seeded by
#: POSTURE_SEED + the performer's index, never the benchmarks' seeds): random anatomically valid ones and
#: variants of every named family (arms overhead, tree pose, deep squat, sitting, kneeling, ...); see
#: docs/decisions/103-human-pose-space.md
RANDOM_POSTURES = 30
FAMILY_VARIANTS = 3
POSTURE_SEED = 1000
#: A posture is kept when at most this many face pairs of different, non-adjacent body segments cross
#: (``poses.plausible``): a hand resting on the body is kept, a limb through it is drawn again; the named
#: families touch more by design (crossed arms, hands on the head)
RANDOM_CROSSINGS, FAMILY_CROSSINGS = 30, 100
#: The skeleton's pose library (starts of the articulated pre-fit): the named families' canonical postures
#: and this many k-means centres of the random training postures' joint rotations
LIBRARY_CENTRES = 16
#: Random bodies: mixtures fitted to the log maps of this many training meshes (evenly chosen among
#: the frames and rest bodies); many narrow pose components keep draws near poses people take.
DISTRIBUTION_SAMPLES = 240
DISTRIBUTION_COMPONENTS = {"pose": 12, "shape": 3}
#: Registration schedule stored in the card: the paper's body schedule with a stiffer second level that keeps
#: the pose candidates' pose, a binned middle level for the limbs sliding into place, a finest level allowed
#: 300 iterations; see docs/decisions/102-human-registration-schedule.md.
HUMAN_SCHEDULE = (PAPER_BODY_SCHEDULE[0], replace(PAPER_BODY_SCHEDULE[1], weight=1e6, bin_cell=0.6),
                  Level(0.05 / 1.7, 1e8, 4, 200, plateau=1e-4, binned=True, bin_cell=0.6),
                  replace(PAPER_BODY_SCHEDULE[2], max_iter=300))

#: The articulated pre-fit's skeleton (``bareesa.registration.articulated``): mannequin bone -> the Anny bone
#: at whose head it turns; every other Anny bone's skinning weight goes to the nearest of these up its chain
#: (fingers to the hand, toes to the foot, twist bones to their limb)
SKELETON_HEADS = {"hips": "root", "spine": "spine05", "chest": "spine03", "neck": "neck01", "head": "head"}
for _s in "LR":
    SKELETON_HEADS.update({f"clavicle.{_s}": f"clavicle.{_s}", f"upper_arm.{_s}": f"upperarm01.{_s}",
                           f"forearm.{_s}": f"lowerarm01.{_s}", f"hand.{_s}": f"wrist.{_s}",
                           f"thigh.{_s}": f"upperleg01.{_s}", f"shin.{_s}": f"lowerleg01.{_s}",
                           f"foot.{_s}": f"foot.{_s}"})
#: The skeleton's joint ranges: the training postures' rotation vectors (rest axes) between these percentiles,
#: widened by SKELETON_MARGIN (radians) on each side
SKELETON_PERCENTILES = (0.5, 99.5)
SKELETON_MARGIN = math.radians(10.0)

#: Mannequin bone -> [(Anny bone, share of the rotation angle)].
BONE_MAP = {"spine": [("spine05", 0.5), ("spine04", 0.5)], "chest": [("spine03", 0.5), ("spine02", 0.5)],
            "neck": [("neck01", 0.5), ("neck02", 0.5)], "head": [("head", 1.0)]}
for _s in "LR":
    BONE_MAP.update({f"clavicle.{_s}": [(f"clavicle.{_s}", 1.0)], f"upper_arm.{_s}": [(f"upperarm01.{_s}", 1.0)],
                     f"forearm.{_s}": [(f"lowerarm01.{_s}", 1.0)], f"hand.{_s}": [(f"wrist.{_s}", 1.0)],
                     f"thigh.{_s}": [(f"upperleg01.{_s}", 1.0)], f"shin.{_s}": [(f"lowerleg01.{_s}", 1.0)],
                     f"foot.{_s}": [(f"foot.{_s}", 1.0)],
                     f"toes.{_s}": [(f"toe{k}-1.{_s}", 1.0) for k in range(1, 6)],
                     f"fingers.{_s}": [(f"finger{k}-{j}.{_s}", 1.0) for k in range(2, 6) for j in range(1, 4)],
                     f"thumb.{_s}": [(f"finger1-{j}.{_s}", 1.0) for j in range(1, 4)]})


# ------------------------------------------------------------------------------- Anny


def anny_model():
    """Anny with the cavity-pocket topology (the first call builds Anny's cache: minutes, ~0.8 GB)."""
    try:
        import anny
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise SystemExit("building the human basis needs Anny: pip install -e '.[bases]'") from exc
    return anny.Anny(topology=TOPOLOGY)


def cavity_faces(model):
    """Boolean mask (F,) of the faces of the mouth and eye pockets (Anny's segmentation)."""
    from anny.face_segmentation import get_face_segmentation_mask

    return get_face_segmentation_mask(model, list(CAVITIES)).cpu().numpy()


def composed(seq, share=1.0):
    """A bone's rotations [(axis, degrees)] composed in order (later ones act after earlier ones), each angle
    times ``share``: -> (3, 3)."""
    from scipy.spatial.transform import Rotation

    r = np.eye(3)
    for axis, deg in seq:
        r = Rotation.from_rotvec(np.asarray(axis) * math.radians(deg * share)).as_matrix() @ r
    return r


def posture_matrices(postures, bone_labels, dtype=np.float64):
    """Anny pose parameters of postures [(rotations {mannequin bone: [(axis, degrees)]}, root (3,))] (the
    format of ``motions.pose_at``) -> (T, n_bones, 4, 4) local-ref rotations, root offsets (T, 3)."""
    index = {b: i for i, b in enumerate(bone_labels)}
    out = np.tile(np.eye(4, dtype=dtype), (len(postures), len(bone_labels), 1, 1))
    roots = np.zeros((len(postures), 3))
    for t, (rots, root) in enumerate(postures):
        roots[t] = root
        for bone, seq in rots.items():
            for target, share in BONE_MAP.get(bone, ()):
                out[t, index[target], :3, :3] = composed(seq, share)
    return out, roots


def pose_matrices(motion, phases, bone_labels, dtype=np.float64):
    """Anny pose parameters of a motion: phases (T,) -> (T, n_bones, 4, 4) local-ref rotations, root offsets (T, 3)."""
    return posture_matrices([pose_at(motion, float(u)) for u in phases], bone_labels, dtype)


def skeleton_rotations(rotations, names):
    """The rotation vectors (J, 3) of the skeleton's joints (``SKELETON_HEADS`` names) in a posture's
    rotations {mannequin bone: [(axis, degrees)]} (each bone's rotations composed; fingers, thumbs and toes
    belong to their hand or foot and are left out)."""
    from scipy.spatial.transform import Rotation

    return np.stack([Rotation.from_matrix(composed(rotations.get(name, ()))).as_rotvec() for name in names])


def identities(n_train=N_TRAIN_IDENTITIES, n_test=N_TEST_IDENTITIES, seed=SEED, model=None):
    """Phenotypes of realistic people: -> (train, test) dicts {label: (n,) array} (deterministic)."""
    import torch
    from anny.shape_distribution import SimpleShapeDistribution

    model = model or anny_model()
    ages = torch.distributions.Uniform(torch.tensor(AGE_RANGE[0], dtype=model.dtype),
                                       torch.tensor(AGE_RANGE[1], dtype=model.dtype))
    dist = SimpleShapeDistribution(model, morphological_age_distribution=ages)
    torch.manual_seed(seed)
    years, pheno = dist.sample(n_train + n_test)
    pheno = {k: v.detach().cpu().numpy().astype(np.float64) for k, v in pheno.items()}
    pheno["years"] = years.detach().cpu().numpy().astype(np.float64)
    return ({k: v[:n_train] for k, v in pheno.items()}, {k: v[n_train:] for k, v in pheno.items()})


def anny_bodies(model, phenotypes, poses=None, batch=64):
    """Anny vertices (B, 13348, 3) float64 for phenotypes {label: (B,)} and poses (B, n_bones, 4, 4) or rest."""
    import torch

    n = len(next(iter(phenotypes.values())))
    out = []
    for s in range(0, n, batch):
        kw = {k: torch.as_tensor(phenotypes[k][s:s + batch], dtype=model.dtype) for k in model.phenotype_labels}
        pose = None if poses is None else torch.as_tensor(poses[s:s + batch], dtype=model.dtype)
        with torch.no_grad():
            out.append(model(pose_parameters=pose, phenotype_kwargs=kw)["vertices"].cpu().numpy())
    return np.concatenate(out).astype(np.float64)


# ------------------------------------------------------------------------------ template


def boundary_loops(faces):
    """Ordered vertex loops of a mesh's boundary (each following its faces' orientation)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    have = {(int(a), int(b)) for a, b in e}
    nxt = {a: b for a, b in have if (b, a) not in have}
    loops, seen = [], set()
    for a in sorted(nxt):
        if a in seen:
            continue
        loop, b = [a], nxt[a]
        seen.add(a)
        while b != a:
            loop.append(b)
            seen.add(b)
            b = nxt[b]
        loops.append(loop)
    return loops


def closed_body(verts, faces, drop):
    """Remove the faces ``drop`` (F,) bool and cap each hole with a fan around its rim's mean.

    -> verts (N', 3), faces (F', 3), closure (N', N) sparse: verts' = closure @ verts (each
    kept vertex is itself, each cap centre the mean of its rim), so the map stays linear.
    """
    faces = np.asarray(faces, dtype=np.int64)[~np.asarray(drop)]
    used = np.unique(faces)
    remap = -np.ones(len(verts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    faces = remap[faces]
    rows, cols, vals = list(range(len(used))), list(used), [1.0] * len(used)
    caps, n = [], len(used)
    for loop in boundary_loops(faces):
        rows += [n] * len(loop)
        cols += list(used[loop])
        vals += [1.0 / len(loop)] * len(loop)
        caps.append(np.array([[loop[(i + 1) % len(loop)], loop[i], n] for i in range(len(loop))]))
        n += 1
    closure = sp.csr_matrix((vals, (rows, cols)), shape=(n, len(verts)))
    return closure @ np.asarray(verts, dtype=np.float64), np.concatenate([faces] + caps), closure


def _angles(x, t):
    p = x[t]
    out = []
    for i in range(3):
        u, v = p[:, (i + 1) % 3] - p[:, i], p[:, (i + 2) % 3] - p[:, i]
        c = (u * v).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1) + 1e-30)
        out.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.stack(out, 1)


def min_angle_stats(verts, faces):
    """{'min_angle', 'p01_angle', 'under_15'}: the smallest triangle angles in degrees."""
    a = _angles(np.asarray(verts, dtype=np.float64), np.asarray(faces)).min(1)
    return {"min_angle": float(a.min()), "p01_angle": float(np.percentile(a, 1)), "under_15": int((a < 15).sum())}


def mirror_residual(verts):
    """Left-right symmetry of a vertex set: -> (share of vertices whose mirror image is a vertex
    within 1 micron, largest distance from a mirror image to the nearest vertex)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(verts).query(verts * np.array([-1.0, 1.0, 1.0]))
    return float((d < 1e-6).mean()), float(d.max())


def _beautify(verts, half):
    """Blender's angle-based edge flips: faces (K, 3) -> faces (K, 3)."""
    import bpy  # noqa: F401  (bmesh comes with it)
    import bmesh

    bm = bmesh.new()
    vs = [bm.verts.new(v) for v in verts]
    for f in half:
        bm.faces.new([vs[i] for i in f])
    bm.verts.index_update()
    bmesh.ops.beautify_fill(bm, faces=bm.faces[:], edges=bm.edges[:], use_restrict_tag=False, method="ANGLE")
    out = np.array([[v.index for v in f.verts] for f in bm.faces], dtype=np.int64)
    bm.free()
    return out


def symmetric_remesh(verts, faces, ratio=DECIMATE_RATIO, rounds=REMESH_ROUNDS):
    """A left-right symmetric remesh of a closed, nearly symmetric surface: -> verts (M, 3), faces (K, 3).

    Symmetric collapse decimation to ``ratio`` of the faces (Blender), then ``rounds`` of
    edge flips (on one half, mirrored) and tangential Laplacian relaxation projected back onto
    the input surface and re-symmetrised. Every output vertex lies on the input surface.
    """
    import bpy
    import bmesh
    from mathutils.bvhtree import BVHTree

    from .blender import mesh_object, reset_scene

    reset_scene()
    bm = bmesh.new()  # exact symmetry first: keep the x >= 0 half and mirror it (Anny is symmetric to 0.4 mm)
    vs = [bm.verts.new(v) for v in np.asarray(verts, dtype=np.float64)]
    for f in faces:
        bm.faces.new([vs[i] for i in f])
    bmesh.ops.bisect_plane(bm, geom=bm.verts[:] + bm.edges[:] + bm.faces[:], dist=1e-7, plane_co=(0, 0, 0),
                           plane_no=(1, 0, 0), clear_inner=True)
    bmesh.ops.triangulate(bm, faces=bm.faces[:])
    bmesh.ops.mirror(bm, geom=bm.verts[:] + bm.edges[:] + bm.faces[:], axis="X", merge_dist=1e-7)
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces[:])  # the mirrored half comes with reversed winding
    bm.verts.index_update()
    sym_v = np.array([v.co[:] for v in bm.verts], dtype=np.float64)
    sym_f = np.array([[v.index for v in f.verts] for f in bm.faces], dtype=np.int64)
    bm.free()
    obj = mesh_object("body", sym_v, sym_f)
    mod = obj.modifiers.new("decimate", "DECIMATE")
    mod.decimate_type, mod.ratio, mod.use_symmetry, mod.symmetry_axis = "COLLAPSE", ratio, True, "X"
    bm = bmesh.new()
    bm.from_object(obj, bpy.context.evaluated_depsgraph_get())
    bmesh.ops.dissolve_degenerate(bm, dist=1e-3, edges=bm.edges[:])  # needles the decimator leaves at the midline
    bmesh.ops.triangulate(bm, faces=bm.faces[:])
    bm.verts.index_update()
    x = np.array([v.co[:] for v in bm.verts], dtype=np.float64)
    t = np.array([[v.index for v in f.verts] for f in bm.faces], dtype=np.int64)
    bm.free()
    bpy.data.objects.remove(obj)
    mid = np.abs(x[:, 0]) < 1e-9
    from scipy.spatial import cKDTree

    dist, partner = cKDTree(x).query(x * np.array([-1.0, 1.0, 1.0]))
    paired = (dist < 1e-4) & (partner[partner] == np.arange(len(x)))  # the decimator is symmetric but near the midline
    flip = np.array([-1.0, 1.0, 1.0])

    def symmetrise(y):
        y = y.copy()
        y[paired] = 0.5 * (y[paired] + y[partner[paired]] * flip)
        y[mid, 0] = 0.0
        return y

    x = symmetrise(x)
    tree = BVHTree.FromPolygons(np.asarray(verts).tolist(), np.asarray(faces).tolist())
    for r in range(rounds + 1):
        t = _beautify(x, t)
        if r == rounds:
            break
        n = len(x)
        e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        adj = sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        adj = ((adj + adj.T) > 0).astype(np.float64)
        deg = np.asarray(adj.sum(1)).ravel()
        fn = np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])
        normal = np.zeros_like(x)
        for k in range(3):
            np.add.at(normal, t[:, k], fn)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-30
        lap = adj @ x / deg[:, None] - x
        lap -= (lap * normal).sum(1, keepdims=True) * normal
        x = symmetrise(np.array([tree.find_nearest(p)[0][:] for p in x + 0.5 * lap]))
    _check_closed(x, t)
    return x, t


def _check_closed(verts, faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    if (counts != 2).any() or len(np.unique(faces)) != len(verts):
        raise RuntimeError(f"the symmetric remesh is not a closed manifold ({int((counts != 2).sum())} bad edges, "
                           f"{len(verts) - len(np.unique(faces))} unused vertices)")


def barycentric_map(surface_verts, surface_faces, points):
    """Sparse (M, N) matrix W with W @ surface_verts = points, for points on the surface (3 entries per row)."""
    import bpy  # noqa: F401  (mathutils comes with it)
    from mathutils.bvhtree import BVHTree

    tree = BVHTree.FromPolygons(np.asarray(surface_verts).tolist(), np.asarray(surface_faces).tolist())
    rows, cols, vals = [], [], []
    for i, p in enumerate(points):
        loc, _, f, _ = tree.find_nearest(p)
        tri = surface_faces[f]
        a, b, c = surface_verts[tri]
        v0, v1, v2 = b - a, c - a, np.asarray(loc) - a
        d00, d01, d11, d20, d21 = v0 @ v0, v0 @ v1, v1 @ v1, v2 @ v0, v2 @ v1
        den = d00 * d11 - d01 * d01
        wb, wc = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
        w = np.clip([1 - wb - wc, wb, wc], 0.0, 1.0)
        rows += [i] * 3
        cols += list(tri)
        vals += list(w / w.sum())
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(points), len(surface_verts)))


def template_uvs(anny_verts, anny_faces, anny_uv, anny_face_uv, keep, verts, faces):
    """Anny's UV layout carried onto the template: -> (K, 3, 2) float32 UVs per face corner.

    Each template face takes the chart of the kept Anny face nearest its centre: its corners'
    barycentric coordinates in that face's plane (extrapolated where a corner lies beyond it)
    applied to the face's UV triangle, so a face never straddles two UV islands.
    """
    import bpy  # noqa: F401  (mathutils comes with it)
    from mathutils.bvhtree import BVHTree

    kept = np.flatnonzero(keep)
    tree = BVHTree.FromPolygons(np.asarray(anny_verts).tolist(), np.asarray(anny_faces)[kept].tolist())
    out = np.zeros((len(faces), 3, 2))
    for k, tri in enumerate(faces):
        j = kept[tree.find_nearest(verts[tri].mean(0))[2]]
        a, b, c = anny_verts[anny_faces[j]]
        e0, e1 = b - a, c - a
        gram = np.array([[e0 @ e0, e0 @ e1], [e0 @ e1, e1 @ e1]])
        rhs = np.stack([(verts[tri] - a) @ e0, (verts[tri] - a) @ e1], 1)
        w = np.linalg.solve(gram, rhs.T).T  # (3, 2) barycentric (w_b, w_c) of the corners
        uv = anny_uv[anny_face_uv[j]]
        out[k] = uv[0] + w[:, :1] * (uv[1] - uv[0]) + w[:, 1:] * (uv[2] - uv[0])
    return out.astype(np.float32)


class Human:
    """Anny, the template and the sparse map Anny vertices -> template vertices."""

    def __init__(self, log=print):
        t0 = time.perf_counter()
        self.model = anny_model()
        self.bones = list(self.model.bone_labels)
        rest = anny_bodies(self.model, {k: np.array([0.5]) for k in self.model.phenotype_labels})[0]
        closed_v, closed_f, closure = closed_body(rest, self.model.faces.cpu().numpy(), cavity_faces(self.model))
        verts, self.faces = symmetric_remesh(closed_v, closed_f)
        self.map = (barycentric_map(closed_v, closed_f, verts) @ closure).tocsr()
        anny_faces = self.model.faces.cpu().numpy()
        self.uv = template_uvs(rest, anny_faces, self.model.texture_coordinates.detach().cpu().numpy(),
                               self.model.face_texture_coordinate_indices.cpu().numpy(), ~cavity_faces(self.model),
                               verts, self.faces)
        self.template = self.to_template(rest[None])[0]
        self.quality = min_angle_stats(self.template, self.faces)
        self.quality["mirrored_share"], self.quality["mirror_max_distance"] = mirror_residual(self.template)
        log(f"human: template {len(self.template)} vertices, {len(self.faces)} faces from {len(rest)} Anny "
            f"vertices (min angle {self.quality['min_angle']:.1f} deg, {self.quality['under_15']} triangles "
            f"under 15 deg; {100 * self.quality['mirrored_share']:.1f} % of the vertices mirrored; "
            f"{time.perf_counter() - t0:.0f} s)")

    def to_template(self, anny_verts):
        """Anny vertices (B, 13348, 3) -> template topology (B, N, 3), feet on the floor (min z = 0)."""
        out = np.stack([self.map @ v for v in anny_verts])
        out[..., 2] -= out[..., 2].min(axis=1, keepdims=True)
        return out

    def rest(self, phenotypes):
        """Rest bodies (B, N, 3) of phenotypes {label: (B,)}."""
        return self.to_template(anny_bodies(self.model, phenotypes))

    def postures(self, phenotype, postures):
        """Bodies (K, N, 3) of one phenotype {label: scalar} in postures [(rotations, root)] (``posture_matrices``),
        each on the floor."""
        poses, _ = posture_matrices(postures, self.bones)
        pheno = {k: np.full(len(postures), float(np.asarray(phenotype[k]).ravel()[0]))
                 for k in self.model.phenotype_labels}
        return self.to_template(anny_bodies(self.model, pheno, poses))

    def segments(self):
        """Each template vertex's body segment (N,) int (``poses.vertex_segments``)."""
        return vertex_segments(self.bones, self.model.vertex_bone_indices.cpu().numpy(),
                               self.model.vertex_bone_weights.cpu().numpy(), self.map)[0]

    def skeleton(self):
        """The template's skeleton as ``bareesa.registration.articulated`` reads it from a basis' extras (without
        its ranges and pose library): joints (J, 3) at Anny's rest bone heads (the template's frame), parents,
        skinning weights (N, J) from Anny's mapped onto the template, names -> dict of arrays."""
        import torch

        parents = [int(p) for p in np.asarray(self.model.bone_parents)]
        position = {anny: name for name, anny in SKELETON_HEADS.items()}
        heads = sorted(self.bones.index(anny) for anny in SKELETON_HEADS.values())  # parents before children
        names = [position[self.bones[b]] for b in heads]
        owner = np.empty(len(self.bones), dtype=np.int64)
        for b, label in enumerate(self.bones):  # Anny lists parents before children
            owner[b] = names.index(position[label]) if label in position else owner[parents[b]]
        index = np.asarray(self.model.vertex_bone_indices.cpu().numpy(), dtype=np.int64)
        weight = np.asarray(self.model.vertex_bone_weights.cpu().numpy(), dtype=np.float64)
        dense = np.zeros((len(index), len(names)))
        np.add.at(dense, (np.repeat(np.arange(len(index)), index.shape[1]), owner[index].ravel()), weight.ravel())
        skin = np.asarray(self.map @ dense)
        skin /= np.maximum(skin.sum(1, keepdims=True), 1e-12)
        kw = {k: torch.full((1,), 0.5, dtype=self.model.dtype) for k in self.model.phenotype_labels}
        with torch.no_grad():
            out = self.model(pose_parameters=None, phenotype_kwargs=kw)
        rest = out["vertices"][0].cpu().numpy().astype(np.float64)
        joints = out["rest_bone_heads"][0].cpu().numpy().astype(np.float64)[heads]
        joints[:, 2] -= (self.map @ rest)[:, 2].min()  # on the floor, as ``to_template`` puts the body
        joint_parents = np.array([-1 if parents[b] < 0 else owner[parents[b]] for b in heads])
        return {"skeleton_joints": joints, "skeleton_parents": joint_parents, "skinning_weights": skin,
                "skeleton_names": np.array(["|".join(names)])}

    def motion(self, phenotype, motion, frames=FRAMES, step=BAKE_STEP):
        """A sequence (T, N, 3) of one phenotype {label: scalar} performing a motion."""
        phases = np.arange(0, frames + 1, step) / frames
        poses, roots = pose_matrices(motion, phases, self.bones)
        pheno = {k: np.full(len(phases), float(np.asarray(phenotype[k]).ravel()[0])) for k in self.model.phenotype_labels}
        seq = self.to_template(anny_bodies(self.model, pheno, poses))
        seq[..., :2] += roots[:, None, :2]
        seq[..., 2] += np.maximum(roots[:, None, 2], 0.0)  # flight; crouches are put on the floor by to_template
        return seq


SKELETON_NOTE = ("Anny's rig reduced to the mannequin's bones (SKELETON_HEADS: joints at Anny's rest bone heads, "
                 "Anny's skinning weights summed per joint and mapped onto the template); ranges: the training "
                 "postures' rotation vectors between the 0.5 and 99.5 percentiles, widened by 10 degrees; pose "
                 "library: the named families' canonical postures and k-means centres of the random postures")


def skeleton_extras(human, postures):
    """The skeleton's arrays for ``basis.extras`` (``Human.skeleton``), with its ranges and pose library from
    the training postures [(rotations, root)]: -> dict."""
    from sklearn.cluster import KMeans

    extras = human.skeleton()
    names = str(extras["skeleton_names"][0]).split("|")
    rotvecs = np.stack([skeleton_rotations(rot, names) for rot, _ in postures])
    lo, hi = np.percentile(rotvecs, SKELETON_PERCENTILES, axis=0)
    limits = np.stack([lo - SKELETON_MARGIN, hi + SKELETON_MARGIN], -1)
    limits[0] = [-math.pi, math.pi]  # the root's rotation is the alignment's
    named = np.stack([skeleton_rotations(rot, names) for rot, _ in EXTREME_POSES.values()])
    centres = KMeans(LIBRARY_CENTRES, n_init=4, random_state=SEED).fit(rotvecs.reshape(len(rotvecs), -1))
    library = np.concatenate([named, centres.cluster_centers_.reshape(-1, len(names), 3)])
    return {**extras, "skeleton_limits": limits, "skeleton_pose_library": np.clip(library, limits[..., 0],
                                                                                 limits[..., 1])}


def training_postures(human, phenotype, seed, segments=None):
    """The static postures one performer {label: scalar} takes in the build (seeded by ``seed``):
    RANDOM_POSTURES random ones and FAMILY_VARIANTS of every named family, each drawn again while it
    crosses itself in more face pairs than its kind allows (``poses.plausible``; segments: ``Human.segments``)
    -> (postures [(rotations, root)], bodies [(N, 3)], the draws dropped)."""
    rng = np.random.default_rng(seed)
    segments = human.segments() if segments is None else segments
    postures, bodies, dropped = [], [], 0
    draws = [(lambda: random_pose(rng), RANDOM_POSTURES, RANDOM_CROSSINGS)]
    draws += [(lambda name=name: pose_family(name, rng), FAMILY_VARIANTS, FAMILY_CROSSINGS) for name in POSE_FAMILIES]
    for draw, wanted, crossings in draws:
        found = 0
        for _ in range(4):  # batches of draws until enough cross no more than allowed
            batch = [draw() for _ in range(wanted - found)]
            for posture, body in zip(batch, human.postures(phenotype, batch)):
                if plausible(body, human.faces, crossings, segments):
                    postures.append(posture)
                    bodies.append(body)
                    found += 1
                else:
                    dropped += 1
            if found == wanted:
                break
    return postures, bodies, dropped


def _take(pheno, i):
    return {k: v[i:i + 1] for k, v in pheno.items()}


def generate(log=print, test=True, motion_identities=MOTION_IDENTITIES, n_train=N_TRAIN_IDENTITIES):
    """Bake the training (and held-out) data: -> dict of arrays (float32 sequences)."""
    t0 = time.perf_counter()
    human = Human(log)
    train, test_ids = identities(n_train=n_train, model=human.model)
    rests = human.rest(train)
    log(f"human: {len(rests)} training identities ({time.perf_counter() - t0:.0f} s)")
    performers = motion_performers(human, train, motion_identities)
    sequences = training_motions(human, performers)
    log(f"human: baked {len(sequences)} training sequences ({time.perf_counter() - t0:.0f} s)")
    segments = human.segments()
    postures, bodies, dropped = [], [], 0
    for i, p in enumerate(performers):
        drawn, kept, lost = training_postures(human, p, POSTURE_SEED + i, segments)
        postures += drawn
        dropped += lost
        bodies.append(np.stack([human.rest(p)[0], *kept]).astype(np.float32))
    log(f"human: baked {len(postures)} training postures, {dropped} crossing ones drawn again "
        f"({time.perf_counter() - t0:.0f} s)")
    data = {"template": human.template, "faces": human.faces, "train_identities": train, "train_rest": rests,
            "sequences": sequences, "postures": postures, "posture_bodies": bodies, "human": human}
    if test:
        data["test_identities"] = test_ids
        data["test_rest"] = human.rest(test_ids)
        data["test_sequences"] = {(i, m): human.motion(_take(test_ids, i), m).astype(np.float32)
                                  for i in range(len(test_ids["age"])) for m in HUMAN_TEST_MOTIONS}
    return data


METRICS_NOTE = ("metric: motion paths (fitted to the training motions, provenance.metric_fit); shape_metric: "
                "registration and random bodies (the paper's body weights)")


def fit_motion_metric(basis, sequences, log=print):
    """Set the basis' motion metric to the one ``bareesa.metric_fit.choose_motion_metric`` keeps on the training
    motions {(performer, motion): (T, N, 3)} of the first METRIC_FIT_PERFORMERS performers (candidates: the
    presets and MOTION_WEIGHTS, the hand-picked grid of decision 101): -> the MetricFit."""
    from bareesa.metric_fit import choose_motion_metric

    motions = [np.asarray(s, dtype=np.float64) for (i, _), s in sequences.items() if i < METRIC_FIT_PERFORMERS]
    fit = choose_motion_metric(basis, motions, candidates={"body": "body", "face": "face", "grid": MOTION_WEIGHTS})
    basis.weights = fit.weights
    basis.provenance["metric_fit"] = fit.card() | {
        "training_motions": f"{len(motions)}: every training motion of the template and the first "
                            f"{METRIC_FIT_PERFORMERS - 1} training identities",
        "candidates": {"grid": "MOTION_WEIGHTS, chosen on a grid with bench.human_metric (decision 101)"}}
    log(f"human: motion metric {fit.chosen} {tuple(round(w, 4) for w in fit.weights.as_tuple())}, held-out "
        "frame error " + ", ".join(f"{k} {1e3 * v:.1f} mm" for k, v in fit.scores.items()))
    return fit


def motion_performers(human, train, count):
    """Who performs the training motions: Anny's default body, then the first count - 1 training identities."""
    neutral = {k: np.array([0.5]) for k in human.model.phenotype_labels}
    return [neutral] + [_take(train, i) for i in range(count - 1)]


def training_motions(human, performers):
    """Every training motion of each performer: -> {(performer, motion): (T, N, 3) float32}."""
    return {(i, m): human.motion(p, m).astype(np.float32) for i, p in enumerate(performers)
            for m in HUMAN_TRAIN_MOTIONS}


def motion_sequences(log=print, performers=METRIC_FIT_PERFORMERS):
    """The training motions of the first ``performers`` performers, as ``generate`` bakes them (no postures,
    no held-out data): -> {(performer, motion): (T, N, 3)}."""
    human = Human(log)
    train, _ = identities(model=human.model)
    return training_motions(human, motion_performers(human, train, performers))


def build(pose_components=POSE_COMPONENTS, shape_components=SHAPE_COMPONENTS, log=print, data=None,
          elastic_iter=30, distribution=True):
    """Generate the data and build the basis: -> (Basis, data)."""
    start = time.perf_counter()
    data = data or generate(log, test=False)
    template, faces = data["template"], data["faces"]
    checked_template(template, faces, NAME)
    log(f"human: elastic geodesics template -> {len(data['train_rest'])} training identities")
    shape_paths = elastic_paths([(template, v) for v in data["train_rest"]], faces, steps=3, max_iter=elastic_iter,
                                log=lambda m: None)
    log(f"human: elastic geodesics done ({time.perf_counter() - start:.0f} s)")
    height = float(template[:, 2].max() - template[:, 2].min())
    human = data.get("human")
    provenance = {
        "built_by": "python -m bases.build human (Anny body model, topology anny-noeyes-notongue, cavities "
                    "removed and closed, symmetric remesh in Blender, joint-angle motions on Anny's rig)",
        "source": "Anny (NAVER, code Apache-2.0) with MakeHuman body data (CC0): "
                  "https://github.com/naver/anny",
        "template": f"Anny's default body (phenotypes 0.5), rest pose, Z-up, facing -Y, metres, height {height:.3f}",
        "training_identities": len(data["train_rest"]), "identity_seed": SEED,
        "identity_distribution": f"anny.shape_distribution.SimpleShapeDistribution, morphological age "
                                 f"{AGE_RANGE[0]:g}-{AGE_RANGE[1]:g} years, both sexes",
        "held_out_identities": N_TEST_IDENTITIES, "motion_identities": MOTION_IDENTITIES,
        "training_motions": HUMAN_TRAIN_MOTIONS, "held_out_motions": HUMAN_TEST_MOTIONS,
        "frames_per_motion": FRAMES // BAKE_STEP + 1, "topology": topology_signature(faces)}
    if human is not None:
        provenance["template_quality"] = human.quality
    log("human: PCA")
    # a posture is a step from its performer's rest body (the first of each performer's bodies)
    steps = [np.stack([b[0], x]) for b in data.get("posture_bodies", ()) for x in b[1:]]
    basis = build_basis(template, faces, {"pose": list(data["sequences"].values()) + steps, "shape": shape_paths},
                        {"pose": pose_components, "shape": shape_components}, weights=MOTION_WEIGHTS,
                        scale=height, name=NAME, units="m", schedule=HUMAN_SCHEDULE, provenance=provenance,
                        landmarks=human_landmarks(template))
    basis.shape_weights = H2Weights(*SHAPE_WEIGHTS)
    log("human: fitting the motion metric")
    fit_motion_metric(basis, data["sequences"], log)
    basis.provenance["metrics"] = METRICS_NOTE
    basis.provenance["landmarks"] = LANDMARK_NOTES[NAME]
    basis.provenance["groups"]["shape"]["construction"] = "elastic H2 geodesics template -> identity (3 meshes)"
    if human is not None:
        basis.extras["template_uv"] = human.uv
        basis.provenance["template_uv"] = "Anny's UV layout (MakeHuman's), per face corner (F, 3, 2)"
        basis.extras.update(human_parts(faces, human.uv))
        basis.provenance["parts"] = PARTS_NOTE
    frames = np.concatenate([s[1:] for s in data["sequences"].values()])
    held = [b[1:] for b in data.get("posture_bodies", ())]
    every = np.concatenate([frames, *held]) if held else frames
    log(f"human: {POSE_PROTOTYPES} pose prototypes from {len(every)} training frames and postures")
    basis.extras["pose_prototypes"] = pose_prototypes(basis, every, POSE_PROTOTYPES, seed=SEED)
    basis.provenance["pose_prototypes"] = (f"{POSE_PROTOTYPES} k-means centres of the codes of the {len(every)} "
                                           "training frames and postures (clustered on the pose group): "
                                           "registration's pose candidates")
    if human is not None and data.get("postures"):
        basis.extras.update(skeleton_extras(human, data["postures"]))
        basis.provenance["skeleton"] = SKELETON_NOTE
        basis.provenance["postures"] = (f"{len(data['postures'])} static postures of the motion performers "
                                        f"(bases/build/poses.py, seeds {POSTURE_SEED}+): {RANDOM_POSTURES} "
                                        f"random anatomically valid ones and {FAMILY_VARIANTS} variants of each of "
                                        f"{len(POSE_FAMILIES)} families each")
    if distribution:
        log("human: fitting the distribution of initial velocities")
        frames = np.concatenate([frames, data["train_rest"]])
        basis.extras.update(fit_basis_distribution(basis, frames, DISTRIBUTION_COMPONENTS,
                                                   max_samples=DISTRIBUTION_SAMPLES, steps=3, max_iter=12))
        basis.provenance["distribution"] = (f"Gaussian mixtures {DISTRIBUTION_COMPONENTS} on the log maps of "
                                            f"{DISTRIBUTION_SAMPLES} training frames and rest bodies (evenly chosen)")
    basis.provenance["build_seconds"] = round(time.perf_counter() - start, 1)
    return basis, data
