"""The metric of motion paths fitted to training sequences (``build-basis --metric fit``).

A training motion should be close to a geodesic of the basis' motion metric. For each interior
frame k of a sequence, the frames k - 1 and k + 1 fix a two-step discrete geodesic whose middle
frame is the prediction of k; one Gauss-Newton step of the discrete path energy from the true
frame gives that prediction's displacement delta_k = H_k(w)^-1 r_k(w), linear in the six H2
weights w through r_k (the energy's gradient) and H_k (2 (G(m_k-1) + G(m_k)) / dt). Its part
along the motion (a change of pace, which uneven frame times make) is left out and the rest is
measured as the mean squared vertex displacement. The weights minimising it over the training
frames are the fit. Which metric a basis keeps is then decided on held-out frames: interior
frames are left out in groups, the weights fitted without them and the presets predict each
left-out frame as the middle of the geodesic between its neighbours (``geodesics.geodesic``), and
the lowest mean vertex error wins.
"""

from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import torch

from . import geometry
from .errors import InputError
from .geodesics import decode_path, geodesic
from .h2_metric import PRESETS, H2Weights, assembled_metric_matrix, path_energy
from .latent import decode, project_to_basis
from .progress import Monitor

#: Interior frames used by the fit (evenly chosen among the training sequences' frames).
FIT_FRAMES = 120
#: Groups the interior frames are held out in, and held-out frames predicted per group.
FOLDS = 5
SCORE_FRAMES = 8
#: The presets a fit competes with (by default) and starts from.
CANDIDATES = ("body", "face")
#: Time points of the geodesics that predict a held-out frame (its middle point is the prediction): the
#: fit's two-step geodesic.
SCORE_STEPS = 3
#: Ridge of the Gauss-Newton blocks, relative to their mean eigenvalue.
RIDGE = 1e-12
#: Bounds of the log weights relative to a0 = 1 (the metric's scale does not change its geodesics).
LOG_BOUND = 25.0


@dataclass
class MetricFit:
    """The motion metric a basis keeps: weights; chosen, "fit" or the preset that predicted held-out
    frames best; scores {candidate: mean vertex error of the held-out frames' predictions}; the fit's
    own weights; how many sequences and frames were used."""

    weights: H2Weights
    chosen: str
    scores: dict = field(default_factory=dict)
    fitted: H2Weights | None = None
    sequences: int = 0
    frames: int = 0

    def card(self):
        """The JSON-able record kept in a basis' provenance."""
        return {"chosen": self.chosen, "weights": list(self.weights.as_tuple()),
                "fitted_weights": None if self.fitted is None else list(self.fitted.as_tuple()),
                "held_out_frame_error": {k: float(v) for k, v in self.scores.items()},
                "sequences": self.sequences, "frames": self.frames,
                "measured_by": "interior frames held out in groups, each predicted as the middle of the "
                               "geodesic between its neighbours (fit without the group), mean vertex error"}


def _interior(sequences, cap):
    """(sequence index, frame index) of interior frames, at most cap, evenly spread."""
    pairs = [(i, k) for i, s in enumerate(sequences) for k in range(1, len(s) - 1)]
    if len(pairs) > cap:
        pairs = [pairs[j] for j in np.linspace(0, len(pairs) - 1, cap).round().astype(int)]
    return pairs


class _LocalTerms:
    """Per interior frame: the six unit-weight energy gradients r (6, P), Gauss-Newton blocks
    H (6, P, P) and the motion's direction v (P,); the fields' area-weighted Gram matrix M (P, P)."""

    def __init__(self, basis, codes, pairs, monitor):
        t, f, h = basis.tensors()
        units = np.eye(6)
        area = geometry.vertex_areas(t, f).numpy()
        flat = basis.fields.reshape(basis.n_fields, -1)
        self.gram = (flat * np.repeat(area / area.sum(), 3)) @ flat.T
        evals, evecs = np.linalg.eigh(self.gram)
        self.root = evecs * np.sqrt(np.clip(evals, 0.0, None))  # (P, P): |delta @ root|^2 = delta^T M delta
        self.r, self.h, self.v = [], [], []
        wanted = {}
        for i, k in pairs:
            wanted.setdefault(i, []).append(k)
        done = 0
        for i, ks in wanted.items():
            seq = torch.as_tensor(codes[i])
            dt = 1.0 / (len(seq) - 1)
            grads = []
            for j in range(6):
                x = seq.clone().requires_grad_(True)
                e = path_energy(decode(t, h, x), f, H2Weights(*units[j]))
                grads.append(torch.autograd.grad(e, x)[0].numpy())
            grads = np.stack(grads, 1)  # (T, 6, P)
            blocks = {}

            def block(step):  # (6, P, P) component metrics at the middle of step -> step + 1
                if step not in blocks:
                    mid = decode(t, h, (seq[step] + seq[step + 1]) / 2)
                    blocks[step] = np.stack([assembled_metric_matrix(mid, f, h, H2Weights(*units[j])).numpy()
                                             for j in range(6)])
                return blocks[step]

            for k in ks:
                self.r.append(grads[k])
                self.h.append(2.0 * (block(k - 1) + block(k)) / dt)
                self.v.append(codes[i][k + 1] - codes[i][k - 1])
                done += 1
                monitor.check()
                monitor.report(done / len(pairs), "metric fit: local terms")
        self.r, self.h, self.v = np.stack(self.r), np.stack(self.h), np.stack(self.v)

    def residuals(self, w, keep=slice(None)):
        """The one-step predictions' displacements of the frames ``keep`` (an index or mask into the pairs),
        pace left out, in vertex units (M^1/2 delta, flattened) over sqrt(frames)."""
        r, h, v = self.r[keep], self.h[keep], self.v[keep]
        g = np.einsum("j,kjp->kp", w, r)
        hess = np.einsum("j,kjpq->kpq", w, h)
        # a relative ridge: groups may share directions, making the blocks singular (the gradient has no part
        # along such a direction, and M measures none)
        ridge = RIDGE * np.trace(hess, axis1=1, axis2=2) / hess.shape[1]
        delta = np.linalg.solve(hess + ridge[:, None, None] * np.eye(hess.shape[1]), g[..., None])[..., 0]
        mv = v @ self.gram
        delta = delta - ((delta * mv).sum(1) / np.maximum((v * mv).sum(1), 1e-300))[:, None] * v
        return (delta @ self.root).ravel() / np.sqrt(len(delta))

    def displacement(self, w, keep=slice(None)):
        """Mean squared vertex displacement of the one-step predictions of the frames ``keep``."""
        return float(np.sum(self.residuals(w, keep) ** 2))

    def fit(self, keep=slice(None)):
        """H2 weights (a0 = 1) minimising ``displacement`` over the frames ``keep`` (Gauss-Newton in the log
        weights, from each preset and from equal weights; the best kept)."""
        best = None
        for w in (*(np.array(PRESETS[name].as_tuple()) for name in CANDIDATES), np.ones(6)):
            u0 = np.clip(np.log(np.maximum(w[1:] / w[0], np.exp(-LOG_BOUND))), -LOG_BOUND, LOG_BOUND)
            res = scipy.optimize.least_squares(lambda u: self.residuals(np.array(_weights(u).as_tuple()), keep),
                                               u0, bounds=(-LOG_BOUND, LOG_BOUND), x_scale=1.0)
            if best is None or res.cost < best.cost:
                best = res
        return _weights(best.x)


def _weights(u):
    return H2Weights(1.0, *np.exp(u))


def held_out_errors(basis, codes, frames, pairs, weights):
    """Mean vertex error of each frame in ``pairs`` predicted as the middle of the geodesic between its
    neighbours' codes (``SCORE_STEPS`` time points) against the true frame: -> (len(pairs),)."""
    t, f, h = basis.tensors()
    out = []
    for i, k in pairs:
        g = geodesic(t, f, h, codes[i][k - 1], codes[i][k + 1], weights, steps=SCORE_STEPS, max_iter=200)
        mid = decode_path(t, h, g.path[SCORE_STEPS // 2:SCORE_STEPS // 2 + 1])[0]
        out.append(float(np.linalg.norm(mid - frames[i][k], axis=1).mean()))
    return np.array(out)


def choose_motion_metric(basis, sequences, candidates=None, folds=FOLDS, callback=None, cancel=None):
    """The motion metric for a basis from its training sequences (list of (T_i, N, 3), at least two
    with three frames or more): interior frames are held out in ``folds`` groups; the weights fitted
    without a group (no prediction that uses one of its frames) and the ``candidates`` ({label: weights},
    default the presets) predict the group's frames from their neighbours; the one with the lowest mean
    error is kept, the fit refitted on every frame -> MetricFit."""
    candidates = {name: PRESETS[name] for name in CANDIDATES} if candidates is None else {
        label: H2Weights.parse(w) for label, w in candidates.items()}
    monitor = Monitor("metric fit", callback, cancel)
    frames = [np.asarray(s, dtype=np.float64) for s in sequences if len(s) >= 3]
    if len(frames) < 2:
        raise InputError("fitting the metric needs at least two training sequences of three frames or more; "
                         "give --metric body, face or six weights instead")
    codes = [project_to_basis(basis, s, ridge=0.0)[0] for s in frames]
    pairs = _interior(codes, FIT_FRAMES)
    terms = _LocalTerms(basis, codes, pairs, Monitor("metric fit", monitor.scaled(0.0, 0.3), cancel))
    folds = max(2, min(folds, len(pairs)))
    scores = {name: [] for name in ("fit", *candidates)}
    for fold in range(folds):
        held = pairs[fold::folds][:SCORE_FRAMES]
        near = {(i, k + d) for i, k in held for d in (-1, 0, 1)}
        keep = np.array([(i, k) not in near for i, k in pairs])
        if not keep.any():
            continue
        fitted = terms.fit(keep)
        for name, w in (("fit", fitted), *candidates.items()):
            scores[name].extend(held_out_errors(basis, codes, frames, held, w))
            monitor.check()
        monitor.report(0.3 + 0.65 * (fold + 1) / folds, f"metric fit: held-out frames {fold + 1} of {folds}")
    means = {name: float(np.mean(v)) for name, v in scores.items() if v}
    fitted = terms.fit()
    chosen = min(means, key=means.get) if means else "fit"
    monitor.report(1.0, "metric fit done")
    return MetricFit(weights=fitted if chosen == "fit" else candidates[chosen], chosen=chosen, scores=means,
                     fitted=fitted, sequences=len(frames), frames=len(pairs))
