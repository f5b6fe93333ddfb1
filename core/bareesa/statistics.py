"""Shape statistics in latent space (paper sections 4.4, 4.5 and 5.2).

Motion transfer (swap the identity coefficients), the log map at the template
(initial velocities of boundary-value geodesics), Gaussian mixtures on those
velocities (scikit-learn) with sampling and shooting, and the training
statistics a basis stores (distribution, pose prototypes).
"""

import numpy as np

from .errors import InputError
from .geodesics import geodesic
from .latent import project_to_basis
from .progress import Monitor
from .shooting import initial_velocity, shoot
from .threads import with_one_blas_thread


def transfer_motion(frame_codes, identity_code, identity_slice):
    """Replace the identity coefficients of every frame: (T, P), (P,), slice -> (T, P)."""
    frames = np.array(frame_codes, dtype=np.float64)
    identity = np.asarray(identity_code, dtype=np.float64)
    if frames.ndim != 2 or identity.shape != frames.shape[1:]:
        raise InputError(f"frame codes (T, P) and an identity code (P,) are needed, got {frames.shape} "
                         f"and {identity.shape}")
    frames[:, identity_slice] = identity[identity_slice]
    return frames


@with_one_blas_thread
def log_map(template, faces, fields, codes, weights, steps=6, callback=None, cancel=None):
    """Initial velocities at the template (code 0) of the geodesics to each code: (M, P) -> (M, P)."""
    codes = np.atleast_2d(np.asarray(codes, dtype=np.float64))
    monitor = Monitor("log map", callback, cancel)
    out = []
    for i, code in enumerate(codes):
        monitor.report(i / len(codes), f"geodesic {i + 1}/{len(codes)}")
        g = geodesic(template, faces, fields, np.zeros_like(code), code, weights, steps=steps, cancel=cancel)
        out.append(initial_velocity(g.path))
    monitor.report(1.0, "done")
    return np.stack(out)


def fit_distribution(velocities, groups, n_components, seed=0):
    """Gaussian mixture per group on initial velocities -> dict of arrays (storable in a basis).

    velocities (M, P); groups {name: (start, stop)}; n_components {name: K}
    (clipped to the number of samples). Keys: ``gmm_<group>_{weights,means,covariances}``.
    """
    from sklearn.mixture import GaussianMixture

    v = np.asarray(velocities, dtype=np.float64)
    if v.ndim != 2 or v.shape[0] < 2:
        raise InputError(f"fitting a distribution needs at least two velocity vectors, got shape {v.shape}")
    out = {}
    for name, (a, b) in groups.items():
        k = int(min(n_components.get(name, 1), v.shape[0]))
        gmm = GaussianMixture(n_components=k, covariance_type="full", reg_covar=1e-6, random_state=seed,
                              n_init=2).fit(v[:, a:b])
        out[f"gmm_{name}_weights"] = gmm.weights_
        out[f"gmm_{name}_means"] = gmm.means_
        out[f"gmm_{name}_covariances"] = gmm.covariances_
    return out


def sample_velocities(distribution, groups, n, seed=0):
    """Draw n initial velocities from a fitted per-group mixture: -> (n, P).

    Groups without a fitted mixture get zero velocity (they keep the template's value).
    """
    rng = np.random.default_rng(seed)
    p = max(b for _, b in groups.values())
    out = np.zeros((n, p))
    for name, (a, b) in groups.items():
        key = f"gmm_{name}_"
        if key + "weights" not in distribution:
            continue
        w = np.asarray(distribution[key + "weights"], dtype=np.float64)
        means, covs = distribution[key + "means"], distribution[key + "covariances"]
        comp = rng.choice(len(w), size=n, p=w / w.sum())
        for c in np.unique(comp):
            rows = comp == c
            out[rows, a:b] = rng.multivariate_normal(means[c], covs[c], size=int(rows.sum()))
    return out


@with_one_blas_thread
def sample_codes(template, faces, fields, distribution, groups, weights, n, seed=0, steps=8,
                 callback=None, cancel=None):
    """Random shapes: sample initial velocities, shoot from the template: -> codes (n, P)."""
    velocities = sample_velocities(distribution, groups, n, seed)
    monitor = Monitor("sample", callback, cancel)
    codes = []
    for i, v in enumerate(velocities):
        monitor.report(i / n, f"shape {i + 1}/{n}")
        codes.append(shoot(template, faces, fields, np.zeros_like(v), v, weights, steps=steps, cancel=cancel)[-1])
    monitor.report(1.0, "done")
    return np.stack(codes)


def distinct_codes(basis, frames):
    """Codes of registered frames (M, N, 3), duplicates (to 12 decimals) removed: -> (K, P) sorted."""
    return np.unique(project_to_basis(basis, np.asarray(frames, dtype=np.float64))[0].round(12), axis=0)


def fit_training_distribution(basis, sequences, components=None, seed=0):
    """Gaussian mixtures on the log maps of a basis' own training frames (random generation), in its
    ``shape_metric``.

    sequences: list of (T_i, N, 3) registered frames; components {group: K} (paper: pose 10, shape 6).
    """
    codes = distinct_codes(basis, np.concatenate([np.asarray(s) for s in sequences]))
    codes = codes[np.abs(codes).sum(1) > 0]
    t, f, h = basis.tensors()
    velocities = log_map(t, f, h, codes, basis.shape_metric, steps=4)
    return fit_distribution(velocities, basis.groups, components or {"pose": 10, "shape": 6}, seed=seed)


def pose_prototypes(basis, frames, k=24, seed=0):
    """Typical poses for registration's pose-candidate stage: k-means centres (scikit-learn) of
    the codes of training frames (M, N, 3), clustered on the "pose" group when the basis has one
    -> (min(k, distinct codes), P), each centre the mean code of its cluster."""
    from sklearn.cluster import KMeans

    codes = distinct_codes(basis, frames)
    part = codes[:, basis.group_slice("pose")] if "pose" in basis.groups else codes
    labels = KMeans(n_clusters=min(k, len(codes)), n_init=4, random_state=seed).fit_predict(part)
    return np.stack([codes[labels == j].mean(0) for j in np.unique(labels)])
