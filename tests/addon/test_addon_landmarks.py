"""Landmarks, ignore masks and the Basis menu in Blender: Add Landmarks, what Register takes from them."""

import math

import numpy as np
import pytest

from tests.addon.support import add_mesh, bpy, code_surface, select, snapshot

NAMES = ["pose_000", "pose_001", "shape_000", "shape_001"]


@pytest.fixture
def marked(scene, tiny, tmp_path):
    """The tiny basis with three named landmarks (two poles and a point of the equator), chosen in the panel."""
    from dataclasses import replace

    from bareesa.basis_io import save_basis

    basis = tiny[0]
    t = basis.template
    marks = {"north": int(np.argmax(t[:, 2])), "south": int(np.argmin(t[:, 2])), "east": int(np.argmax(t[:, 0]))}
    path = tmp_path / "marked.npz"
    save_basis(path, replace(basis, landmarks=marks))
    scene.bareesa.basis = str(path)
    return replace(basis, landmarks=marks), path, tiny[2]


def sphere_scan(surface, name="scan", alpha=(0.0, 0.0, 0.0, 0.0)):
    verts, faces = code_surface(surface, alpha)
    return add_mesh(name, verts, faces)


def landmark_objects(scan):
    from bareesa_addon import convert

    return {o[convert.PROP_LANDMARK]: o for o in scan.children if convert.PROP_LANDMARK in o}


def test_add_landmarks_puts_one_named_empty_per_landmark_under_the_scan_and_keeps_moved_ones(marked):
    from mathutils import Vector

    basis, _, surface = marked
    scan = sphere_scan(surface)
    scan.location = (3.0, 0.0, 1.0)
    scan.scale = (2.0, 2.0, 2.0)
    bpy.context.view_layer.update()
    select(scan)
    assert bpy.ops.bareesa.add_landmarks(guess="BOUNDS") == {"FINISHED"}
    empties = landmark_objects(scan)
    assert set(empties) == {"north", "south", "east"}
    coll = bpy.data.collections["scan Landmarks"]
    assert coll.name in bpy.context.scene.collection.children
    for name, empty in empties.items():
        assert empty.type == "EMPTY" and empty.parent == scan and empty.users_collection[0] == coll
        # the first guess of a pole lies on the scan's pole (the bounding box maps onto the scan's)
        world = np.array(empty.matrix_world.translation)
        target = np.array(scan.matrix_world @ Vector(basis.template[basis.landmarks[name]]))
        assert np.linalg.norm(world - target) < 0.1 * 2.0
    assert bpy.context.scene.tool_settings.use_snap
    empties["north"].location = (0.1, 0.2, 0.9)
    bpy.context.view_layer.update()
    before = snapshot()
    select(scan)
    assert bpy.ops.bareesa.add_landmarks() == {"CANCELLED"}  # all there already: nothing added or moved
    assert snapshot() == before
    bpy.data.objects.remove(empties["east"])
    assert bpy.ops.bareesa.add_landmarks() == {"FINISHED"}  # only the deleted one comes back
    again = landmark_objects(scan)
    assert set(again) == {"north", "south", "east"}
    assert tuple(again["north"].location) == pytest.approx((0.1, 0.2, 0.9))


def test_add_landmarks_refuses_a_basis_without_landmarks_and_a_registered_object(scene, tiny):
    scan = sphere_scan(tiny[2])
    select(scan)
    before = snapshot()
    with pytest.raises(RuntimeError, match="has no named landmarks"):
        bpy.ops.bareesa.add_landmarks()
    assert snapshot() == before
    select()
    assert bpy.ops.bareesa.add_landmarks.poll() is False
    bpy.ops.bareesa.load_template()
    assert bpy.ops.bareesa.add_landmarks.poll() is False  # a registered result is not a scan


def test_visible_landmarks_reach_the_solver_in_the_scan_frame_hidden_ones_do_not(marked):
    from bareesa_addon.operators.common import scan_input

    basis, _, surface = marked
    scan = sphere_scan(surface)
    scan.location = (1.0, 2.0, 0.0)
    scan.rotation_euler = (0.0, 0.0, math.radians(40))
    bpy.context.view_layer.update()
    select(scan)
    bpy.ops.bareesa.add_landmarks(guess="BOUNDS")
    empties = landmark_objects(scan)
    empties["north"].location = (0.0, 0.1, 1.2)
    empties["east"].hide_set(True)
    bpy.context.view_layer.update()
    item = scan_input(bpy.context, scan, basis)
    marks = {v: p for v, p, _ in item.landmarks}
    assert set(marks) == {basis.landmarks["north"], basis.landmarks["south"]}
    assert marks[basis.landmarks["north"]] == pytest.approx((0.0, 0.1, 1.2), abs=1e-6)  # the scan's local frame
    assert item.face_weights is None
    empties["east"].hide_set(False)
    twin = empties["east"].copy()
    bpy.context.scene.collection.objects.link(twin)
    bpy.context.view_layer.update()
    with pytest.raises(Exception, match="two visible 'east' landmarks"):
        scan_input(bpy.context, scan, basis)


def test_three_landmarks_fix_a_registration_that_symmetry_leaves_open(marked):
    """A sphere turned 90 degrees: every rotation fits the surface; the landmarks say which is right."""
    from mathutils import Matrix, Vector

    basis, _, surface = marked
    s = bpy.context.scene.bareesa
    s.prealign = True
    s.detail_layer = False  # vertices against their true places: the basis fit's (detail slides them on the surface)
    rot = Matrix.Rotation(math.radians(90), 4, "X") @ Matrix.Rotation(math.radians(60), 4, "Z")
    errors = {}
    for use in (False, True):
        name = f"scan_{use}"
        scan = sphere_scan(surface, name)
        scan.matrix_world = rot
        bpy.context.view_layer.update()
        truth = np.array([tuple(rot @ Vector(v)) for v in basis.template])
        if use:
            select(scan)
            bpy.ops.bareesa.add_landmarks(guess="BOUNDS")
            for lm, empty in landmark_objects(scan).items():
                empty.location = tuple(basis.template[basis.landmarks[lm]])  # placed by the artist
            bpy.context.view_layer.update()
        select(scan)
        assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
        reg = bpy.data.objects[f"{name}_registered"]
        depsgraph = bpy.context.evaluated_depsgraph_get()
        from bareesa_addon import convert

        v, _ = convert.evaluated_mesh(reg, depsgraph)
        m = np.array(reg.matrix_world)
        errors[use] = np.linalg.norm(v @ m[:3, :3].T + m[:3, 3] - truth, axis=1).mean()
    assert errors[True] < 0.1 and errors[False] > 0.3, errors


def floor_scene(surface, alpha, mask):
    """A scan standing on a floor plate (one mesh), the plate in the ignore group when ``mask``."""
    verts, faces = code_surface(surface, alpha)
    g = np.linspace(-3.0, 3.0, 7)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    plate = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, verts[:, 2].min() - 0.02)], 1)
    a = (np.arange(6)[:, None] * 7 + np.arange(6)[None, :]).ravel()
    plate_faces = np.concatenate([np.stack([a, a + 7, a + 8], 1), np.stack([a, a + 8, a + 1], 1)]) + len(verts)
    obj = add_mesh(f"floor_{mask}", np.concatenate([verts, plate]), np.concatenate([faces, plate_faces]))
    if mask:
        group = obj.vertex_groups.new(name="bareesa_ignore")
        group.add(list(range(len(verts), len(verts) + len(plate))), 1.0, "REPLACE")
    return obj


def test_the_ignore_group_becomes_face_weights_and_a_masked_floor_registers_like_the_clean_scan(marked):
    from bareesa_addon.operators.common import scan_input
    from bareesa_addon import convert

    basis, _, surface = marked
    alpha = np.array([0.5, -0.4, 0.4, 0.3])
    s = bpy.context.scene.bareesa
    s.prealign = False
    masked = floor_scene(surface, alpha, True)
    item = scan_input(bpy.context, masked, basis)
    n_scan = len(code_surface(surface, alpha)[1])
    assert np.all(item.face_weights[:n_scan] == 1.0) and np.all(item.face_weights[n_scan:] == 0.0)
    masked.vertex_groups["bareesa_ignore"].add([len(masked.data.vertices) - 1], 0.5, "REPLACE")
    half = scan_input(bpy.context, masked, basis).face_weights
    assert 0.0 < half[n_scan:].max() < 1.0  # a face with a half-ignored corner is weighted between
    masked.vertex_groups["bareesa_ignore"].add([len(masked.data.vertices) - 1], 1.0, "REPLACE")
    free = floor_scene(surface, alpha, False)
    clean = sphere_scan(surface, "clean", alpha)
    codes = {}
    for obj in (masked, free, clean):
        select(obj)
        assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
        codes[obj.name] = convert.get_code(bpy.data.objects[f"{obj.name}_registered"], NAMES)
    err = {k: np.abs(c - alpha).max() for k, c in codes.items()}
    assert err["floor_True"] < 1.5 * err["clean"] + 0.02 and err["floor_False"] > 2 * err["floor_True"], err
    s.mask_group = "no_such_group"  # a scan without the chosen group is used whole
    assert scan_input(bpy.context, masked, basis).face_weights is None
    s.mask_group = "bareesa_ignore"
    masked.vertex_groups["bareesa_ignore"].add(list(range(len(masked.data.vertices))), 1.0, "REPLACE")
    select(masked)
    with pytest.raises(RuntimeError, match="covers the whole scan"):
        bpy.ops.bareesa.register_scan()


def test_the_basis_menu_lists_bundled_bases_with_their_card_and_a_file_entry(scene, tiny):
    from bareesa_addon.properties import OTHER_BASIS, basis_items

    s = scene.bareesa
    items = {i[0]: i for i in basis_items(s, bpy.context)}
    assert {"human", "deformables", OTHER_BASIS} <= set(items)
    assert "landmarks" in items["human"][2] and "vertices" in items["human"][2]
    assert s.basis_choice == OTHER_BASIS  # the fixture chose the tiny basis by path
    s.basis_choice = "deformables"
    assert s.basis == "deformables"
    s.basis_file = str(tiny[1])
    assert s.basis == str(tiny[1]) and s.basis_choice == OTHER_BASIS
