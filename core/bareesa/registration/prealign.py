r"""Rigid + uniform-scale pre-alignment of a scan to a template, from any initial orientation.

Both surfaces are normalised (area-weighted centroid, RMS radius); candidate rotations map the
principal axes of the scan's area-weighted second moments onto the template's (the 24 proper
signed permutations, so near-equal moments and any axis order are covered) plus the identity;
each is scored by a coarse binet varifold (faces binned into cubic cells, each cell keeping its
area-weighted centroid and orientation tensor sum a n n^T, which is exact for the binet kernel up
to the binning of positions; ``bareesa.varifold``'s binned measures, summed by its backends);
the best few are refined by L-BFGS over (axis-angle, translation, log-scale) at a coarse then a
finer sigma. The binet kernel ignores normal orientation, so inconsistently oriented scans align
as well. A scan in a pose far from the template's (a crouch, arms spread) can have second moments
whose axes say nothing of the template's: reference surfaces in the template frame (a basis' decoded
pose prototypes), the few whose normalised moments are nearest the scan's, give candidates too.
"""

import math
from itertools import permutations, product
from typing import NamedTuple

import numpy as np
import torch

from ..errors import MeshError
from ..mesh import face_geometry
from ..optimize import minimize_lbfgs
from ..progress import Monitor
from ..transforms import Similarity, axis_angle_rotation, rotation_angle
from ..varifold import BinnedMeasureLoss, cell_features, moved_measure, varifold_measure
from .config import Prealignment

class Alignment(NamedTuple):
    """A candidate alignment: score (the normalised squared varifold it reached), transform (Similarity
    scan -> template frame), reference (the index of the reference surface it was found against, None
    for the template) and code (P,) the latent code the registration starts from (None: rest or the
    reference's)."""

    score: float
    transform: Similarity
    reference: int = None
    code: np.ndarray = None


def bounded_log_scale(l, limit):
    """The refinement's log-scale (tensor or float) mapped smoothly into +-limit: an unbounded one let a
    line search try e^(hundreds) and overflow."""
    if isinstance(l, torch.Tensor):
        return limit * torch.tanh(l / limit)
    return limit * math.tanh(l / limit)


def _area_centroid(verts, faces, face_weights):
    """Face areas (F,) (times face weights), their total and the area-weighted centroid (3,)."""
    _, a, barycentres = face_geometry(verts, faces)
    if face_weights is not None:
        a = a * face_weights
    total = a.sum()
    if not total > 0:
        raise MeshError("the scan has zero (weighted) surface area; nothing to register")
    return a, total, (a[:, None] * barycentres).sum(0) / total


def surface_centroid(verts, faces, face_weights=None):
    """Weighted area and centroid (3,) of a surface, as ``surface_moments`` gives them (without the
    second moment's cost): verts (N, 3), faces (F, 3), face_weights (F,) or None."""
    _, total, center = _area_centroid(verts, faces, face_weights)
    return float(total), center


def surface_moments(verts, faces, face_weights=None):
    """Weighted area, centroid (3,) and second moment about it (3, 3) of a surface: exact integrals.

    verts (N, 3), faces (F, 3), face_weights (F,) or None; the second moment is
    int (x - c)(x - c)^T dA / A, so sqrt of its trace is the RMS radius.
    """
    p = np.asarray(verts, dtype=np.float64)[np.asarray(faces)]
    a, total, center = _area_centroid(verts, faces, face_weights)
    q = p - center
    s = q.sum(1)
    # int over a triangle of x x^T = A/12 (sum_i q_i q_i^T + s s^T), s = sum_i q_i, as matrix products (an
    # einsum of three operands is far slower, and a registration takes dozens of such moments)
    second = (q * a[:, None, None]).reshape(-1, 3).T @ q.reshape(-1, 3) + (s * a[:, None]).T @ s
    return float(total), center, second / (12.0 * total)


def moment_table(surfaces, faces):
    """Centroid and second moment of each surface (``surface_moments``) with faces (F, 3), as
    ``prealign_candidates``' reference_moments: (K, N, 3) -> (K, 12) = centroid (3) | moment (9)."""
    out = [surface_moments(verts, faces)[1:] for verts in surfaces]
    return np.array([np.concatenate([c, m.ravel()]) for c, m in out]).reshape(len(out), 12)


def coarse_measure(verts, faces, face_weights, cell):
    """A surface binned into cubic cells (``varifold.cell_features``, binet), float64 on the CPU:
    verts (N, 3), faces (F, 3), face_weights (F,) or None -> centroids (C, 3), tensors sum a n n^T (C, 9)."""
    as64 = lambda a: torch.as_tensor(a, dtype=torch.float64, device="cpu")  # noqa: E731
    weights = None if face_weights is None else as64(face_weights)
    measure = varifold_measure(as64(verts), torch.as_tensor(faces, dtype=torch.long, device="cpu"), weights)
    return cell_features(*measure, cell, "binet")[:2]


class CoarseVarifold:
    """Binet varifold of binned measures against a fixed target; the source moves by a similarity.

    target: a binned measure (centroids (D, 3), features (D, 9)), or a ``BinnedMeasureLoss`` against
    one, to share its cached self term among several sources (``RegistrationProblem.realign``)."""

    def __init__(self, target, source, sigma):
        self.loss = target if isinstance(target, BinnedMeasureLoss) else BinnedMeasureLoss(*target, sigma)
        self.source = source
        self.self_t = float(self.loss.self_t)

    def __call__(self, params, base):
        """Squared distance after x -> e^l R(w) base x + tau; params (w, tau, l) (7,) tensor."""
        r = axis_angle_rotation(params[:3]) @ base
        return self.loss(*moved_measure(*self.source, r, torch.exp(params[6]), params[3:6], "binet"))


def _candidate_rotations(axes_t, axes_s):
    """Rotations mapping the scan's principal axes onto the template's (24) plus the identity."""
    out = []
    for perm in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            q = np.zeros((3, 3))
            q[list(perm), range(3)] = signs
            r = axes_t @ q @ axes_s.T
            if np.linalg.det(r) > 0:
                out.append(r)
    out.append(np.eye(3))
    return out



def prealign_candidates(template_verts, template_faces, scan_verts, scan_faces, scan_face_weights=None,
                        keep=None, monitor=None, progress=(0.0, 1.0), references=None,
                        reference_moments=None, settings=None):
    """Distinct candidate alignments of a scan to a template, best first: -> [Alignment].

    template (N, 3), (F, 3); scan (M, 3), (G, 3); scan_face_weights (G,) or None (zero-weight
    faces are ignored); references (K, N, 3) or None: other surfaces with the template's faces, in
    its frame (decoded pose prototypes), of which the ``settings.references`` with normalised second
    moments nearest the scan's give candidates too; reference_moments (K, 12) or None: their centroids
    and second moments as ``moment_table`` gives them (computed here when None). Each transform maps
    scan coordinates into the template frame; the score is the (binned, binet) squared distance at the
    finer pre-alignment sigma between the normalised template (or reference) and the mapped scan, over
    the former's squared norm. At most ``keep`` (None: ``settings.keep``) candidates, pairwise more than
    ``settings.distinct_degrees`` apart. settings: a ``config.Prealignment`` (None: its defaults).
    """
    settings = Prealignment() if settings is None else settings
    keep = settings.keep if keep is None else keep
    monitor = monitor or Monitor("prealign")
    lo, hi = progress
    tf = np.asarray(template_faces, np.int64)
    sv, sf = np.asarray(scan_verts, np.float64), np.asarray(scan_faces, np.int64)
    _, cs, ms = surface_moments(sv, sf, scan_face_weights)
    rho_s = math.sqrt(np.trace(ms))
    zs = (sv - cs) / rho_s
    surfaces = [np.asarray(template_verts, np.float64)]
    moments = [surface_moments(surfaces[0], tf)[1:]]
    if references is not None:
        surfaces += [np.asarray(r, np.float64) for r in references]
        if reference_moments is None:
            reference_moments = moment_table(surfaces[1:], tf)
        moments += [(m[:3], m[3:].reshape(3, 3)) for m in np.asarray(reference_moments, np.float64)]
    targets = []  # per surface: centroid, RMS radius, vertices, principal axes, normalised moments, reference
    for k, (verts, (ct, mt)) in enumerate(zip(surfaces, moments)):
        rho_t = math.sqrt(np.trace(mt))
        spread, axes = np.linalg.eigh(mt)
        targets.append((ct, rho_t, verts, axes, spread / rho_t ** 2, k - 1 if k else None))
    spread_s, axes_s = np.linalg.eigh(ms)
    nearest = sorted(range(1, len(targets)), key=lambda i: np.abs(targets[i][4] - spread_s / rho_s ** 2).sum())
    targets = targets[:1] + [targets[i] for i in nearest[:settings.references]]

    cache = {}

    def objective(i, sigma):
        """The coarse varifold against target i at sigma (its measures built once)."""
        cell = settings.cell * sigma
        if sigma not in cache:
            cache[sigma] = coarse_measure(zs, sf, scan_face_weights, cell)
        if (i, sigma) not in cache:
            ct, rho_t, verts = targets[i][:3]
            cache[i, sigma] = CoarseVarifold(coarse_measure((verts - ct) / rho_t, tf, None, cell), cache[sigma], sigma)
        return cache[i, sigma]

    zero = torch.zeros(7, dtype=torch.float64)
    scored = []  # (score, surface, rotation)
    for i, target in enumerate(targets):
        coarse = objective(i, settings.sigmas[0])
        for r in _candidate_rotations(target[3], axes_s):
            monitor.check()
            with torch.no_grad():
                scored.append((float(coarse(zero, torch.from_numpy(r))) / coarse.self_t, i, r))
    scored.sort(key=lambda c: c[0])
    span = (hi - lo) / (settings.refine + keep + 1)
    monitor.report(lo + span, "pre-alignment: candidates scored", scored[0][0])

    def refine(obj, r, x0, k):
        bounded = lambda p: torch.cat([p[:6], bounded_log_scale(p[6:], settings.log_scale_limit)])  # noqa: E731
        x, value, _ = minimize_lbfgs(lambda p: obj(bounded(p), torch.from_numpy(r)), x0, monitor,
                                     max_iter=settings.max_iter, progress=(lo + k * span, lo + (k + 1) * span),
                                     message="pre-alignment", gtol=1e-9, ftol=1e-10)
        return axis_angle_rotation(x[:3]) @ r, x, value / obj.self_t

    stage = []
    for k, (_, i, r0) in enumerate(scored[:settings.refine]):
        r, x, value = refine(objective(i, settings.sigmas[0]), r0, np.zeros(7), k + 1)
        stage.append((value, i, r, x))
    stage.sort(key=lambda s: s[0])
    distinct = []
    for value, i, r, x in stage:
        if all(rotation_angle(r, d[2]) > settings.distinct_degrees for d in distinct):
            distinct.append((value, i, r, x))
    out = []
    for k, (_, i, r0, x0) in enumerate(distinct[:keep]):
        ct, rho_t = targets[i][:2]
        x0 = np.concatenate([np.zeros(3), x0[3:]])
        r, x, value = refine(objective(i, settings.sigmas[1]), r0, x0, settings.refine + 1 + k)
        scale = rho_t * math.exp(bounded_log_scale(float(x[6]), settings.log_scale_limit)) / rho_s
        out.append(Alignment(value, Similarity(r, scale, ct + rho_t * x[3:6] - scale * r @ cs), targets[i][5]))
    out.sort(key=lambda c: c[0])
    monitor.report(hi, "pre-alignment done", out[0][0])
    return out


def align_to_template(template_verts, template_faces, scan_verts, scan_faces, scan_face_weights=None,
                      monitor=None, progress=(0.0, 1.0)):
    """Rigid + uniform-scale alignment of a scan to a template from any initial orientation.

    template (N, 3), (F, 3); scan (M, 3), (G, 3); scan_face_weights (G,) or None -> the
    Similarity mapping scan coordinates into the template frame (best of ``prealign_candidates``).
    """
    return prealign_candidates(template_verts, template_faces, scan_verts, scan_faces, scan_face_weights,
                               keep=1, monitor=monitor, progress=progress)[0].transform


def landmark_alignment(template_points, scan_points, weights=None):
    """The similarity mapping scan points onto template points in the weighted least-squares sense
    (Umeyama's closed form): (L, 3), (L, 3), (L,) -> Similarity, or None when the weighted points
    span less than a plane (fewer than 3 non-collinear landmarks fix no rotation)."""
    p, q = np.asarray(scan_points, np.float64), np.asarray(template_points, np.float64)
    w = np.ones(len(p)) if weights is None else np.asarray(weights, np.float64)
    use = w > 0
    if use.sum() < 3:
        return None
    p, q, w = p[use], q[use], w[use] / w[use].sum()
    mp, mq = w @ p, w @ q
    dp, dq = p - mp, q - mq
    spread = np.linalg.svd(dp * np.sqrt(w)[:, None], compute_uv=False)
    if spread[1] <= 1e-6 * max(spread[0], 1e-300):
        return None
    u, s, vt = np.linalg.svd((dq * w[:, None]).T @ dp)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ d @ vt
    scale = float(np.trace(np.diag(s) @ d) / (w @ (dp ** 2).sum(1)))
    if not scale > 0:
        return None
    return Similarity(rotation, scale, mq - scale * rotation @ mp)
