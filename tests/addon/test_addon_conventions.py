"""The add-on behaves like Blender's own tools: even in-betweens, non-destructive transfer, sliders in
training units, no silent reductions, Blender's panel layout, polls with reasons, one undo step."""

import numpy as np
import pytest

from tests.addon.support import add_mesh, bpy, code_surface, select, snapshot

NAMES = ["pose_000", "pose_001", "shape_000", "shape_001"]
A = np.array([0.2, -0.3, 0.4, 0.1])
B = np.array([-0.5, 0.6, 0.1, 0.7])


def registered(name, code, location=(0.0, 0.0, 0.0)):
    from bareesa_addon import convert, solver

    bpy.ops.bareesa.load_template()
    obj = bpy.context.active_object
    obj.name = name
    basis, _ = solver.load_basis(bpy.context.scene.bareesa.basis)
    convert.fit_range(obj, NAMES, basis.template, basis.fields, code)
    convert.set_code(obj, NAMES, code)
    obj.location = location
    bpy.context.view_layer.update()
    return obj


def world_verts(obj):
    """The object as Blender shows it now (depsgraph: shape-key mix and transform), world frame."""
    from bareesa_addon import convert

    depsgraph = bpy.context.evaluated_depsgraph_get()
    verts, _ = convert.evaluated_mesh(obj, depsgraph)
    m = np.array(obj.evaluated_get(depsgraph).matrix_world)
    return verts @ m[:3, :3].T + m[:3, 3]


def warnings(capfd):
    """Warning reports Blender printed since the last call (headless Blender prints operator reports)."""
    return [line for line in capfd.readouterr().out.splitlines() if line.startswith("Warning:")]


# ------------------------------------------------------------------------------ 1. even in-betweens


def test_interpolation_steps_evenly_on_every_evaluated_frame_and_keys_are_linear(scene):
    from bareesa_addon import convert

    s = scene.bareesa
    s.use_frame_range = False  # the scene's range
    scene.frame_start, scene.frame_end = 1, 24
    a = registered("A", A)
    b = registered("B", B, location=(2.0, 0.5, 0.0))
    b.rotation_euler = (0.0, 0.0, 0.6)
    b.scale = (1.2, 1.2, 1.2)
    select(a, b)
    assert bpy.ops.bareesa.interpolate(object_a="A", object_b="B") == {"FINISHED"}
    obj = bpy.data.objects["A_to_B"]
    frames = []
    for f in range(1, 25):
        scene.frame_set(f)
        frames.append(world_verts(obj))
    frames = np.array(frames)
    step = np.sqrt(((frames[1:] - frames[:-1]) ** 2).sum(-1).mean(-1))  # RMS vertex motion per frame
    interior = step[1:-1]
    assert interior.max() / interior.min() <= 1.5
    assert np.allclose(frames[0], world_verts(a), atol=1e-5) and np.allclose(frames[-1], world_verts(b), atol=1e-4)
    curves = convert.all_fcurves(obj) + convert.all_fcurves(obj.data.shape_keys)
    assert len(curves) == 3 + 4 + 3 + 4  # location, quaternion, scale; one per field key
    assert {p.interpolation for fc in curves for p in fc.keyframe_points} == {"LINEAR"}


# ------------------------------------------------------------------------------ 2. transfer is non-destructive


def test_transfer_motion_writes_a_new_object_and_leaves_the_target_keys_unchanged(scene, capfd):
    from bareesa_addon import convert

    src = registered("dancer", A)
    poses = np.array([[0.0, 0.0], [0.3, -0.2], [0.6, -0.1], [0.4, 0.5]])
    convert.keyframe_codes(src, NAMES, [1, 2, 3, 4], np.hstack([poses, np.tile([0.2, 0.2], (4, 1))]))
    target = registered("target", np.r_[0.1, 0.1, 0.3, -0.2])
    convert.keyframe_codes(target, NAMES, [1, 9], [np.r_[0.1, 0.1, 0.3, -0.2], np.r_[0.2, 0.0, 0.3, -0.2]])
    target.location = (1.0, 2.0, 0.0)
    bpy.context.view_layer.update()
    scene.bareesa.frame_start, scene.bareesa.frame_end = 1, 4
    select(target)
    before = snapshot()
    warnings(capfd)
    assert bpy.ops.bareesa.transfer_motion(source="dancer", target="target") == {"FINISHED"}
    after = snapshot()
    assert after["target"] == before["target"] and after["dancer"] == before["dancer"]
    assert list(convert.keyed_frames(target, NAMES)) == [1, 9]  # the target's own animation
    result = bpy.data.objects["target_motion"]
    assert list(convert.keyed_frames(result, NAMES)) == [1, 2, 3, 4]
    assert np.allclose(convert.code_at_frame(result, NAMES, 3), [0.6, -0.1, 0.3, -0.2], atol=1e-6)
    assert np.allclose(result.matrix_world.translation, (1.0, 2.0, 0.0))
    assert result["bareesa_training_stds"] < 4.0 and not warnings(capfd)


def test_transfer_onto_an_identity_outside_the_training_range_warns(scene, capfd):
    from bareesa_addon import convert
    from bareesa_addon.operators.common import training_stats

    src = registered("dancer", A)
    convert.keyframe_codes(src, NAMES, [1, 4], [A, B])
    far = np.r_[0.0, 0.0, 9.0, -9.0]  # the tiny basis' training codes have std ~0.5
    registered("target", far)
    scene.bareesa.frame_start, scene.bareesa.frame_end = 1, 4
    warnings(capfd)
    assert bpy.ops.bareesa.transfer_motion(source="dancer", target="target") == {"FINISHED"}
    result = bpy.data.objects["target_motion"]
    from bareesa_addon import solver

    tiny_basis, _ = solver.load_basis(scene.bareesa.basis)
    mean, std = training_stats(tiny_basis)
    assert result["bareesa_training_stds"] == pytest.approx(np.max(np.abs(far[2:] - mean[2:]) / std[2:]), rel=1e-3)
    reported = warnings(capfd)
    assert len(reported) == 1 and "training" in reported[0] and "target_motion" in reported[0]
    assert np.allclose(convert.code_at_frame(result, NAMES, 1)[2:], far[2:], atol=1e-5)  # still written exactly


# ------------------------------------------------------------------------------ 3. sliders in training units


def test_key_scale_and_slider_range_follow_the_training_range(scene, tiny):
    from bareesa_addon import convert

    basis = tiny[0]
    bpy.ops.bareesa.load_template()
    obj = bpy.context.active_object
    blocks = obj.data.shape_keys.key_blocks
    scales = np.array(obj["bareesa_key_scale"])
    for group, (a, b) in basis.groups.items():  # one Gaussian per group in the tiny basis
        mean = basis.extras[f"gmm_{group}_means"][0]
        std = np.sqrt(np.diag(basis.extras[f"gmm_{group}_covariances"][0]))
        assert np.allclose(scales[a:b], std, rtol=1e-6)  # value 1 = one training std
        for j in range(a, b):
            key = blocks[NAMES[j]]
            assert key.slider_min == pytest.approx(max(-10, mean[j - a] / std[j - a] - 4), abs=1e-5)
            assert key.slider_max == pytest.approx(min(10, mean[j - a] / std[j - a] + 4), abs=1e-5)
    blocks["shape_000"].value = 1.0  # one std of the field moves the vertices by std * |h|
    verts, _ = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    assert np.allclose(verts, basis.template + scales[2] * basis.fields[2], atol=1e-5)
    code = np.array([0.37, -0.81, 1.23, 0.05])
    convert.set_code(obj, NAMES, code)
    assert np.allclose(convert.get_code(obj, NAMES), code, rtol=1e-6, atol=1e-7)  # read back exactly


# ------------------------------------------------------------------------------ 4. no silent reductions


def test_build_basis_warns_when_it_builds_fewer_components_than_asked(scene, tiny, capfd):
    basis = tiny[0]
    src = add_mesh("performer", basis.template, basis.faces)
    src.shape_key_add(name="Basis")
    key = src.shape_key_add(name="bend")
    key.data.foreach_set("co", (basis.template + basis.fields[0]).ravel())
    for frame, value in ((1, 0.0), (3, 0.5), (6, 1.0)):
        key.value = value
        key.keyframe_insert("value", frame=frame)
    select(src)
    s = scene.bareesa
    s.build_name, s.build_group, s.build_components = "thin", "pose", 10
    warnings(capfd)
    assert bpy.ops.bareesa.build_basis() == {"FINISHED"}
    from bareesa.basis_io import load_basis

    built = load_basis(s.basis).provenance["groups"]["pose"]["components"]
    reported = warnings(capfd)
    assert built < 10 and len(reported) == 1
    assert "asked for 10" in reported[0] and f"built {built}" in reported[0]


def test_distance_csv_of_an_unsaved_file_asks_for_a_saved_file(scene, tmp_path):
    coll = bpy.data.collections.new("people")
    scene.collection.children.link(coll)
    for name, code in (("p1", A), ("p2", B)):
        obj = registered(name, code)
        scene.collection.objects.unlink(obj)
        coll.objects.link(obj)
    s = scene.bareesa
    s.distance_collection = coll
    assert s.distance_csv.startswith("//") and not bpy.data.filepath
    before = snapshot()
    with pytest.raises(RuntimeError, match="not saved: save the file first or choose an absolute path"):
        bpy.ops.bareesa.distance()
    assert snapshot() == before
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "people.blend"))
    assert bpy.ops.bareesa.distance() == {"FINISHED"}
    assert (tmp_path / "bareesa_distances.csv").exists()  # next to the saved file


def test_register_registers_the_mesh_and_reports_the_skipped_camera(scene, tiny, capfd):
    surface = tiny[2]
    scan = add_mesh("scan", *code_surface(surface, np.array([0.3, -0.2, 0.4, 0.1])))
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    select(scan, camera)
    warnings(capfd)
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    assert "scan_registered" in bpy.data.objects and "Camera_registered" not in bpy.data.objects
    reported = warnings(capfd)
    assert len(reported) == 1 and "Camera" in reported[0] and "not a mesh" in reported[0]


# ------------------------------------------------------------------------------ 5. panels, polls, undo


class RecordingLayout:
    """Records the rows of a panel and the properties drawn into each."""

    def __init__(self, log, kind="layout"):
        self.log, self.kind, self.props, self.labels = log, kind, [], []
        self.use_property_split = self.use_property_decorate = None
        self.enabled = True
        log.append(self)

    def _child(self, kind):
        return lambda *args, **kwargs: RecordingLayout(self.log, kind)

    def __getattr__(self, name):
        if name in ("row", "column", "box", "split", "grid_flow", "column_flow"):
            return self._child(name)
        return lambda *args, **kwargs: self

    def prop(self, data, name, **kwargs):
        self.props.append(data.bl_rna.properties[name])

    def label(self, text="", **kwargs):
        self.labels.append(text)


PANELS = ("BAREESA_PT_main", "BAREESA_PT_basis", "BAREESA_PT_register", "BAREESA_PT_paths", "BAREESA_PT_motion",
          "BAREESA_PT_random", "BAREESA_PT_build", "BAREESA_PT_distance")


def draw_all(context):
    log = []
    for name in PANELS:
        panel = bpy.types.Panel.bl_rna_get_subclass_py(name)
        top = RecordingLayout(log)
        panel.draw(type("P", (), {"layout": top})(), context)
        yield name, top, log


def test_panels_use_property_split_and_put_one_integer_field_per_row(scene):
    registered("A", A)
    for name, top, log in draw_all(bpy.context):
        assert top.use_property_split is True and top.use_property_decorate is False, name
    rows = [layout for layout in log if layout.kind == "row"]
    for row in rows:
        assert sum(p.type == "INT" for p in row.props) <= 1


def test_fit_quality_is_shown_in_the_scenes_units(scene):
    obj = registered("A", A)
    obj["bareesa_chamfer"], obj["bareesa_varifold"] = 0.0023, 0.05
    units = scene.unit_settings
    units.system, units.length_unit = "METRIC", "MILLIMETERS"
    labels = [t for _, top, log in draw_all(bpy.context) for layout in log for t in layout.labels]
    shown = bpy.utils.units.to_string("METRIC", "LENGTH", 0.0023, precision=3)
    assert "mm" in shown and any(shown in t and "Chamfer" in t for t in labels)
    units.system = "IMPERIAL"
    labels = [t for _, top, log in draw_all(bpy.context) for layout in log for t in layout.labels]
    assert any("Chamfer" in t and bpy.utils.units.to_string("IMPERIAL", "LENGTH", 0.0023, precision=3) in t
               for t in labels)


def test_frame_range_and_schedule_defaults_follow_blender(scene):
    props = type(scene.bareesa).bl_rna.properties
    assert props["use_frame_range"].default is False and props["schedule"].default == "FAST"
    s = scene.bareesa
    s.use_frame_range = False
    scene.frame_start, scene.frame_end = 3, 7
    a, b = registered("A", A), registered("B", B)
    select(a, b)
    assert bpy.ops.bareesa.interpolate(object_a="A", object_b="B") == {"FINISHED"}
    from bareesa_addon import convert

    assert list(convert.keyed_frames(bpy.data.objects["A_to_B"], NAMES)) == [3, 4, 5, 6, 7]


def test_keep_body_planted_and_direction_are_panel_settings(scene, monkeypatch):
    from bareesa import geodesics

    seen, real = [], geodesics.keyframe_path

    def spy(*args, anchor=True, **kwargs):
        seen.append(anchor)
        return real(*args, anchor=anchor, **kwargs)

    monkeypatch.setattr(geodesics, "keyframe_path", spy)
    a, b = registered("A", A), registered("B", B)
    s = scene.bareesa
    s.anchor = False
    select(a, b)
    assert bpy.ops.bareesa.interpolate() == {"FINISHED"}
    select(a, b)
    assert bpy.ops.bareesa.interpolate(anchor=True) == {"FINISHED"}  # the operator's own, when set
    assert seen == [False, True]
    s.extrapolate_source = "KEYFRAMES"  # two selected objects would otherwise give the direction
    select(a, b, active=b)
    with pytest.raises(RuntimeError, match="keyframes"):
        bpy.ops.bareesa.extrapolate()


def test_every_data_operator_is_undoable_and_its_poll_explains_an_empty_selection(scene):
    from bareesa_addon import operators

    for cls in operators.CLASSES:
        assert {"REGISTER", "UNDO"} <= set(cls.bl_options), cls.bl_idname
        own = [k for k in cls.__mro__ if k.__module__.startswith("bareesa_addon")]
        assert any("poll" in vars(k) for k in own), cls.bl_idname
    select()
    s = scene.bareesa
    s.object_a = s.object_b = s.motion_target = None
    needs = {"register_scan": "select one or more", "interpolate": "choose two objects",
             "extrapolate": "choose two registered objects", "transfer_motion": "choose the identity",
             "build_basis": "choose an animated mesh", "distance": "choose a collection"}
    for op, reason in needs.items():
        assert getattr(bpy.ops.bareesa, op).poll() is False
        with pytest.raises(RuntimeError, match=reason):
            getattr(bpy.ops.bareesa, op)()
    s.basis = ""
    assert bpy.ops.bareesa.load_template.poll() is False


def test_a_background_result_lands_as_one_undo_step(monkeypatch):
    from types import SimpleNamespace

    from bareesa_addon import jobs
    from tests.addon.support import drive, fake_context, make_operator

    pushed = []
    monkeypatch.setattr(jobs, "push_undo", pushed.append)
    monkeypatch.setattr(jobs, "bpy", SimpleNamespace(app=SimpleNamespace(background=False)))
    applied = []
    op, context = make_operator(lambda callback, cancel: 7, applied), fake_context()
    assert op.invoke(context, None) == {"RUNNING_MODAL"}
    assert drive(op, context) == {"FINISHED"}
    assert len(applied) == 1 and pushed == ["BaRe-ESA: test solve"]

    def fails(callback, cancel):
        raise jobs.ConversionError("bad input")

    op = make_operator(fails, applied)
    assert op.invoke(context, None) == {"RUNNING_MODAL"}
    assert drive(op, context) == {"CANCELLED"}
    assert pushed == ["BaRe-ESA: test solve"]  # nothing written, no undo step
