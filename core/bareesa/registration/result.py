"""``RegistrationResult``: what ``register`` returns."""

from dataclasses import dataclass, fields

import numpy as np

from ..transforms import Similarity


@dataclass
class RegistrationResult:
    """Latent code of a scan and the registered template.

    code (P,); vertices (N, 3) registered template in the scan's frame and units; path (T+1, P)
    the final latent path from 0 to code; transform the similarity scan -> template frame
    (pre-alignment refined by the registration: vertices = transform.invert(F(code)));
    levels one dict per schedule level {sigma, weight, steps, iterations, energy, varifold,
    objective, binned, seconds}; varifold the squared varifold residual at the finest sigma (template
    frame); chamfer between vertices and the scan (scan frame); seconds of wall time;
    prealignment the candidate alignment the registration started from; residual the mean distance
    from the scan to the registered surface over the basis' size (``fit_residual``); poor_fit whether
    it is far above what the basis reaches on its own scans (``basis.fit_check``; None uncalibrated);
    normal_spread the scan's (``problem.normal_spread``), which chose the finest kernel of "auto";
    retried_alignments how many other alignments a poor fit was tried again from (0: none; the result
    is the better of the two tries); articulated the skeleton's pre-fit when the basis has a skeleton
    {score (None: the scan is near rest, no pose searched), start (-1 rest, else the pose library's index),
    seconds}, else None. detail (N, 3) the detail layer (``detail.fit_detail``: the scan's own detail the
    basis cannot make) in the template frame, F(code) + detail the detailed mesh there, or None (turned off,
    a poor fit, or left out); detailed_vertices (N, 3) that mesh in the scan's frame (None without detail);
    detail_report {kept, skipped, stiffened, faded, rms, max, levels, seconds, noise, chamfer, residual}
    (noise: the scan's estimated noise in its own units, ``detail.scan_noise``, None where the layer was
    not fitted; the last two of the detailed mesh, like ``chamfer`` and ``residual`` of the basis fit).
    """

    code: np.ndarray
    vertices: np.ndarray
    path: np.ndarray
    transform: Similarity
    levels: list
    varifold: float
    chamfer: float
    seconds: float
    prealignment: Similarity = None
    residual: float = None
    poor_fit: bool = None
    normal_spread: float = None
    retried_alignments: int = 0
    articulated: dict = None
    detail: np.ndarray = None
    detailed_vertices: np.ndarray = None
    detail_report: dict = None

    @property
    def output_vertices(self):
        """The registered mesh (N, 3) in the scan's frame: the detailed one when there is a detail layer."""
        return self.vertices if self.detailed_vertices is None else self.detailed_vertices

    def to_json(self):
        """JSON-ready summary {code, varifold, chamfer, residual, poor_fit, retried_alignments, normal_spread,
        seconds, levels, transform, detail}: chamfer and residual are the basis fit's, detail the detail
        layer's report (with the detailed mesh's chamfer and residual)."""
        return {"code": [float(c) for c in self.code], "varifold": float(self.varifold),
                "normal_spread": None if self.normal_spread is None else float(self.normal_spread),
                "chamfer": float(self.chamfer), "seconds": float(self.seconds),
                "residual": None if self.residual is None else float(self.residual), "poor_fit": self.poor_fit,
                "retried_alignments": int(self.retried_alignments), "articulated": self.articulated,
                "levels": [{k: (float(v) if isinstance(v, float) else v) for k, v in lv.items()}
                           for lv in self.levels],
                "transform": self.transform.to_dict(), "detail": self.detail_report}

    def to_state(self):
        """Everything as numpy arrays, numbers and dicts (no class of this package; what a worker process
        sends back): the inverse of ``from_state``."""
        state = {f.name: getattr(self, f.name) for f in fields(self)}
        state["transform"] = self.transform.to_dict()
        state["prealignment"] = None if self.prealignment is None else self.prealignment.to_dict()
        return state

    @classmethod
    def from_state(cls, state):
        """The result ``to_state`` gave."""
        state = dict(state)
        state["transform"] = Similarity.from_dict(state["transform"])
        if state.get("prealignment") is not None:
            state["prealignment"] = Similarity.from_dict(state["prealignment"])
        return cls(**state)
