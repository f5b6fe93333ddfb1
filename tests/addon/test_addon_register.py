"""bareesa.register_scan through bpy.ops (synchronous in background mode), its placement and its refusals."""

import math

import numpy as np
import pytest

from tests.addon.support import add_mesh, bpy, code_surface, key_values, select, snapshot

from mathutils import Matrix  # noqa: E402 (after bpy)

NAMES = ["pose_000", "pose_001", "shape_000", "shape_001"]
ALPHA = np.array([0.6, -0.4, 0.5, 0.3])


def world_verts(obj):
    from bareesa_addon import convert

    v, _ = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    m = np.array(obj.matrix_world)
    return v @ m[:3, :3].T + m[:3, 3]


def key_co(obj, name):
    block = obj.data.shape_keys.key_blocks[name]
    co = np.empty(len(block.data) * 3)
    block.data.foreach_get("co", co)
    return co.reshape(-1, 3)


def detail_offset(obj):
    """The 'Detail' key's co - 'Basis' co: -> (N, 3)."""
    return key_co(obj, "Detail") - key_co(obj, "Basis")


def spy_registrations(monkeypatch):
    """Record every RegistrationResult ``registration.register`` returns: -> the list they go into."""
    import bareesa.registration as registration

    seen, real = [], registration.register

    def spy(*args, **kwargs):
        seen.append(real(*args, **kwargs))
        return seen[-1]

    monkeypatch.setattr(registration, "register", spy)
    return seen


def test_register_scan_in_template_frame_gives_code_as_shape_keys_and_leaves_scan_untouched(scene, tiny):
    _, _, surface = tiny
    verts, faces = code_surface(surface, ALPHA)
    scan = add_mesh("scan", verts, faces, location=(2.0, 0.0, 1.0))
    scan.rotation_euler = (0.0, 0.0, math.radians(30))
    bpy.context.view_layer.update()
    select(scan)
    scene.bareesa.prealign = False
    before = snapshot()
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    after = snapshot()
    assert after["scan"] == before["scan"]
    reg = bpy.data.objects["scan_registered"]
    assert [k.name for k in reg.data.shape_keys.key_blocks] == ["Basis"] + NAMES + ["Detail"]
    assert np.abs(key_values(reg, NAMES) - ALPHA).max() < 0.1
    assert len(reg.data.vertices) == 42 and reg["bareesa_scan"] == "scan"
    assert reg["bareesa_varifold"] >= 0 and 0 <= reg["bareesa_chamfer"] < 0.5  # vertex sets of two coarse meshes
    # without pre-alignment the registered object sits exactly in the scan's frame
    assert np.allclose(np.array(reg.matrix_world), np.array(scan.matrix_world), atol=1e-6)
    assert reg.select_get() and bpy.context.view_layer.objects.active == reg


def test_registered_object_carries_the_detail_layer_as_one_detail_key(scene, tiny, monkeypatch, capfd):
    """The registration's detail layer is a 'Detail' key (template + detail, slider 0-1, at 1) after the field
    keys: the object then shows the detailed mesh exactly where the solver put it, its code reads back from
    the field keys as before, and the report gives the detailed Chamfer."""
    from bareesa_addon import convert

    _, _, surface = tiny
    verts, faces = code_surface(surface, ALPHA, subdivisions=2)  # (on 42 vertices the layer flips faces)
    rot = np.array(Matrix.Rotation(math.radians(50), 3, "Z") @ Matrix.Rotation(math.radians(20), 3, "X"))
    scan = add_mesh("scan", 1.5 * verts @ rot.T + [0.3, -1.0, 0.2], faces, location=(2.0, 0.0, 1.0))
    scan.rotation_euler = (0.0, 0.0, math.radians(30))
    bpy.context.view_layer.update()
    select(scan)
    seen = spy_registrations(monkeypatch)
    capfd.readouterr()
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    out = capfd.readouterr().out
    (res,) = seen
    assert res.detail is not None and np.abs(res.detail).max() > 1e-3  # a layer that moves the surface
    assert abs(res.transform.scale - 1 / 1.5) < 0.1  # pre-aligned: the layer goes through the transform
    reg = bpy.data.objects["scan_registered"]
    blocks = reg.data.shape_keys.key_blocks
    assert [k.name for k in blocks] == ["Basis"] + NAMES + ["Detail"]
    detail = blocks["Detail"]
    assert detail.relative_key.name == "Basis" and (detail.slider_min, detail.slider_max, detail.value) == (0, 1, 1)
    np.testing.assert_allclose(detail_offset(reg), res.detail, atol=1e-5)
    # the code is read from the field keys only (the Detail key is not one of them)
    assert convert.has_field_keys(reg, NAMES)
    np.testing.assert_allclose(convert.get_code(reg, NAMES), res.code, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(convert.code_at_frame(reg, NAMES, 1), res.code, rtol=1e-6, atol=1e-6)
    # shown: the detailed mesh, in the scan's frame as the solver has it (with the key at 0: the basis fit)
    m = np.array(scan.matrix_world)
    to_world = lambda v: v @ m[:3, :3].T + m[:3, 3]  # noqa: E731
    np.testing.assert_allclose(world_verts(reg), to_world(res.detailed_vertices), atol=1e-5)
    detail.value = 0.0
    np.testing.assert_allclose(world_verts(reg), to_world(res.vertices), atol=1e-5)
    assert reg["bareesa_detail_chamfer"] == pytest.approx(res.detail_report["chamfer"])
    assert f"detailed Chamfer {res.detail_report['chamfer']:.3g}" in out


def test_detail_layer_off_registers_the_pure_basis_fit(scene, tiny, monkeypatch, capfd):
    _, _, surface = tiny
    select(add_mesh("scan", *code_surface(surface, ALPHA)))
    scene.bareesa.prealign = False
    scene.bareesa.detail_layer = False
    seen = spy_registrations(monkeypatch)
    capfd.readouterr()
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    out = capfd.readouterr().out
    (res,) = seen
    assert res.detail is None and res.detail_report["skipped"] == "turned off"
    reg = bpy.data.objects["scan_registered"]
    assert [k.name for k in reg.data.shape_keys.key_blocks] == ["Basis"] + NAMES
    assert "bareesa_detail_chamfer" not in reg and "detailed Chamfer" not in out and "no detail layer" not in out
    np.testing.assert_allclose(world_verts(reg), res.vertices, atol=1e-5)  # in the scan's frame (at the origin)


def test_register_scan_prealigned_overlays_a_moved_rescaled_scan(scene, tiny):
    from bareesa import synthetic
    from bareesa.evaluation import chamfer

    _, _, surface = tiny
    verts, faces = code_surface(surface, ALPHA)
    rot = np.array(Matrix.Rotation(math.radians(50), 3, "Z") @ Matrix.Rotation(math.radians(20), 3, "X"))
    move = lambda x: 2.5 * x @ rot.T + [0.3, -1.0, 0.2]  # noqa: E731
    scan = add_mesh("moved", move(verts), faces, location=(1.0, 1.0, 0.0))
    scan.scale = (0.5, 0.5, 0.5)
    bpy.context.view_layer.update()
    select(scan)
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    reg = bpy.data.objects["moved_registered"]
    # F(alpha) vertex by vertex, carried into the world exactly as the scan was
    truth = move(surface(synthetic.icosphere(1)[0], ALPHA))
    m = np.array(scan.matrix_world)
    truth = truth @ m[:3, :3].T + m[:3, 3]
    size = np.ptp(truth, axis=0).max()
    assert np.linalg.norm(world_verts(reg) - truth, axis=1).mean() < 0.1 * size  # fast schedule: rough
    # exact placement: in the scan's local frame the object's vertices are the solver's, whose
    # Chamfer distance to the scan the operator stored (the detailed mesh's when it has a Detail key at 1)
    local = (world_verts(reg) - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T
    stored = reg.get("bareesa_detail_chamfer", reg["bareesa_chamfer"]) if "Detail" in reg.data.shape_keys.key_blocks \
        else reg["bareesa_chamfer"]
    assert chamfer(local, move(verts)) == pytest.approx(stored, rel=1e-5)


def test_register_scan_accepts_quads_and_several_scans(scene):
    bpy.ops.mesh.primitive_uv_sphere_add(segments=12, ring_count=6, radius=1.0, location=(0, 0, 0))
    uv = bpy.context.active_object
    bpy.ops.mesh.primitive_cube_add(size=1.6, location=(4, 0, 0))
    cube = bpy.context.active_object
    assert any(len(p.vertices) == 4 for p in uv.data.polygons)
    select(uv, cube)
    scene.bareesa.prealign = False
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    for name in ("Sphere_registered", "Cube_registered"):
        obj = bpy.data.objects[name]
        assert np.isfinite(key_values(obj, NAMES)).all()


def test_register_scan_refuses_a_selection_without_meshes(scene, tiny):
    # (a mesh selected with a non-mesh is registered, the other skipped: test_addon_conventions.py)
    _, _, surface = tiny
    add_mesh("scan", *code_surface(surface, ALPHA))
    empty = bpy.data.objects.new("empty", None)
    scene.collection.objects.link(empty)
    select(empty)
    before = snapshot()
    with pytest.raises(RuntimeError, match="select one or more"):
        bpy.ops.bareesa.register_scan()
    select()
    with pytest.raises(RuntimeError, match="select one or more"):
        bpy.ops.bareesa.register_scan()
    assert snapshot() == before


def test_register_scan_refuses_nan_vertices(scene, tiny):
    _, _, surface = tiny
    verts, faces = code_surface(surface, ALPHA)
    verts[5] = np.nan
    select(add_mesh("bad", verts, faces))
    before = snapshot()
    with pytest.raises(RuntimeError, match="(?i)non-finite|nan"):
        bpy.ops.bareesa.register_scan()
    assert snapshot() == before


def test_register_scan_missing_basis_file_reports_and_changes_nothing(scene, tiny, tmp_path):
    _, _, surface = tiny
    select(add_mesh("scan", *code_surface(surface, ALPHA)))
    scene.bareesa.basis = str(tmp_path / "gone.npz")
    before = snapshot()
    with pytest.raises(RuntimeError, match="does not exist"):
        bpy.ops.bareesa.register_scan()
    assert snapshot() == before


def test_diverged_registration_never_writes_nan_into_shape_keys(scene, tiny, monkeypatch):
    import bareesa.registration as registration
    from bareesa.transforms import Similarity

    def diverged(basis, verts, faces, **kwargs):
        n = basis.template.shape[0]
        return registration.RegistrationResult(code=np.full(basis.n_fields, np.nan), vertices=np.full((n, 3), np.nan),
                                               path=np.zeros((2, basis.n_fields)), transform=Similarity(),
                                               levels=[], varifold=float("nan"), chamfer=float("nan"), seconds=0.0)

    monkeypatch.setattr(registration, "register", diverged)
    _, _, surface = tiny
    select(add_mesh("scan", *code_surface(surface, ALPHA)))
    before = snapshot()
    with pytest.raises(RuntimeError, match="diverged"):
        bpy.ops.bareesa.register_scan()
    assert snapshot() == before


def test_cancelled_registration_leaves_the_scene_exactly_as_it_was(scene, tiny, monkeypatch):
    from bareesa_addon import jobs
    from bareesa.progress import CancelToken

    def cancelled():
        token = CancelToken()
        token.cancel()
        return token

    monkeypatch.setattr(jobs, "new_token", cancelled)
    _, _, surface = tiny
    select(add_mesh("scan", *code_surface(surface, ALPHA)))
    before = snapshot()
    assert bpy.ops.bareesa.register_scan() == {"CANCELLED"}
    assert snapshot() == before


def test_every_solve_operator_is_undoable(scene):
    for name in ("LOAD_TEMPLATE", "REGISTER_SCAN", "INTERPOLATE", "EXTRAPOLATE", "TRANSFER_MOTION",
                 "GENERATE_RANDOM", "BUILD_BASIS", "DISTANCE"):
        cls = getattr(bpy.types, f"BAREESA_OT_{name.lower()}")
        assert "UNDO" in cls.bl_options and "REGISTER" in cls.bl_options


def test_poor_fit_is_stored_on_the_object_and_reported(scene, tiny, monkeypatch, capfd):
    # the registration's poor-fit flag (the basis card's fit_check) reaches the object and a warning; the
    # detail layer is left out of a poor fit, and the report says so
    import bareesa.registration.multiscale as multiscale

    _, _, surface = tiny
    select(add_mesh("scan", *code_surface(surface, ALPHA)))
    scene.bareesa.prealign = False
    monkeypatch.setattr(multiscale, "is_poor_fit", lambda basis, residual: True)
    capfd.readouterr()
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    assert "no detail layer (the basis fit is flagged poor)" in capfd.readouterr().out
    reg = bpy.data.objects["scan_registered"]
    assert "Detail" not in reg.data.shape_keys.key_blocks
    assert reg["bareesa_poor_fit"] is True or reg["bareesa_poor_fit"] == 1
    assert reg["bareesa_fit_residual"] > 0
    monkeypatch.setattr(multiscale, "is_poor_fit", lambda basis, residual: False)
    select(bpy.data.objects["scan"])
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    assert not bpy.data.objects["scan_registered.001"]["bareesa_poor_fit"]


def test_several_scans_register_in_worker_processes_like_in_blender(scene, tiny):
    """Register Scans with processes=2 runs the scans on a Dask LocalCluster: the same objects as one at a
    time in Blender's process; a scan that fails there is reported and the others are still made."""
    pytest.importorskip("distributed")
    _, _, surface = tiny
    moved = [add_mesh(f"scan{k}", *code_surface(surface, a), location=(3.0 * k, 0.0, 0.0))
             for k, a in enumerate((ALPHA, -0.5 * ALPHA))]
    scene.bareesa.prealign = False
    select(*moved)
    assert bpy.ops.bareesa.register_scan(processes=1) == {"FINISHED"}
    serial = {k: key_values(bpy.data.objects[f"scan{k}_registered"], NAMES) for k in range(2)}
    serial_place = {k: np.array(bpy.data.objects[f"scan{k}_registered"].matrix_world) for k in range(2)}
    serial_detail = {k: detail_offset(bpy.data.objects[f"scan{k}_registered"]) for k in range(2)}
    for k in range(2):
        bpy.data.objects.remove(bpy.data.objects[f"scan{k}_registered"])
    select(*moved)
    assert bpy.ops.bareesa.register_scan(processes=2) == {"FINISHED"}
    for k in range(2):
        obj = bpy.data.objects[f"scan{k}_registered"]
        np.testing.assert_allclose(key_values(obj, NAMES), serial[k], atol=1e-5)
        np.testing.assert_allclose(np.array(obj.matrix_world), serial_place[k], atol=1e-5)
        np.testing.assert_allclose(detail_offset(obj), serial_detail[k], atol=1e-4)  # the workers' detail too
    # a one-triangle "scan" beside a real one: refused in its process, the other registered
    tri = add_mesh("tri", np.array([[0.0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0]]), np.array([[0, 1, 2]]))
    select(moved[0], tri)
    before = set(bpy.data.objects.keys())
    assert bpy.ops.bareesa.register_scan(processes=2) == {"FINISHED"}
    made = set(bpy.data.objects.keys()) - before
    assert len(made) == 1 and not any(name.startswith("tri") for name in made)


def test_worker_processes_that_cannot_start_fall_back_to_blenders_process(scene, tiny, monkeypatch):
    distributed = pytest.importorskip("distributed")

    def broken(*args, **kwargs):
        raise OSError("no free port (test)")

    monkeypatch.setattr(distributed, "LocalCluster", broken)
    _, _, surface = tiny
    scene.bareesa.prealign = False
    select(*[add_mesh(f"scan{k}", *code_surface(surface, a), location=(3.0 * k, 0.0, 0.0))
             for k, a in enumerate((ALPHA, -0.5 * ALPHA))])
    assert bpy.ops.bareesa.register_scan(processes=2) == {"FINISHED"}
    for k in range(2):
        assert np.isfinite(key_values(bpy.data.objects[f"scan{k}_registered"], NAMES)).all()


def test_the_panels_registration_settings_reach_the_solve_and_a_bad_one_is_refused(scene, tiny):
    """Pose Search, Retry Poor Fits and the Settings field become RegistrationConfig overrides; an unknown
    setting is refused in one line before anything is solved, and the scene is left as it was."""
    from bareesa_addon.operators.common import solve_options

    basis = tiny[0]
    settings = scene.bareesa
    settings.pose_search, settings.retry_poor_fits, settings.detail_layer = False, False, False
    settings.registration_settings = "poses.finalists=3; solve.memory=20"
    options = solve_options(bpy.context, basis)
    config = options.registration_config(basis)
    assert config.poses.candidates is None and config.retry is False and config.detail.enabled is False
    assert config.poses.finalists == 3 and config.solve.memory == 20
    settings.pose_search, settings.retry_poor_fits, settings.detail_layer = True, True, True
    settings.registration_settings = ""
    default = solve_options(bpy.context, basis).registration_config(basis)
    assert default.poses.candidates == "auto" and default.retry is True and default.solve.memory != 20
    assert default.detail.enabled is True

    _, _, surface = tiny
    verts, faces = code_surface(surface, ALPHA)
    select(add_mesh("scan", verts, faces))
    settings.registration_settings = "poses.finalist=3"
    before = snapshot()
    with pytest.raises(RuntimeError, match="unknown registration setting 'poses.finalist'"):
        bpy.ops.bareesa.register_scan()
    assert snapshot() == before and "scan_registered" not in bpy.data.objects
    settings.registration_settings = ""
