"""Tests of bareesa.mesh: file round trips, validation errors/warnings, normalisation."""

import json
import os
import warnings

import numpy as np
import pytest
import torch
import trimesh

from bareesa.errors import MeshError
from bareesa.mesh import (MeshWarning, Normalisation, as_tensor, face_geometry, load_mesh, normalise,
                          save_mesh, smoothed_normals, surface_center_radius, validate_mesh, winding_parity)
from bareesa.synthetic import blob_mesh, icosphere, random_rotation


def _shuffled_sphere(seed=0):
    """An icosphere with randomly permuted vertices, so that any reordering shows."""
    v, f = icosphere(1)
    perm = np.random.default_rng(seed).permutation(len(v))
    inv = np.argsort(perm)
    return v[perm] + 0.01 * np.random.default_rng(seed).normal(size=v.shape), inv[f]


def _write(path, text):
    path.write_text(text)
    return path


QUAD_PLY = """ply
format ascii 1.0
element vertex 6
property float x
property float y
property float z
element face 2
property list uchar int vertex_indices
end_header
0 0 0
1 0 0
1 1 0
0 1 0
2 0 0
2 1 0
4 0 1 2 3
4 1 4 5 2
"""

QUAD_OBJ = """# quads with texture coordinates and a seam, two objects and materials
mtllib missing.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
v 2 1 0
v 9 9 9
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
o first
usemtl a
f 1/1/1 2/2/1 3/3/1 4/4/1
o second
usemtl b
f 2/1/1 5/2/1 6/3/1 3/4/1
"""


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("name,binary", [("m.ply", True), ("m.ply", False), ("m.obj", True)])
def test_save_load_roundtrip_keeps_vertex_order_and_faces_exactly(tmp_path, name, binary):
    v, f = _shuffled_sphere()
    v = np.vstack([v, [[5.0, 5.0, 5.0]]])  # an unreferenced vertex must survive too
    save_mesh(tmp_path / name, v, f, binary=binary)
    v2, f2 = load_mesh(tmp_path / name)
    assert v2.dtype == np.float64 and f2.dtype == np.int64
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)


def test_ply_binary_file_is_binary_and_ascii_is_text(tmp_path):
    v, f = _shuffled_sphere()
    save_mesh(tmp_path / "b.ply", v, f, binary=True)
    save_mesh(tmp_path / "a.ply", v, f, binary=False)
    assert b"binary_little_endian" in (tmp_path / "b.ply").read_bytes()[:100]
    assert b"format ascii" in (tmp_path / "a.ply").read_bytes()[:100]


@pytest.mark.parametrize("binary", [True, False])
def test_stl_roundtrip_welds_corners_in_first_appearance_order(tmp_path, binary):
    v, f = _shuffled_sphere()
    v = v.astype(np.float32).astype(np.float64)  # STL stores float32
    save_mesh(tmp_path / "m.stl", v, f, binary=binary)
    v2, f2 = load_mesh(tmp_path / "m.stl")
    first_seen = list(dict.fromkeys(f.reshape(-1).tolist()))  # vertex ids by first appearance
    np.testing.assert_array_equal(v2, v[first_seen])
    np.testing.assert_array_equal(v2[f2], v[f])  # same triangles, same face order


def test_stl_without_weld_is_triangle_soup(tmp_path):
    v, f = _shuffled_sphere()
    save_mesh(tmp_path / "m.stl", v, f)
    v2, f2 = load_mesh(tmp_path / "m.stl", weld_stl=False)
    assert v2.shape == (3 * len(f), 3)
    np.testing.assert_array_equal(f2, np.arange(3 * len(f)).reshape(-1, 3))
    np.testing.assert_allclose(v2, v[f].reshape(-1, 3), atol=1e-6)


def test_load_off_keeps_vertex_order(tmp_path):
    path = _write(tmp_path / "m.off", "OFF\n4 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 2 1 0\n3 0 3 2\n")
    v, f = load_mesh(path)
    np.testing.assert_array_equal(v, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    np.testing.assert_array_equal(f, [[2, 1, 0], [0, 3, 2]])


def test_save_leaves_no_partial_file_on_failure(tmp_path):
    v, f = _shuffled_sphere()
    target = tmp_path / "m.ply"
    with pytest.raises(MeshError):
        save_mesh(target, v, f + len(v))  # invalid indices: nothing may be written
    assert list(tmp_path.iterdir()) == []
    save_mesh(target, v, f)
    assert [p.name for p in tmp_path.iterdir()] == ["m.ply"]  # no temp file left behind


def test_save_overwrites_existing_file_atomically(tmp_path):
    v, f = _shuffled_sphere()
    save_mesh(tmp_path / "m.obj", v, f)
    save_mesh(tmp_path / "m.obj", 2 * v, f)
    np.testing.assert_array_equal(load_mesh(tmp_path / "m.obj")[0], 2 * v)


def test_save_unknown_extension_or_missing_folder_raises(tmp_path):
    v, f = _shuffled_sphere()
    with pytest.raises(MeshError, match="glb"):
        save_mesh(tmp_path / "m.glb", v, f)
    with pytest.raises(MeshError, match="does not exist"):
        save_mesh(tmp_path / "nope" / "m.ply", v, f)


# ------------------------------------------------------------ polygons, scenes


def test_quad_ply_is_fan_triangulated_with_vertices_kept(tmp_path):
    v, f = load_mesh(_write(tmp_path / "q.ply", QUAD_PLY))
    assert v.shape == (6, 3)
    # fan triangles (a, b, c), (c, d, a); all first triangles, then all second ones
    np.testing.assert_array_equal(f, [[0, 1, 2], [1, 4, 5], [2, 3, 0], [5, 2, 1]])


def test_quad_obj_with_uv_seams_keeps_every_vertex_in_order(tmp_path):
    v, f = load_mesh(_write(tmp_path / "q.obj", QUAD_OBJ))
    np.testing.assert_array_equal(v[:, 0], [0, 1, 1, 0, 2, 2, 9])  # unreferenced v 7 kept
    np.testing.assert_array_equal(f, [[0, 1, 2], [1, 4, 5], [2, 3, 0], [5, 2, 1]])


def test_mixed_triangle_quad_ply_triangles_come_first(tmp_path):
    text = QUAD_PLY.replace("element vertex 6", "element vertex 7").replace(
        "element face 2", "element face 3").replace("2 1 0\n4 0", "2 1 0\n0 2 0\n4 0") + "3 3 2 6\n"
    v, f = load_mesh(_write(tmp_path / "m.ply", text))
    assert v.shape == (7, 3) and v[6].tolist() == [0, 2, 0]
    np.testing.assert_array_equal(f, [[3, 2, 6], [0, 1, 2], [1, 4, 5], [2, 3, 0], [5, 2, 1]])


def test_multi_solid_stl_raises_naming_the_parts(tmp_path):
    solid = ("solid {0}\nfacet normal 0 0 1\nouter loop\nvertex 0 0 {1}\nvertex 1 0 {1}\n"
             "vertex 0 1 {1}\nendloop\nendfacet\nendsolid {0}\n")
    path = _write(tmp_path / "two.stl", solid.format("partA", 0) + solid.format("partB", 1))
    with pytest.raises(MeshError, match=r"two\.stl.*2 separate meshes.*partA"):
        load_mesh(path)


# ------------------------------------------------------------------ load errors


def test_load_missing_file_raises_with_name(tmp_path):
    with pytest.raises(MeshError, match=r"nothere\.ply.*no such file"):
        load_mesh(tmp_path / "nothere.ply")


def test_load_unknown_extension_raises(tmp_path):
    path = _write(tmp_path / "m.xyz", "0 0 0\n")
    with pytest.raises(MeshError, match=r"m\.xyz.*\.xyz"):
        load_mesh(path)


def test_load_garbage_ply_raises_with_name(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_bytes(b"this is not a ply file\x00\x01\x02")
    with pytest.raises(MeshError, match=r"bad\.ply"):
        load_mesh(path)


@pytest.mark.parametrize("name,text", [
    ("pc.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
    ("pc.ply", "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
               "property float z\nend_header\n0 0 0\n1 0 0\n"),
])
def test_load_point_cloud_raises_no_faces(tmp_path, name, text):
    with pytest.raises(MeshError, match=name.replace(".", r"\.") + ".*no faces"):
        load_mesh(_write(tmp_path / name, text))


def test_load_validates_indices(tmp_path):
    path = _write(tmp_path / "m.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n")
    with pytest.raises(MeshError, match=r"m\.obj"):
        load_mesh(path)


# ------------------------------------------------------------------- validation


def test_validate_report_counts_on_open_mesh_with_unreferenced_vertex():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [7, 7, 7]], dtype=float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rep = validate_mesh(v, f)
    assert (rep.n_verts, rep.n_faces, rep.n_degenerate_faces, rep.n_nonmanifold_edges,
            rep.n_boundary_edges, rep.n_unreferenced_verts) == (5, 2, 0, 0, 4, 1)


def test_validate_closed_sphere_has_no_boundary():
    rep = validate_mesh(*icosphere(2))
    assert rep.n_boundary_edges == 0 and rep.n_nonmanifold_edges == 0


@pytest.mark.parametrize("verts,faces,pattern", [
    (np.zeros((4, 2)), np.array([[0, 1, 2]]), r"vertices must be a real \(N, 3\).*\(4, 2\)"),
    (np.array([["a", "b", "c"]]), np.array([[0, 0, 0]]), "vertices must be a real"),
    (np.zeros((4, 3)), np.array([[0, 1, 2, 3]]), r"faces must be an integer \(F, 3\).*triangul"),
    (np.zeros((4, 3)), np.array([[0.0, 1.0, 2.0]]), "faces must be an integer.*float64"),
    (np.zeros((0, 3)), np.zeros((0, 3), dtype=int), r"empty mesh \(0 vertices, 0 faces\)"),
    (np.zeros((3, 3)), np.zeros((0, 3), dtype=int), r"empty mesh \(3 vertices, 0 faces\)"),
])
def test_validate_rejects_bad_shapes_dtypes_and_empty(verts, faces, pattern):
    with pytest.raises(MeshError, match=pattern):
        validate_mesh(verts, faces, name="thing")


def test_validate_nonfinite_reports_count_and_first_index():
    v, f = icosphere(1)
    v[[5, 9, 30]] = [np.nan, np.inf, -np.inf]
    with pytest.raises(MeshError, match=r"scan: 3 vertices have NaN/Inf.*first: vertex 5"):
        validate_mesh(v, f, name="scan")


def test_validate_index_out_of_range_names_face():
    v, f = icosphere(1)
    f[7, 1] = len(v)
    f[11, 0] = -1
    with pytest.raises(MeshError, match=r"2 faces use vertex indices outside 0\.\.41.*face 7"):
        validate_mesh(v, f)


def test_validate_repeated_indices_reports_count_and_first():
    v, f = icosphere(1)
    f[3] = [4, 4, 5]
    f[8] = [6, 7, 6]
    with pytest.raises(MeshError, match=r"2 faces repeat a vertex.*first: face 3 = \[4, 4, 5\]"):
        validate_mesh(v, f)


def test_validate_warns_degenerate_faces_with_count():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 1, 3], [1, 3, 4]])  # two collinear (zero-area) faces
    with pytest.warns(MeshWarning, match="2 degenerate"):
        rep = validate_mesh(v, f)
    assert rep.n_degenerate_faces == 2


def test_validate_warns_nonmanifold_edges_with_count():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge 0-1 shared by three faces
    with pytest.warns(MeshWarning, match="1 non-manifold edges"):
        rep = validate_mesh(v, f)
    assert rep.n_nonmanifold_edges == 1 and rep.n_degenerate_faces == 0


def test_validate_accepts_torch_tensors():
    v, f = as_tensor(*icosphere(1))
    assert validate_mesh(v, f).n_faces == 80


def test_as_tensor_dtypes():
    v, f = as_tensor(*icosphere(1), dtype=torch.float32)
    assert v.dtype == torch.float32 and f.dtype == torch.long and v.shape == (42, 3)


# ---------------------------------------------------------------- normalisation


def test_normalise_invert_is_identity_numpy_and_torch():
    v, f = blob_mesh(2)
    v = 37.0 * v @ random_rotation(1).T + np.array([10.0, -4.0, 2.5])
    vn, norm = normalise(v, f, size=2.0)
    np.testing.assert_allclose(norm.invert(vn), v, rtol=0, atol=1e-12)
    t = torch.as_tensor(vn, dtype=torch.float64)
    back = norm.invert(t)
    assert isinstance(back, torch.Tensor)
    np.testing.assert_allclose(back.numpy(), v, atol=1e-12)
    np.testing.assert_allclose(norm.apply(torch.as_tensor(v)).numpy(), vn, atol=1e-12)


def test_normalise_gives_zero_centre_and_rms_radius_half_size():
    v, f = blob_mesh(3)
    vn, norm = normalise(5.0 * v + 3.0, f, size=1.0)
    center, radius = surface_center_radius(vn, f)
    np.testing.assert_allclose(center, 0.0, atol=1e-12)
    assert radius == pytest.approx(0.5, rel=1e-12)


def test_normalisation_centre_and_scale_are_remeshing_robust():
    v3, f3 = blob_mesh(3)
    v5, f5 = blob_mesh(5)
    _, n3 = normalise(v3, f3)
    _, n5 = normalise(v5, f5)
    assert np.linalg.norm(n3.center - n5.center) < 1e-3 * n5.scale
    assert n3.scale == pytest.approx(n5.scale, rel=5e-3)


def test_normalisation_ignores_unreferenced_outlier_vertex():
    v, f = blob_mesh(3)
    _, n = normalise(v, f)
    _, n_out = normalise(np.vstack([v, [[100.0, 0, 0]]]), f)
    np.testing.assert_array_equal(n.center, n_out.center)
    assert n.scale == n_out.scale


def test_normalisation_dict_roundtrip_through_json():
    _, norm = normalise(*blob_mesh(2))
    back = Normalisation.from_dict(json.loads(json.dumps(norm.to_dict())))
    np.testing.assert_array_equal(back.center, norm.center)
    assert back.scale == norm.scale


def test_normalisation_is_immutable():
    _, norm = normalise(*blob_mesh(2))
    with pytest.raises(Exception):
        norm.scale = 2.0
    with pytest.raises(ValueError):
        norm.center[0] = 1.0


def test_normalise_zero_area_raises():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], dtype=float)
    with pytest.raises(MeshError, match="zero surface area"):
        normalise(v, np.array([[0, 1, 2]]))


def test_files_written_are_only_the_target(tmp_path):
    v, f = _shuffled_sphere()
    for ext in ("ply", "obj", "stl"):
        save_mesh(os.fspath(tmp_path / f"m.{ext}"), v, f)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.obj", "m.ply", "m.stl"]


def _directed_edge_agreement(faces):
    """Share of the edges between two faces that the faces run through in opposite directions."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inner = counts[inverse.ravel()] == 2
    forward = directed[:, 0] < directed[:, 1]
    per_edge = np.bincount(inverse.ravel()[inner], weights=forward[inner].astype(float))
    return float((per_edge[counts == 2] == 1).mean())


def test_winding_parity_makes_randomly_flipped_faces_consistent_piece_by_piece():
    v, f = icosphere(3)
    other = f + len(v)  # a second, disjoint sphere
    faces = np.concatenate([f, other])
    flip = np.random.default_rng(0).random(len(faces)) < 0.4
    faces[flip] = faces[flip][:, ::-1]
    assert _directed_edge_agreement(faces) < 0.7
    parity, pieces = winding_parity(faces)
    assert set(np.unique(parity)) <= {-1, 1} and len(np.unique(pieces)) == 2
    assert (pieces[:len(f)] == pieces[0]).all() and (pieces[len(f):] == pieces[len(f)]).all()
    fixed = faces.copy()
    fixed[parity < 0] = fixed[parity < 0][:, ::-1]
    assert _directed_edge_agreement(fixed) == 1.0
    # each piece is either all as the original or all reversed
    for piece in (slice(0, len(f)), slice(len(f), None)):
        same = ~(flip[piece] ^ (parity[piece] < 0))
        assert same.all() or not same.any()


def test_winding_parity_of_a_consistent_mesh_turns_nothing():
    v, f = blob_mesh(2)
    parity, pieces = winding_parity(f)
    assert (parity == 1).all() and (pieces == 0).all()


def test_smoothed_normals_of_a_noisy_sphere_point_outwards_and_keep_its_area():
    v, f = icosphere(4)
    noisy = v + 0.01 * np.random.default_rng(1).normal(size=v.shape)
    vectors, areas, centres = face_geometry(noisy, f)
    normals, projected = smoothed_normals(noisy, f, rings=2)
    radial = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    raw_angle = np.arccos(np.clip(np.einsum("fk,fk->f", vectors / areas[:, None], radial), -1, 1)).mean()
    smooth_angle = np.arccos(np.clip(np.einsum("fk,fk->f", normals, radial), -1, 1)).mean()
    assert smooth_angle < 0.5 * raw_angle
    clean_area = face_geometry(v, f)[1].sum()
    assert areas.sum() > 1.01 * clean_area  # noise inflates the area ...
    assert abs(projected.sum() - clean_area) < 0.6 * (areas.sum() - clean_area)  # ... the projected far less
    flipped = f.copy()
    flipped[::2] = flipped[::2][:, ::-1]
    assert np.allclose(smoothed_normals(noisy, flipped, rings=2)[1], projected)


def _two_spheres(offset):
    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=2)
    b.apply_translation((offset, 0.1, 0.05))
    both = trimesh.util.concatenate([a, b])
    return np.asarray(both.vertices), np.asarray(both.faces)


def test_self_intersections_are_the_face_pairs_blender_finds():
    import bpy  # noqa: F401  (puts bpy's mathutils on the path)
    from mathutils.bvhtree import BVHTree

    from bareesa.mesh import self_intersections

    sphere = trimesh.creation.icosphere(subdivisions=3)
    assert self_intersections(sphere.vertices, sphere.faces).shape == (0, 2)
    assert len(self_intersections(*_two_spheres(2.5))) == 0  # apart
    verts, faces = _two_spheres(1.2)  # the spheres run through each other along a circle
    pairs = self_intersections(verts, faces)
    assert len(pairs) > 20 and (pairs[:, 0] < pairs[:, 1]).all()
    half = len(faces) // 2
    assert ((pairs[:, 0] < half) & (pairs[:, 1] >= half)).all()  # always one face of each sphere
    tree = BVHTree.FromPolygons(verts.tolist(), faces.tolist(), epsilon=0.0)
    shared = [set(f) for f in faces.tolist()]
    blender = {(min(i, j), max(i, j)) for i, j in tree.overlap(tree) if i != j and not shared[i] & shared[j]}
    assert {tuple(p) for p in pairs.tolist()} == blender
