"""Tests of bareesa.scan_simulator: seeded, really remeshed, defects as asked, transform recorded."""

import argparse
import json

import numpy as np
import pytest

from bareesa.errors import InputError
from bareesa.evaluation import chamfer
from bareesa.mesh import load_mesh, save_mesh, surface_center_radius, validate_mesh
from bareesa.scan_simulator import (add_simulate_scan_arguments, apply_similarity, info_to_json, simulate_scan,
                                    simulate_scan_cli, undo_similarity)
from bareesa.synthetic import blob_mesh
from bareesa.transforms import Similarity


@pytest.fixture(scope="module")
def blob():
    return blob_mesh(3)


def _area(v, f):
    p = v[f]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()


def test_same_seed_gives_identical_scan_and_other_seed_differs(blob):
    a = simulate_scan(*blob, seed=3, resolution=0.04)
    b = simulate_scan(*blob, seed=3, resolution=0.04)
    c = simulate_scan(*blob, seed=4, resolution=0.04)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert a[0].shape != c[0].shape or not np.allclose(a[0], c[0])


@pytest.mark.parametrize("remesh", ["voxel", "isotropic"])
def test_remesh_changes_triangulation_but_keeps_the_surface(blob, remesh):
    v, f = blob
    sv, sf, info = simulate_scan(v, f, seed=0, remesh=remesh, noise=0, holes=0, resolution=0.03)
    assert validate_mesh(sv, sf).n_nonmanifold_edges == 0
    back = undo_similarity(info, sv)
    assert len(sv) != len(v)
    # no scan vertex coincides with an input vertex
    d = np.linalg.norm(back[:, None] - v[None], axis=2).min(1)
    assert (d > 1e-6).mean() > 0.99
    # ... but the surface is the same: every point close to the input
    assert chamfer(back, v) < 0.05 * info["size"]
    assert abs(_area(back, sf) / _area(v, f) - 1) < 0.1


def test_isotropic_remesh_has_more_regular_triangles_than_voxel(blob):
    def spread(remesh):
        sv, sf, _ = simulate_scan(*blob, seed=0, remesh=remesh, noise=0, holes=0, resolution=0.03)
        e = np.linalg.norm(sv[sf] - sv[sf[:, [1, 2, 0]]], axis=2)
        return e.std() / e.mean()

    assert spread("isotropic") < spread("voxel")


def test_rigid_motion_and_scale_are_recorded_exactly(blob):
    v, f = blob
    sv, sf, info = simulate_scan(v, f, seed=5, remesh=None, noise=0, holes=0, scale=0.3)
    assert not np.allclose(info["rotation"], np.eye(3))
    assert np.allclose(info["rotation"] @ info["rotation"].T, np.eye(3))
    assert 1 / 1.3 <= info["scale"] <= 1.3 and info["scale"] != 1.0
    # without remeshing the scan is a shuffled copy: undoing the similarity finds every vertex
    back = undo_similarity(info, sv)
    d = np.linalg.norm(back[:, None] - v[None], axis=2).min(1)
    assert d.max() < 1e-9
    assert np.allclose(apply_similarity(info, back), sv)
    assert np.allclose(info["matrix"][:3, :3], info["scale"] * info["rotation"])


def test_info_carries_one_similarity_that_survives_json(blob):
    v, f = blob
    sv, _, info = simulate_scan(v, f, seed=5, remesh=None, noise=0, holes=0, scale=0.3)
    assert isinstance(info["similarity"], Similarity)
    assert np.array_equal(info["matrix"], info["similarity"].matrix())
    copy = json.loads(json.dumps(info_to_json(info)))
    assert np.allclose(apply_similarity(copy, v), apply_similarity(info, v), rtol=0, atol=1e-12)
    assert np.allclose(undo_similarity(copy, sv), undo_similarity(info, sv), rtol=0, atol=1e-12)
    older = {k: x for k, x in copy.items() if k != "similarity"}  # rotation, scale, translation only
    assert np.allclose(apply_similarity(older, v), apply_similarity(info, v), rtol=0, atol=1e-12)


def test_no_rigid_keeps_the_frame(blob):
    v, f = blob
    sv, _, info = simulate_scan(v, f, seed=1, remesh=None, noise=0, holes=0, rigid=False)
    assert np.allclose(info["rotation"], np.eye(3)) and np.allclose(info["translation"], 0)
    assert np.allclose(np.sort(sv, axis=0), np.sort(v, axis=0))


def test_holes_and_crop_remove_the_asked_amount_of_surface(blob):
    v, f = blob
    full = simulate_scan(v, f, seed=2, remesh=None, noise=0, holes=0)
    holed = simulate_scan(v, f, seed=2, remesh=None, noise=0, holes=4, hole_radius=0.1)
    cropped = simulate_scan(v, f, seed=2, remesh=None, noise=0, holes=0, crop=0.3)
    assert validate_mesh(*full[:2]).n_boundary_edges == 0
    assert validate_mesh(*holed[:2]).n_boundary_edges > 0
    a = _area(*full[:2])
    assert _area(*holed[:2]) < 0.97 * a
    assert 0.6 < _area(*cropped[:2]) / a < 0.75


def test_noise_is_of_the_requested_size(blob):
    v, f = blob
    sv, _, info = simulate_scan(v, f, seed=0, remesh=None, holes=0, noise=0.01, rigid=False)
    clean, _, _ = simulate_scan(v, f, seed=0, remesh=None, holes=0, noise=0.0, rigid=False)
    rms = np.sqrt(((sv - clean) ** 2).sum(1).mean() / 3)
    assert abs(rms / (0.01 * info["size"]) - 1) < 0.1


def test_clutter_adds_an_upward_floor_under_the_lowest_point(blob):
    v, f = blob
    sv, sf, info = simulate_scan(v, f, seed=0, remesh=None, holes=0, noise=0, rigid=False, clutter=True, up="y")
    assert info["n_clutter_vertices"] > 0
    low = np.isclose(sv[:, 1], v[:, 1].min())
    assert low.sum() >= info["n_clutter_vertices"]
    p = sv[sf]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flat = np.isclose(p[:, :, 1], v[:, 1].min()).all(1)
    assert flat.any() and (n[flat, 1] > 0).all()


def test_amounts_are_relative_to_mesh_size(blob):
    v, f = blob
    a = simulate_scan(v, f, seed=0, resolution=0.03, holes=2)
    b = simulate_scan(10 * v, f, seed=0, resolution=0.03, holes=2)
    assert a[0].shape == b[0].shape and a[1].shape == b[1].shape
    assert np.isclose(b[2]["size"], 10 * a[2]["size"])


@pytest.mark.parametrize("kwargs", [dict(remesh="marching"), dict(noise=-1), dict(crop=1.0), dict(up="w"),
                                    dict(holes=1.5)])
def test_bad_options_raise_input_error(blob, kwargs):
    with pytest.raises(InputError):
        simulate_scan(*blob, **kwargs)


def test_cli_function_writes_scan_and_info(blob, tmp_path):
    save_mesh(tmp_path / "in.ply", *blob)
    parser = add_simulate_scan_arguments(argparse.ArgumentParser())
    args = parser.parse_args([str(tmp_path / "in.ply"), "-o", str(tmp_path / "scan.ply"), "--seed", "7",
                              "--remesh", "isotropic", "--resolution", "0.04", "--info", str(tmp_path / "info.json"), "--clutter"])
    out = simulate_scan_cli(args)
    v, f = load_mesh(tmp_path / "scan.ply")
    info = json.loads((tmp_path / "info.json").read_text())
    assert len(v) == out["n_vertices"] == info["n_vertices"] and info["seed"] == 7
    assert np.asarray(info["matrix"]).shape == (4, 4)
    assert surface_center_radius(v, f)[1] > 0
