"""Scan simulator: turn any mesh into a realistic unregistered scan (numpy + trimesh, no bpy).

A scan of a surface differs from a registered mesh of it in every way the
registration must be invariant to: another triangulation (``remesh``), sensor
noise, holes, a partial view (``crop``), an unknown pose and scale (``rigid``,
``scale``) and clutter (a piece of floor under the feet). All amounts are
relative to the mesh size, ``2 x`` the area-weighted RMS radius of the surface
(the size ``bareesa.mesh.normalise`` and ``bareesa.evaluation.default_sigma`` use), so
the same settings fit a 1.7 m body and a unit sphere.

The result is seeded: the same input, options and seed give the same scan;
every random step draws from its own stream, so switching one step on or off
leaves the others unchanged. ``info`` records the similarity applied (a
:class:`~bareesa.transforms.Similarity`), so that a benchmark can map the ground
truth into the scan's frame (:func:`apply_similarity`).

Remeshing (no marching-cubes dependency):

- ``"voxel"``: the surface is subdivided finely and its vertices are clustered
  in the cells of a randomly rotated and shifted grid of pitch
  ``resolution x size``: one vertex per occupied cell, as a voxel remesher gives.
- ``"isotropic"``: the voxel result, then tangential relaxation with
  projection back onto the surface: near-equilateral triangles of about the
  same size.
- ``None``: keep the triangulation (vertex and face orders are still shuffled).
"""

import json
from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .errors import InputError
from .mesh import check_mesh, face_geometry, surface_center_radius, vertex_adjacency
from .transforms import Similarity

REMESH_CHOICES = ("voxel", "isotropic", "none")
UP_AXES = {"x": 0, "y": 1, "z": 2}

#: Defaults of :func:`simulate_scan`; amounts are fractions of the mesh size.
DEFAULTS = dict(remesh="voxel", resolution=0.015, noise=0.001, holes=3, hole_radius=0.04, crop=0.0,
                rigid=True, scale=0.0, clutter=False, up="z", min_component=0.01)


# ------------------------------------------------------------------------------- helpers


def random_rotation_matrix(rng):
    """Uniformly random rotation (3, 3) from a numpy Generator (QR of a Gaussian matrix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _vertex_normals(verts, faces):
    fn = face_geometry(verts, faces)[0]  # area-weighted
    n = np.zeros_like(verts)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(length, 1e-300)


def _compact(verts, faces):
    """Drop unreferenced vertices: -> (verts', faces')."""
    used = np.unique(faces)
    remap = -np.ones(len(verts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return verts[used], remap[faces]


def _clean_faces(faces):
    """Drop faces repeating a vertex and every face whose vertex set occurs twice (collapsed sheets)."""
    f = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    if len(f) == 0:
        return f
    _, inverse, counts = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
    return f[counts[inverse.ravel()] == 1]


def _drop_nonmanifold(faces, max_rounds=5):
    """Remove the faces on edges shared by more than two faces (a scanner's clean-up step)."""
    for _ in range(max_rounds):
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
        bad = (counts[inverse.ravel()] > 2).reshape(-1, 3).any(1)
        if not bad.any():
            break
        faces = faces[~bad]
    return faces


def _drop_small_components(verts, faces, min_fraction):
    """Remove connected pieces with less than ``min_fraction`` of the faces (scan clean-up)."""
    if len(faces) == 0 or min_fraction <= 0:
        return _compact(verts, faces)
    n_comp, labels = connected_components(vertex_adjacency(len(verts), faces), directed=False)
    if n_comp == 1:
        return _compact(verts, faces)
    face_label = labels[faces[:, 0]]
    counts = np.bincount(face_label, minlength=n_comp)
    keep = counts[face_label] >= min_fraction * len(faces)
    return _compact(verts, faces[keep])


def _shuffle(verts, faces, rng):
    perm = rng.permutation(len(verts))
    rank = np.empty_like(perm)
    rank[perm] = np.arange(len(perm))
    faces = rank[faces][rng.permutation(len(faces))]
    # rotate each face's index order (same orientation) so no face keeps its first vertex
    roll = rng.integers(0, 3, size=len(faces))
    idx = (np.arange(3)[None, :] + roll[:, None]) % 3
    return verts[perm], np.take_along_axis(faces, idx, axis=1)


# ------------------------------------------------------------------------------ remeshing


def cluster_remesh(verts, faces, pitch, rng):
    """Vertex clustering on a randomly rotated, shifted grid of cell ``pitch``: -> (N', 3), (F', 3).

    The surface is first subdivided until every edge is shorter than pitch / 3,
    so each occupied cell holds several vertices; each cell's vertices merge
    into their area-weighted mean. Faces on non-manifold edges (where a thin
    part collapsed) are removed, as a scanner's clean-up would.
    """
    fine_v, fine_f = trimesh.remesh.subdivide_to_size(verts, faces, max_edge=pitch / 3.0, max_iter=12)
    fine_v, fine_f = np.asarray(fine_v, dtype=np.float64), np.asarray(fine_f, dtype=np.int64)
    rot = random_rotation_matrix(rng)
    shift = rng.uniform(0.0, pitch, size=3)
    cells = np.floor((fine_v @ rot.T + shift) / pitch).astype(np.int64)
    _, cluster = np.unique(cells, axis=0, return_inverse=True)
    cluster = cluster.ravel()
    n = int(cluster.max()) + 1
    w = np.zeros(len(fine_v))
    area = face_geometry(fine_v, fine_f)[1]
    for k in range(3):
        np.add.at(w, fine_f[:, k], area / 3.0)
    w = np.maximum(w, 1e-30)
    pos = np.zeros((n, 3))
    np.add.at(pos, cluster, fine_v * w[:, None])
    total = np.bincount(cluster, weights=w, minlength=n)
    pos /= total[:, None]
    new_faces = _drop_nonmanifold(_clean_faces(cluster[fine_f]))
    if len(new_faces) == 0:
        raise InputError(f"remeshing at pitch {pitch:.4g} left no faces: the resolution is too coarse "
                         "for this mesh")
    v, f = _compact(pos, new_faces)
    return v, f, (fine_v, fine_f)


def relax_remesh(verts, faces, fine, iterations=8, step=0.5):
    """Tangential Laplacian relaxation projected back onto the fine surface: -> verts (N, 3)."""
    fine_v, fine_f = fine
    fine_n = _vertex_normals(fine_v, fine_f)
    tree = cKDTree(fine_v)
    adj = vertex_adjacency(len(verts), faces)
    deg = np.maximum(np.asarray(adj.sum(1)).ravel(), 1.0)
    v = verts.copy()
    for _ in range(iterations):
        n = _vertex_normals(v, faces)
        lap = adj @ v / deg[:, None] - v
        lap -= (lap * n).sum(1, keepdims=True) * n
        v = v + step * lap
        _, idx = tree.query(v)
        p, pn = fine_v[idx], fine_n[idx]
        v = v - ((v - p) * pn).sum(1, keepdims=True) * pn
    return v


# ----------------------------------------------------------------------------- defects


def cut_holes(verts, faces, n_holes, radius, rng):
    """Remove the faces within ``radius`` of ``n_holes`` area-uniform random surface points."""
    if n_holes <= 0 or radius <= 0:
        return faces
    _, area, centers = face_geometry(verts, faces)
    seeds = centers[rng.choice(len(faces), size=int(n_holes), p=area / area.sum())]
    d = np.linalg.norm(centers[:, None, :] - seeds[None, :, :], axis=2).min(1)
    return faces[d > radius]


def crop_view(verts, faces, fraction, rng):
    """Remove the ``fraction`` of surface area beyond a plane of random direction (a partial view)."""
    if fraction <= 0:
        return faces
    if fraction >= 1:
        raise InputError(f"crop must be a fraction of the surface in [0, 1), got {fraction}")
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    _, area, centers = face_geometry(verts, faces)
    h = centers @ d
    order = np.argsort(-h)
    removed = np.cumsum(area[order]) <= fraction * area.sum()
    keep = np.ones(len(faces), dtype=bool)
    keep[order[removed]] = False
    return faces[keep]


def floor_patch(verts, up, pitch, rng, margin=0.3):
    """A horizontal square grid under the lowest point along axis ``up``: -> (M, 3), (K, 3).

    Normals point up; the patch spans the footprint plus ``margin`` on each side
    and touches the lowest point (feet standing on the floor).
    """
    axes = [a for a in range(3) if a != up]
    lo, hi = verts[:, axes].min(0), verts[:, axes].max(0)
    ext = hi - lo
    lo, hi = lo - margin * ext, hi + margin * ext
    n = np.maximum(np.ceil((hi - lo) / pitch).astype(int), 1)
    g0, g1 = np.meshgrid(np.linspace(lo[0], hi[0], n[0] + 1), np.linspace(lo[1], hi[1], n[1] + 1),
                         indexing="ij")
    pts = np.zeros((g0.size, 3))
    pts[:, axes[0]], pts[:, axes[1]] = g0.ravel(), g1.ravel()
    pts[:, axes] += rng.uniform(-0.2, 0.2, size=(len(pts), 2)) * pitch
    pts[:, up] = verts[:, up].min()
    idx = np.arange(g0.size).reshape(g0.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    # orient so that normals point along +up
    normal_up = face_geometry(pts, tri)[0][:, up]
    tri[normal_up < 0] = tri[normal_up < 0][:, [0, 2, 1]]
    return pts, tri


# ------------------------------------------------------------------------------ public


def scan_similarity(info):
    """The Similarity source frame -> scan frame of a simulate_scan ``info`` (or its JSON copy)."""
    record = info.get("similarity", info)  # a JSON copy without it: rotation, scale, translation
    return record if isinstance(record, Similarity) else Similarity.from_dict(record)


def apply_similarity(info, points):
    """Map points of the source mesh's frame into the scan's frame: (..., 3) -> (..., 3) float64.

    x_scan = scale * R x + t, the :func:`scan_similarity` of ``info``.
    """
    return scan_similarity(info).apply(np.asarray(points, dtype=np.float64))


def undo_similarity(info, points):
    """Inverse of :func:`apply_similarity`: scan frame -> source frame, (..., 3) -> (..., 3) float64."""
    return scan_similarity(info).invert(np.asarray(points, dtype=np.float64))


def simulate_scan(verts, faces, seed=0, remesh=DEFAULTS["remesh"], resolution=DEFAULTS["resolution"],
                  noise=DEFAULTS["noise"], holes=DEFAULTS["holes"], hole_radius=DEFAULTS["hole_radius"],
                  crop=DEFAULTS["crop"], rigid=DEFAULTS["rigid"], scale=DEFAULTS["scale"],
                  clutter=DEFAULTS["clutter"], up=DEFAULTS["up"], min_component=DEFAULTS["min_component"]):
    """A simulated unregistered scan of a mesh: (N, 3), (F, 3) -> verts (N', 3), faces (F', 3), info dict.

    remesh: "voxel" | "isotropic" | None (keep the triangulation); resolution:
    remeshing pitch; noise: std of the Gaussian vertex noise; holes: number of
    holes of radius hole_radius; crop: fraction of the surface area cut away by
    a random plane; rigid: apply a uniformly random rotation and a translation of
    up to one size; scale: the scale factor is drawn log-uniformly in
    [1 / (1 + scale), 1 + scale]; clutter: add a floor patch under the lowest
    point along axis ``up`` ("x", "y" or "z"); min_component: pieces with fewer
    faces than this fraction are dropped. Lengths are fractions of the mesh size
    (2 x RMS radius). ``info`` holds similarity (the Similarity x_scan = scale R x + t,
    applied last) and its rotation (3, 3), translation (3,), scale and matrix (4, 4),
    size, pitch, the options and counts; JSON-able through :func:`info_to_json`.
    """
    verts, faces = check_mesh(verts, faces, "input mesh")
    remesh = None if remesh in (None, "none") else remesh
    if remesh not in (None, "voxel", "isotropic"):
        raise InputError(f"remesh must be one of {', '.join(REMESH_CHOICES)}, got {remesh!r}")
    if up not in UP_AXES:
        raise InputError(f"up must be one of x, y, z, got {up!r}")
    for name, value in (("resolution", resolution), ("noise", noise), ("hole_radius", hole_radius),
                        ("crop", crop), ("scale", scale), ("min_component", min_component)):
        if not (np.isfinite(value) and value >= 0):
            raise InputError(f"{name} must be a non-negative number, got {value}")
    if remesh and not resolution > 0:
        raise InputError("resolution must be positive when remeshing")
    if crop >= 1:
        raise InputError(f"crop must be a fraction of the surface in [0, 1), got {crop}")
    if int(holes) != holes or holes < 0:
        raise InputError(f"holes must be a non-negative integer, got {holes}")
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(8)]
    _, radius = surface_center_radius(verts, faces)
    size = 2.0 * radius
    pitch = resolution * size

    v, f = verts.copy(), faces.copy()
    if remesh:
        v, f, fine = cluster_remesh(v, f, pitch, streams[0])
        if remesh == "isotropic":
            v = relax_remesh(v, f, fine)
    if noise > 0:
        v = v + streams[1].normal(scale=noise * size, size=v.shape)
    f = cut_holes(v, f, int(holes), hole_radius * size, streams[2])
    f = crop_view(v, f, crop, streams[3])
    if len(f) == 0:
        raise InputError("holes and crop removed the whole surface: use fewer or smaller defects")
    v, f = _drop_small_components(v, f, min_component)
    n_object = len(v)
    if clutter:
        fv, ff = floor_patch(v, UP_AXES[up], max(2 * pitch, 0.04 * size), streams[4])
        f = np.concatenate([f, ff + len(v)])
        v = np.concatenate([v, fv])
    rot = random_rotation_matrix(streams[5]) if rigid else np.eye(3)
    trans = streams[5].uniform(-1.0, 1.0, size=3) * size if rigid else np.zeros(3)
    factor = float(np.exp(streams[6].uniform(-1.0, 1.0) * np.log1p(scale))) if scale > 0 else 1.0
    v, f = _shuffle(v, f, streams[7])
    similarity = Similarity(rot, factor, trans)
    info = {"seed": int(seed), "similarity": similarity, "rotation": similarity.rotation,
            "translation": similarity.translation, "scale": similarity.scale, "matrix": similarity.matrix(),
            "size": float(size), "pitch": float(pitch) if remesh else None,
            "options": {"remesh": remesh or "none", "resolution": float(resolution), "noise": float(noise),
                        "holes": int(holes), "hole_radius": float(hole_radius), "crop": float(crop),
                        "rigid": bool(rigid), "scale": float(scale), "clutter": bool(clutter), "up": up,
                        "min_component": float(min_component)},
            "n_vertices": int(len(v)), "n_faces": int(len(f)), "n_object_vertices": int(n_object),
            "n_clutter_vertices": int(len(v) - n_object)}
    info["similarity_note"] = "x_scan = scale * rotation @ x + translation (applied to the noisy, cut surface)"
    return similarity.apply(v), f, info


def info_to_json(info):
    """JSON-able copy of a simulate_scan ``info`` dict (arrays to lists, the Similarity to its dict)."""
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v.to_dict() if isinstance(v, Similarity) else v)
            for k, v in info.items()}


# ------------------------------------------------------------------------ command line


def add_simulate_scan_arguments(parser):
    """Add the options of ``bareesa simulate-scan IN -o OUT`` to an argparse parser."""
    d = DEFAULTS
    parser.add_argument("input", type=Path, help="mesh to scan (PLY, OBJ, STL)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="scan to write (.ply or .obj)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--remesh", choices=REMESH_CHOICES, default=d["remesh"],
                        help=f"new triangulation (default {d['remesh']})")
    parser.add_argument("--resolution", type=float, default=d["resolution"],
                        help=f"remeshing pitch, fraction of the mesh size (default {d['resolution']})")
    parser.add_argument("--noise", type=float, default=d["noise"],
                        help=f"vertex noise std, fraction of the mesh size (default {d['noise']})")
    parser.add_argument("--holes", type=int, default=d["holes"], help=f"number of holes (default {d['holes']})")
    parser.add_argument("--hole-radius", type=float, default=d["hole_radius"],
                        help=f"hole radius, fraction of the mesh size (default {d['hole_radius']})")
    parser.add_argument("--crop", type=float, default=d["crop"],
                        help="fraction of the surface area cut away by a random plane (default 0)")
    parser.add_argument("--no-rigid", dest="rigid", action="store_false",
                        help="keep the mesh's position and orientation (default: random rigid motion)")
    parser.add_argument("--scale", type=float, default=d["scale"],
                        help="random scale factor in [1/(1+S), 1+S] (default 0: keep the size)")
    parser.add_argument("--clutter", action="store_true", help="add a piece of floor under the lowest point")
    parser.add_argument("--up", choices=sorted(UP_AXES), default=d["up"],
                        help=f"up axis for --clutter (default {d['up']})")
    parser.add_argument("--info", type=Path, default=None,
                        help="also write the applied transform and options as JSON to this file")
    return parser


def simulate_scan_cli(args):
    """Run ``bareesa simulate-scan`` from parsed arguments: -> info dict (JSON-able)."""
    from .mesh import load_mesh, save_mesh

    verts, faces = load_mesh(args.input)
    v, f, info = simulate_scan(verts, faces, seed=args.seed, remesh=args.remesh, resolution=args.resolution,
                               noise=args.noise, holes=args.holes, hole_radius=args.hole_radius, crop=args.crop,
                               rigid=args.rigid, scale=args.scale, clutter=args.clutter, up=args.up)
    save_mesh(args.output, v, f)
    out = info_to_json(info)
    out.update(input=str(args.input), output=str(args.output))
    if args.info is not None:
        args.info.parent.mkdir(parents=True, exist_ok=True)
        args.info.write_text(json.dumps(out, indent=2) + "\n")
    return out
