"""Motions as joint-angle curves, shared by the ``humanoid`` and ``human`` builders (no bpy).

A motion is a function of the phase u in [0, 1] (rest at 0 and 1) that returns
rotations per bone, given in the rest armature's (world) axes and composed in
order, and a root offset. Bone names are the mannequin's (``hips``, ``spine``,
``chest``, ``neck``, ``head``, ``clavicle.L``, ``upper_arm.L``, ``forearm.L``,
``hand.L``, ``thigh.L``, ``shin.L``, ``foot.L`` and the ``.R`` side; the ``human``
motions also move ``toes.L``, ``fingers.L`` and ``thumb.L``); a builder maps them
onto its rig. Conventions: Z-up, facing -Y, left = +X; flexion of a downward bone
about -X moves it forward (-Y); abduction of the left arm/leg is about -Y; the
right side mirrors the left (axis (x, y, z) -> (x, -y, -z)).
"""

import math

X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def _side(side, axis, angle):
    """Mirror a rotation given for the left side (+X) to the right: axis (x, y, z) -> (x, -y, -z)."""
    return (axis, angle) if side == "L" else ((axis[0], -axis[1], -axis[2]), angle)


def _bump(u, k=1):
    """0 -> 1 -> 0 smoothly k times over u in [0, 1]."""
    return math.sin(math.pi * k * u) ** 2


def _pos(x):
    return max(0.0, x)


def pose_at(motion, u):
    """Rotations (armature rest axes, degrees) and root offset of a motion at phase u in [0, 1].

    -> ({bone: [(axis, degrees), ...]}, (dx, dy, dz) metres). Conventions: flexion of a
    downward bone about -X moves it forward (-Y); abduction of the left arm/leg is about -Y.
    """
    r, root = {}, (0.0, 0.0, 0.0)

    def add(bone, axis, deg):
        r.setdefault(bone, []).append((axis, deg))

    def both(bone, axis, deg):
        for s in "LR":
            ax, a = _side(s, axis, deg)
            add(f"{bone}.{s}", ax, a)

    s1 = math.sin(2 * math.pi * u)
    if motion == "arms_raise_side":  # left arm overhead, then the right one, then both to the side
        for s, (lo, hi, deg) in (("L", (0, 1 / 3, 150)), ("R", (1 / 3, 2 / 3, 150))):
            ax, a = _side(s, Y, -deg * _bump(min(1.0, max(0.0, (u - lo) / (hi - lo)))))
            add(f"upper_arm.{s}", ax, a)
        both("upper_arm", Y, -95 * _bump(max(0.0, 3 * u - 2)))
    elif motion == "arms_raise_front":
        both("upper_arm", X, -130 * _bump(u))
        both("upper_arm", Y, 25 * _bump(u))
    elif motion == "punch":
        for s, ph in (("L", 1.0), ("R", -1.0)):
            p = _pos(ph * math.sin(4 * math.pi * u)) ** 1.5
            ax, a = _side(s, Y, 25)
            add(f"upper_arm.{s}", ax, a * min(1, 4 * u, 4 * (1 - u)))
            add(f"upper_arm.{s}", X, -(45 + 40 * p) * min(1, 4 * u, 4 * (1 - u)))
            add(f"forearm.{s}", X, -(110 * (1 - p)) * min(1, 4 * u, 4 * (1 - u)))
    elif motion == "jumping_jacks":
        a = _bump(u, 2)
        both("upper_arm", Y, -120 * a)
        both("thigh", Y, -14 * a)
        root = (0.0, 0.0, 0.06 * math.sin(2 * math.pi * u) ** 2)
    elif motion == "squat":
        a = _bump(u)
        hip, knee = 95 * a, 125 * a
        both("thigh", X, -hip)
        both("shin", X, knee)
        both("foot", X, -(knee - hip))
        add("spine", X, 25 * a)
        add("chest", X, 10 * a)
        both("upper_arm", X, -80 * a)
        drop = 0.43 * (1 - math.cos(math.radians(hip))) + 0.41 * (1 - math.cos(math.radians(knee - hip)))
        root = (0.0, 0.0, -drop)
    elif motion == "knee_lift":
        for s, ph in (("L", 1.0), ("R", -1.0)):
            p = _pos(ph * math.sin(4 * math.pi * u))
            add(f"thigh.{s}", X, -95 * p)
            add(f"shin.{s}", X, 100 * p)
    elif motion == "one_leg_jump":
        a = min(1.0, 5 * u, 5 * (1 - u))
        add("thigh.L", X, -30 * a)
        add("shin.L", X, 95 * a)
        hop = abs(math.sin(3 * math.pi * u)) * a
        add("thigh.R", X, -15 * (1 - hop) * a)
        add("shin.R", X, 25 * (1 - hop) * a)
        both("upper_arm", Y, -30 * a)
        root = (0.0, 0.0, 0.09 * hop)
    elif motion == "run_in_place":
        a = min(1.0, 4 * u, 4 * (1 - u))
        for s, ph in (("L", 1.0), ("R", -1.0)):
            p = ph * math.sin(4 * math.pi * u)
            add(f"thigh.{s}", X, -70 * _pos(p) * a)
            add(f"shin.{s}", X, 110 * _pos(p) * a)
            add(f"upper_arm.{s}", X, 40 * p * a)
            add(f"forearm.{s}", X, -85 * a)
        root = (0.0, 0.0, 0.03 * abs(math.sin(4 * math.pi * u)) * a)
    elif motion == "torso_twist":
        add("spine", Z, 28 * s1)
        add("chest", Z, 22 * s1)
        add("neck", Z, 10 * s1)
        both("upper_arm", Y, -25 * _bump(u))
        both("forearm", X, -60 * _bump(u))
    elif motion == "torso_bend":
        fwd, side = _bump(2 * u) if u < 0.5 else 0.0, math.sin(2 * math.pi * u) if u >= 0.5 else 0.0
        add("spine", X, 45 * fwd)
        add("chest", X, 25 * fwd)
        add("spine", Y, 20 * side)
        add("chest", Y, 15 * side)
    elif motion == "head_turn":
        turn = math.sin(2 * math.pi * u) if u < 0.5 else 0.0
        nod = math.sin(2 * math.pi * u) if u >= 0.5 else 0.0
        add("neck", Z, 35 * turn)
        add("head", Z, 30 * turn)
        add("neck", X, 25 * nod)
        add("head", X, 20 * nod)
    elif motion == "shake_arms":
        a = min(1.0, 5 * u, 5 * (1 - u))
        both("upper_arm", Y, -(35 + 18 * math.sin(12 * math.pi * u)) * a)
        both("upper_arm", X, -20 * math.sin(12 * math.pi * u + 1.0) * a)
        both("forearm", X, -(35 + 30 * math.sin(12 * math.pi * u + 2.0)) * a)
        both("hand", X, 30 * math.sin(12 * math.pi * u + 3.0) * a)
    elif motion == "biceps_curl":
        for s, ph in (("L", 0.0), ("R", 0.5)):
            p = _bump(u + ph, 2)
            ax, a = _side(s, Y, 30)
            add(f"upper_arm.{s}", ax, a)
            add(f"forearm.{s}", X, -135 * p)
            add(f"hand.{s}", X, -20 * p)
    elif motion == "side_steps":
        for s, ph in (("L", 1.0), ("R", -1.0)):
            p = _pos(ph * math.sin(4 * math.pi * u))
            ax, a = _side(s, Y, -30 * p)
            add(f"thigh.{s}", ax, a)
            add(f"shin.{s}", X, 30 * p)
        both("upper_arm", Y, 15 * _bump(u))
    elif motion == "wave":  # held out
        a = _bump(u) ** 0.5
        ax, ang = _side("R", Y, -130 * a)
        add("upper_arm.R", ax, ang)
        add("forearm.R", X, -(55 + 35 * math.sin(8 * math.pi * u)) * a)
        add("hand.R", Y, 20 * math.sin(8 * math.pi * u) * a)
        add("neck", Z, -15 * a)
    elif motion == "lunge":  # held out
        a = _bump(u)
        add("thigh.L", X, -75 * a)
        add("shin.L", X, 80 * a)
        add("foot.L", X, -5 * a)
        add("thigh.R", X, 25 * a)
        add("shin.R", X, 70 * a)
        add("foot.R", X, -50 * a)
        add("spine", X, -5 * a)
        root = (0.0, -0.1 * a, -0.2 * a)
    elif motion == "walk":  # walking in place (a treadmill): legs and arms swing in opposition
        a = min(1.0, 4 * u, 4 * (1 - u))
        for s, ph in (("L", 1.0), ("R", -1.0)):
            p = ph * math.sin(4 * math.pi * u)
            add(f"thigh.{s}", X, -30 * p * a)
            add(f"shin.{s}", X, 45 * _pos(-math.cos(4 * math.pi * u + ph * math.pi / 2)) * a)
            add(f"foot.{s}", X, -10 * p * a)
            add(f"upper_arm.{s}", X, 25 * p * a)
            add(f"forearm.{s}", X, -(15 + 10 * _pos(-p)) * a)
        add("spine", Z, 6 * math.sin(4 * math.pi * u) * a)
    elif motion == "run":  # running in place: high knees behind, bent elbows, a flight phase
        a = min(1.0, 4 * u, 4 * (1 - u))
        for s, ph in (("L", 1.0), ("R", -1.0)):
            p = ph * math.sin(6 * math.pi * u)
            add(f"thigh.{s}", X, (-55 * _pos(p) + 20 * _pos(-p)) * a)
            add(f"shin.{s}", X, (40 + 70 * _pos(-p)) * a)
            add(f"upper_arm.{s}", X, 45 * p * a)
            add(f"forearm.{s}", X, -90 * a)
        add("spine", X, 10 * a)
        root = (0.0, 0.0, 0.05 * abs(math.sin(6 * math.pi * u)) * a)
    elif motion == "sit_down":  # sit on an unseen chair and stand up again
        a = _bump(u) ** 0.7
        both("thigh", X, -90 * a)
        both("shin", X, 90 * a)
        add("spine", X, 20 * a * (1 - a) * 4)
        both("upper_arm", X, -25 * a)
        both("forearm", X, -40 * a)
    elif motion == "crouch":  # a deep crouch on the toes, arms forward for balance
        a = _bump(u)
        hip, knee = 115 * a, 140 * a
        both("thigh", X, -hip)
        both("shin", X, knee)
        both("foot", X, -(knee - hip) + 15 * a)
        add("spine", X, 35 * a)
        both("upper_arm", X, -70 * a)
        both("forearm", X, -20 * a)
    elif motion == "reach":  # reach up and forward with the right hand, then up with the left
        for s, lo in (("R", 0.0), ("L", 0.5)):
            p = _bump(min(1.0, max(0.0, (u - lo) / 0.5)))
            add(f"upper_arm.{s}", X, -150 * p)
            add(f"forearm.{s}", X, -10 * p)
            ax, ang = _side(s, Z, 10 * p)
            add("spine", ax, ang)
            ax, ang = _side(s, Y, 8 * p)
            add("chest", ax, ang)
    elif motion == "jump":  # crouch, take off with the arms up, land, stand
        load = _bump(min(1.0, u / 0.3)) if u < 0.3 else (_bump(min(1.0, (u - 0.6) / 0.3)) if 0.6 <= u < 0.9 else 0.0)
        air = _bump((u - 0.3) / 0.3) if 0.3 <= u < 0.6 else 0.0
        both("thigh", X, -70 * load - 10 * air)
        both("shin", X, 90 * load + 15 * air)
        both("foot", X, -20 * load + 25 * air)
        add("spine", X, 25 * load)
        both("upper_arm", X, 40 * load - 150 * air)
        root = (0.0, 0.0, 0.25 * air)
    elif motion == "dance":  # hips sway, arms up in turn, knees bounce, head follows
        a = min(1.0, 4 * u, 4 * (1 - u))
        sway = math.sin(4 * math.pi * u)
        add("spine", Y, 10 * sway * a)
        add("chest", Y, -8 * sway * a)
        add("chest", Z, 12 * math.sin(2 * math.pi * u) * a)
        for s, ph in (("L", 1.0), ("R", -1.0)):
            p = _pos(ph * math.sin(4 * math.pi * u))
            ax, ang = _side(s, Y, -(40 + 90 * p) * a)
            add(f"upper_arm.{s}", ax, ang)
            add(f"forearm.{s}", X, -(30 + 60 * (1 - p)) * a)
            add(f"thigh.{s}", X, -25 * _bump(2 * u + 0.25 * (ph + 1)) * a)
            add(f"shin.{s}", X, 40 * _bump(2 * u + 0.25 * (ph + 1)) * a)
        add("neck", Z, 15 * sway * a)
    elif motion == "feet_turn":  # toes out, up on the toes, toes in with the soles rolled in, toes curled
        seg = [_bump(min(1.0, max(0.0, 4 * u - k))) for k in range(4)]
        both("thigh", Z, 30 * seg[0] - 15 * seg[2])
        both("foot", Z, 20 * seg[0] - 15 * seg[2])
        both("foot", X, 35 * seg[1])
        both("toes", X, -35 * seg[1] + 30 * seg[3])
        both("foot", Y, 15 * seg[2] - 12 * seg[3])
        both("thigh", Y, -8 * seg[3])
    elif motion == "hand_gestures":  # fists, fingers spread and bent back, wrists flexed, hands cupped
        seg = [_bump(min(1.0, max(0.0, 4 * u - k))) for k in range(4)]
        both("fingers", X, 30 * seg[0] - 12 * seg[1] + 10 * seg[3])
        both("thumb", X, 25 * seg[0] - 10 * seg[1])
        both("fingers", Y, 15 * seg[3] - 8 * seg[1])
        both("thumb", Y, 20 * seg[3])
        both("hand", X, 40 * seg[2])
        both("hand", Y, -20 * seg[2] + 10 * seg[1])
        both("forearm", X, -30 * seg[2])
    elif motion == "pick_up":  # bend at the hips and knees to pick something up from the floor
        a = _bump(u)
        add("spine", X, 55 * a)
        add("chest", X, 30 * a)
        add("neck", X, -20 * a)
        both("thigh", X, -45 * a)
        both("shin", X, 60 * a)
        both("foot", X, -15 * a)
        both("upper_arm", X, -60 * a)
        both("forearm", X, -15 * a)
    else:
        raise KeyError(motion)
    return r, root


TRAIN_MOTIONS = ["arms_raise_side", "arms_raise_front", "punch", "jumping_jacks", "squat", "knee_lift",
                 "one_leg_jump", "run_in_place", "torso_twist", "torso_bend", "head_turn", "shake_arms",
                 "biceps_curl", "side_steps"]
TEST_MOTIONS = ["wave", "lunge"]
#: The human basis trains on the mannequin's motions and these ten; it holds out the same two. The last two
#: (toes turned out and in, fingers and wrists) let it reach feet and hands as scans of real people hold them.
NEW_MOTIONS = ["walk", "run", "sit_down", "crouch", "reach", "jump", "dance", "pick_up", "feet_turn",
               "hand_gestures"]
HUMAN_TRAIN_MOTIONS = TRAIN_MOTIONS + NEW_MOTIONS
HUMAN_TEST_MOTIONS = TEST_MOTIONS
