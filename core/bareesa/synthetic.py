"""Procedural test surfaces: smooth closed meshes the project generates itself.

Used by tests, the demo and benchmarks; no third-party meshes are shipped.
Returns numpy arrays ``verts (N, 3) float64`` and ``faces (F, 3) int64``.
"""

import numpy as np
import trimesh

from .mesh import edge_split


def icosphere(subdivisions=3, radius=1.0):
    """Unit icosphere: -> verts (N, 3), faces (F, 3)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def blob(verts, amplitude=0.2, frequency=2.0, stretch=(1.0, 0.8, 0.6), seed=0):
    """Smooth star-shaped deformation of points on the unit sphere: (N, 3) -> (N, 3).

    The displacement is a deterministic function of position (so two meshes of
    the same sphere at different resolutions sample the *same* surface).
    """
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(4, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    phases = rng.uniform(0, 2 * np.pi, size=4)
    u = verts / np.linalg.norm(verts, axis=1, keepdims=True)
    r = 1.0 + amplitude * np.sin(frequency * u @ dirs.T + phases).mean(axis=1)
    return u * r[:, None] * np.asarray(stretch)


def blob_mesh(subdivisions=3, seed=0, **kwargs):
    """A smooth closed genus-0 surface (deformed, stretched icosphere)."""
    v, f = icosphere(subdivisions)
    return blob(v, seed=seed, **kwargs), f


def torus(n_major=32, n_minor=16, major=1.0, minor=0.35):
    """Regular torus grid mesh: -> verts (n_major*n_minor, 3), faces (2*n_major*n_minor, 3)."""
    u = np.linspace(0, 2 * np.pi, n_major, endpoint=False)
    v = np.linspace(0, 2 * np.pi, n_minor, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    verts = np.stack([(major + minor * np.cos(vv)) * np.cos(uu),
                      (major + minor * np.cos(vv)) * np.sin(uu),
                      minor * np.sin(vv)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    a = i * n_minor + j
    b = ((i + 1) % n_major) * n_minor + j
    c = ((i + 1) % n_major) * n_minor + (j + 1) % n_minor
    d = i * n_minor + (j + 1) % n_minor
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces.astype(np.int64)


def random_rotation(seed=0):
    """A uniformly random rotation matrix (3, 3) with det +1."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# ------------------------------------------------------------------ smooth latent bases


def _smooth_field_params(n_fields, seed):
    rng = np.random.default_rng(seed + 1)
    return {"a": rng.normal(size=(n_fields, 3)), "d": rng.normal(size=(n_fields, 3)),
            "freq": rng.uniform(1.0, 2.0, size=n_fields), "phase": rng.uniform(0, 2 * np.pi, size=n_fields),
            "b": rng.normal(size=(n_fields, 3)), "e": rng.normal(size=(n_fields, 2, 3))}


def smooth_sphere_surface(n_fields=6, seed=0, amplitude=0.12):
    """The smooth map (u (M, 3) unit vectors, alpha (P,)) -> points (M, 3) of a synthetic latent space.

    Template: ``blob(u)`` (a star-shaped stretched sphere); field i:
    amplitude * (a_i sin(f_i u.d_i + phi_i) + b_i (u.e_i)(u.e'_i)), smooth and low-frequency,
    so evaluating it on two different samplings of the sphere gives two meshes
    of (nearly) the same surface F(alpha).
    """
    prm = _smooth_field_params(n_fields, seed)

    def surface(u, alpha=None):
        u = np.asarray(u, dtype=np.float64)
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        out = blob(u, seed=seed)
        if alpha is not None:
            alpha = np.asarray(alpha, dtype=np.float64)
            out = out + np.tensordot(alpha, smooth_sphere_fields(u, prm, amplitude), axes=1)
        return out

    return surface


def smooth_sphere_fields(u, prm, amplitude):
    """Fields of :func:`smooth_sphere_surface` at unit vectors u (M, 3): -> (P, M, 3)."""
    wave = np.sin(prm["freq"][:, None] * (prm["d"] @ u.T) + prm["phase"][:, None])       # (P, M)
    quad = np.einsum("pm,pm->pm", prm["e"][:, 0] @ u.T, prm["e"][:, 1] @ u.T)              # (P, M)
    return amplitude * (wave[:, :, None] * prm["a"][:, None, :] + quad[:, :, None] * prm["b"][:, None, :])


def smooth_sphere_basis(subdivisions=3, n_fields=6, seed=0, amplitude=0.12, schedule=None):
    """A small synthetic latent space sampled on icosphere(subdivisions) -> (Basis, surface).

    ``surface(u, alpha)`` is the generating map of :func:`smooth_sphere_surface`:
    ``surface(*resampled_sphere(...)[0], alpha)`` is a differently meshed copy of
    F(alpha). Metric weights "face"; the schedule is short, for tests.
    """
    from .latent import Basis, Level

    u, faces = icosphere(subdivisions)
    surface = smooth_sphere_surface(n_fields, seed, amplitude)
    prm = _smooth_field_params(n_fields, seed)
    fields = smooth_sphere_fields(u, prm, amplitude)
    template = surface(u)
    if schedule is None:
        schedule = (Level(0.25, 1e3, 1, 60), Level(0.15, 1e6, 2, 100))
    basis = Basis(template=template, faces=faces, fields=fields, groups={"all": (0, n_fields)},
                  weights="face", schedule=schedule, scale=float((template.max(0) - template.min(0)).max()),
                  name=f"smooth_sphere_{n_fields}", units="")
    return basis, surface


def resampled_sphere(subdivisions=3, seed=0, jitter=0.15):
    """A different triangulation of the unit sphere: -> u (N, 3) unit vectors, faces (F, 3).

    The icosphere is randomly rotated, its vertices jittered tangentially by
    ``jitter`` x the mean edge length and renormalised, and the vertex and face
    orders are shuffled, so no vertex or face coincides with the plain icosphere's.
    """
    rng = np.random.default_rng(seed)
    u, faces = icosphere(subdivisions)
    u = u @ random_rotation(seed + 7).T
    edge = np.linalg.norm(u[faces[:, 0]] - u[faces[:, 1]], axis=1).mean()
    u = u + jitter * edge * rng.uniform(-1, 1, size=u.shape)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    perm = rng.permutation(len(u))
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(u))
    return u[perm], inverse[faces][rng.permutation(len(faces))]


def remesh_same_surface(verts, faces, seed=0):
    """A different triangulation of exactly the same piecewise-linear surface: -> (N', 3), (4F, 3).

    Every edge gets a new vertex at a random position along it (30-70%), every
    triangle is split into four, and vertex and face orders are shuffled: three
    quarters of the vertices are new and no face is kept, but the surface is unchanged.
    """
    rng = np.random.default_rng(seed)
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    edges, split = edge_split(faces, len(verts))
    t = rng.uniform(0.3, 0.7, size=(len(edges), 1))
    new = (1 - t) * verts[edges[:, 0]] + t * verts[edges[:, 1]]
    all_verts = np.concatenate([verts, new])
    perm = rng.permutation(len(all_verts))
    rank = np.empty_like(perm)
    rank[perm] = np.arange(len(perm))
    return all_verts[perm], rank[split][rng.permutation(len(split))]


_FREE, _HIP, _KNEE = ((-180, 180),) * 3, ((-130, 30), (-45, 45), (-45, 45)), ((0, 150), (-5, 5), (-5, 5))
#: The joints of ``articulated_figure``: name, centre (3,), parent (-1: the root), range of the rotation
#: vector about each rest axis (degrees): a hip flexes forward (-x), a knee bends back (+x) only
FIGURE_JOINTS = (("root", (0.0, 0.0, 0.9), -1, _FREE),
                 ("shoulder.L", (0.22, 0.0, 1.38), 0, _FREE), ("shoulder.R", (-0.22, 0.0, 1.38), 0, _FREE),
                 ("hip.L", (0.1, 0.0, 0.9), 0, _HIP), ("knee.L", (0.1, 0.0, 0.5), 3, _KNEE),
                 ("hip.R", (-0.1, 0.0, 0.9), 0, _HIP), ("knee.R", (-0.1, 0.0, 0.5), 5, _KNEE))


def _capsule_between(a, b, radius, count=(10, 10)):
    """A capsule mesh from point a to point b (3,): -> (V, 3), (F, 3)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    axis = b - a
    length = float(np.linalg.norm(axis))
    cap = trimesh.creation.capsule(height=length, radius=radius, count=list(count))
    verts = np.asarray(cap.vertices) + [0.0, 0.0, length / 2]  # along +z from the origin
    z = axis / length
    x = np.cross(z, [0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    frame = np.stack([x, np.cross(z, x), z], 1)
    return verts @ frame.T + a, np.asarray(cap.faces, dtype=np.int64)


def articulated_figure():
    """A stick figure of capsules (torso, arms hanging down, thighs, shins) and its skeleton, arms down at
    rest: -> verts (N, 3), faces (F, 3), skinning weights (N, J) (each capsule on one joint), joints (J, 3),
    parents (J,), limits (J, 3, 2) radians (``FIGURE_JOINTS``)."""
    parts = [((0.0, 0.0, 0.85), (0.0, 0.0, 1.45), 0.16, 0), ((0.22, 0.0, 1.36), (0.22, 0.0, 0.86), 0.05, 1),
             ((-0.22, 0.0, 1.36), (-0.22, 0.0, 0.86), 0.05, 2), ((0.1, 0.0, 0.88), (0.1, 0.0, 0.52), 0.07, 3),
             ((0.1, 0.0, 0.48), (0.1, 0.0, 0.1), 0.055, 4), ((-0.1, 0.0, 0.88), (-0.1, 0.0, 0.52), 0.07, 5),
             ((-0.1, 0.0, 0.48), (-0.1, 0.0, 0.1), 0.055, 6)]
    verts, faces, owner = [], [], []
    for a, b, radius, joint in parts:
        v, f = _capsule_between(a, b, radius)
        faces.append(f + sum(len(x) for x in verts))
        verts.append(v)
        owner.append(np.full(len(v), joint))
    owner = np.concatenate(owner)
    weights = np.zeros((len(owner), len(FIGURE_JOINTS)))
    weights[np.arange(len(owner)), owner] = 1.0
    joints = np.array([c for _, c, _, _ in FIGURE_JOINTS])
    parents = np.array([p for _, _, p, _ in FIGURE_JOINTS])
    limits = np.radians([m for *_, m in FIGURE_JOINTS])
    return np.concatenate(verts), np.concatenate(faces), weights, joints, parents, limits


def figure_pose(degrees):
    """Rotation vectors (J, 3) of the figure from {joint: (x, y, z) degrees}: a rotation vector in the
    rest frame's axes (left = +x, facing -y; a hip's -x flexion raises the knee forward)."""
    out = np.zeros((len(FIGURE_JOINTS), 3))
    names = [n for n, *_ in FIGURE_JOINTS]
    for name, rotvec in degrees.items():
        out[names.index(name)] = np.radians(rotvec)
    return out


def articulated_figure_basis(n_train=80, n_fields=60, seed=0, max_degrees=60.0, schedule=None):
    """A small latent space of the articulated figure (``articulated_figure``) with its skeleton in extras:
    pose fields from the PCA of ``n_train`` random poses (each joint's rotation vector drawn inside its
    range, each component at most ``max_degrees``), a short test schedule -> (Basis, posed(rotvecs (J, 3)) -> (N, 3) vertices)."""
    import torch

    from .latent import Basis, Level
    from .registration.articulated import Skeleton, skin

    verts, faces, weights, joints, parents, limits = articulated_figure()
    names = np.array(["|".join(n for n, *_ in FIGURE_JOINTS)])
    skeleton = Skeleton(joints, parents, weights, limits, np.zeros((0, len(joints), 3)), ())
    rest = torch.as_tensor(verts)

    def posed(rotvecs):
        with torch.no_grad():
            return skin(skeleton, rest, torch.as_tensor(np.asarray(rotvecs, dtype=np.float64))).numpy()

    rng = np.random.default_rng(seed)
    reach = np.radians(max_degrees)
    draws = rng.uniform(np.maximum(limits[..., 0], -reach), np.minimum(limits[..., 1], reach),
                        size=(n_train, len(joints), 3))
    draws[:, 0] = 0.0
    offsets = np.stack([posed(d) - verts for d in draws]).reshape(n_train, -1)
    _, _, vt = np.linalg.svd(offsets, full_matrices=False)
    fields = vt[:n_fields].reshape(n_fields, -1, 3) * 0.3
    if schedule is None:
        schedule = (Level(0.2, 1e3, 1, 60), Level(0.08, 1e5, 2, 80), Level(0.04, 1e7, 2, 80))
    extras = {"skeleton_joints": joints, "skeleton_parents": parents, "skinning_weights": weights,
              "skeleton_limits": limits, "skeleton_names": names}
    basis = Basis(template=verts, faces=faces, fields=fields, groups={"pose": (0, n_fields)}, weights="body",
                  schedule=schedule, scale=float(np.ptp(verts[:, 2])), name="figure", units="m", extras=extras)
    return basis, posed
