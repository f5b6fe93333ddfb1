"""bareesa.interpolate / extrapolate / transfer_motion / generate_random / build_basis / distance via bpy.ops."""

import csv

import numpy as np
import pytest

from tests.addon.support import add_mesh, bpy, code_surface, key_values, mesh_verts, select, snapshot

NAMES = ["pose_000", "pose_001", "shape_000", "shape_001"]
A = np.array([0.2, -0.3, 0.4, 0.1])
B = np.array([-0.5, 0.6, 0.1, 0.7])

#: codes of template-topology frames come from the ridge-regularised projection (shrinks them by
#: up to ~0.5 %, bareesa.latent.PROJECTION_RIDGE): compare to this absolute tolerance
RIDGE_ATOL = 5e-3


def registered(name, code, location=(0.0, 0.0, 0.0)):
    """A template object with a code, as register_scan leaves it."""
    from bareesa_addon import convert

    bpy.ops.bareesa.load_template()
    obj = bpy.context.active_object
    obj.name = name
    convert.set_code(obj, NAMES, code)
    obj.location = location
    bpy.context.view_layer.update()
    return obj


def keyed(obj):
    from bareesa_addon import convert

    frames = convert.keyed_frames(obj, NAMES)
    return frames, np.stack([convert.code_at_frame(obj, NAMES, f) for f in frames])


def decode(basis, code):
    return basis.template + np.tensordot(np.asarray(code), basis.fields, axes=(-1, 0))


# ------------------------------------------------------------------------------ interpolate


def test_interpolate_keyframes_an_evenly_paced_geodesic_on_every_frame(scene, tiny, tmp_path):
    from bareesa.geodesics import step_lengths

    basis = tiny[0]
    a, b = registered("A", A), registered("B", B, location=(3.0, 0.0, 0.0))
    scene.bareesa.make_collection = True
    before = snapshot()
    assert bpy.ops.bareesa.interpolate(object_a="A", object_b="B") == {"FINISHED"}
    after = snapshot()
    assert after["A"] == before["A"] and after["B"] == before["B"]
    path_obj = bpy.data.objects["A_to_B"]
    frames, codes = keyed(path_obj)
    assert list(frames) == [1, 2, 3, 4, 5, 6]
    assert np.allclose(codes[0], A, atol=1e-6) and np.allclose(codes[-1], B, atol=1e-6)
    lengths = step_lengths(*basis.tensors(), codes, basis.weights)
    assert lengths.std() < 0.05 * lengths.mean()
    scene.frame_set(1)
    assert np.allclose(path_obj.matrix_world.translation, (0, 0, 0), atol=1e-6)
    scene.frame_set(6)
    assert np.allclose(path_obj.matrix_world.translation, (3, 0, 0), atol=1e-6)
    assert scene.bareesa.distance > 0 and scene.bareesa.distance_pair == "A - B"
    meshes = sorted(bpy.data.collections["A_to_B_frames"].objects, key=lambda o: o.name)
    assert len(meshes) == 6
    v = np.empty(len(meshes[3].data.vertices) * 3)
    meshes[3].data.vertices.foreach_get("co", v)
    assert np.allclose(v.reshape(-1, 3), decode(basis, codes[3]), atol=1e-5)
    # save -> reload keeps the keyframes
    blend = tmp_path / "path.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    frames2, codes2 = keyed(bpy.data.objects["A_to_B"])
    assert np.array_equal(frames2, frames) and np.allclose(codes2, codes)


def anchor_spy(monkeypatch, module, name):
    """Record the ``anchor`` argument of core.<module>.<name> on every call: -> the list of values."""
    import importlib

    mod = importlib.import_module(f"bareesa.{module}")
    real, seen = getattr(mod, name), []

    def spy(*args, anchor=False, **kwargs):
        seen.append(anchor)
        return real(*args, anchor=anchor, **kwargs)

    monkeypatch.setattr(mod, name, spy)
    return seen


def test_interpolate_keep_body_planted_is_core_keyframe_path_with_anchor(scene, tiny, monkeypatch):
    from bareesa.geodesics import geodesic, keyframe_path

    basis = tiny[0]
    t, f, h = basis.tensors()
    registered("A", A), registered("B", B)
    raw = geodesic(t, f, h, A, B, basis.weights, steps=scene.bareesa.steps, max_iter=scene.bareesa.geodesic_iterations)
    # the tiny basis spans no translation, so anchoring changes no code here: the spy checks the
    # setting reaches core (what anchoring does is tested in test_geodesic and test_cli)
    seen = anchor_spy(monkeypatch, "geodesics", "keyframe_path")
    for anchor in (True, False):
        select(bpy.data.objects["A"], bpy.data.objects["B"])  # the poll wants a selection
        assert bpy.ops.bareesa.interpolate(object_a="A", object_b="B", anchor=anchor) == {"FINISHED"}
        codes = keyed(bpy.data.objects["A_to_B"])[1]
        assert np.allclose(codes, keyframe_path(t, f, h, raw.path, basis.weights, len(codes), anchor=anchor),
                           atol=1e-5)
        bpy.data.objects.remove(bpy.data.objects["A_to_B"])
    assert seen == [True, False]  # (this test imported the real keyframe_path before the spy)


def test_interpolate_uses_selection_and_registers_a_raw_scan_end(scene, tiny):
    surface = tiny[2]
    a = registered("A", A)
    scan = add_mesh("scan", *code_surface(surface, B), location=(2.0, 0.0, 0.0))
    scene.bareesa.prealign = False
    select(a, scan, active=scan)
    assert bpy.ops.bareesa.interpolate() == {"FINISHED"}
    reg = bpy.data.objects["scan_registered"]
    frames, codes = keyed(bpy.data.objects["A_to_scan"])
    assert np.allclose(codes[-1], key_values(reg, NAMES), atol=1e-6)
    assert np.allclose(codes[0], A, atol=1e-6)


def test_interpolate_two_raw_scans_by_symmetric_matching(scene, tiny):
    surface = tiny[2]
    scan_a = add_mesh("scan_a", *code_surface(surface, A, seed=4))
    scan_b = add_mesh("scan_b", *code_surface(surface, B, seed=6), location=(3.0, 0.0, 0.0))
    select(scan_a, scan_b)  # the operator's poll wants a selection (or the panel's From and To)
    before = snapshot()
    assert bpy.ops.bareesa.interpolate(object_a="scan_a", object_b="scan_b") == {"FINISHED"}
    after = snapshot()
    assert after["scan_a"] == before["scan_a"] and after["scan_b"] == before["scan_b"]
    reg_a, reg_b = bpy.data.objects["scan_a_registered"], bpy.data.objects["scan_b_registered"]
    frames, codes = keyed(bpy.data.objects["scan_a_to_scan_b"])
    assert list(frames) == [1, 2, 3, 4, 5, 6]
    assert np.allclose(codes[0], key_values(reg_a, NAMES), atol=1e-6)
    assert np.allclose(codes[-1], key_values(reg_b, NAMES), atol=1e-6)
    assert np.abs(codes[0] - A).max() < 0.3 and np.abs(codes[-1] - B).max() < 0.3
    scene.frame_set(6)
    assert np.allclose(bpy.data.objects["scan_a_to_scan_b"].matrix_world, reg_b.matrix_world, atol=1e-5)


def test_interpolate_refuses_an_edited_registered_object_and_changes_nothing(scene):
    import bmesh

    a, b = registered("A", A), registered("B", B)
    bm = bmesh.new()
    bm.from_mesh(b.data)
    bm.verts.ensure_lookup_table()
    bm.verts.remove(bm.verts[0])
    bm.to_mesh(b.data)
    bm.free()
    before = snapshot()
    with pytest.raises(RuntimeError, match="no longer has the topology"):
        bpy.ops.bareesa.interpolate(object_a="A", object_b="B")
    assert snapshot() == before


def test_interpolate_refuses_objects_of_different_bases(scene, tiny, tmp_path):
    import shutil

    registered("A", A)
    other = tmp_path / "other.npz"
    shutil.copy(tiny[1], other)
    bpy.ops.bareesa.load_template(basis=str(other))
    bpy.context.active_object.name = "B"
    before = snapshot()
    with pytest.raises(RuntimeError, match="different bases"):
        bpy.ops.bareesa.interpolate(object_a="A", object_b="B")
    with pytest.raises(RuntimeError, match="choose two objects"):
        select()
        bpy.ops.bareesa.interpolate()
    assert snapshot() == before


# ------------------------------------------------------------------------------ extrapolate


def test_extrapolate_two_objects_continues_the_geodesic_as_keyframes(scene, tiny):
    from bareesa.shooting import extrapolate

    basis = tiny[0]
    registered("A", 0.5 * A), registered("B", 0.5 * B)
    scene.bareesa.extrapolate_steps, scene.bareesa.extrapolate_spacing = 2, 5
    assert bpy.ops.bareesa.extrapolate(source="OBJECTS", object_a="A", object_b="B") == {"FINISHED"}
    frames, codes = keyed(bpy.data.objects["A_B_extrapolated"])
    assert list(frames) == [1, 6, 11, 16]
    expected = extrapolate(*basis.tensors(), 0.5 * A, 0.5 * B, basis.weights, 2)
    assert np.allclose(codes, expected, atol=1e-6)


def test_extrapolate_keep_body_planted_reaches_core(scene, tiny, monkeypatch):
    registered("A", 0.5 * A), registered("B", 0.5 * B)
    scene.bareesa.extrapolate_steps = 2
    seen = anchor_spy(monkeypatch, "shooting", "extrapolate")
    for anchor in (True, False):
        assert bpy.ops.bareesa.extrapolate(source="OBJECTS", object_a="A", object_b="B", anchor=anchor) == {
            "FINISHED"}
    assert seen == [True, False]


def test_extrapolate_warns_of_frames_continued_in_the_frozen_metric(scene, tiny, monkeypatch, capfd):
    import bareesa.shooting as shooting

    real = shooting.extrapolate

    def frozen_at_2(*args, **kwargs):  # the real shot, reported as continued in the frozen metric at frame 2
        path, report = real(*args, **kwargs)
        report.frozen = [2]
        return path, report

    monkeypatch.setattr(shooting, "extrapolate", frozen_at_2)
    registered("A", 0.5 * A), registered("B", 0.5 * B)
    scene.bareesa.extrapolate_steps = 2
    capfd.readouterr()
    assert bpy.ops.bareesa.extrapolate(source="OBJECTS", object_a="A", object_b="B") == {"FINISHED"}
    out = capfd.readouterr().out
    assert "no geodesic step converged at new frame 2: continued there in the metric" in out
    assert len(keyed(bpy.data.objects["A_B_extrapolated"])[0]) == 4


def test_extrapolate_keyframes_adds_keys_after_the_last_two(scene, tiny):
    from bareesa_addon import convert
    from bareesa.shooting import extrapolate

    basis = tiny[0]
    obj = registered("anim", A)
    convert.keyframe_codes(obj, NAMES, [1, 5], [0.5 * A, 0.5 * B])
    scene.bareesa.extrapolate_steps = 2
    select(obj)
    assert bpy.ops.bareesa.extrapolate() == {"FINISHED"}
    frames, codes = keyed(obj)
    assert list(frames) == [1, 5, 9, 13]
    expected = extrapolate(*basis.tensors(), 0.5 * A, 0.5 * B, basis.weights, 2)
    assert np.allclose(codes, expected, atol=1e-6)


def test_extrapolate_without_keyframes_reports_and_changes_nothing(scene):
    select(registered("still", A))
    before = snapshot()
    with pytest.raises(RuntimeError, match="keyframes"):
        bpy.ops.bareesa.extrapolate()
    assert snapshot() == before


# ------------------------------------------------------------------------------ detail along paths


def some_detail(basis, k):
    """A smooth off-basis displacement (N, 3) of the template, different for each k."""
    return 0.04 * (k + 1) * np.sin((2.0 + k) * basis.template[:, [1, 2, 0]] + k)


def with_detail(obj, basis, detail, value=1.0):
    """Give a registered object a 'Detail' key (as Register Scans does) at ``value``."""
    from bareesa_addon import convert

    convert.set_detail_key(obj, basis.template, detail, value=value)
    return obj


def local_at(obj, frame):
    """The object's evaluated (shape-key mixed) vertices at a frame, its local frame."""
    from bareesa_addon import convert

    bpy.context.scene.frame_set(int(frame))
    return convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())[0]


def test_interpolate_carries_the_ends_detail_keys_along_the_frames(scene, tiny, capfd):
    """Both ends' detail keys (times their values) are blended along the frames as path_between carries detail
    (latent.detail_along): 'Detail' = the start's, 'Detail Change' keyed 0 -> 1; the codes are the same as
    without detail, and the frame meshes carry it too."""
    from bareesa.latent import detail_along

    basis = tiny[0]
    d_a, d_b = some_detail(basis, 0), some_detail(basis, 1)
    with_detail(registered("A", A), basis, d_a)
    with_detail(registered("B", B), basis, d_b, value=0.5)  # a key at 0.5 gives half its detail
    scene.bareesa.make_collection = True
    capfd.readouterr()
    assert bpy.ops.bareesa.interpolate(object_a="A", object_b="B") == {"FINISHED"}
    assert "with the inputs' detail" in capfd.readouterr().out
    path_obj = bpy.data.objects["A_to_B"]
    blocks = path_obj.data.shape_keys.key_blocks
    assert [k.name for k in blocks] == ["Basis"] + NAMES + ["Detail", "Detail Change"]
    frames, codes = keyed(path_obj)  # the field keys only
    assert list(frames) == [1, 2, 3, 4, 5, 6]
    assert np.allclose(codes[0], A, atol=1e-6) and np.allclose(codes[-1], B, atol=1e-6)
    detail = detail_along(d_a, 0.5 * d_b, np.linspace(0, 1, 6))
    for k, f in enumerate(frames):
        np.testing.assert_allclose(local_at(path_obj, f), decode(basis, codes[k]) + detail[k], atol=1e-5)
    meshes = sorted(bpy.data.collections["A_to_B_frames"].objects, key=lambda o: o.name)
    np.testing.assert_allclose(mesh_verts(meshes[2]), decode(basis, codes[2]) + detail[2], atol=1e-5)
    # the same codes as a path without detail
    bpy.data.objects["B"].data.shape_keys.key_blocks["Detail"].value = 0.0
    scene.bareesa.make_collection = False
    assert bpy.ops.bareesa.interpolate(object_a="A", object_b="B") == {"FINISHED"}
    assert "without detail: only 'A' has some" in capfd.readouterr().out
    plain = bpy.data.objects["A_to_B.001"]
    assert [k.name for k in plain.data.shape_keys.key_blocks] == ["Basis"] + NAMES
    np.testing.assert_allclose(keyed(plain)[1], codes, atol=1e-6)


def test_extrapolate_two_objects_continues_their_detail_linearly(scene, tiny):
    from bareesa.latent import detail_along

    basis = tiny[0]
    d_a, d_b = some_detail(basis, 0), some_detail(basis, 1)
    with_detail(registered("A", 0.5 * A), basis, d_a)
    with_detail(registered("B", 0.5 * B), basis, d_b)
    scene.bareesa.extrapolate_steps, scene.bareesa.extrapolate_spacing = 2, 5
    assert bpy.ops.bareesa.extrapolate(source="OBJECTS", object_a="A", object_b="B") == {"FINISHED"}
    obj = bpy.data.objects["A_B_extrapolated"]
    frames, codes = keyed(obj)
    assert list(frames) == [1, 6, 11, 16]
    detail = detail_along(d_a, d_b, np.arange(4))  # the inputs at times 0 and 1, continued to 3
    for k, f in enumerate(frames):
        np.testing.assert_allclose(local_at(obj, f), decode(basis, codes[k]) + detail[k], atol=1e-5)
    change = obj.data.shape_keys.key_blocks["Detail Change"]
    assert (change.slider_min, change.slider_max) == (0, 1)


def test_extrapolate_keyframes_continues_the_animated_detail(scene, tiny):
    """On keyframes, an animated 'Detail Change' is keyed on the new frames along its line through the last two
    keyframes (the detail continued as extrapolate continues it); the static 'Detail' holds."""
    from bareesa_addon import convert

    basis = tiny[0]
    d, change = some_detail(basis, 0), some_detail(basis, 1)
    obj = with_detail(registered("anim", A), basis, d)
    convert.keyframe_codes(obj, NAMES, [1, 5], [0.5 * A, 0.5 * B])
    key = convert.set_detail_key(obj, basis.template, change, "Detail Change", 0.0)
    for frame, value in ((1, 0.0), (5, 0.4)):
        key.value = value
        key.keyframe_insert("value", frame=frame)
    scene.bareesa.extrapolate_steps = 2
    select(obj)
    assert bpy.ops.bareesa.extrapolate() == {"FINISHED"}
    frames, codes = keyed(obj)
    assert list(frames) == [1, 5, 9, 13]
    for k, f in enumerate(frames):
        np.testing.assert_allclose(local_at(obj, f), decode(basis, codes[k]) + d + 0.4 * k * change, atol=1e-5)
    assert obj.data.shape_keys.key_blocks["Detail Change"].slider_max >= 1.2


# ------------------------------------------------------------------------------ motion transfer

POSES = np.array([[0.0, 0.0], [0.3, -0.2], [0.6, -0.1], [0.4, 0.5]])
IDENTITY = np.array([0.9, -0.6])


def expected_motion():
    return np.hstack([POSES, np.tile(IDENTITY, (len(POSES), 1))])


def test_transfer_motion_from_shape_key_animation_keeps_pose_and_target_identity(scene):
    from bareesa_addon import convert

    src = registered("dancer", A)
    convert.keyframe_codes(src, NAMES, [1, 2, 3, 4], np.hstack([POSES, np.tile([0.2, 0.2], (4, 1))]))
    target = registered("target", np.r_[0.1, 0.1, IDENTITY])
    scene.bareesa.frame_start, scene.bareesa.frame_end = 1, 4
    assert bpy.ops.bareesa.transfer_motion(source="dancer", target="target") == {"FINISHED"}
    frames, codes = keyed(bpy.data.objects["target_motion"])  # a new object
    assert list(frames) == [1, 2, 3, 4]
    assert np.allclose(codes, expected_motion(), atol=1e-6)
    assert scene.frame_current == 1


def test_transfer_motion_gives_the_new_object_the_identitys_detail(scene, tiny):
    """The identity's detail (its Detail key times its value) is one 'Detail' key at 1 on the new object, on
    every frame; the motion's codes are as without it."""
    from bareesa_addon import convert

    basis = tiny[0]
    src = with_detail(registered("dancer", A), basis, some_detail(basis, 1))  # the motion's own: not carried
    convert.keyframe_codes(src, NAMES, [1, 2, 3, 4], np.hstack([POSES, np.tile([0.2, 0.2], (4, 1))]))
    d = some_detail(basis, 0)
    with_detail(registered("target", np.r_[0.1, 0.1, IDENTITY]), basis, d, value=0.7)
    scene.bareesa.frame_start, scene.bareesa.frame_end = 1, 4
    assert bpy.ops.bareesa.transfer_motion(source="dancer", target="target") == {"FINISHED"}
    obj = bpy.data.objects["target_motion"]
    assert [k.name for k in obj.data.shape_keys.key_blocks] == ["Basis"] + NAMES + ["Detail"]
    frames, codes = keyed(obj)
    assert np.allclose(codes, expected_motion(), atol=1e-6)
    for k, f in enumerate(frames):
        np.testing.assert_allclose(local_at(obj, f), decode(basis, codes[k]) + 0.7 * d, atol=1e-5)


def animated_mesh(name, basis, code_from, code_to):
    """A plain mesh (no basis keys) at F(code_from) moved to F(code_to) by its own shape key, keyed 0 at
    frame 1 and 1 at frame 4."""
    obj = add_mesh(name, decode(basis, code_from), basis.faces)
    obj.shape_key_add(name="Basis")
    key = obj.shape_key_add(name="move")
    key.data.foreach_set("co", decode(basis, code_to).ravel())
    for frame, value in ((1, 0.0), (4, 1.0)):
        key.value = value
        key.keyframe_insert("value", frame=frame)
    return obj


def test_transfer_motion_from_any_animated_mesh_evaluated_per_frame(scene, tiny):
    """A plain mesh (no basis keys) animated by its own shape key: evaluated by the depsgraph per frame."""
    basis = tiny[0]
    c0, c1 = np.r_[POSES[0], 0.2, 0.2], np.r_[POSES[3], 0.2, 0.2]
    animated_mesh("cache_like", basis, c0, c1)
    target = registered("target", np.r_[0.0, 0.0, IDENTITY])
    scene.bareesa.frame_start, scene.bareesa.frame_end = 1, 4
    assert bpy.ops.bareesa.transfer_motion(source="cache_like", target="target") == {"FINISHED"}
    frames, codes = keyed(bpy.data.objects["target_motion"])  # a new object
    # source frames are projected with bareesa.latent.PROJECTION_RIDGE: within its small shrinkage
    assert np.allclose(codes[0], np.r_[POSES[0], IDENTITY], atol=RIDGE_ATOL)
    assert np.allclose(codes[-1], np.r_[POSES[3], IDENTITY], atol=RIDGE_ATOL)
    assert np.allclose(codes[:, 2:], IDENTITY, atol=1e-6)


def test_transfer_motion_from_an_ordered_collection_of_frame_objects(scene, tiny):
    basis = tiny[0]
    coll = bpy.data.collections.new("frames")
    scene.collection.children.link(coll)
    order = [1, 2, 3, 10]  # natural name order; created shuffled
    for i in (10, 2, 1, 3):
        obj = add_mesh(f"frame_{i}", decode(basis, np.r_[POSES[order.index(i)], 0.0, 0.0]), basis.faces)
        scene.collection.objects.unlink(obj)
        coll.objects.link(obj)
    registered("target", np.r_[0.0, 0.0, IDENTITY])
    scene.bareesa.frame_start = 20
    assert bpy.ops.bareesa.transfer_motion(source_collection="frames", target="target") == {"FINISHED"}
    frames, codes = keyed(bpy.data.objects["target_motion"])  # a new object
    assert list(frames) == [20, 21, 22, 23]
    assert np.allclose(codes, expected_motion(), atol=RIDGE_ATOL)  # ridge-projected frames


def test_transfer_motion_refuses_unknown_identity_group(scene):
    from bareesa_addon import convert

    src = registered("dancer", A)
    convert.keyframe_codes(src, NAMES, [1, 6], [A, B])
    registered("target", B)
    scene.bareesa.identity_group = "body"
    before = snapshot()
    with pytest.raises(RuntimeError, match="no group 'body'"):
        bpy.ops.bareesa.transfer_motion(source="dancer", target="target")
    assert snapshot() == before


# ------------------------------------------------------------------------------ random bodies


def test_generate_random_bakes_seeded_bodies_in_a_grid_collection(scene):
    assert bpy.ops.bareesa.generate_random(count=4, seed=3) == {"FINISHED"}
    coll = bpy.data.collections["tiny_random_seed3"]
    objs = sorted(coll.objects, key=lambda o: o.name)
    assert len(objs) == 4
    codes = np.stack([key_values(o, NAMES) for o in objs])
    assert np.isfinite(codes).all() and np.ptp(codes, axis=0).min() > 0
    assert len({tuple(round(x, 6) for x in o.location) for o in objs}) == 4
    bpy.data.collections.remove(coll)
    for o in objs:
        bpy.data.objects.remove(o)
    assert bpy.ops.bareesa.generate_random(count=4, seed=3) == {"FINISHED"}
    again = np.stack([key_values(o, NAMES) for o in sorted(bpy.data.collections["tiny_random_seed3"].objects,
                                                           key=lambda o: o.name)])
    assert np.allclose(again, codes)


def test_generate_random_fitted_to_a_collection_of_registered_objects(scene):
    coll = bpy.data.collections.new("cast")
    scene.collection.children.link(coll)
    for i, code in enumerate((A, B, 0.5 * (A + B), -A)):
        obj = registered(f"person_{i}", code)
        scene.collection.objects.unlink(obj)
        coll.objects.link(obj)
    scene.bareesa.fit_collection = coll
    assert bpy.ops.bareesa.generate_random(count=3, seed=1) == {"FINISHED"}
    assert len(bpy.data.collections["tiny_random_seed1"].objects) == 3


def failing_shots(monkeypatch, fail):
    """Make bareesa.shooting.shoot raise ShootingFailed on the calls ``fail(call number, steps)`` says: -> call log."""
    from bareesa import shooting

    real, calls = shooting.shoot, []

    def shoot(*args, steps=10, **kwargs):
        calls.append(steps)
        if fail(len(calls), steps):
            raise shooting.ShootingFailed("a geodesic step did not converge (test)")
        return real(*args, steps=steps, **kwargs)

    monkeypatch.setattr(shooting, "shoot", shoot)
    return calls


def test_generate_random_retries_with_more_steps_then_replaces_a_draw_that_cannot_be_shot(scene, monkeypatch):
    from bareesa_addon import solver
    from bareesa.workflows import sample_bodies

    assert bpy.ops.bareesa.generate_random(count=3, seed=2) == {"FINISHED"}
    plain = np.stack([key_values(o, NAMES) for o in sorted(bpy.data.collections["tiny_random_seed2"].objects,
                                                           key=lambda o: o.name)])
    steps = scene.bareesa.shoot_steps
    # the first draw fails with the panel's steps and with twice as many; the second only with the panel's
    calls = failing_shots(monkeypatch, lambda k, s: k in (1, 2, 3))
    basis, _ = solver.load_basis(scene.bareesa.basis)
    dist = {k: v for k, v in basis.extras.items() if k.startswith("gmm_")}
    codes, replaced = sample_bodies(*basis.tensors(), dist, basis.groups, basis.weights, 3, 2, steps)
    assert replaced == 1 and calls[:4] == [steps, 2 * steps, steps, 2 * steps]
    assert codes.shape == plain.shape and np.isfinite(codes).all()
    assert np.allclose(codes[1], plain[2])  # the third draw is kept as drawn; the first is replaced
    assert not np.isclose(codes, plain[0]).all(axis=1).any()


def test_generate_random_reports_and_changes_nothing_when_no_draw_can_be_shot(scene, monkeypatch):
    failing_shots(monkeypatch, lambda k, s: True)
    before = snapshot()
    with pytest.raises(RuntimeError, match="could be shot"):
        bpy.ops.bareesa.generate_random(count=2, seed=0)
    assert snapshot() == before


def test_generate_random_without_a_distribution_reports_and_changes_nothing(scene, tiny, tmp_path):
    from bareesa.basis_io import save_basis

    basis = tiny[0]
    bare = type(basis)(template=basis.template, faces=basis.faces, fields=basis.fields, groups=basis.groups,
                       weights=basis.weights, schedule=basis.schedule, name="bare")
    save_basis(tmp_path / "bare.npz", bare)
    scene.bareesa.basis = str(tmp_path / "bare.npz")
    before = snapshot()
    with pytest.raises(RuntimeError, match="stores no distribution"):
        bpy.ops.bareesa.generate_random()
    assert snapshot() == before


# ------------------------------------------------------------------------------ build basis


def test_build_basis_from_an_animated_mesh_saves_and_loads_it(scene, tiny, tmp_path):
    basis = tiny[0]
    src = add_mesh("performer", basis.template, basis.faces)
    src.shape_key_add(name="Basis")
    for name, field in (("bend", basis.fields[0]), ("bulge", basis.fields[2])):
        key = src.shape_key_add(name=name)
        key.data.foreach_set("co", (basis.template + field).ravel())
    rng = np.random.default_rng(0)
    for frame in range(1, 7):
        for name in ("bend", "bulge"):
            key = src.data.shape_keys.key_blocks[name]
            key.value = float(rng.uniform(0, 1))
            key.keyframe_insert("value", frame=frame)
    select(src)
    s = scene.bareesa
    s.build_name, s.build_group, s.build_components = "learned", "pose", 5
    assert bpy.ops.bareesa.build_basis() == {"FINISHED"}
    path = tmp_path / "user_bases" / "learned.npz"
    assert path.exists() and s.basis == str(path)
    template = bpy.context.active_object
    names = [k.name for k in template.data.shape_keys.key_blocks]
    assert names[:3] == ["Basis", "pose_000", "pose_001"] and len(names) <= 6
    from bareesa.basis_io import load_basis

    learned = load_basis(path)
    protos = learned.extras["pose_prototypes"]  # a "pose" group: registration's starting poses are stored
    assert protos.shape[1] == learned.n_fields and 1 <= len(protos) <= 6 and np.isfinite(protos).all()
    # ... with the constants every registration would compute (registration.prepare_basis)
    assert np.array_equal(learned.extras["pose_prototype_moments_codes"], protos)
    assert np.array_equal(learned.extras["template_metric_weights"], learned.weights.as_tuple())
    ratios = learned.provenance["groups"]["pose"]["variance_ratios"]
    assert sum(ratios[:2]) > 0.9999  # the frames mix two shape keys: two motions (Blender's float32 noise aside)
    assert bpy.ops.bareesa.load_template(basis="learned") == {"FINISHED"}
    assert scene.frame_current == 1


def test_build_basis_refuses_a_collection_of_mixed_topologies(scene, tiny):
    basis, _, surface = tiny
    coll = bpy.data.collections.new("mixed")
    scene.collection.children.link(coll)
    for name, (v, f) in (("m1", (basis.template, basis.faces)), ("m2", code_surface(surface, A, seed=5))):
        obj = add_mesh(name, v, f)
        scene.collection.objects.unlink(obj)
        coll.objects.link(obj)
    scene.bareesa.build_collection = coll
    before = snapshot()
    with pytest.raises(RuntimeError, match="one topology"):
        bpy.ops.bareesa.build_basis()
    assert snapshot() == before


# ------------------------------------------------------------------------------ distance


def test_distance_between_two_objects_shown_in_settings(scene, tiny):
    from bareesa.geodesics import geodesic

    basis = tiny[0]
    registered("A", A), registered("B", B)
    assert bpy.ops.bareesa.distance(object_a="A", object_b="B") == {"FINISHED"}
    expected = geodesic(*basis.tensors(), A, B, basis.weights, steps=scene.bareesa.steps).distance
    assert scene.bareesa.distance == pytest.approx(expected, rel=1e-4)


def test_distance_matrix_of_a_collection_written_to_csv(scene, tmp_path):
    coll = bpy.data.collections.new("people")
    scene.collection.children.link(coll)
    for name, code in (("p1", A), ("p2", B), ("p3", 0.5 * A)):
        obj = registered(name, code)
        scene.collection.objects.unlink(obj)
        coll.objects.link(obj)
    out = tmp_path / "d.csv"
    assert bpy.ops.bareesa.distance(collection="people", filepath=str(out)) == {"FINISHED"}
    rows = list(csv.reader(out.open()))
    assert rows[0] == ["", "p1", "p2", "p3"]
    d = np.array([[float(x) for x in r[1:]] for r in rows[1:]])
    assert d.shape == (3, 3) and np.allclose(d, d.T) and np.allclose(np.diag(d), 0)
    assert (d[~np.eye(3, dtype=bool)] > 0).all()


def test_transfer_motion_from_an_alembic_mesh_cache(scene, tiny, tmp_path):
    """A mesh-sequence cache (Alembic, MeshSequenceCache modifier) is evaluated per frame like any animation."""
    basis = tiny[0]
    c0, c1 = np.r_[POSES[1], 0.3, 0.3], np.r_[POSES[2], 0.3, 0.3]
    src = animated_mesh("to_cache", basis, c0, c1)
    select(src)
    scene.frame_start, scene.frame_end = 1, 4
    abc = tmp_path / "motion.abc"
    assert bpy.ops.wm.alembic_export(filepath=str(abc), start=1, end=4, selected=True) == {"FINISHED"}
    bpy.data.objects.remove(src)
    assert bpy.ops.wm.alembic_import(filepath=str(abc)) == {"FINISHED"}
    cache = bpy.context.selected_objects[0]
    assert cache.modifiers[0].type == "MESH_SEQUENCE_CACHE" and cache.data.shape_keys is None
    registered("target", np.r_[0.0, 0.0, IDENTITY])
    scene.bareesa.frame_start, scene.bareesa.frame_end = 1, 4
    assert bpy.ops.bareesa.transfer_motion(source=cache.name, target="target") == {"FINISHED"}
    frames, codes = keyed(bpy.data.objects["target_motion"])  # a new object
    assert list(frames) == [1, 2, 3, 4]
    assert np.allclose(codes[0], np.r_[POSES[1], IDENTITY], atol=RIDGE_ATOL)  # ridge-projected frames
    assert np.allclose(codes[-1], np.r_[POSES[2], IDENTITY], atol=RIDGE_ATOL)
