r"""Latent code retrieval of an unregistered scan (paper section 4.1), with rigid pre-alignment.

Given a basis (template q-bar, fields h_i, metric weights, schedule) and a scan q with any
vertices and faces, ``register`` minimises over discrete latent paths
alpha = (alpha(0) = 0, alpha(1/T), ..., alpha(1))  (P*T free variables)

    weight * [ Gamma(S(F(alpha(1))), T(q)) + landmark term ]  +  E(alpha),

where Gamma is the squared varifold distance at scale sigma (``bareesa.varifold``), E the discrete
H2 path energy of the decoded path (``h2_metric.path_energy``; this is the paper's energy
Gamma + (1/lambda) E multiplied by lambda = ``weight``), T the similarity that maps the scan
into the template frame (the pre-alignment) and S a small similarity (rotation, translation,
log-scale; 7 variables) optimised jointly with the path, so that the pre-alignment is refined
at every level (``refine_transform``). The schedule is multiscale (sigma decreasing, weight
and steps increasing); each level is warm-started from the last, its latent path resampled
linearly in time to the new number of steps.

Every setting lives in one frozen ``RegistrationConfig`` (``config``), defaulted from the basis card.
Modules, in dependency order: ``config`` (the settings), ``prealign`` (candidate alignments from any
orientation), ``problem`` (one level's objective, preconditioning, re-alignment and scoring),
``checks`` (input checks and the poor-fit test), ``prepared`` (per-basis constants kept in the basis),
``result``, ``detail`` (the detail layer after the basis fit: free displacements under the H2 energy),
``poses`` (typical poses tried as starts of the second level), ``multiscale``
(``register``: the schedule from pre-alignment to the finest level), ``symmetric`` (two raw scans and
the geodesic between them in one solve).

Frames: registration happens in the template frame; ``RegistrationResult.vertices`` are mapped
back with the inverse similarity, so they overlay the scan in the scan's units.
"""

from .config import (DetailFit, LevelSolve, MatchingSolve, PoseSearch, Prealignment, RegistrationConfig,
                     Screening, check_schedule)
from .detail import Detail, detail_of, fit_detail
from .multiscale import DETAIL_SHARE, WARM_LEVELS, register, register_in_frame, warm_schedule
from .poses import pose_starts
from .prealign import Alignment, align_to_template, prealign_candidates, surface_moments
from .prepared import PREPARED_EXTRAS, prepare_basis
from .problem import resample_in_time
from .result import RegistrationResult
from .symmetric import Matching, symmetric_match

__all__ = ["DETAIL_SHARE", "PREPARED_EXTRAS", "WARM_LEVELS", "Alignment", "Detail", "DetailFit", "LevelSolve",
           "Matching", "MatchingSolve", "PoseSearch", "Prealignment", "RegistrationConfig", "RegistrationResult",
           "Screening", "align_to_template", "check_schedule", "detail_of", "fit_detail", "pose_starts",
           "prealign_candidates", "prepare_basis", "register", "register_in_frame", "resample_in_time",
           "surface_moments", "symmetric_match", "warm_schedule"]
