"""The ``deformables`` basis: a capsule bent, twisted, tapered and stretched by Blender's Simple Deform.

Template: a closed capsule (Z-up, length 2, radius 0.3, 24 segments around,
~800 vertices). Identities (group ``shape``): the capsule with other
proportions (radius, length, elliptical cross-section), same topology.
Motions (group ``pose``): for every identity, a Simple Deform modifier
(bend about X and Y, twist about Z, taper along Z, stretch along Z, and two
combined stacks) whose angle/factor is keyframed from 0 to a maximum (both
signs), baked frame by frame through the depsgraph into registered sequences.
"""

import math
import time

import bpy
import numpy as np

from bareesa.latent import Level

from bareesa.basis_building import build_basis
from bareesa.mesh import validate_mesh

from .blender import bake, mesh_object, reset_scene
from .common import elastic_paths, fit_basis_distribution, topology_signature
from .landmarks import LANDMARK_NOTES, deformables_landmarks

NAME = "deformables"
SEGMENTS = 24
RADIUS = 0.3
HALF_LENGTH = 0.7  # of the cylindrical part; total length 2 * (HALF_LENGTH + RADIUS) = 2
FRAMES = 13        # keyframes 1..13: rest pose to the maximum deformation

#: (name, radius scale x, radius scale y, half-length scale); the first is the template.
IDENTITIES = [("base", 1.0, 1.0, 1.0), ("thin", 0.7, 0.7, 1.0), ("thick", 1.3, 1.3, 1.0),
              ("short", 1.0, 1.0, 0.6), ("long", 1.0, 1.0, 1.4), ("flat", 1.3, 0.7, 1.0),
              ("slim_long", 0.8, 0.8, 1.3)]
#: (name, [(mode, axis, max angle in degrees or factor)]) — a stack of Simple Deform modifiers.
MOTIONS = [("bend_x", [("BEND", "X", 120.0)]), ("bend_y", [("BEND", "Y", 120.0)]),
           ("twist_z", [("TWIST", "Z", 150.0)]), ("taper_z", [("TAPER", "Z", 0.8)]),
           ("stretch_z", [("STRETCH", "Z", 0.4)]),
           ("bend_twist", [("TWIST", "Z", 90.0), ("BEND", "X", 90.0)]),
           ("bend_taper", [("TAPER", "Z", 0.5), ("BEND", "Y", 90.0)])]
SCHEDULE = (Level(0.25, 1e1, 2, 100), Level(0.08, 1e4, 3, 120), Level(0.03, 1e7, 4, 150))


def capsule(segments=SEGMENTS, radius=RADIUS, half_length=HALF_LENGTH):
    """Closed capsule along Z with rings spaced evenly in arc length: -> verts (N, 3), quads/tris list."""
    spacing = 2 * math.pi * radius / segments
    cap_rings = max(2, round(0.5 * math.pi * radius / spacing))
    body_rings = max(1, round(2 * half_length / spacing))
    rings = []  # (z, r) of each ring from bottom to top, poles excluded
    for k in range(1, cap_rings):
        a = -0.5 * math.pi + 0.5 * math.pi * k / cap_rings
        rings.append((-half_length + radius * math.sin(a), radius * math.cos(a)))
    for k in range(body_rings + 1):
        rings.append((-half_length + 2 * half_length * k / body_rings, radius))
    for k in range(1, cap_rings):
        a = 0.5 * math.pi * k / cap_rings
        rings.append((half_length + radius * math.sin(a), radius * math.cos(a)))
    phi = 2 * math.pi * np.arange(segments) / segments
    verts = [(0.0, 0.0, -half_length - radius)]
    for z, r in rings:
        verts += [(r * math.cos(p), r * math.sin(p), z) for p in phi]
    verts.append((0.0, 0.0, half_length + radius))
    n_ring, top = len(rings), 1 + len(rings) * segments
    faces = [(0, 1 + (j + 1) % segments, 1 + j) for j in range(segments)]
    for i in range(n_ring - 1):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        faces += [(a + j, a + (j + 1) % segments, b + (j + 1) % segments, b + j) for j in range(segments)]
    last = 1 + (n_ring - 1) * segments
    faces += [(last + j, last + (j + 1) % segments, top) for j in range(segments)]
    return np.asarray(verts), faces


def identity_mesh(sx, sy, sl):
    """The capsule with radius scaled by (sx, sy) and cylinder half-length by sl (same topology)."""
    v, faces = capsule()
    v = v.copy()
    z = v[:, 2]
    cap = np.sign(z) * np.maximum(np.abs(z) - HALF_LENGTH, 0.0)  # offset into the caps
    body = z - cap
    v[:, 0] *= sx
    v[:, 1] *= sy
    v[:, 2] = body * sl + cap * 0.5 * (sx + sy)
    return v, faces


def animate(obj, stack, frames=FRAMES, sign=1.0):
    """Add the Simple Deform stack to obj, keyframed from rest (frame 1) to the maximum (frame ``frames``)."""
    for mode, axis, amount in stack:
        mod = obj.modifiers.new(f"{mode.lower()}_{axis}", "SIMPLE_DEFORM")
        mod.deform_method = mode
        mod.deform_axis = axis
        prop = "angle" if mode in ("BEND", "TWIST") else "factor"
        value = math.radians(amount) if prop == "angle" else amount
        setattr(mod, prop, 0.0)
        mod.keyframe_insert(prop, frame=1)
        setattr(mod, prop, sign * value)
        mod.keyframe_insert(prop, frame=frames)
    if obj.animation_data and obj.animation_data.action:
        for fc in _fcurves(obj.animation_data.action):
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"


def _fcurves(action):
    """F-curves of an action (Blender 4.4+ layered actions, or the legacy list)."""
    if hasattr(action, "layers") and len(action.layers):
        out = []
        for layer in action.layers:
            for strip in layer.strips:
                for bag in strip.channelbags:
                    out.extend(bag.fcurves)
        return out
    return list(action.fcurves)


def generate(log=print):
    """Bake the data set: -> dict(template, faces (F, 3), identities {name: (N, 3)}, sequences {name: (T, N, 3)})."""
    from .blender import triangles

    reset_scene()
    identities, sequences = {}, {}
    faces = None
    for name, sx, sy, sl in IDENTITIES:
        v, polys = identity_mesh(sx, sy, sl)
        tri = triangles(polys)
        faces = tri if faces is None else faces
        if not np.array_equal(faces, tri):
            raise RuntimeError(f"identity {name} changed the topology")
        identities[name] = v
        for motion, stack in MOTIONS:
            for sign in (1.0, -1.0):
                obj = mesh_object(f"{name}_{motion}", v, polys)
                animate(obj, stack, sign=sign)
                seq = bake(obj, range(1, FRAMES + 1))
                if seq.shape[1] != len(v):
                    raise RuntimeError("Simple Deform changed the vertex count")
                sequences[f"{name}/{motion}{'+' if sign > 0 else '-'}"] = seq
                bpy.data.objects.remove(obj)
    log(f"deformables: {len(identities)} identities, {len(sequences)} sequences of {FRAMES} frames, "
        f"{len(faces)} faces")
    return {"template": identities["base"], "faces": faces, "identities": identities, "sequences": sequences}


def build(pose_components=16, shape_components=4, log=print):
    """Generate the data and build the basis: -> (Basis, data)."""
    start = time.perf_counter()
    data = generate(log)
    template, faces = data["template"], data["faces"]
    rep = validate_mesh(template, faces, NAME)
    if rep.n_boundary_edges or rep.n_nonmanifold_edges:
        raise RuntimeError(f"deformables template is not closed and manifold: {rep}")
    log("deformables: elastic geodesics template -> identities")
    shape_seqs = elastic_paths([(template, v) for k, v in data["identities"].items() if k != "base"], faces,
                               steps=4, max_iter=100)
    provenance = {"built_by": "python -m bases.build deformables (Blender Simple Deform modifier)",
                  "template": f"capsule, Z-up, length 2, radius {RADIUS}, {SEGMENTS} segments",
                  "identities": [x[0] for x in IDENTITIES],
                  "motions": [m[0] for m in MOTIONS] + ["(each with both signs)"],
                  "frames_per_motion": FRAMES, "topology": topology_signature(faces)}
    basis = build_basis(template, faces, {"pose": list(data["sequences"].values()), "shape": shape_seqs},
                        {"pose": pose_components, "shape": shape_components}, weights="body", name=NAME,
                        units="", schedule=SCHEDULE, provenance=provenance,
                        landmarks=deformables_landmarks(template))
    basis.provenance["landmarks"] = LANDMARK_NOTES[NAME]
    basis.provenance["groups"]["shape"]["construction"] = "elastic H2 geodesics template -> identity (4 meshes)"
    log("deformables: fitting the distribution of initial velocities")
    frames = np.concatenate([s[1:] for s in data["sequences"].values()])
    basis.extras.update(fit_basis_distribution(basis, frames, {"pose": 4, "shape": 2}, max_samples=60))
    log("deformables: done")
    basis.provenance["build_seconds"] = round(time.perf_counter() - start, 1)
    return basis, data
