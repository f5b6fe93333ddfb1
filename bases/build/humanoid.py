"""The ``humanoid`` basis: a procedural human body modelled, rigged and animated in Blender.

Model. A skeleton graph (joints and mid-limb nodes, Z-up, facing -Y, left = +X,
metres, feet on z = 0) is turned into a closed quad cage by Blender's Skin
modifier (once, for the reference body), relaxed tangentially (the Skin modifier
leaves coincident vertices where the branches meet at the chest) and smoothed by a
Subdivision Surface modifier (level 2) into the surface (~5k vertices); quads are split
along the diagonal that gives the rounder triangles on the template. The Skin modifier's output
topology depends on the joint positions and radii, so body types are *not*
re-skinned: each identity moves the reference cage vertices with its own
skeleton (every cage vertex keeps its position along, and offset around, the
skeleton segments, with offsets scaled by the identity's radii), so all
identities share one topology by construction (checked on every build).

Identities. Seeded random body types (height, leg/arm/torso/neck length,
shoulder and hip width, torso girth, belly, limb girth, head size) around the
reference body; the reference (all multipliers 1) is the template.

Motions. An armature with one bone per skeleton segment chain, weighted by
Blender's automatic (bone heat) weights on the reference cage and shared by
every identity (same vertex indices). Each motion is an action: rotations
given in the rest armature axes at keyframes every KEY_STEP frames, converted
to pose-bone quaternions; the evaluated surface (Armature then Subdivision) is
baked every BAKE_STEP frames through the depsgraph: registered 4D sequences,
a synthetic counterpart of DFAUST.

Basis. ``pose``: PCA of the frame-to-frame tangent vectors of the training
motions of the training identities; ``shape``: PCA of the steps of elastic H2
geodesics (body metric) from the template to each training identity in the
rest pose (the paper's construction). Held-out identities and motions are
never used to build the basis (bench/humanoid_accuracy.py evaluates on them).
"""

import math
import time

import bpy
import numpy as np
from mathutils import Quaternion, Vector

from bareesa.latent import PAPER_BODY_SCHEDULE

from bareesa.basis_building import build_basis
from bareesa.statistics import pose_prototypes

from .blender import bake, mesh_arrays, mesh_object, reset_scene, triangles
from .common import checked_template, elastic_paths, fit_basis_distribution, topology_signature

NAME = "humanoid"
SEED = 5
N_TRAIN_IDENTITIES = 16
N_TEST_IDENTITIES = 4
MOTION_IDENTITIES = 9      # training identities (the template and 8 others) that perform every training motion
FRAMES = 48                # frames per motion at 24 fps
KEY_STEP = 3               # a keyframe every KEY_STEP frames
BAKE_STEP = 3              # a baked mesh every BAKE_STEP frames -> 17 meshes per motion
SUBDIVISION = 2
CAGE_RELAX_ITERATIONS = 10  # tangential relaxation of the Skin cage (coincident vertices at the chest)
POSE_COMPONENTS = 80
SHAPE_COMPONENTS = 12
POSE_PROTOTYPES = 24       # k-means centres of the training frames' codes (registration's pose candidates)

# ------------------------------------------------------------------------------ skeleton

#: Body-type multipliers and their range (uniform in [lo, hi]) for random identities.
PARAMETERS = {"height": (0.9, 1.1), "legs": (0.9, 1.1), "arms": (0.9, 1.1), "torso": (0.92, 1.08),
              "neck": (0.8, 1.2), "shoulders": (0.85, 1.15), "hips": (0.85, 1.2), "girth": (0.85, 1.3),
              "belly": (0.9, 1.45), "limbs": (0.85, 1.25), "head": (0.92, 1.08)}

#: Skeleton graph: (node, node, extra rings); each edge gets that many evenly spaced extra nodes
#: (radii interpolated), which sets the cage resolution along the body.
GRAPH = [("pelvis", "waist", 2), ("waist", "chest", 2), ("chest", "neck_base", 2), ("neck_base", "head_base", 1),
         ("head_base", "head", 1), ("head", "head_top", 1)]
for _s in "LR":
    GRAPH += [("pelvis", f"hip{_s}", 0), (f"hip{_s}", f"thigh{_s}", 2), (f"thigh{_s}", f"knee{_s}", 2),
              (f"knee{_s}", f"shin{_s}", 2), (f"shin{_s}", f"ankle{_s}", 2), (f"ankle{_s}", f"toe{_s}", 2),
              ("chest", f"shoulder{_s}", 1), (f"shoulder{_s}", f"upperarm{_s}", 2),
              (f"upperarm{_s}", f"elbow{_s}", 2), (f"elbow{_s}", f"forearm{_s}", 2),
              (f"forearm{_s}", f"wrist{_s}", 2), (f"wrist{_s}", f"hand{_s}", 2)]
EDGES = []
for _a, _b, _k in GRAPH:
    _chain = [_a] + [f"{_a}~{_b}~{_i}" for _i in range(1, _k + 1)] + [_b]
    EDGES += list(zip(_chain[:-1], _chain[1:]))

#: Bones: name -> (head node, tail node, parent); the segments of a bone's chain move with it.
BONES = {"hips": ("pelvis", "waist", None), "spine": ("waist", "chest", "hips"),
         "chest": ("chest", "neck_base", "spine"), "neck": ("neck_base", "head_base", "chest"),
         "head": ("head_base", "head_top", "neck")}
for _s in "LR":
    BONES.update({f"thigh.{_s}": (f"hip{_s}", f"knee{_s}", "hips"), f"shin.{_s}": (f"knee{_s}", f"ankle{_s}", f"thigh.{_s}"),
                  f"foot.{_s}": (f"ankle{_s}", f"toe{_s}", f"shin.{_s}"),
                  f"clavicle.{_s}": ("chest", f"shoulder{_s}", "chest"),
                  f"upper_arm.{_s}": (f"shoulder{_s}", f"elbow{_s}", f"clavicle.{_s}"),
                  f"forearm.{_s}": (f"elbow{_s}", f"wrist{_s}", f"upper_arm.{_s}"),
                  f"hand.{_s}": (f"wrist{_s}", f"hand{_s}", f"forearm.{_s}")})


def skeleton(p=None):
    """Joint positions and radii of a body type: multipliers {name: value} -> {node: (pos (3,), (rx, ry))}.

    Z-up, facing -Y, left = +X, metres; the reference body (all 1) is about 1.72 m tall.
    """
    p = {k: 1.0 for k in PARAMETERS} | dict(p or {})
    L, A, T, S, H, G, B, M, Hd = (p[k] for k in ("legs", "arms", "torso", "shoulders", "hips", "girth", "belly",
                                                 "limbs", "head"))
    nodes = {}
    ankle_z, shin, thigh = 0.075, 0.41 * L, 0.43 * L
    knee_z = ankle_z + shin
    hip_z = knee_z + thigh
    pelvis_z = hip_z + 0.06
    waist_z = pelvis_z + 0.15 * T
    chest_z = waist_z + 0.17 * T
    neck_base_z = chest_z + 0.17 * T
    head_base_z = neck_base_z + 0.08 * p["neck"]
    nodes["pelvis"] = ((0, 0.0, pelvis_z), (0.155 * G * H, 0.105 * G * (1 + 0.4 * (B - 1))))
    nodes["waist"] = ((0, -0.005 * (B - 1), waist_z), (0.135 * G, 0.1 * G * B))
    nodes["chest"] = ((0, 0.0, chest_z), (0.16 * G * (0.6 + 0.4 * S), 0.105 * G * (1 + 0.2 * (B - 1))))
    nodes["neck_base"] = ((0, 0.01, neck_base_z), (0.065 * M, 0.06 * M))
    nodes["head_base"] = ((0, 0.005, head_base_z), (0.055 * M, 0.055 * M))
    nodes["head"] = ((0, -0.005, head_base_z + 0.1 * Hd), (0.08 * Hd, 0.095 * Hd))
    nodes["head_top"] = ((0, 0.005, head_base_z + 0.19 * Hd), (0.06 * Hd, 0.07 * Hd))
    down40 = np.array([math.sin(math.radians(40)), 0.0, -math.cos(math.radians(40))])
    for side, sx in (("L", 1.0), ("R", -1.0)):
        hip = np.array([sx * 0.09 * H, 0.0, hip_z])
        knee = np.array([sx * 0.095 * H, -0.01, knee_z])
        ankle = np.array([sx * 0.1 * H, 0.02, ankle_z])
        nodes[f"hip{side}"] = (hip, (0.085 * M * G ** 0.5, 0.085 * M * G ** 0.5))
        nodes[f"thigh{side}"] = (0.5 * (hip + knee), (0.072 * M, 0.072 * M))
        nodes[f"knee{side}"] = (knee, (0.05 * M, 0.05 * M))
        nodes[f"shin{side}"] = (0.45 * knee + 0.55 * ankle + (0, 0.012, 0), (0.048 * M, 0.05 * M))
        nodes[f"ankle{side}"] = (ankle, (0.035 * M, 0.035 * M))
        nodes[f"toe{side}"] = (ankle + (0.0, -0.16, -0.045), (0.04 * M, 0.025 * M))
        shoulder = np.array([sx * 0.185 * S, 0.0, chest_z + 0.14 * T])
        d = down40 * (sx, 1, 1)
        elbow = shoulder + 0.29 * A * d
        wrist = elbow + 0.25 * A * d
        nodes[f"shoulder{side}"] = (shoulder, (0.05 * M, 0.05 * M))
        nodes[f"upperarm{side}"] = (0.5 * (shoulder + elbow), (0.045 * M, 0.045 * M))
        nodes[f"elbow{side}"] = (elbow, (0.037 * M, 0.037 * M))
        nodes[f"forearm{side}"] = (0.5 * (elbow + wrist), (0.036 * M, 0.036 * M))
        nodes[f"wrist{side}"] = (wrist, (0.028 * M, 0.028 * M))
        nodes[f"hand{side}"] = (wrist + 0.15 * A * d, (0.035 * M, 0.025 * M))
    for a, b, k in GRAPH:
        for i in range(1, k + 1):
            t = i / (k + 1)
            nodes[f"{a}~{b}~{i}"] = ((1 - t) * np.asarray(nodes[a][0]) + t * np.asarray(nodes[b][0]),
                                     tuple((1 - t) * np.asarray(nodes[a][1]) + t * np.asarray(nodes[b][1])))
    h = p["height"]
    return {k: (h * np.asarray(pos, dtype=np.float64), (h * r[0], h * r[1])) for k, (pos, r) in nodes.items()}


def random_identities(n, seed):
    """n body types: list of multiplier dicts, uniform in PARAMETERS' ranges."""
    rng = np.random.default_rng(seed)
    return [{k: float(rng.uniform(lo, hi)) for k, (lo, hi) in PARAMETERS.items()} for _ in range(n)]


# ------------------------------------------------------------------------ cage & identities


def reference_cage():
    """The Skin-modifier cage of the reference body: -> verts (N, 3), polygons (quads)."""
    nodes = skeleton()
    names = list(nodes)
    obj = mesh_object("skeleton", [nodes[n][0] for n in names],
                      edges=[(names.index(a), names.index(b)) for a, b in EDGES])
    skin = obj.modifiers.new("skin", "SKIN")
    skin.branch_smoothing = 0.0
    skin.use_x_symmetry = True
    for i, n in enumerate(names):
        sv = obj.data.skin_vertices[0].data[i]
        sv.radius = nodes[n][1]
        sv.use_root = n == "pelvis"
    depsgraph = bpy.context.evaluated_depsgraph_get()
    me = bpy.data.meshes.new_from_object(obj.evaluated_get(depsgraph))
    verts, polys = mesh_arrays(me)
    bpy.data.objects.remove(obj)
    bpy.data.meshes.remove(me)
    return relax_cage(verts, polys), polys


def relax_cage(verts, polys, iterations=CAGE_RELAX_ITERATIONS, step=0.5):
    """Tangential Laplacian relaxation of a cage: verts (N, 3), polygons -> verts (N, 3).

    The Skin modifier leaves coincident vertices and needle quads where branches meet
    (the chest); subdivided, they become near-zero-area slivers, and the H2 energy of any
    motion that moves them (a raised arm) explodes. Each step moves every vertex towards
    its neighbours' mean within its tangent plane, which evens the quads out; on the coarse
    cage of the thin limbs it still thins the subdivided surface (template area 1.62 -> 1.46
    m^2 with 10 iterations).
    """
    x = np.asarray(verts, dtype=np.float64).copy()
    n = len(x)
    edges = {(min(a, b), max(a, b)) for p in polys for a, b in zip(p, p[1:] + p[:1])}
    i, j = np.array(sorted(edges)).T
    degree = np.bincount(np.r_[i, j], minlength=n).astype(np.float64)
    tris = np.array([(p[0], p[k], p[k + 1]) for p in polys for k in range(1, len(p) - 1)])
    for _ in range(iterations):
        mean = np.zeros_like(x)
        np.add.at(mean, i, x[j])
        np.add.at(mean, j, x[i])
        d = mean / degree[:, None] - x
        face_n = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
        normal = np.zeros_like(x)
        for c in range(3):
            np.add.at(normal, tris[:, c], face_n)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-15
        x += step * (d - (d * normal).sum(1, keepdims=True) * normal)
    return x


def _frame(u):
    """Unit axis u (3,) -> two unit vectors completing an orthonormal frame (e1 ~ X for vertical u)."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([0.0, -1.0, 0.0])
    e1 = np.cross(ref, u) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0]) - u[0] * u
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def _min_rotation(a, b):
    """Rotation matrix (3, 3) turning unit vector a into unit vector b by the smallest angle."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -0.999999:
        raise ValueError("segment direction reversed")
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def _ratio(rx, ry, e):
    """Radius ratio along unit direction e from per-axis ratios (rx: X, ry: Y, mean for Z)."""
    return e[..., 0] ** 2 * rx + e[..., 1] ** 2 * ry + e[..., 2] ** 2 * 0.5 * (rx + ry)


class Reshaper:
    """Moves the reference cage to another body type, vertex for vertex (one topology for all)."""

    def __init__(self, cage_verts, blend=0.012):
        self.ref = skeleton()
        self.x = np.asarray(cage_verts, dtype=np.float64)
        feats, dists = [], []
        for a, b in EDGES:
            pa, pb = self.ref[a][0], self.ref[b][0]
            length = np.linalg.norm(pb - pa)
            u = (pb - pa) / length
            e1, e2 = _frame(u)
            t = np.clip((self.x - pa) @ u / length, 0.0, 1.0)
            d = self.x - (pa + t[:, None] * (pb - pa))
            feats.append((t, d @ u, d @ e1, d @ e2, (u, e1, e2)))
            dists.append(np.linalg.norm(d, axis=1))
        dists = np.stack(dists, 1)
        w = np.exp(-(dists - dists.min(1, keepdims=True)) / blend)
        self.weights = w / w.sum(1, keepdims=True)
        self.feats = feats

    def __call__(self, params):
        """Cage vertices (N, 3) of the body type ``params``."""
        new = skeleton(params)
        out = np.zeros_like(self.x)
        for (a, b), (t, du, d1, d2, (u, e1, e2)), w in zip(EDGES, self.feats, self.weights.T):
            pa, pb = new[a][0], new[b][0]
            un = (pb - pa) / np.linalg.norm(pb - pa)
            rot = _min_rotation(u, un)
            ratio = [np.asarray(new[n][1]) / np.asarray(self.ref[n][1]) for n in (a, b)]
            rx = (1 - t) * ratio[0][0] + t * ratio[1][0]
            ry = (1 - t) * ratio[0][1] + t * ratio[1][1]
            r_u, r_1, r_2 = (_ratio(rx, ry, e[None, :]) for e in (u, e1, e2))
            pos = (pa + t[:, None] * (pb - pa) + (du * r_u)[:, None] * un + (d1 * r_1)[:, None] * (rot @ e1)
                   + (d2 * r_2)[:, None] * (rot @ e2))
            out += w[:, None] * pos
        return out


# ------------------------------------------------------------------------------- rigging


def armature(name, nodes):
    """An armature object with BONES placed on a skeleton's nodes."""
    arm = bpy.data.armatures.new(name)
    obj = bpy.data.objects.new(name, arm)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    for bone, (head, tail, parent) in BONES.items():
        eb = arm.edit_bones.new(bone)
        eb.head, eb.tail = Vector(nodes[head][0]), Vector(nodes[tail][0])
        eb.roll = 0.0
    for bone, (head, tail, parent) in BONES.items():
        if parent:
            arm.edit_bones[bone].parent = arm.edit_bones[parent]
    bpy.ops.object.mode_set(mode="OBJECT")
    return obj


def automatic_weights(cage_verts, polys):
    """Bone-heat weights (Blender's ARMATURE_AUTO) on the reference cage: -> (N, n_bones) array."""
    body = mesh_object("reference_body", cage_verts, polys)
    rig = armature("reference_rig", skeleton())
    for o in bpy.context.scene.objects:
        o.select_set(False)
    body.select_set(True)
    rig.select_set(True)
    bpy.context.view_layer.objects.active = rig
    result = bpy.ops.object.parent_set(type="ARMATURE_AUTO")
    if "FINISHED" not in result:
        raise RuntimeError(f"automatic weights failed: {result}")
    names = list(BONES)
    w = np.zeros((len(cage_verts), len(names)))
    index = {g.index: names.index(g.name) for g in body.vertex_groups}
    for v in body.data.vertices:
        for g in v.groups:
            w[v.index, index[g.group]] = g.weight
    if (w.sum(1) <= 0).any():
        raise RuntimeError(f"{int((w.sum(1) <= 0).sum())} cage vertices got no bone weight")
    bpy.data.objects.remove(body)
    bpy.data.objects.remove(rig)
    return w / w.sum(1, keepdims=True)


def rigged_body(name, cage_verts, polys, nodes, weights):
    """Body object (vertex groups, Armature then Subdivision modifiers) and its armature."""
    body = mesh_object(name, cage_verts, polys)
    rig = armature(name + "_rig", nodes)
    for j, bone in enumerate(BONES):
        group = body.vertex_groups.new(name=bone)
        for i in np.flatnonzero(weights[:, j] > 0):
            group.add([int(i)], float(weights[i, j]), "REPLACE")
    mod = body.modifiers.new("armature", "ARMATURE")
    mod.object = rig
    sub = body.modifiers.new("subdivision", "SUBSURF")
    sub.levels = sub.render_levels = SUBDIVISION
    return body, rig


# ------------------------------------------------------------------------------- motions

from .motions import TEST_MOTIONS, TRAIN_MOTIONS, pose_at  # noqa: E402  (shared with the human basis)



def keyframe_motion(rig, motion, frames=FRAMES, key_step=KEY_STEP):
    """Create and assign an action: pose-bone quaternions keyed every key_step frames (motion starts and ends at rest)."""
    if rig.animation_data is None:
        rig.animation_data_create()
    rig.animation_data.action = bpy.data.actions.new(f"{rig.name}_{motion}")
    rest = {b.name: b.matrix_local.to_quaternion() for b in rig.data.bones}
    for pb in rig.pose.bones:
        pb.rotation_mode = "QUATERNION"
    for fr in range(1, frames + 2, key_step):
        u = (fr - 1) / frames
        rots, root = pose_at(motion, u)
        for pb in rig.pose.bones:
            q = Quaternion()
            for axis, deg in rots.get(pb.name, ()):
                q = Quaternion(Vector(axis), math.radians(deg)) @ q
            qr = rest[pb.name]
            pb.rotation_quaternion = qr.inverted() @ q @ qr
            pb.keyframe_insert("rotation_quaternion", frame=fr)
            if pb.parent is None:
                pb.location = qr.inverted() @ Vector(root)
                pb.keyframe_insert("location", frame=fr)


# ---------------------------------------------------------------------------------- data


class Generator:
    """Blender scene holding the reference cage and weights; makes identities and bakes motions."""

    def __init__(self, log=print):
        reset_scene()
        self.cage, self.polys = reference_cage()
        self.reshaper = Reshaper(self.cage)
        self.weights = automatic_weights(self.cage, self.polys)
        self.faces = self._polygons = None
        self.log = log
        self.template = self.rest_mesh({})[0]  # decides how quads are split, for every body

    def rest_mesh(self, params):
        """Rest-pose surface of a body type: -> verts (N, 3), faces (F, 3) (triangulated quads)."""
        body, rig = rigged_body("body", self.reshaper(params), self.polys, skeleton(params), self.weights)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        ev = body.evaluated_get(depsgraph)
        me = ev.to_mesh()
        verts, polys = mesh_arrays(me)
        ev.to_mesh_clear()
        self._remove(body, rig)
        if self.faces is None:  # the first body (the template) decides how quads are split
            self.faces, self._polygons = triangles(polys, verts)
        elif [set(p) for p in polys] != [set(p) for p in self._polygons]:
            raise RuntimeError("a body type changed the topology")
        return verts, self.faces

    def motion(self, params, motion, step=BAKE_STEP):
        """Baked sequence (T, N, 3) of a body type performing a motion, a mesh every ``step`` frames."""
        body, rig = rigged_body("body", self.reshaper(params), self.polys, skeleton(params), self.weights)
        keyframe_motion(rig, motion)
        seq = bake(body, range(1, FRAMES + 2, step))
        action = rig.animation_data.action
        self._remove(body, rig)
        bpy.data.actions.remove(action)
        return seq

    @staticmethod
    def _remove(body, rig):
        me, arm = body.data, rig.data
        bpy.data.objects.remove(body)
        bpy.data.objects.remove(rig)
        bpy.data.meshes.remove(me)
        bpy.data.armatures.remove(arm)


def identity_sets(seed=SEED):
    """(train, test) lists of body-type multiplier dicts (deterministic)."""
    ids = random_identities(N_TRAIN_IDENTITIES + N_TEST_IDENTITIES, seed)
    return ids[:N_TRAIN_IDENTITIES], ids[N_TRAIN_IDENTITIES:]


def generate(log=print, motion_identities=MOTION_IDENTITIES, test=True):
    """Bake the training (and held-out) data: -> dict of arrays (float32 sequences)."""
    t0 = time.perf_counter()
    gen = Generator(log)
    template, faces = gen.template, gen.faces
    train, test_ids = identity_sets()
    rests = [gen.rest_mesh(p)[0] for p in train]
    log(f"humanoid: cage {len(gen.cage)} vertices, surface {len(template)} vertices, {len(faces)} faces; "
        f"{len(train)} training identities ({time.perf_counter() - t0:.0f} s)")
    performers = [{}] + train[:motion_identities - 1]
    sequences = {}
    for i, p in enumerate(performers):
        for m in TRAIN_MOTIONS:
            sequences[(i, m)] = gen.motion(p, m).astype(np.float32)
    log(f"humanoid: baked {len(sequences)} training sequences of {FRAMES // BAKE_STEP + 1} frames "
        f"({time.perf_counter() - t0:.0f} s)")
    data = {"template": template, "faces": faces, "train_identities": train, "train_rest": np.stack(rests),
            "sequences": sequences, "cage_vertices": len(gen.cage), "generator": gen}
    if test:
        data["test_identities"] = test_ids
        data["test_rest"] = np.stack([gen.rest_mesh(p)[0] for p in test_ids])
        data["test_sequences"] = {(i, m): gen.motion(p, m).astype(np.float32)
                                  for i, p in enumerate(test_ids) for m in TEST_MOTIONS + TRAIN_MOTIONS[:2]}
    return data


def build(pose_components=POSE_COMPONENTS, shape_components=SHAPE_COMPONENTS, log=print, data=None,
          elastic_iter=40, distribution=True):
    """Generate the data and build the basis: -> (Basis, data)."""
    start = time.perf_counter()
    data = data or generate(log, test=False)
    template, faces = data["template"], data["faces"]
    checked_template(template, faces, NAME)
    log("humanoid: elastic geodesics template -> training identities")
    shape_paths = elastic_paths([(template, v) for v in data["train_rest"]], faces, steps=4, max_iter=elastic_iter)
    height = float(template[:, 2].max() - template[:, 2].min())
    provenance = {
        "built_by": "python -m bases.build humanoid (Blender: Skin + Subdivision modifiers, armature with "
                    "automatic weights, keyframed actions baked per frame)",
        "template": f"procedural reference body, Z-up, facing -Y, metres, height {height:.3f}",
        "training_identities": len(data["train_identities"]), "identity_seed": SEED,
        "motion_identities": MOTION_IDENTITIES, "training_motions": TRAIN_MOTIONS,
        "held_out_motions": TEST_MOTIONS, "held_out_identities": N_TEST_IDENTITIES,
        "frames_per_motion": FRAMES // BAKE_STEP + 1, "topology": topology_signature(faces),
        "cage_vertices": int(data["cage_vertices"])}
    log("humanoid: PCA")
    basis = build_basis(template, faces, {"pose": list(data["sequences"].values()), "shape": shape_paths},
                        {"pose": pose_components, "shape": shape_components}, weights="body", scale=height,
                        name=NAME, units="m", schedule=PAPER_BODY_SCHEDULE, provenance=provenance)
    basis.provenance["groups"]["shape"]["construction"] = "elastic H2 geodesics template -> identity (4 meshes)"
    frames = np.concatenate([s[1:] for s in data["sequences"].values()])
    log(f"humanoid: {POSE_PROTOTYPES} pose prototypes from {len(frames)} training frames")
    basis.extras["pose_prototypes"] = pose_prototypes(basis, frames, POSE_PROTOTYPES, seed=SEED)
    basis.provenance["pose_prototypes"] = (f"{POSE_PROTOTYPES} k-means centres of the codes of the {len(frames)} "
                                           "training frames (clustered on the pose group): registration's pose "
                                           "candidates")
    if distribution:
        log("humanoid: fitting the distribution of initial velocities")
        frames = np.concatenate([frames, data["train_rest"]])
        basis.extras.update(fit_basis_distribution(basis, frames, {"pose": 4, "shape": 2}, max_samples=40,
                                                   steps=3, max_iter=20))
    basis.provenance["build_seconds"] = round(time.perf_counter() - start, 1)
    return basis, data
