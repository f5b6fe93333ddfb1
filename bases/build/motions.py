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

The motions are data (``MOTIONS``): each is a table of curves, evaluated by ``pose_at``.
"""

import math
from dataclasses import dataclass, field

X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
AXES = {"X": X, "Y": Y, "Z": Z}


def _side(side, axis, angle):
    """Mirror a rotation given for the left side (+X) to the right: axis (x, y, z) -> (x, -y, -z)."""
    return (axis, angle) if side == "L" else ((axis[0], -axis[1], -axis[2]), angle)


def _bump(u, k=1):
    """0 -> 1 -> 0 smoothly k times over u in [0, 1]."""
    return math.sin(math.pi * k * u) ** 2


def _pos(x):
    return max(0.0, x)


# ------------------------------------------------------------------------------ the table
#
# A motion: ``let`` names computed in order from the phase ``u``; ``tracks`` in order, each
# (bone, axis, degrees) appending one rotation to that bone, or a ``Sides`` block; ``root``
# the root offset (metres). Values are Python expressions over ``u``, the names before them
# and ``FUNCTIONS``. A bone ``name.*`` is both sides, the right one mirrored (the angle given
# for the left). In a ``Sides`` block the tracks run once per side, in the order given, with
# that side's names; ``{s}`` in a bone is the side and an axis ``~Y`` is Y mirrored to it.


@dataclass(frozen=True)
class Sides:
    """Tracks run once per side: side -> {name: expression}, then ``let`` and ``tracks`` per side."""
    values: dict
    tracks: tuple
    let: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Motion:
    tracks: tuple
    let: dict = field(default_factory=dict)
    root: tuple = ("0.0", "0.0", "0.0")


OPPOSED = {"L": {"ph": "1.0"}, "R": {"ph": "-1.0"}}  # the sides half a cycle apart
RAMP = "min(1.0, 4 * u, 4 * (1 - u))"                 # in over the first quarter, out over the last
SEGMENTS = "[bump(min(1.0, max(0.0, 4 * u - k))) for k in range(4)]"  # four bumps, one after the other

MOTIONS = {
    # left arm overhead, then the right one, then both to the side
    "arms_raise_side": Motion(tracks=(
        Sides({"L": {"lo": "0", "hi": "1 / 3", "deg": "150"}, "R": {"lo": "1 / 3", "hi": "2 / 3", "deg": "150"}},
              (("upper_arm.{s}", "~Y", "-deg * bump(min(1.0, max(0.0, (u - lo) / (hi - lo))))"),)),
        ("upper_arm.*", "Y", "-95 * bump(max(0.0, 3 * u - 2))"))),
    "arms_raise_front": Motion(tracks=(
        ("upper_arm.*", "X", "-130 * bump(u)"),
        ("upper_arm.*", "Y", "25 * bump(u)"))),
    "punch": Motion(tracks=(
        Sides(OPPOSED, let={"p": "pos(ph * sin(4 * pi * u)) ** 1.5"}, tracks=(
            ("upper_arm.{s}", "~Y", "25 * min(1, 4 * u, 4 * (1 - u))"),
            ("upper_arm.{s}", "X", "-(45 + 40 * p) * min(1, 4 * u, 4 * (1 - u))"),
            ("forearm.{s}", "X", "-(110 * (1 - p)) * min(1, 4 * u, 4 * (1 - u))"))),)),
    "jumping_jacks": Motion(let={"a": "bump(u, 2)"}, root=("0.0", "0.0", "0.06 * sin(2 * pi * u) ** 2"), tracks=(
        ("upper_arm.*", "Y", "-120 * a"),
        ("thigh.*", "Y", "-14 * a"))),
    "squat": Motion(
        let={"a": "bump(u)", "hip": "95 * a", "knee": "125 * a"},
        root=("0.0", "0.0", "-(0.43 * (1 - cos(radians(hip))) + 0.41 * (1 - cos(radians(knee - hip))))"),
        tracks=(
            ("thigh.*", "X", "-hip"),
            ("shin.*", "X", "knee"),
            ("foot.*", "X", "-(knee - hip)"),
            ("spine", "X", "25 * a"),
            ("chest", "X", "10 * a"),
            ("upper_arm.*", "X", "-80 * a"))),
    "knee_lift": Motion(tracks=(
        Sides(OPPOSED, let={"p": "pos(ph * sin(4 * pi * u))"}, tracks=(
            ("thigh.{s}", "X", "-95 * p"),
            ("shin.{s}", "X", "100 * p"))),)),
    "one_leg_jump": Motion(
        let={"a": "min(1.0, 5 * u, 5 * (1 - u))", "hop": "abs(sin(3 * pi * u)) * a"},
        root=("0.0", "0.0", "0.09 * hop"),
        tracks=(
            ("thigh.L", "X", "-30 * a"),
            ("shin.L", "X", "95 * a"),
            ("thigh.R", "X", "-15 * (1 - hop) * a"),
            ("shin.R", "X", "25 * (1 - hop) * a"),
            ("upper_arm.*", "Y", "-30 * a"))),
    "run_in_place": Motion(let={"a": RAMP}, root=("0.0", "0.0", "0.03 * abs(sin(4 * pi * u)) * a"), tracks=(
        Sides(OPPOSED, let={"p": "ph * sin(4 * pi * u)"}, tracks=(
            ("thigh.{s}", "X", "-70 * pos(p) * a"),
            ("shin.{s}", "X", "110 * pos(p) * a"),
            ("upper_arm.{s}", "X", "40 * p * a"),
            ("forearm.{s}", "X", "-85 * a"))),)),
    "torso_twist": Motion(let={"s1": "sin(2 * pi * u)"}, tracks=(
        ("spine", "Z", "28 * s1"),
        ("chest", "Z", "22 * s1"),
        ("neck", "Z", "10 * s1"),
        ("upper_arm.*", "Y", "-25 * bump(u)"),
        ("forearm.*", "X", "-60 * bump(u)"))),
    "torso_bend": Motion(  # forward in the first half, to the sides in the second
        let={"fwd": "bump(2 * u) if u < 0.5 else 0.0", "side": "sin(2 * pi * u) if u >= 0.5 else 0.0"},
        tracks=(
            ("spine", "X", "45 * fwd"),
            ("chest", "X", "25 * fwd"),
            ("spine", "Y", "20 * side"),
            ("chest", "Y", "15 * side"))),
    "head_turn": Motion(  # turn in the first half, nod in the second
        let={"turn": "sin(2 * pi * u) if u < 0.5 else 0.0", "nod": "sin(2 * pi * u) if u >= 0.5 else 0.0"},
        tracks=(
            ("neck", "Z", "35 * turn"),
            ("head", "Z", "30 * turn"),
            ("neck", "X", "25 * nod"),
            ("head", "X", "20 * nod"))),
    "shake_arms": Motion(let={"a": "min(1.0, 5 * u, 5 * (1 - u))"}, tracks=(
        ("upper_arm.*", "Y", "-(35 + 18 * sin(12 * pi * u)) * a"),
        ("upper_arm.*", "X", "-20 * sin(12 * pi * u + 1.0) * a"),
        ("forearm.*", "X", "-(35 + 30 * sin(12 * pi * u + 2.0)) * a"),
        ("hand.*", "X", "30 * sin(12 * pi * u + 3.0) * a"))),
    "biceps_curl": Motion(tracks=(
        Sides({"L": {"ph": "0.0"}, "R": {"ph": "0.5"}}, let={"p": "bump(u + ph, 2)"}, tracks=(
            ("upper_arm.{s}", "~Y", "30"),
            ("forearm.{s}", "X", "-135 * p"),
            ("hand.{s}", "X", "-20 * p"))),)),
    "side_steps": Motion(tracks=(
        Sides(OPPOSED, let={"p": "pos(ph * sin(4 * pi * u))"}, tracks=(
            ("thigh.{s}", "~Y", "-30 * p"),
            ("shin.{s}", "X", "30 * p"))),
        ("upper_arm.*", "Y", "15 * bump(u)"))),
    # held out
    "wave": Motion(let={"a": "bump(u) ** 0.5"}, tracks=(
        Sides({"R": {}}, (("upper_arm.{s}", "~Y", "-130 * a"),)),
        ("forearm.R", "X", "-(55 + 35 * sin(8 * pi * u)) * a"),
        ("hand.R", "Y", "20 * sin(8 * pi * u) * a"),
        ("neck", "Z", "-15 * a"))),
    "lunge": Motion(let={"a": "bump(u)"}, root=("0.0", "-0.1 * a", "-0.2 * a"), tracks=(
        ("thigh.L", "X", "-75 * a"),
        ("shin.L", "X", "80 * a"),
        ("foot.L", "X", "-5 * a"),
        ("thigh.R", "X", "25 * a"),
        ("shin.R", "X", "70 * a"),
        ("foot.R", "X", "-50 * a"),
        ("spine", "X", "-5 * a"))),
    # walking in place (a treadmill): legs and arms swing in opposition
    "walk": Motion(let={"a": RAMP}, tracks=(
        Sides(OPPOSED, let={"p": "ph * sin(4 * pi * u)"}, tracks=(
            ("thigh.{s}", "X", "-30 * p * a"),
            ("shin.{s}", "X", "45 * pos(-cos(4 * pi * u + ph * pi / 2)) * a"),
            ("foot.{s}", "X", "-10 * p * a"),
            ("upper_arm.{s}", "X", "25 * p * a"),
            ("forearm.{s}", "X", "-(15 + 10 * pos(-p)) * a"))),
        ("spine", "Z", "6 * sin(4 * pi * u) * a"))),
    # running in place: high knees behind, bent elbows, a flight phase
    "run": Motion(let={"a": RAMP}, root=("0.0", "0.0", "0.05 * abs(sin(6 * pi * u)) * a"), tracks=(
        Sides(OPPOSED, let={"p": "ph * sin(6 * pi * u)"}, tracks=(
            ("thigh.{s}", "X", "(-55 * pos(p) + 20 * pos(-p)) * a"),
            ("shin.{s}", "X", "(40 + 70 * pos(-p)) * a"),
            ("upper_arm.{s}", "X", "45 * p * a"),
            ("forearm.{s}", "X", "-90 * a"))),
        ("spine", "X", "10 * a"))),
    # sit on an unseen chair and stand up again
    "sit_down": Motion(let={"a": "bump(u) ** 0.7"}, tracks=(
        ("thigh.*", "X", "-90 * a"),
        ("shin.*", "X", "90 * a"),
        ("spine", "X", "20 * a * (1 - a) * 4"),
        ("upper_arm.*", "X", "-25 * a"),
        ("forearm.*", "X", "-40 * a"))),
    # a deep crouch on the toes, arms forward for balance
    "crouch": Motion(let={"a": "bump(u)", "hip": "115 * a", "knee": "140 * a"}, tracks=(
        ("thigh.*", "X", "-hip"),
        ("shin.*", "X", "knee"),
        ("foot.*", "X", "-(knee - hip) + 15 * a"),
        ("spine", "X", "35 * a"),
        ("upper_arm.*", "X", "-70 * a"),
        ("forearm.*", "X", "-20 * a"))),
    # reach up and forward with the right hand, then up with the left
    "reach": Motion(tracks=(
        Sides({"R": {"lo": "0.0"}, "L": {"lo": "0.5"}}, let={"p": "bump(min(1.0, max(0.0, (u - lo) / 0.5)))"},
              tracks=(
                  ("upper_arm.{s}", "X", "-150 * p"),
                  ("forearm.{s}", "X", "-10 * p"),
                  ("spine", "~Z", "10 * p"),
                  ("chest", "~Y", "8 * p"))),)),
    # crouch, take off with the arms up, land, stand
    "jump": Motion(
        let={"load": "bump(min(1.0, u / 0.3)) if u < 0.3 else "
                     "(bump(min(1.0, (u - 0.6) / 0.3)) if 0.6 <= u < 0.9 else 0.0)",
             "air": "bump((u - 0.3) / 0.3) if 0.3 <= u < 0.6 else 0.0"},
        root=("0.0", "0.0", "0.25 * air"),
        tracks=(
            ("thigh.*", "X", "-70 * load - 10 * air"),
            ("shin.*", "X", "90 * load + 15 * air"),
            ("foot.*", "X", "-20 * load + 25 * air"),
            ("spine", "X", "25 * load"),
            ("upper_arm.*", "X", "40 * load - 150 * air"))),
    # hips sway, arms up in turn, knees bounce, head follows
    "dance": Motion(let={"a": RAMP, "sway": "sin(4 * pi * u)"}, tracks=(
        ("spine", "Y", "10 * sway * a"),
        ("chest", "Y", "-8 * sway * a"),
        ("chest", "Z", "12 * sin(2 * pi * u) * a"),
        Sides(OPPOSED, let={"p": "pos(ph * sin(4 * pi * u))"}, tracks=(
            ("upper_arm.{s}", "~Y", "-(40 + 90 * p) * a"),
            ("forearm.{s}", "X", "-(30 + 60 * (1 - p)) * a"),
            ("thigh.{s}", "X", "-25 * bump(2 * u + 0.25 * (ph + 1)) * a"),
            ("shin.{s}", "X", "40 * bump(2 * u + 0.25 * (ph + 1)) * a"))),
        ("neck", "Z", "15 * sway * a"))),
    # toes out, up on the toes, toes in with the soles rolled in, toes curled
    "feet_turn": Motion(let={"seg": SEGMENTS}, tracks=(
        ("thigh.*", "Z", "30 * seg[0] - 15 * seg[2]"),
        ("foot.*", "Z", "20 * seg[0] - 15 * seg[2]"),
        ("foot.*", "X", "35 * seg[1]"),
        ("toes.*", "X", "-35 * seg[1] + 30 * seg[3]"),
        ("foot.*", "Y", "15 * seg[2] - 12 * seg[3]"),
        ("thigh.*", "Y", "-8 * seg[3]"))),
    # fists, fingers spread and bent back, wrists flexed, hands cupped
    "hand_gestures": Motion(let={"seg": SEGMENTS}, tracks=(
        ("fingers.*", "X", "30 * seg[0] - 12 * seg[1] + 10 * seg[3]"),
        ("thumb.*", "X", "25 * seg[0] - 10 * seg[1]"),
        ("fingers.*", "Y", "15 * seg[3] - 8 * seg[1]"),
        ("thumb.*", "Y", "20 * seg[3]"),
        ("hand.*", "X", "40 * seg[2]"),
        ("hand.*", "Y", "-20 * seg[2] + 10 * seg[1]"),
        ("forearm.*", "X", "-30 * seg[2]"))),
    # bend at the hips and knees to pick something up from the floor
    "pick_up": Motion(let={"a": "bump(u)"}, tracks=(
        ("spine", "X", "55 * a"),
        ("chest", "X", "30 * a"),
        ("neck", "X", "-20 * a"),
        ("thigh.*", "X", "-45 * a"),
        ("shin.*", "X", "60 * a"),
        ("foot.*", "X", "-15 * a"),
        ("upper_arm.*", "X", "-60 * a"),
        ("forearm.*", "X", "-15 * a"))),
}

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


# ------------------------------------------------------------------------------ evaluation

#: What the expressions may use besides ``u`` and their motion's names.
FUNCTIONS = {"__builtins__": {}, "sin": math.sin, "cos": math.cos, "radians": math.radians, "pi": math.pi,
             "min": min, "max": max, "abs": abs, "range": range, "bump": _bump, "pos": _pos}
_CODE = {}


def _eval(expr, env):
    code = _CODE.get(expr)
    if code is None:
        code = _CODE[expr] = compile(expr, f"<motion expression {expr!r}>", "eval")
    return eval(code, env)  # noqa: S307  (the expressions are this module's table)


def _let(names, env):
    for name, expr in names.items():
        env[name] = _eval(expr, env)
    return env


def pose_at(motion, u):
    """Rotations (armature rest axes, degrees) and root offset of a motion at phase u in [0, 1].

    -> ({bone: [(axis, degrees), ...]}, (dx, dy, dz) metres). Conventions: flexion of a
    downward bone about -X moves it forward (-Y); abduction of the left arm/leg is about -Y.
    """
    spec = MOTIONS[motion]
    env = _let(spec.let, dict(FUNCTIONS, u=u))
    r = {}
    for track in spec.tracks:
        if isinstance(track, Sides):
            for s, values in track.values.items():
                side_env = _let(track.let, _let(values, dict(env)))
                for bone, axis, expr in track.tracks:
                    deg = _eval(expr, side_env)
                    ax, deg = _side(s, AXES[axis[1:]], deg) if axis[0] == "~" else (AXES[axis], deg)
                    r.setdefault(bone.format(s=s), []).append((ax, deg))
            continue
        bone, axis, expr = track
        deg = _eval(expr, env)
        if bone.endswith(".*"):
            for s in "LR":
                r.setdefault(bone[:-1] + s, []).append(_side(s, AXES[axis], deg))
        else:
            r.setdefault(bone, []).append((AXES[axis], deg))
    return r, tuple(_eval(e, env) for e in spec.root)
