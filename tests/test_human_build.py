"""The human basis' builder pieces that need no Anny (bases/build/human.py, motions.py).

Anny is a build-time dependency only; these check the geometry steps on synthetic meshes
(hole closing, the symmetric remesh, the barycentric map) and the motion curves on the rig.
"""

import math

import numpy as np
import pytest
import trimesh

from bases.build import human, motions


def _capsule():
    """A closed ellipsoid, symmetric about x = 0: -> verts (642, 3), faces."""
    m = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(m.vertices, dtype=np.float64) * [0.3, 0.24, 0.8] + [0.0, 0.0, 0.8], \
        np.asarray(m.faces, dtype=np.int64)


def test_closed_body_caps_each_hole_with_a_linear_fan():
    v, f = _capsule()
    centres = v[f].mean(1)
    drop = (np.linalg.norm(centres - [0.3, 0.0, 0.8], axis=1) < 0.08) | (
        np.linalg.norm(centres - [-0.3, 0.0, 0.8], axis=1) < 0.08)
    assert len(human.boundary_loops(f[~drop])) == 2
    cv, cf, closure = human.closed_body(v, f, drop)
    assert human.boundary_loops(cf) == []  # closed again
    assert cv.shape == (closure.shape[0], 3) and closure.shape[1] == len(v)
    np.testing.assert_allclose(closure @ v, cv)
    # each cap centre is the mean of its rim, and rows sum to one (the map is an affine combination)
    np.testing.assert_allclose(np.asarray(closure.sum(1)).ravel(), 1.0)
    mesh = trimesh.Trimesh(cv, cf, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


def test_symmetric_remesh_is_closed_symmetric_on_the_surface_and_well_shaped():
    pytest.importorskip("bpy")
    v, f = _capsule()
    v, f = trimesh.remesh.subdivide(v, f)
    x, t = human.symmetric_remesh(v, f, ratio=0.4, rounds=4)
    assert 0.3 * len(v) < len(x) < 0.6 * len(v)
    human._check_closed(x, t)
    mesh = trimesh.Trimesh(x, t, process=False)
    assert mesh.is_winding_consistent and mesh.volume > 0
    q = human.min_angle_stats(x, t)
    assert q["min_angle"] > 10 and q["under_15"] <= 0.01 * len(t)
    # left-right symmetric: the mirror image of every vertex is (nearly) a vertex
    from scipy.spatial import cKDTree

    d, _ = cKDTree(x).query(x * [-1, 1, 1])
    assert np.percentile(d, 99) < 1e-6
    # every vertex lies on the input surface
    from mathutils.bvhtree import BVHTree

    src = BVHTree.FromPolygons(v.tolist(), f.tolist())
    assert max(src.find_nearest(p)[3] for p in x) < 1e-6


def test_barycentric_map_reproduces_points_on_the_surface_and_follows_deformations():
    pytest.importorskip("bpy")
    v, f = _capsule()
    rng = np.random.default_rng(0)
    pts, fid = trimesh.sample.sample_surface(trimesh.Trimesh(v, f, process=False), 200, seed=1)
    w = human.barycentric_map(v, f, pts)
    assert w.shape == (200, len(v)) and (w.getnnz(axis=1) <= 3).all()
    np.testing.assert_allclose(w @ v, pts, atol=1e-6)  # Blender's BVH is single precision
    moved = v * [1.3, 1.0, 0.7] + rng.normal(size=3)  # an affine motion moves the mapped points alike
    np.testing.assert_allclose(w @ moved, pts * [1.3, 1.0, 0.7] + (moved - v * [1.3, 1.0, 0.7])[0], atol=1e-6)


def test_min_angle_stats_find_a_sliver():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0.01, 0]], dtype=float)
    q = human.min_angle_stats(v, np.array([[0, 1, 2], [0, 3, 1]]))
    assert q["under_15"] == 1 and q["min_angle"] < 1


def test_every_human_motion_moves_and_the_new_ones_start_and_end_at_rest():
    for m in motions.HUMAN_TRAIN_MOTIONS + motions.HUMAN_TEST_MOTIONS:
        for u in (0.0, 1.0) if m in motions.NEW_MOTIONS else ():
            rots, root = motions.pose_at(m, u)
            assert all(abs(deg) < 1e-6 for seq in rots.values() for _, deg in seq), (m, u)
            assert np.allclose(root, 0), (m, u)
        moving = max(abs(deg) for u in np.linspace(0.1, 0.9, 9) for seq in motions.pose_at(m, u)[0].values()
                     for _, deg in seq)
        assert moving > 10, m
    assert len(motions.HUMAN_TRAIN_MOTIONS) + len(motions.HUMAN_TEST_MOTIONS) >= 20
    assert not set(motions.HUMAN_TRAIN_MOTIONS) & set(motions.HUMAN_TEST_MOTIONS)


def test_pose_matrices_put_each_rotation_on_the_mapped_anny_bones():
    bones = ["root"] + sorted({b for targets in human.BONE_MAP.values() for b, _ in targets})
    poses, roots = human.pose_matrices("arms_raise_side", np.array([0.0, 1 / 6]), bones)
    assert poses.shape == (2, len(bones), 4, 4) and roots.shape == (2, 3)
    np.testing.assert_allclose(poses[0], np.tile(np.eye(4), (len(bones), 1, 1)))  # rest at u = 0
    r = poses[1, bones.index("upperarm01.L"), :3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    # the left arm is abducted about -Y: a downward arm swings out to +X and up
    down = np.array([math.sin(math.radians(40)), 0, -math.cos(math.radians(40))])
    assert (r @ down)[2] > down[2] + 0.5
    np.testing.assert_allclose(poses[1, bones.index("upperarm01.R")], np.eye(4))  # the right arm waits
    # a rotation shared by two spine bones composes to the whole angle
    twist, _ = human.pose_matrices("torso_twist", np.array([0.25]), bones)
    both = twist[0, bones.index("spine04"), :3, :3] @ twist[0, bones.index("spine05"), :3, :3]
    angle = math.degrees(math.acos((np.trace(both) - 1) / 2))
    assert angle == pytest.approx(28.0, abs=1e-6)


def test_feet_and_hand_motions_turn_the_toes_out_and_curl_every_finger_on_both_sides():
    bones = ["root"] + sorted({b for targets in human.BONE_MAP.values() for b, _ in targets})
    named = {b for m in motions.HUMAN_TRAIN_MOTIONS + motions.HUMAN_TEST_MOTIONS
             for u in np.linspace(0, 1, 17) for b in motions.pose_at(m, u)[0]}
    assert named <= set(human.BONE_MAP)  # every bone a motion rotates reaches Anny's rig
    feet, _ = human.pose_matrices("feet_turn", np.array([1 / 8]), bones)  # the toes-out peak
    forward = np.array([0.0, -1.0, 0.0])
    for side, sign in (("L", 1), ("R", -1)):
        turned = feet[0, bones.index(f"upperleg01.{side}"), :3, :3] @ feet[0, bones.index(f"foot.{side}"), :3, :3]
        assert sign * (turned @ forward)[0] > math.sin(math.radians(40))  # toes out by more than 40 deg
    fist, _ = human.pose_matrices("hand_gestures", np.array([1 / 8]), bones)
    for side in "LR":
        for finger in range(1, 6):
            for joint in range(1, 4):
                r = fist[0, bones.index(f"finger{finger}-{joint}.{side}"), :3, :3]
                assert math.degrees(math.acos((np.trace(r) - 1) / 2)) > 20, (side, finger, joint)


def test_bases_build_names_the_human_and_refuses_an_unknown_basis(capsys):
    from bases.build.__main__ import BUILDERS, DEFAULT, main

    assert DEFAULT == ("human", "deformables") and "humanoid" in BUILDERS
    with pytest.raises(SystemExit):
        main(["nosuch"])
    assert "choose from human, deformables, humanoid" in capsys.readouterr().err


def test_the_solver_never_imports_anny():
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1]
    for folder in ("core", "bareesa_addon", "tools"):
        for path in (root / folder).rglob("*.py"):
            assert "import anny" not in path.read_text() and "from anny" not in path.read_text(), path


def test_the_shipped_human_basis_registers_with_the_builders_schedule():
    """bases/human.npz stores HUMAN_SCHEDULE (the finest level's iteration cap raised, see its comment):
    a card rewritten by hand or left at the paper's schedule fails here."""
    from bareesa.basis_io import load_basis
    from bareesa.latent import PAPER_BODY_SCHEDULE

    shipped = tuple(load_basis("human").schedule)
    assert shipped == tuple(human.HUMAN_SCHEDULE)
    assert shipped[-1].max_iter > PAPER_BODY_SCHEDULE[-1].max_iter
