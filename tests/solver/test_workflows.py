"""bareesa.workflows: what the CLI and the add-on both run (metric and preconditioning reach the
solvers, replaced random draws are reported, one path for the same inputs from either front end)."""

import dataclasses
import json
import re

import numpy as np
import pytest

from bareesa import cli, geodesics, registration, shooting, synthetic, workflows
from bareesa.basis_io import save_basis
from bareesa.errors import InputError
from bareesa.h2_metric import PRESETS
from bareesa.mesh import save_mesh, triangle_quality
from bareesa.transforms import Similarity, axis_angle_rotation
from tests.solver.support import A, B

def raw_scan(surface, code, seed):
    """F(code) on another triangulation of the sphere: a workflows.Scan."""
    u, faces = synthetic.resampled_sphere(1, seed=seed)
    return workflows.Scan(surface(u, np.asarray(code, dtype=np.float64)), faces)


def test_symmetric_matching_of_two_scans_solves_with_the_given_metric_steps_and_schedule(sphere, monkeypatch):
    basis, surface = sphere
    seen = {}

    def fake(b, scan0, scan1, steps=10, config=None, weights=None, face_weights=(None, None),
             landmarks=(None, None), callback=None, cancel=None):
        seen.update(weights=weights, steps=steps, schedule=config.schedule, device=config.device,
                    kernel=config.kernel, face_weights=face_weights, landmarks=landmarks)
        path = geodesics.straight_path(A, B, steps)
        return registration.Matching(path=path, energy=1.0, distance=1.0, transforms=(Similarity(), Similarity()),
                                     varifold=(0.0, 0.0), seconds=0.0)

    monkeypatch.setattr(registration, "symmetric_match", fake)
    schedule = basis.schedule[:1]
    options = workflows.Options(weights="body", schedule=schedule, steps=5, device="meta", kernel="linear",
                                registration={"detail.enabled": False})  # (no detail layer on the meta device)
    found = workflows.path_between(basis, raw_scan(surface, A, 4), raw_scan(surface, B, 6), 4,
                                   workflows.Options(weights="body", schedule=schedule, steps=5))
    assert seen == {"weights": PRESETS["body"], "steps": 5, "schedule": schedule, "device": "cpu", "kernel": "auto",
                    "face_weights": (None, None), "landmarks": (None, None)}
    masked, marked = raw_scan(surface, A, 4), raw_scan(surface, B, 6)
    masked = dataclasses.replace(masked, face_weights=np.ones(len(masked.faces)))
    marked = dataclasses.replace(marked, landmarks=[(0, (0.0, 0.0, 1.0))])
    workflows.geodesic_between(basis, masked, marked, options)
    assert seen["device"] == "meta" and seen["kernel"] == "linear"  # the caller's device and kernel reach it
    assert seen["face_weights"][0] is masked.face_weights and seen["face_weights"][1] is None  # and each scan's
    assert seen["landmarks"] == (None, marked.landmarks)  # mask and landmarks
    assert basis.weights == PRESETS["face"]  # the caller's basis keeps its own metric
    assert found.frames.shape == (4, 4) and found.matching is not None
    for end, code in zip(found.ends, (A, B)):
        reg = end.registration
        assert isinstance(reg, workflows.MatchedEnd) and np.allclose(reg.code, code)
        # each end's detail layer is fitted after the matching (kept, or why not) and is the end's detail
        assert reg.detail is not None and (end.detail is None) == (reg.detail.displacement is None)
        assert np.allclose(reg.vertices, basis.template + np.tensordot(code, basis.fields, 1))
        assert reg.chamfer > 0 and reg.varifold == 0.0


def test_geodesic_between_codes_is_preconditioned_at_their_mean_for_the_given_metric(sphere, monkeypatch):
    basis, _ = sphere
    real, calls = geodesics.midpoint_metric, []

    def spy(template, faces, fields, alpha0, alpha1, weights):
        calls.append((alpha0, alpha1, weights))
        return real(template, faces, fields, alpha0, alpha1, weights)

    monkeypatch.setattr(geodesics, "midpoint_metric", spy)
    found = workflows.geodesic_between(basis, workflows.KnownCode(A), workflows.KnownCode(B),
                                       workflows.Options(weights="body", steps=4))
    assert len(calls) == 1
    assert np.array_equal(calls[0][0], A) and np.array_equal(calls[0][1], B) and calls[0][2] == PRESETS["body"]
    assert found.distance > 0 and found.path.shape == (4, 4)


def test_random_bodies_report_replaced_draws_and_the_cli_prints_them(sphere, monkeypatch, tmp_path, capsys):
    basis, _ = sphere
    plain = workflows.random_bodies(basis, 3, 2, shoot_steps=2)
    assert plain.replaced == 0
    real, calls = shooting.shoot, []

    def shoot(*args, steps=10, **kwargs):  # the first draw fails with 2 and with 4 steps
        calls.append(steps)
        if len(calls) <= 2:
            raise shooting.ShootingFailed("a geodesic step did not converge (test)")
        return real(*args, steps=steps, **kwargs)

    monkeypatch.setattr(shooting, "shoot", shoot)
    bodies = workflows.random_bodies(basis, 3, 2, shoot_steps=2)
    assert bodies.replaced == 1 and calls[:3] == [2, 4, 2]
    assert np.allclose(bodies.codes[:2], plain.codes[1:])  # the first draw replaced by a spare
    save_basis(tmp_path / "s.npz", basis)
    calls.clear()
    assert cli.main(["sample", "--basis", str(tmp_path / "s.npz"), "-n", "2", "-o", str(tmp_path / "out"),
                     "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["replaced"] == 1
    calls.clear()
    assert cli.main(["sample", "--basis", str(tmp_path / "s.npz"), "-n", "2", "-o", str(tmp_path / "out")]) == 0
    assert re.search(r"^\s+replaced\s+1$", capsys.readouterr().out, re.M)


def test_code_of_each_input_kind(sphere):
    basis, surface = sphere
    known = workflows.code_of(basis, workflows.KnownCode(A))
    assert np.array_equal(known.code, A) and known.detail is None and known.registration is None
    verts = basis.template + np.tensordot(A, basis.fields, 1) + 0.01
    mesh = workflows.mesh_input(basis, verts, basis.faces)
    assert isinstance(mesh, workflows.TemplateMesh)
    projected = workflows.code_of(basis, mesh)
    assert np.allclose(basis.template + np.tensordot(projected.code, basis.fields, 1) + projected.detail, verts)
    scan = raw_scan(surface, A, 4)
    assert isinstance(workflows.mesh_input(basis, scan.verts, scan.faces), workflows.Scan)
    with pytest.raises(InputError, match="Scan, a TemplateMesh or a KnownCode"):
        workflows.code_of(basis, A)


def test_cli_and_addon_interpolate_to_the_same_path(tmp_path, capsys):
    """Two meshes through ``bareesa interpolate`` and the same codes through the add-on's Interpolate
    (registered objects): one path (geodesic steps, preconditioning, anchoring and pacing agree)."""
    support = pytest.importorskip("tests.addon.support")
    import bareesa_addon
    from bareesa.latent import project_to_basis
    from bareesa_addon import convert

    bpy = support.bpy
    basis, _ = support.tiny_basis()
    save_basis(tmp_path / "tiny.npz", basis)
    codes = []
    for name, code in (("a", A), ("b", B)):
        save_mesh(tmp_path / f"{name}.ply", basis.template + np.tensordot(code, basis.fields, 1), basis.faces)
        codes.append(project_to_basis(basis, basis.template + np.tensordot(code, basis.fields, 1))[0])
    assert cli.main(["interpolate", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--basis",
                     str(tmp_path / "tiny.npz"), "--steps", "6", "-o", str(tmp_path / "cli")]) == 0
    capsys.readouterr()
    from_cli = np.load(tmp_path / "cli" / "codes.npy")

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bareesa_addon.register()
    try:
        s = bpy.context.scene.bareesa
        # the CLI solves the geodesic at workflows.Options' 10 time points, then keys 6 frames
        s.basis, s.metric, s.steps, s.geodesic_iterations = str(tmp_path / "tiny.npz"), "BASIS", 10, 500
        bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 6  # the add-on keys the scene's range
        names = bareesa_addon.solver.field_names(basis)
        for name, code in zip(("a", "b"), codes):
            bpy.ops.bareesa.load_template()
            bpy.context.active_object.name = name
            convert.set_code(bpy.context.active_object, names, code)
        assert bpy.ops.bareesa.interpolate(object_a="a", object_b="b") == {"FINISHED"}
        obj = bpy.data.objects["a_to_b"]
        from_addon = np.stack([convert.code_at_frame(obj, names, f) for f in convert.keyed_frames(obj, names)])
    finally:
        bareesa_addon.unregister()
    assert from_addon.shape == from_cli.shape == (6, 4)
    assert np.allclose(from_addon, from_cli, atol=1e-5)


def test_random_bodies_over_many_seeds_are_finite_and_non_degenerate(sphere):
    # shooting refines its steps where they do not converge, so every draw of the fitted distribution
    # (wide: 0.5 x the training spread, 20 seeds) gives a body, none folded or collapsed
    from bareesa.mesh import face_geometry

    basis, _ = sphere
    template_areas = face_geometry(basis.template, basis.faces)[1]
    for seed in range(20):
        bodies = workflows.random_bodies(basis, 2, seed, shoot_steps=4)
        assert bodies.codes.shape == (2, basis.n_fields) and np.isfinite(bodies.codes).all() and bodies.replaced == 0
        for code in bodies.codes:
            verts = basis.template + np.tensordot(code, basis.fields, 1)
            vectors, areas, _ = face_geometry(verts, basis.faces)
            assert areas.min() > 0.05 * template_areas.min()
            # no face flipped against the template's orientation (a fold-over)
            assert (np.einsum("fk,fk->f", vectors, face_geometry(basis.template, basis.faces)[0]) > 0).all()


def test_a_random_body_that_creases_a_joint_flat_is_replaced_and_counted(sphere, monkeypatch):
    from bareesa.mesh import triangle_quality

    basis, _ = sphere
    plain = workflows.random_bodies(basis, 3, 2, shoot_steps=2)
    assert plain.replaced == 0 and not any(
        workflows.creased(basis.template, basis.faces, basis.template + np.tensordot(c, basis.fields, 1))
        for c in plain.codes)
    flat = basis.template.copy()  # one triangle flattened to a sliver
    a, b, c = basis.faces[0]
    flat[c] = (flat[a] + flat[b]) / 2 + 1e-3 * (flat[c] - (flat[a] + flat[b]) / 2)
    assert triangle_quality(flat, basis.faces)[0] < 0.01
    real_creased, asked = workflows.creased, []

    def creased(template, faces, verts, **kwargs):  # the first draw's body creased
        asked.append(verts)
        return len(asked) == 1 or real_creased(template, faces, verts, **kwargs)

    monkeypatch.setattr(workflows, "creased", creased)
    bodies = workflows.random_bodies(basis, 3, 2, shoot_steps=2)
    assert bodies.replaced == 1 and np.allclose(bodies.codes[:2], plain.codes[1:])
    assert real_creased(basis.template, basis.faces, flat) and not real_creased(basis.template, basis.faces,
                                                                                 2.0 * basis.template)


def test_a_shot_that_creases_a_joint_stops_at_that_frame(sphere, monkeypatch):
    basis, _ = sphere
    plain = workflows.random_bodies(basis, 3, 2, shoot_steps=4)
    real_creased, seen = workflows.creased, []

    def creased(template, faces, verts, **kwargs):  # the first frame the solver checks is creased
        seen.append(verts)
        return len(seen) == 1 or real_creased(template, faces, verts, **kwargs)

    monkeypatch.setattr(workflows, "creased", creased)
    bodies = workflows.random_bodies(basis, 3, 2, shoot_steps=4)
    assert bodies.replaced == 1 and np.allclose(bodies.codes[:2], plain.codes[1:])
    # the first draw's shot stopped at its first new frame; each kept draw: 3 new frames and its end
    assert len(seen) == 1 + 3 * (3 + 1)


def test_an_extrapolation_that_fails_past_a_creased_frame_names_that_frame(sphere, monkeypatch):
    basis, _ = sphere
    real_shoot, real_creased = shooting.extrapolate, workflows.creased

    def failing(*args, **kwargs):  # the real shot's first two frames, then a step that does not converge
        frames = real_shoot(*args[:6], 2, max_substeps=1)[2:]
        raise shooting.ShootingFailed("frame 3 of 4: a geodesic step did not converge", frames=frames)

    monkeypatch.setattr(shooting, "extrapolate", failing)
    with pytest.raises(shooting.ShootingFailed) as err:  # no creased frame: the shot's own message
        workflows.extrapolate(basis, workflows.KnownCode(A), workflows.KnownCode(B), 4)
    assert str(err.value) == "frame 3 of 4: a geodesic step did not converge" and err.value.frames.shape == (2, 4)
    seen = []

    def creased(template, faces, verts, **kwargs):  # the second frame reached is creased
        seen.append(verts)
        return len(seen) == 2 or real_creased(template, faces, verts, **kwargs)

    monkeypatch.setattr(workflows, "creased", creased)
    named = r"^frame 3 of 4: .*converge; frame 2 already creases a joint flat"
    with pytest.raises(shooting.ShootingFailed, match=named):
        workflows.extrapolate(basis, workflows.KnownCode(A), workflows.KnownCode(B), 4)
    assert len(seen) == 2 and np.allclose(seen[0], basis.template + np.tensordot(err.value.frames[0], basis.fields, 1))


def test_an_extrapolation_continued_in_the_frozen_metric_finishes_unless_it_creases_a_joint(sphere, monkeypatch):
    basis, _ = sphere
    real_shoot, real_creased = shooting.extrapolate, workflows.creased
    asked = {}

    def frozen_at_2(*args, **kwargs):  # the real shot, reported as frozen from frame 2 on
        asked.update(kwargs)
        path, report = real_shoot(*args, **kwargs)
        report.frozen = [2, 3]
        return path, report

    monkeypatch.setattr(shooting, "extrapolate", frozen_at_2)
    motion = workflows.extrapolate(basis, workflows.KnownCode(A), workflows.KnownCode(B), 4)
    assert asked["frozen"] is True and motion.shooting.frozen == [2, 3] and motion.path.shape == (6, 4)
    monkeypatch.setattr(shooting, "extrapolate", real_shoot)
    seen = []

    def creased(template, faces, verts, **kwargs):  # the third frame shot is creased
        seen.append(verts)
        return len(seen) == 3 or real_creased(template, faces, verts, **kwargs)

    monkeypatch.setattr(workflows, "creased", creased)
    with pytest.raises(shooting.ShootingFailed, match=r"^frame 3 of 4: it creases a joint flat that the inputs did "
                                                      r"not: .*basis can make; ask for at most 2 frames$") as err:
        workflows.extrapolate(basis, workflows.KnownCode(A), workflows.KnownCode(B), 4)
    assert len(seen) == 3 and np.allclose(err.value.frames, motion.path[2:4], atol=1e-9)  # frames 1 and 2
    # the check judges against the inputs: the same motion unchecked passes
    monkeypatch.setattr(workflows, "creased", real_creased)
    assert workflows.extrapolate(basis, workflows.KnownCode(A), workflows.KnownCode(B), 4).path.shape == (6, 4)


def test_a_random_body_whose_faces_cross_is_replaced_and_counted(sphere, monkeypatch):
    from bareesa.mesh import self_intersections

    basis, _ = sphere
    plain = workflows.random_bodies(basis, 3, 2, shoot_steps=2)
    assert plain.replaced == 0 and not any(
        len(self_intersections(basis.template + np.tensordot(c, basis.fields, 1), basis.faces)) for c in plain.codes)
    bodies_seen = []

    def crossing(verts, faces):  # the template is asked first; then the first draw's body runs through itself
        bodies_seen.append(verts)
        return np.array([[0, 7]]) if len(bodies_seen) == 2 else self_intersections(verts, faces)

    monkeypatch.setattr(workflows, "self_intersections", crossing)
    bodies = workflows.random_bodies(basis, 3, 2, shoot_steps=2)
    assert np.array_equal(bodies_seen[0], basis.template)
    assert bodies.replaced == 1 and np.allclose(bodies.codes[:2], plain.codes[1:])


def test_a_crease_is_judged_against_the_motions_inputs_not_the_template(sphere):
    basis, _ = sphere
    thin = np.zeros(basis.n_fields)
    thin[0] = 16.0  # a body whose triangles are already far thinner than the template's
    assert workflows.first_creased(basis, [thin]) == 1  # against the template: creased
    assert workflows.first_creased(basis, [thin], inputs=[thin, 0.9 * thin]) is None  # the inputs are so already
    reference = workflows.input_quality(basis, [thin, np.zeros(basis.n_fields)])
    assert np.all(reference <= triangle_quality(basis.template, basis.faces) + 1e-12)
    squashed = basis.template.copy()
    tri = basis.faces[0]
    squashed[tri[2]] = squashed[tri[:2]].mean(0)  # one triangle flattened to a segment: creased whatever the inputs
    assert workflows.creased(basis.template, basis.faces, squashed, reference=reference)
    assert workflows.creased(basis.template, basis.faces, squashed, floor=workflows.MOTION_CREASE["floor"],
                             reference=reference)
    # a motion's frame may thin a triangle far more than a random body may (a joint at full flexion) ...
    thinned = basis.template.copy()
    a, b, c = thinned[tri]
    foot = a + np.dot(c - a, b - a) / np.dot(b - a, b - a) * (b - a)
    own = triangle_quality(basis.template, basis.faces)[0]
    for keep, refused in ((0.05, False), (0.002, True)):  # ... but not collapse it
        thinned[tri[2]] = foot + keep * (c - foot)
        ratio = triangle_quality(thinned, basis.faces)[0] / own
        assert (ratio < workflows.MOTION_CREASE["floor"]) == refused
        assert workflows.creased(basis.template, basis.faces, thinned, floor=workflows.MOTION_CREASE["floor"]) == refused
        assert workflows.creased(basis.template, basis.faces, thinned)  # a random body that thin is refused


def test_a_motions_crease_is_a_patch_a_user_sees_or_a_flattened_triangle_not_a_sliver(sphere):
    from bareesa.mesh import face_geometry, vertex_adjacency

    basis, _ = sphere
    floor, share, flat = (workflows.MOTION_CREASE[k] for k in ("floor", "share", "flat"))
    assert 0 < flat < floor and 0 < share < 1e-3
    area = face_geometry(basis.template, basis.faces)[1]
    one = area[0] / area.sum()  # the share of the surface one triangle covers
    tri = basis.faces[0]
    a, b, c = basis.template[tri]
    foot = a + np.dot(c - a, b - a) / np.dot(b - a, b - a) * (b - a)
    own = triangle_quality(basis.template, basis.faces)[0]
    for keep, flattened in ((0.2 * floor, False), (0.0, True)):  # one triangle thinned to a sliver, then flat
        thinned = basis.template.copy()
        thinned[tri[2]] = foot + keep * (c - foot)
        ratio = triangle_quality(thinned, basis.faces)[0] / own
        assert ratio < floor and (ratio < flat) == flattened
        for patch, refused in ((0.0, True), (0.5 * one, True), (2.0 * one, flattened)):
            # a sliver over less of the surface than ``share`` passes; a flattened one never does
            assert workflows.creased(basis.template, basis.faces, thinned, floor=floor, share=patch,
                                     flat=flat) == refused
    # a joint folded flat: every triangle around a vertex flattened onto a line through it covers far more
    v = tri[0]
    around = np.flatnonzero((basis.faces == v).any(1))
    folded = basis.template.copy()
    patch_verts = np.append(vertex_adjacency(len(folded), basis.faces)[v].indices, v)
    d = np.array([1.0, 0.0, 0.0])
    folded[patch_verts] = folded[v] + np.outer((folded[patch_verts] - folded[v]) @ d, d)
    patch = area[around].sum() / area.sum()
    assert patch > 2 * one
    assert workflows.creased(basis.template, basis.faces, folded, floor=floor, share=0.5 * patch)
    assert not workflows.creased(basis.template, basis.faces, basis.template, floor=floor, share=0.5 * patch,
                                 flat=flat)


def test_a_known_codes_detail_is_carried_along_a_path_and_a_continuation(sphere):
    basis, _ = sphere
    rng = np.random.default_rng(3)
    detail_a, detail_b = (0.01 * rng.normal(size=basis.template.shape) for _ in range(2))
    a, b = workflows.KnownCode(A, detail=detail_a), workflows.KnownCode(B, detail=detail_b)
    found = workflows.path_between(basis, a, b, 5)
    assert np.allclose(found.detail[0], detail_a) and np.allclose(found.detail[-1], detail_b)
    assert np.allclose(found.detail[2], (detail_a + detail_b) / 2)
    assert workflows.path_between(basis, a, workflows.KnownCode(B), 5).detail is None  # one end without: none
    moved = workflows.transfer(basis, [workflows.KnownCode(A), workflows.KnownCode(B)], a, "all")
    assert moved.detail.shape == (2,) + basis.template.shape and np.allclose(moved.detail[1], detail_a)


def test_two_scans_of_one_capture_extrapolate_from_one_frame_and_scans_of_two_sessions_from_their_own(sphere):
    """Extrapolating from two Scans registers the second in the first's frame (their codes then differ by
    the motion, not by a difference of alignments); where that refit is far from the scan (the body moved
    between two sessions) the second scan's own registration is kept."""
    basis, surface = sphere
    frame = Similarity(axis_angle_rotation(np.array([0.3, -0.5, 0.2])), 2.0, np.array([0.5, 1.0, -0.3]))
    a, b = (raw_scan(surface, code, seed) for code, seed in ((A, 4), (B, 6)))
    a, b = (dataclasses.replace(scan, verts=frame.apply(scan.verts)) for scan in (a, b))
    options = workflows.Options(registration={"detail.enabled": False})
    found = workflows.extrapolate(basis, a, b, 1, options)
    first, second = (end.registration for end in found.ends)
    assert found.same_frame is True and len(second.levels) < len(basis.schedule)
    assert np.allclose(second.transform.rotation, first.transform.rotation)
    assert np.allclose(second.transform.translation, first.transform.translation)
    own = workflows.code_of(basis, b, options).code  # (registered apart, a coarse sphere's code is farther off)
    assert np.linalg.norm(found.path[1] - B) < np.linalg.norm(own - B)
    size = float(np.ptp(b.verts, axis=0).max())
    moved = dataclasses.replace(b, verts=b.verts + np.array([0.4, 0.0, 0.0]) * size)
    found = workflows.extrapolate(basis, a, moved, 1, options)
    assert found.same_frame is False and len(found.ends[1].registration.levels) == len(basis.schedule)
    assert found.ends[1].registration.residual < 0.1
    known = workflows.extrapolate(basis, workflows.KnownCode(A), workflows.KnownCode(B), 1, options)
    assert known.same_frame is None


def test_the_second_scan_is_refitted_from_the_firsts_code_then_its_own_then_left_as_registered(sphere, monkeypatch):
    """``in_frame_of`` tries the first scan's code (a capture's next frame), then the second's own code
    (poses far apart in one frame), each kept only within SAME_FRAME_RESIDUAL of the scan's own fit."""
    from types import SimpleNamespace

    basis, surface = sphere
    frame = Similarity(axis_angle_rotation(np.array([0.1, 0.2, 0.3])), 1.5, np.array([0.2, 0.0, 0.1]))
    first = workflows.Code(A, registration=SimpleNamespace(transform=frame))
    second = workflows.Code(B, registration=SimpleNamespace(residual=0.01))
    scan = raw_scan(surface, B, 6)
    for residuals, kept in (([0.0105, 0.001], 0), ([0.02, 0.0105], 1), ([0.02, 0.02], None)):
        starts = []

        def fake(b, verts, faces, transform, init_code, config, *, residuals=residuals, **kwargs):
            starts.append(np.array(init_code))
            assert transform is frame and verts is scan.verts
            return SimpleNamespace(code=init_code + 1.0, detail=None, residual=residuals[len(starts) - 1])

        monkeypatch.setattr(registration, "register_in_frame", fake)
        got = workflows.in_frame_of(basis, first, second, scan)
        assert np.array_equal(starts[0], A) and (len(starts) == 1) == (kept == 0)
        if len(starts) > 1:
            assert np.array_equal(starts[1], B)
        if kept is None:
            assert got is second
        else:
            assert np.allclose(got.code, (A, B)[kept] + 1.0) and got.registration.residual == residuals[kept]
