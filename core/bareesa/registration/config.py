"""``RegistrationConfig``: every setting of a registration in one frozen object.

A configuration is defaulted from the basis (its card's schedule, shape metric and optional
``"registration"`` overrides, ``RegistrationConfig.from_basis``) and overridden in one place: the
API (``register(..., config=...)`` or keywords), the CLI (``--set KEY=VALUE``, ``--config FILE``) and
the add-on's panel all build a variant with ``with_overrides``. Keys of nested settings are dotted:
``"poses.finalists"``, ``"solve.memory"``. Why each default is what it is: docs/decisions/ (005-008 for the
solve, screening, retries and poses, 021 for the articulated pre-fit).
"""

import json
import math
from dataclasses import dataclass, field, fields, replace

import numpy as np
import torch

from ..errors import InputError
from ..h2_metric import H2Weights
from ..latent import Level
from ..varifold import BIN_CELL

DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass(frozen=True)
class Prealignment:
    """Rigid + scale pre-alignment from any orientation (``prealign.prealign_candidates``).

    sigmas: scoring/refinement and final sigmas in units of the RMS radius; cell: bin size in units of
    sigma; refine: candidates refined at the coarse sigma; keep: distinct ones refined at the finer one;
    distinct_degrees: between two distinct candidates; ratio: candidates within this factor of the best's
    varifold are tried; max_iter: L-BFGS steps of a refinement; references: pose prototypes nearest the
    scan's moments tried besides the template; log_scale_limit: the refinement's bound on the log-scale;
    tie: with pose prototypes only candidates within this factor of the best are screened (the
    pre-alignment's ranking is more reliable than the latent screening's); progress_share: of the bar.
    """

    sigmas: tuple = (0.5, 0.25)
    cell: float = 0.5
    refine: int = 8
    keep: int = 6
    distinct_degrees: float = 20.0
    ratio: float = 4.0
    max_iter: int = 40
    references: int = 4
    log_scale_limit: float = math.log(4.0)
    tie: float = 1.05
    progress_share: float = 0.1


@dataclass(frozen=True)
class LevelSolve:
    """How one level is solved (``problem.RegistrationProblem``).

    ftol, plateau_window, plateau: L-BFGS stops below this relative fall in one step, or in
    plateau_window steps (a level's own ``Level.plateau`` replaces ``plateau``); memory: L-BFGS' past
    steps; bin_gain: "auto" bins a level with no ``Level.binned`` when that leaves at most this share of
    face pairs; bin_cell: a binned level's cells in units of sigma when it gives none; fine_tol: kernel
    truncation tolerance of unbinned levels; scan_cell, oriented_scan_cell: the scan summed over cells of
    this x sigma on unbinned levels (None: its faces as they are); scale_log_limit: a level changes the
    alignment's scale by at most this (log); preview_every: iterations between previews; energy_dtype:
    the per-face algebra of the path energy; straight_batch: straight paths summed per energy call.
    """

    ftol: float = 1e-9
    plateau_window: int = 5
    plateau: float = 1e-3
    memory: int = 100
    bin_gain: float = 0.05
    bin_cell: float = BIN_CELL
    fine_tol: float = 1e-4
    scan_cell: float | None = 0.5
    oriented_scan_cell: float | None = 0.3
    scale_log_limit: float = math.log(1.15)
    preview_every: int = 5
    energy_dtype: torch.dtype = torch.float32
    straight_batch: int = 8


@dataclass(frozen=True)
class Screening:
    """How candidate alignments are compared (``multiscale``).

    divisor: the screening's short first level runs max_iter / divisor iterations on a one-step path;
    finalists, tie: the best screened alignments within tie x the best get second_iterations of the
    second level, which decides; kernel, cell: the scores' kernel and cells (x sigma); deep_iterations:
    second-level iterations of the deeper screening of a retry that is still poor.
    """

    divisor: int = 8
    finalists: int = 2
    second_iterations: int = 5
    tie: float = 1.5
    kernel: str = "binet"
    cell: float = 0.25
    deep_iterations: int = 30


@dataclass(frozen=True)
class PoseSearch:
    """The pose stage before the second level (``poses.try_poses``).

    candidates: "auto" (the basis' ``pose_prototypes``), None (no pose stage) or codes (K, P); realign:
    candidates re-aligned (the best by their centroid-matched score); skip: none is when all score above
    skip x the current code; align_iterations: L-BFGS steps of a re-alignment; finalists, tie: the best
    re-aligned within tie x the current code's score get a short solve at weight_gain x the level's
    weight, on ``steps`` time steps with cells of bin_cell x sigma, ranked after pick_iterations; the
    best runs to ``iterations``.
    """

    candidates: object = "auto"
    finalists: int = 2
    tie: float = 2.0
    realign: int = 6
    skip: float = 4.0
    align_iterations: int = 10
    iterations: int = 40
    pick_iterations: int = 20
    weight_gain: float = 10.0
    steps: int = 1
    bin_cell: float = 0.8


@dataclass(frozen=True)
class ArticulatedFit:
    """The articulated pre-fit of a basis with a skeleton (``articulated.fit_pose``).

    enabled: run it (a basis without a skeleton never does); alignments: the best pre-alignment candidates
    it starts from, of which the ``searched`` whose best start (rest or the library's) scores lowest are
    searched and fitted (the one that fits best is kept; the rest too while the best fit's score, its
    finest varifold over the scan's self term, is above ``poor_score``); sigmas: of its coarse then finer varifold,
    relative to the basis' scale (the alignments are compared at the last); search_sigma: the index of
    the sigma the starts are first searched at (a coarser one cannot tell arms overhead from a body upside
    down, or from another body's shape); cell, search_cell: both surfaces' cells in units of sigma, in the
    fits and in the (discrete) searches; samples: area samples of the template that stand for it in the
    fit; settle_iter: L-BFGS steps settling the alignment and size after the coarse search; max_iter:
    L-BFGS steps per sigma of the fits; limit_weight: of the penalty on rotations past a joint's range;
    prior: of the squared rotations (rest is preferred where the scan cannot tell); scale_limit: the
    largest change of the posed template's scale from the one that matches the scan's area;
    projection_ridge: of the posed template's projection into the latent space (``latent.project_to_basis``);
    coarse_levels: after an articulated start, also run the schedule's levels coarser than its coarsest
    sigma, and the pose stage (off: their light data term pulls a far pose back toward rest, crossed arms
    come undone; decision 021).
    """

    enabled: bool = True
    alignments: int = 4
    searched: int = 2
    poor_score: float = 0.2
    sigmas: tuple = (0.15, 0.07)
    search_sigma: int = 0
    cell: float = 0.5
    search_cell: float = 0.5
    samples: int = 1500
    settle_iter: int = 10
    max_iter: int = 30
    limit_weight: float = 10.0
    prior: float = 1e-4
    scale_limit: float = 1.3
    projection_ridge: float = 5e-3
    coarse_levels: bool = False


@dataclass(frozen=True)
class DetailFit:
    """The detail layer after the basis fit (``detail.fit_detail``): free per-vertex displacements.

    enabled: fit it (off: the pure basis fit); kernel: its varifold's (oriented, "linear": the scan's pieces
    are turned like the basis fit, and surfaces facing each other across a narrow gap, toes or fingers, are
    not pulled into one another); sigmas: its levels' varifold sigmas, relative to the basis'
    scale, none finer than ``spacing`` x the scan's sampling (``detail.scan_spacing``); weights, max_iter,
    subdivided: each level's data term weight, L-BFGS iterations, and whether its data term sees each face as
    its four midpoint sub-faces (finer quadrature: the last level; a tuple shorter than sigmas repeats its
    last); reach: template faces farther than this x the first sigma from the scan are left out
    of the data term (holes); tangential: a displacement along the surface (the basis fit's vertex normals)
    costs this many times the data term's curvature (the varifold cannot see a vertex slide along the surface,
    and the energy barely: without it the layer moves vertices from their places); steps: of the straight path whose H2 energy regularises it; ftol,
    plateau_window, plateau, memory: each level's preconditioned L-BFGS; tol: kernel truncation; ranges_margin: the truncated sums' ranges
    are kept while no point moved more than this x the cutoff (``VarifoldLoss``); scan_cell: the scan summed over cells of this x sigma; flip_cos, collapse: a face whose normal turns past this cosine
    from the basis fit's, or whose area falls below this share of it, is bad; retries, stiffen: a fit with
    bad faces is fitted again with the energy this many times stiffer, so many times (then faded as below);
    noise_floor: relative to the basis' scale, the share of the scan's estimated noise
    (``detail.scan_noise``) a clean mesh's sampling makes, and the noise the data term takes at full weight:
    a scan of estimate s weighs floor^2 / (s^2 - floor^2) of the weights where that is under 1, the inverse
    of its noise's variance (None: never lowered); fade_rings, fade_rounds: where the detail makes the surface
    cross itself it is faded out over this many
    rings around the crossing faces, one ring more each round, so many rounds, then left out; poor_fits:
    also fit it on a registration flagged poor.
    """

    enabled: bool = True
    kernel: str = "linear"
    sigmas: tuple = (0.005, 0.004)
    weights: tuple = (1e8,)
    subdivided: tuple = (False, True)
    spacing: float = 0.5
    reach: float = 1.5
    tangential: float = 1.0
    steps: int = 1
    max_iter: tuple = (20, 4)
    ftol: float = 1e-9
    plateau_window: int = 5
    plateau: float = 1e-3
    memory: int = 10
    tol: float = 1e-4
    ranges_margin: float = 0.1
    scan_cell: float = 0.3
    noise_floor: float | None = 0.00028
    flip_cos: float = 0.0
    collapse: float = 0.1
    retries: int = 2
    stiffen: float = 4.0
    fade_rings: int = 2
    fade_rounds: int = 6
    poor_fits: bool = False


@dataclass(frozen=True)
class MatchingSolve:
    """The joint solve of symmetric matching: plateau_window, plateau its stop (the path energy is a
    small part of the objective, so a level's plateau would stop it too early); start_dtype: of the
    geodesic between the two registrations it starts from."""

    plateau_window: int = 5
    plateau: float = 1e-4
    start_dtype: torch.dtype = torch.float32


_SECTIONS = {"prealignment": Prealignment, "articulated": ArticulatedFit, "solve": LevelSolve,
             "screening": Screening, "poses": PoseSearch, "matching": MatchingSolve,
             "detail": DetailFit}


@dataclass(frozen=True, eq=False)
class RegistrationConfig:
    """Every setting of ``register`` (and of ``symmetric_match``'s registrations and joint solve).

    schedule: Levels, coarse to fine (None: the basis'); metric: H2 weights of the regularizer (None: the basis'
    ``shape_metric``); kernel: "auto" (binet, the finest level linear on a noisy scan), a name of
    ``varifold.KERNELS``, a sum "binet+linear" or one per level; backend: of the varifold; binning:
    "auto" (a level's ``binned``, else ``solve.bin_gain``), True, False; prealign: align from any
    orientation first (else the scan is in the template frame); refine_transform: optimise the
    similarity with the path (None: as prealign); retry: register a poor fit again from other
    alignments; landmark_weight: of the landmark term; noisy_spread: the normal spread above which
    "auto" matches the finest level with the linear kernel; min_scan_faces, min_flatness_ratio: what a
    scan needs to be registered; dtype, device: of the objective.
    """

    schedule: tuple | None = None
    metric: object = None
    kernel: object = "auto"
    backend: str = "auto"
    binning: object = "auto"
    prealign: bool = True
    refine_transform: bool | None = None
    retry: bool = True
    landmark_weight: float = 1.0
    noisy_spread: float = 0.05
    min_scan_faces: int = 100
    min_flatness_ratio: float = 0.02
    dtype: torch.dtype = torch.float64
    device: str = "cpu"
    prealignment: Prealignment = field(default_factory=Prealignment)
    articulated: ArticulatedFit = field(default_factory=ArticulatedFit)
    solve: LevelSolve = field(default_factory=LevelSolve)
    screening: Screening = field(default_factory=Screening)
    poses: PoseSearch = field(default_factory=PoseSearch)
    matching: MatchingSolve = field(default_factory=MatchingSolve)
    detail: DetailFit = field(default_factory=DetailFit)

    def __post_init__(self):
        if self.schedule is not None:
            object.__setattr__(self, "schedule", check_schedule(self.schedule))
        if not (isinstance(self.dtype, torch.dtype) and self.dtype.is_floating_point):
            raise InputError(f"dtype must be a torch floating point dtype, got {self.dtype!r}")
        if self.binning not in ("auto", True, False):
            raise InputError(f"binning must be 'auto', True or False, got {self.binning!r}")
        if not (math.isfinite(self.landmark_weight) and self.landmark_weight >= 0):
            raise InputError(f"landmark_weight must be finite and >= 0, got {self.landmark_weight}")
        if self.metric is not None:
            object.__setattr__(self, "metric", H2Weights.parse(self.metric))
        if not isinstance(self.kernel, str):
            object.__setattr__(self, "kernel", tuple(self.kernel))

    @classmethod
    def from_basis(cls, basis, overrides=None, **settings):
        """The basis' defaults (its schedule and the card's ``registration`` overrides), then ``overrides``
        (a mapping, dotted keys allowed) and keyword ``settings`` -> RegistrationConfig."""
        config = cls(schedule=basis.schedule)
        card = getattr(basis, "registration", None) or {}
        return config.with_overrides(card).with_overrides(overrides or {}).with_overrides(settings)

    @property
    def refines_transform(self):
        """Whether the similarity is optimised with the path (``refine_transform``, default as prealign)."""
        return self.prealign if self.refine_transform is None else bool(self.refine_transform)

    def shape_metric(self, basis):
        """The H2 weights of the regularizer: ``metric``, else the basis' shape metric."""
        return H2Weights.parse(basis.shape_metric if self.metric is None else self.metric)

    def pose_candidates(self, basis):
        """The pose stage's candidate codes (K, P) float64, or None (no pose stage)."""
        candidates = self.poses.candidates
        if isinstance(candidates, str):
            if candidates != "auto":
                raise InputError(f"pose candidates must be 'auto', None or an array of codes, got {candidates!r}")
            candidates = basis.extras.get("pose_prototypes")
        if candidates is None:
            return None
        codes = np.asarray(candidates, dtype=np.float64)
        if codes.ndim != 2 or codes.shape[1] != basis.n_fields or not np.isfinite(codes).all():
            raise InputError(f"pose candidates must be finite codes of shape (K, {basis.n_fields}), got {codes.shape}")
        return codes if len(codes) else None

    def with_overrides(self, overrides=None, **settings):
        """A copy with settings changed: a mapping (dotted keys "poses.finalists", or a section's name
        with a mapping or a section object) and/or keywords -> RegistrationConfig (InputError naming an
        unknown key or a bad value)."""
        changes = dict(overrides or {})
        changes.update(settings)
        if not changes:
            return self
        top, nested = {}, {}
        for key, value in changes.items():
            if not isinstance(key, str):
                raise InputError(f"a registration setting is named by a string, got {key!r}")
            section, _, name = key.partition(".")
            if name:
                nested.setdefault(section, {})[name] = value
            elif key in _SECTIONS and isinstance(value, dict):
                nested.setdefault(key, {}).update(value)
            else:
                top[key] = value
        known = {f.name: f for f in fields(self)}
        for key, value in list(top.items()):
            if key not in known:
                raise InputError(f"unknown registration setting {key!r}; settings: {', '.join(sorted(known))}")
            top[key] = _coerce(key, value, getattr(self, key))
        for section, values in nested.items():
            if section not in _SECTIONS:
                raise InputError(f"unknown registration setting section {section!r}; sections: "
                                 f"{', '.join(sorted(_SECTIONS))}")
            current = top.get(section, getattr(self, section))
            names = {f.name for f in fields(current)}
            for name, value in values.items():
                if name not in names:
                    raise InputError(f"unknown registration setting '{section}.{name}'; {section} has: "
                                     f"{', '.join(sorted(names))}")
            top[section] = replace(current, **{n: _coerce(f"{section}.{n}", v, getattr(current, n))
                                               for n, v in values.items()})
        return replace(self, **top)

    def to_dict(self):
        """Plain values (JSON-ready; dtypes by name, levels as dicts, codes as lists): the inverse of
        ``from_dict``. What a Dask worker receives."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in _SECTIONS:
                out[f.name] = {g.name: _plain(getattr(value, g.name)) for g in fields(value)}
            else:
                out[f.name] = _plain(value)
        return out

    @classmethod
    def from_dict(cls, values):
        """The configuration ``to_dict`` gave."""
        return cls().with_overrides(values)

    def describe(self):
        """The settings as one JSON text (what ``bareesa register --show-config`` prints)."""
        return json.dumps(self.to_dict(), indent=2)


def parse_settings(text):
    """Settings written as text, "KEY=VALUE" items separated by ";" or new lines (the add-on's field, one
    ``--set`` each): -> dict of key: value text (InputError on an item without "=")."""
    out = {}
    for item in text.replace("\n", ";").split(";"):
        if not item.strip():
            continue
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise InputError(f"registration setting {item.strip()!r}: expected KEY=VALUE, e.g. poses.finalists=3")
        out[key.strip()] = value.strip()
    return out


def check_schedule(schedule):
    """A sequence of Level or dicts -> tuple of Level (InputError otherwise)."""
    try:
        levels = tuple(lv if isinstance(lv, Level) else Level(**lv) for lv in schedule)
    except TypeError as err:
        raise InputError(f"a schedule is a sequence of Level(sigma, weight, steps, max_iter): {err}") from None
    if not levels:
        raise InputError("the registration schedule is empty")
    return levels


def _plain(value):
    """A setting as a JSON-ready value."""
    if isinstance(value, torch.dtype):
        return str(value).removeprefix("torch.")
    if isinstance(value, H2Weights):
        return list(value.as_tuple())
    if isinstance(value, Level):
        return {f.name: getattr(value, f.name) for f in fields(value)}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def _coerce(key, value, current):
    """``value`` for the setting ``key`` whose current value is ``current``: dtypes from names, numbers
    from strings (CLI), sections from mappings; InputError when it cannot be."""
    if isinstance(current, torch.dtype) or key.endswith("dtype"):
        if isinstance(value, torch.dtype):
            return value
        name = str(value).removeprefix("torch.")
        if name not in DTYPES:
            raise InputError(f"{key}: a dtype is one of {', '.join(DTYPES)}, got {value!r}")
        return DTYPES[name]
    if key in _SECTIONS:
        if isinstance(value, _SECTIONS[key]):
            return value
        raise InputError(f"{key}: give a {_SECTIONS[key].__name__} or a mapping of its settings")
    if isinstance(value, str):
        value = _parse_text(key, value, current)
    if isinstance(current, bool) and not isinstance(value, bool):
        raise InputError(f"{key}: expected true or false, got {value!r}")
    if isinstance(current, (int, float)) and not isinstance(current, bool) and value is not None:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise InputError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(float(value)) and value != math.inf:
            raise InputError(f"{key}: expected a finite number, got {value!r}")
        if isinstance(current, int) and not float(value).is_integer():
            raise InputError(f"{key}: expected a whole number, got {value!r}")
        value = type(current)(value)
    if isinstance(current, tuple) and key != "schedule" and isinstance(value, list):
        value = tuple(value)
    return value


def _parse_text(key, text, current):
    """A setting given as text (``--set KEY=VALUE``): JSON where it parses (numbers, true/false/null,
    lists), else the string itself."""
    if isinstance(current, str) and current != "auto" and not text.strip().startswith(("[", "{")):
        return text
    try:
        return json.loads(text)
    except ValueError:
        lowered = text.strip().lower()
        if lowered in ("true", "false"):
            return lowered == "true"
        if lowered in ("none", "null"):
            return None
        return text
