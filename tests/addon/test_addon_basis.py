"""bareesa.load_template, conversions, save/reload, and the bad-input reports that change nothing."""

import numpy as np
import pytest

from tests.addon.support import bpy, mesh_verts, snapshot


NAMES = ["pose_000", "pose_001", "shape_000", "shape_001"]


def test_load_template_adds_basis_and_one_shape_key_per_field(scene, tiny):
    basis, path, _ = tiny
    assert bpy.ops.bareesa.load_template() == {"FINISHED"}
    obj = bpy.context.active_object
    blocks = obj.data.shape_keys.key_blocks
    assert [k.name for k in blocks] == ["Basis"] + NAMES
    assert all(-10 <= k.slider_min < k.slider_max <= 10 for k in list(blocks)[1:])  # the training range
    assert np.allclose(mesh_verts(obj), basis.template)
    co = np.empty(len(obj.data.vertices) * 3)
    blocks["shape_001"].data.foreach_get("co", co)
    scale = obj["bareesa_key_scale"][3]  # one training std of the field (tests/addon/test_addon_conventions.py)
    assert np.allclose(co.reshape(-1, 3), basis.template + scale * basis.fields[3])
    assert obj["bareesa_basis"] == str(path.resolve())
    assert len(obj.data.polygons) == len(basis.faces)


def test_shape_key_mix_is_the_decoder(scene, tiny):
    from bareesa_addon import convert

    basis, _, _ = tiny
    bpy.ops.bareesa.load_template()
    obj = bpy.context.active_object
    code = np.array([0.7, -1.2, 0.3, 2.5])
    convert.set_code(obj, NAMES, code)
    verts, tris = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    assert np.allclose(verts, basis.template + np.tensordot(code, basis.fields, 1), atol=1e-5)
    assert np.array_equal(tris, basis.faces)
    assert np.allclose(convert.get_code(obj, NAMES), code, atol=1e-6)


def test_load_template_accepts_a_name_from_the_user_bases_directory(scene, tiny, tmp_path):
    import shutil

    user = tmp_path / "user_bases"
    user.mkdir()
    shutil.copy(tiny[1], user / "mine.npz")
    assert bpy.ops.bareesa.load_template(basis="mine") == {"FINISHED"}
    assert bpy.context.active_object["bareesa_basis"] == "mine"


def test_missing_basis_file_reports_and_changes_nothing(scene, tmp_path):
    before = snapshot()
    with pytest.raises(RuntimeError, match="does not exist"):
        bpy.ops.bareesa.load_template(basis=str(tmp_path / "nope.npz"))
    with pytest.raises(RuntimeError, match="no bundled basis"):
        bpy.ops.bareesa.load_template(basis="no_such_basis_name")
    assert snapshot() == before


def test_template_with_code_survives_save_and_reload(scene, tiny, tmp_path):
    from bareesa_addon import convert

    bpy.ops.bareesa.load_template()
    obj = bpy.context.active_object
    convert.set_code(obj, NAMES, [0.5, 0.25, -0.75, 1.5])
    convert.keyframe_codes(obj, NAMES, [1, 5], [[0, 0, 0, 0], [0.5, 0.25, -0.75, 1.5]])
    scene.bareesa.steps = 7
    name = obj.name
    blend = tmp_path / "saved.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert name not in bpy.data.objects
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects[name]
    assert obj["bareesa_basis"] == str(tiny[1].resolve())
    assert bpy.context.scene.bareesa.steps == 7
    assert np.allclose(convert.code_at_frame(obj, NAMES, 5), [0.5, 0.25, -0.75, 1.5])
    assert np.allclose(convert.code_at_frame(obj, NAMES, 3), [0.25, 0.125, -0.375, 0.75])
    assert list(convert.keyed_frames(obj, NAMES)) == [1.0, 5.0]


def test_check_code_refuses_nan_and_diverged_codes():
    from bareesa_addon import convert

    with pytest.raises(convert.ConversionError, match="NaN"):
        convert.check_code([0.0, np.nan])
    with pytest.raises(convert.ConversionError, match="diverged"):
        convert.check_code([0.0, 1e9])


def test_codes_beyond_blender_slider_range_use_a_key_scale_and_still_decode(scene, tiny):
    from bareesa_addon import convert

    basis = tiny[0]
    bpy.ops.bareesa.load_template()
    obj = bpy.context.active_object
    scales = np.array(obj["bareesa_key_scale"])
    convert.keyframe_codes(obj, NAMES, [1, 3], [[1.0, 0, 0, 0], [2.0, 0, 0, 0]])
    big = np.array([25.0, -3.0, 0.5, 12.0])
    with pytest.raises(convert.ConversionError, match="does not fit"):
        convert.set_code(obj, NAMES, big)
    convert.fit_range(obj, NAMES, basis.template, basis.fields, big)
    grown = np.array(obj["bareesa_key_scale"])
    assert grown[0] > scales[0] and grown[3] > scales[3]  # keys 0 and 3 pass +-10 at one std per unit
    assert np.all(np.abs(big / grown) <= 10)
    convert.set_code(obj, NAMES, big)
    assert np.allclose(convert.get_code(obj, NAMES), big, atol=1e-5)
    assert np.allclose(convert.code_at_frame(obj, NAMES, 2), [1.5, 0, 0, 0], atol=1e-6)  # old keys kept
    bpy.context.scene.frame_set(5)  # past the keys: the (rescaled) animation holds its last key
    verts, _ = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    expected = np.array([2.0, 0.0, 0.0, 0.0])
    assert np.allclose(verts, basis.template + np.tensordot(expected, basis.fields, 1), atol=1e-4)


def test_quads_are_triangulated_by_mesh_conversion(scene):
    from bareesa_addon import convert
    from tests.addon.support import add_mesh

    verts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    obj = add_mesh("quad", verts, None, quads=[(0, 1, 2, 3)])
    v, t = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    assert v.shape == (4, 3) and t.shape == (2, 3)


def test_panel_sections_are_registered_in_the_sidebar(scene):
    for name in ("BAREESA_PT_basis", "BAREESA_PT_register", "BAREESA_PT_paths", "BAREESA_PT_motion",
                 "BAREESA_PT_random", "BAREESA_PT_build", "BAREESA_PT_distance"):
        panel = bpy.types.Panel.bl_rna_get_subclass_py(name)
        assert panel is not None and panel.bl_parent_id == "BAREESA_PT_main"
    for op in ("load_template", "register_scan", "interpolate", "extrapolate", "transfer_motion",
               "generate_random", "build_basis", "distance", "install_dependencies"):
        assert hasattr(bpy.ops.bareesa, op)


class FakeLayout:
    """Records what a panel draws; checks that every drawn property exists."""

    def __init__(self, drawn):
        self.drawn = drawn
        self.enabled = True

    def __getattr__(self, name):  # column, row, box, grid_flow, separator...
        return lambda *args, **kwargs: self

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"no property {name!r} on {data}"
        self.drawn.append(name)
        return self

    def prop_search(self, data, name, search_data, search_name, **kwargs):
        assert search_name in search_data.bl_rna.properties, f"no collection {search_name!r} on {search_data}"
        return self.prop(data, name)

    def operator(self, idname, **kwargs):
        module, op = idname.split(".")
        assert hasattr(getattr(bpy.ops, module), op), idname
        self.drawn.append(idname)
        return self


def test_every_panel_section_draws_existing_properties_and_operators(scene, tiny):
    bpy.ops.bareesa.load_template()
    drawn = []
    for name in ("BAREESA_PT_main", "BAREESA_PT_basis", "BAREESA_PT_register", "BAREESA_PT_paths",
                 "BAREESA_PT_motion", "BAREESA_PT_random", "BAREESA_PT_build", "BAREESA_PT_distance"):
        panel = bpy.types.Panel.bl_rna_get_subclass_py(name)
        panel.draw(type("P", (), {"layout": FakeLayout(drawn)})(), bpy.context)
    for op in ("bareesa.load_template", "bareesa.register_scan", "bareesa.interpolate", "bareesa.extrapolate",
               "bareesa.transfer_motion", "bareesa.generate_random", "bareesa.build_basis", "bareesa.distance",
               "bareesa.add_landmarks"):
        assert op in drawn
    assert {"basis_choice", "basis_file", "mask_group", "schedule", "steps", "frame_start", "frame_end", "seed", "metric"} <= set(drawn)


def test_template_uvs_of_a_basis_become_the_uv_map_of_its_objects(scene, tiny, tmp_path):
    from bareesa.basis_io import load_basis, save_basis

    basis, _, _ = tiny
    rng = np.random.default_rng(0)
    basis = load_basis(tiny[1])
    basis.extras["template_uv"] = rng.uniform(size=(len(basis.faces), 3, 2)).astype(np.float32)
    path = tmp_path / "uv_basis.npz"
    save_basis(path, basis)
    bpy.context.scene.bareesa.basis = str(path)
    assert bpy.ops.bareesa.load_template() == {"FINISHED"}
    mesh = bpy.context.active_object.data
    assert [uv.name for uv in mesh.uv_layers] == ["UVMap"]
    got = np.empty(len(mesh.loops) * 2, dtype=np.float32)
    mesh.uv_layers["UVMap"].data.foreach_get("uv", got)
    np.testing.assert_allclose(got.reshape(-1, 3, 2), basis.extras["template_uv"], atol=1e-6)
    loops = np.array([v for p in mesh.polygons for v in p.vertices]).reshape(-1, 3)
    np.testing.assert_array_equal(loops, basis.faces)  # corner k of face f is the loop the UV was written to


def test_named_parts_of_a_basis_become_vertex_groups_of_registered_objects(scene, tiny, tmp_path):
    from bareesa.basis_io import load_basis, save_basis

    from tests.addon.support import add_mesh, code_surface, select

    basis = load_basis(tiny[1])
    n = len(basis.template)
    weights = np.zeros((2, n), dtype=np.float32)
    north = basis.template[:, 2] > 0
    weights[0, north], weights[1, ~north] = 1.0, 1.0
    weights[:, 0] = 0.5  # a vertex shared by both
    basis.extras.update(part_names=np.array(["top", "bottom"]), part_weights=weights)
    save_basis(tmp_path / "parts.npz", basis)
    bpy.context.scene.bareesa.basis = str(tmp_path / "parts.npz")
    scan = add_mesh("scan", *code_surface(tiny[2], [0.2, 0.1, 0.0, 0.1]))
    select(scan)
    bpy.context.scene.bareesa.prealign = False
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    obj = bpy.data.objects["scan_registered"]
    assert [g.name for g in obj.vertex_groups] == ["top", "bottom"]
    for k, group in enumerate(obj.vertex_groups):
        got = np.zeros(n)
        for v in obj.data.vertices:
            for g in v.groups:
                if g.group == group.index:
                    got[v.index] = g.weight
        np.testing.assert_allclose(got, weights[k], atol=1e-6)


def test_the_fast_schedule_shortens_every_level_of_the_basis_and_keeps_the_rest():
    from bareesa.basis_io import load_basis
    from bareesa_addon import solver

    basis = load_basis("human")
    fast = solver.schedule(basis, "FAST")
    assert len(fast) == len(basis.schedule) and any(lv.plateau for lv in basis.schedule)
    assert any(lv.binned for lv in basis.schedule)
    for short, level in zip(fast, basis.schedule):
        assert short.steps == min(level.steps, solver.FAST_STEPS) and short.max_iter == min(level.max_iter,
                                                                                               solver.FAST_ITER)
        assert (short.sigma, short.weight, short.plateau, short.binned) == (level.sigma, level.weight, level.plateau,
                                                                            level.binned)
    assert solver.schedule(basis, "PAPER") == basis.schedule
