"""The steps both front ends take (the CLI and the Blender add-on): typed inputs -> codes -> paths.

An input is a ``Scan`` (any topology: registered), a ``TemplateMesh`` (the basis' template
topology: projected, keeping what the basis misses as off-basis detail) or a ``KnownCode``.
The workflows (``code_of``, ``geodesic_between``, ``path_between``, ``extrapolate``,
``random_bodies``, ``transfer``, ``distances``) take a basis, inputs and ``Options`` (metric
weights, registration schedule, geodesic time points, device, dtype: nothing global) and
return small result dataclasses of numpy arrays. Progress goes to a ``bareesa.progress``
callback, cancellation through a ``CancelToken``. Solvers are called through their modules
at call time (``shooting.shoot``, ``geodesics.keyframe_path``), so tests can replace them.
"""

from dataclasses import dataclass, field

import numpy as np
import torch

from . import evaluation, geodesics, latent, registration, shooting, statistics
from .errors import FrameRejected, InputError
from .h2_metric import H2Weights
from .mesh import face_geometry, self_intersections, triangle_quality
from .progress import Monitor

# ------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, eq=False)
class Scan:
    """A raw scan in any topology: verts (M, 3), faces (G, 3); optional face weights (G,) >= 0 and
    landmarks [(template vertex, (x, y, z)[, weight])], as ``registration.register`` takes them."""

    verts: np.ndarray
    faces: np.ndarray
    face_weights: np.ndarray | None = None
    landmarks: list | None = None


@dataclass(frozen=True, eq=False)
class TemplateMesh:
    """A mesh in the basis' template topology: verts (N, 3); its code is a projection."""

    verts: np.ndarray


@dataclass(frozen=True, eq=False)
class KnownCode:
    """A latent code known already (e.g. read from shape keys): code (P,); detail (N, 3) its off-basis detail
    in the template frame (e.g. a registered object's detail layer), or None."""

    code: np.ndarray
    detail: np.ndarray | None = None


def mesh_input(basis, verts, faces):
    """A mesh as the input it is: a TemplateMesh in the basis' template topology, else a Scan."""
    verts, faces = np.asarray(verts), np.asarray(faces)
    if verts.shape == basis.template.shape and np.array_equal(faces, basis.faces):
        return TemplateMesh(verts)
    return Scan(verts, faces)


@dataclass(frozen=True)
class Options:
    """How the workflows solve: H2 weights (None: the basis'), registration schedule (None: the
    basis'), pre-alignment and varifold kernel (``RegistrationConfig``'s), further registration settings
    (``registration``: overrides of ``RegistrationConfig``, dotted keys such as "poses.finalists"), geodesic
    time points and L-BFGS cap, torch device and dtype (and ``path_dtype``, that of a geodesic between
    two known codes).

    steps is the time resolution of the boundary value problem, not the number of keyframes
    written (``path_between`` resamples to those): on humanoid geodesics keyframed at 24 frames,
    10 points move the frames by at most 1.1 mm from 24 points at 40 % of the time, 6 points by 3.5 mm.
    """

    weights: H2Weights | str | None = None
    schedule: tuple | None = None
    prealign: bool = True
    kernel: str | tuple = "auto"
    steps: int = 10
    max_iter: int = 500
    device: str = "cpu"
    dtype: torch.dtype = torch.float64
    path_dtype: torch.dtype | None = torch.float32
    registration: dict = field(default_factory=dict)

    def registration_config(self, basis):
        """The ``RegistrationConfig`` of a scan's registration: the basis' defaults, these options' schedule,
        pre-alignment, kernel, metric, device and dtype, then the ``registration`` overrides."""
        settings = {"prealign": self.prealign, "kernel": self.kernel, "metric": self.weights, "dtype": self.dtype,
                    "device": self.device}
        if self.schedule is not None:
            settings["schedule"] = self.schedule
        return registration.RegistrationConfig.from_basis(basis, **settings).with_overrides(self.registration)

    def path_tensors(self, basis):
        """The basis' tensors in which a geodesic between two known codes is solved: ``path_dtype`` (None:
        ``dtype``). float32 halves the time of each iteration; with ``geodesics.FRAMES_PLATEAU`` the path
        is within 0.2 mm of float64's on human bodies."""
        return basis.tensors(dtype=self.path_dtype or self.dtype, device=self.device)

    def metric(self, basis):
        """The H2 weights to solve paths with (the basis' ``weights`` unless given)."""
        return basis.weights if self.weights is None else H2Weights.parse(self.weights)

    def shape_metric(self, basis):
        """The H2 weights measured from the template (registration, log maps, random bodies): the
        basis' ``shape_metric`` unless given."""
        return basis.shape_metric if self.weights is None else H2Weights.parse(self.weights)

    def tensors(self, basis):
        """The basis' (template (N, 3), faces (F, 3), fields (P, N, 3)) on this device and dtype."""
        return basis.tensors(dtype=self.dtype, device=self.device)


# ------------------------------------------------------------------------------------ codes


def check_device(device):
    """A torch device name the solvers can use here ("cpu", "cuda", "cuda:1"): -> the name; InputError
    (one line) when torch does not know it or sees no such GPU."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise InputError(f"unknown device {device!r}: use cpu, cuda or cuda:N") from None
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise InputError(f"device {device!r}: this torch sees no CUDA GPU (a CPU-only build, or no driver); "
                             "use cpu")
        if dev.index is not None and dev.index >= count:
            raise InputError(f"device {device!r}: this machine has {count} CUDA GPU(s) (cuda:0-{count - 1})")
    elif dev.type != "cpu":
        raise InputError(f"device {device!r}: the solver runs on cpu or cuda")
    return str(device)


@dataclass
class MatchedEnd:
    """One end of a symmetric matching, as a registration gives it: code (P,), transform (scan ->
    template frame), vertices (N, 3) in the scan's frame, varifold residual, Chamfer to the scan; detail the
    end's ``registration.detail.Detail`` (its displacement None when turned off or left out)."""

    code: np.ndarray
    transform: object
    vertices: np.ndarray
    varifold: float
    chamfer: float
    detail: object = None


@dataclass
class Code:
    """The code (P,) of one input; detail (N, 3) its off-basis detail, template frame: what the basis misses of a
    TemplateMesh, the detail layer of a registered or matched Scan (``registration.detail``), a KnownCode's own
    (None without);
    registration the RegistrationResult of a Scan, or the MatchedEnd of a matched one (else None)."""

    code: np.ndarray
    detail: np.ndarray | None = None
    registration: object = None


def code_of(basis, item, options=Options(), callback=None, cancel=None):
    """The code of one input: a KnownCode as is, a TemplateMesh projected, a Scan registered: -> Code."""
    if isinstance(item, KnownCode):
        detail = None if item.detail is None else np.asarray(item.detail, dtype=np.float64)
        return Code(np.asarray(item.code, dtype=np.float64), detail=detail)
    if isinstance(item, TemplateMesh):
        code = latent.project_to_basis(basis, item.verts)[0]
        return Code(code, detail=latent.off_basis_detail(basis, item.verts, code))
    if isinstance(item, Scan):
        res = registration.register(basis, item.verts, item.faces, options.registration_config(basis),
                                    landmarks=item.landmarks, scan_face_weights=item.face_weights,
                                    callback=callback, cancel=cancel)
        return Code(res.code, detail=res.detail, registration=res)
    raise InputError(f"an input is a Scan, a TemplateMesh or a KnownCode, got {type(item).__name__}")


def codes_of(basis, items, options=Options(), callback=None, cancel=None):
    """Codes of several inputs, the progress bar shared by the scans among them: -> list of Code."""
    monitor = Monitor("codes", callback, cancel)
    scans = [i for i, item in enumerate(items) if isinstance(item, Scan)]
    out = []
    for i, item in enumerate(items):
        sub = None
        if i in scans:
            k = scans.index(i)
            sub = monitor.scaled(k / len(scans), (k + 1) / len(scans), tag={"item": i})
        out.append(code_of(basis, item, options, sub, cancel))
    return out


def _scan_share(items, share=0.5):
    """Share of a progress bar given to registering the inputs: share if any is a Scan, else 0."""
    return share if any(isinstance(item, Scan) for item in items) else 0.0


def matched_ends(basis, matching, scans, config=None, callback=None, cancel=None):
    """Both ends of a symmetric matching of two Scans, each with its detail layer when ``config`` (a
    ``RegistrationConfig``) asks for one: -> (MatchedEnd, MatchedEnd)."""
    monitor = Monitor("detail", callback, cancel)
    ends = []
    for k, scan in enumerate(scans):
        code = matching.path[0 if k == 0 else -1]
        verts = matching.transforms[k].invert(basis.template + np.tensordot(code, basis.fields, axes=1))
        detail = None
        if config is not None and config.detail.enabled:
            detail = registration.detail_of(basis, code, matching.transforms[k], scan.verts, scan.faces, config,
                                            scan.face_weights, monitor=monitor, progress=(k / 2, (k + 1) / 2))
        ends.append(MatchedEnd(code=code, transform=matching.transforms[k], vertices=verts,
                               varifold=matching.varifold[k], chamfer=evaluation.chamfer(verts, scan.verts),
                               detail=detail))
    return tuple(ends)


# ------------------------------------------------------------------------------------ paths


@dataclass
class LatentPath:
    """A geodesic between two inputs: ends (Code, Code); path (T, P) as solved; distance; frames
    (n_frames, P) evenly paced keyframes and detail (n_frames, N, 3) the inputs' off-basis detail
    along them (None when not asked for / not both inputs have detail); matching when both were scans."""

    ends: tuple
    path: np.ndarray
    distance: float
    frames: np.ndarray | None = None
    detail: np.ndarray | None = None
    matching: object = None


def _detail_along(ends, times, keep_detail):
    """Off-basis detail of two ends along times (T,): -> (T, N, 3), or None without detail at both ends."""
    if not keep_detail or ends[0].detail is None or ends[1].detail is None:
        return None
    return latent.detail_along(ends[0].detail, ends[1].detail, times)


def geodesic_between(basis, a, b, options=Options(), callback=None, cancel=None):
    """The geodesic between two inputs: two Scans by symmetric matching (codes and path in one solve),
    otherwise their codes, then the boundary value problem preconditioned at the template: -> LatentPath."""
    monitor = Monitor("geodesic", callback, cancel)
    weights = options.metric(basis)
    if isinstance(a, Scan) and isinstance(b, Scan):
        config = options.registration_config(basis)
        share = registration.DETAIL_SHARE if config.detail.enabled else 1.0  # then both ends' detail layers
        m = registration.symmetric_match(basis, (a.verts, a.faces), (b.verts, b.faces), steps=options.steps,
                                         config=config, weights=None if options.weights is None else weights,
                                         face_weights=(a.face_weights, b.face_weights),
                                         landmarks=(a.landmarks, b.landmarks), callback=monitor.scaled(0.0, share),
                                         cancel=cancel)
        ends = tuple(Code(e.code, detail=None if e.detail is None else e.detail.displacement, registration=e)
                     for e in matched_ends(basis, m, (a, b), config, monitor.scaled(share, 1.0), cancel))
        return LatentPath(ends=ends, path=m.path, distance=m.distance, matching=m)
    lo = _scan_share((a, b))
    ends = tuple(codes_of(basis, [a, b], options, monitor.scaled(0.0, lo), cancel))
    template, faces, fields = options.path_tensors(basis)
    g = geodesics.geodesic(template, faces, fields, ends[0].code, ends[1].code, weights, steps=options.steps,
                           max_iter=options.max_iter, callback=monitor.scaled(lo, 1.0), cancel=cancel,
                           plateau=geodesics.FRAMES_PLATEAU)
    return LatentPath(ends=ends, path=g.path, distance=g.distance)


def path_between(basis, a, b, n_frames, options=Options(), anchor=True, keep_detail=True, callback=None,
                 cancel=None):
    """n_frames evenly paced keyframes between two inputs: ``geodesic_between``, then
    ``geodesics.keyframe_path`` (anchored unless anchor is False); the inputs' off-basis detail is
    carried along when both have some (unless keep_detail is False): -> LatentPath with frames."""
    monitor = Monitor("path", callback, cancel)
    found = geodesic_between(basis, a, b, options, monitor.scaled(0.0, 0.95), cancel)
    template, faces, fields = options.tensors(basis)
    found.frames = geodesics.keyframe_path(template, faces, fields, found.path, options.metric(basis), n_frames,
                                           anchor=anchor)
    found.detail = _detail_along(found.ends, np.linspace(0.0, 1.0, len(found.frames)), keep_detail)
    monitor.report(1.0, "path done")
    return found


@dataclass
class Continuation:
    """A motion continued along the geodesic: ends (Code, Code) of the inputs; path (n_new + 2, P),
    frames 0 and 1 the inputs; detail (n_new + 2, N, 3) their off-basis detail continued linearly, or None;
    shooting the ``shooting.ShootingReport`` (where time was refined); same_frame, for two Scans, whether the
    second was registered in the first's frame (``in_frame_of``), else None."""

    ends: tuple
    path: np.ndarray
    detail: np.ndarray | None = None
    shooting: object = None
    same_frame: bool | None = None


#: The second of two scans refitted in the first's frame is kept when its mean distance to the scan
#: (``RegistrationResult.residual``) is at most this many times its own registration's: scans of one capture
#: share a frame, scans of two sessions do not (their refit cannot take the body's move between them).
SAME_FRAME_RESIDUAL = 1.1


def in_frame_of(basis, first, second, scan, options=Options(), callback=None, cancel=None):
    """The second of two registered scans refitted in the first's frame (``registration.register_in_frame``),
    so that their codes differ by the motion between them and not also by a difference of alignments the pose
    fields absorb, nor by the directions a scan barely determines: started from the first's code (as a
    capture's next frame), else, where that fit is far from the scan (the poses are far apart), from its own
    code. first, second: Codes of Scans; scan the second Scan -> its Code, the refitted one, or ``second``
    itself where neither refit comes within SAME_FRAME_RESIDUAL of its own fit (not one frame)."""
    own = second.registration
    monitor = Monitor("same frame", callback, cancel)
    for k, start in enumerate((first.code, second.code)):
        res = registration.register_in_frame(basis, scan.verts, scan.faces, first.registration.transform, start,
                                             options.registration_config(basis), landmarks=scan.landmarks,
                                             scan_face_weights=scan.face_weights,
                                             callback=monitor.scaled(k / 2, (k + 1) / 2), cancel=cancel)
        if own.residual is None or res.residual is None or res.residual <= SAME_FRAME_RESIDUAL * own.residual:
            return Code(res.code, detail=res.detail, registration=res)
    return second


def extrapolate(basis, a, b, n_new, options=Options(), anchor=True, keep_detail=True, callback=None, cancel=None):
    """Continue the motion a -> b by n_new geodesic steps (``shooting.extrapolate``, anchored unless
    anchor is False), with the off-basis detail continued as the latent line is: -> Continuation.

    Two Scans are taken as frames of one capture: the second is refitted in the first's frame
    (``in_frame_of``; ``Continuation.same_frame`` says whether that refit was kept).

    Where no step converges even at the finest refinement, the frame is finished in the metric frozen there
    (``shooting.extrapolate(frozen=True)``; ``Continuation.shooting.frozen`` names those frames). The motion
    stops with ShootingFailed (naming the frame; ``reached``: the Continuation of the frames before it) at the
    first frame that creases a joint flat that the inputs did not (a patch of collapsed triangles or a flattened
    one: MOTION_CREASE): it has left the bodies the basis can make."""
    monitor = Monitor("extrapolate", callback, cancel)
    lo = _scan_share((a, b))
    both = isinstance(a, Scan) and isinstance(b, Scan)
    ends = tuple(codes_of(basis, [a, b], options, monitor.scaled(0.0, 0.8 * lo if both else lo), cancel))
    same_frame = None
    if both:  # two scans of one capture: the second refitted in the first's frame
        second = in_frame_of(basis, ends[0], ends[1], b, options, monitor.scaled(0.8 * lo, lo), cancel)
        same_frame = second is not ends[1]
        ends = (ends[0], second)
    inputs = [end.code for end in ends]
    reference = input_quality(basis, inputs)

    def check(code):
        body = basis.template + np.tensordot(code, basis.fields, axes=1)
        return CREASED_MOTION if creased(basis.template, basis.faces, body, reference=reference,
                                         **MOTION_CREASE) else None

    def continuation(path, report=None):  # the frames, their detail continued as the latent line is
        return Continuation(ends=ends, path=path, detail=_detail_along(ends, np.arange(len(path)), keep_detail),
                            shooting=report, same_frame=same_frame)

    template, faces, fields = options.tensors(basis)
    try:
        path, report = shooting.extrapolate(template, faces, fields, ends[0].code, ends[1].code,
                                            options.metric(basis), n_new, callback=monitor.scaled(lo, 1.0),
                                            cancel=cancel, anchor=anchor, with_report=True, frozen=True,
                                            frame_check=check)
    except FrameRejected as err:
        k = len(err.frames)
        fewer = f"ask for at most {k} frame{'s' if k > 1 else ''}" if k else "start from closer inputs"
        failed = shooting.ShootingFailed(f"{err}; {fewer}", frames=err.frames)
        # the frames before it, as asking for k frames would give them (``Continuation``; nothing is lost)
        path = np.concatenate([np.stack(inputs), err.frames])
        if anchor:
            path = shooting.anchor_extrapolation(template, fields, path)
        failed.reached = continuation(path)
        raise failed from None
    except shooting.ShootingFailed as err:
        first = first_creased(basis, err.frames, inputs, **MOTION_CREASE)
        if first is None:
            raise
        raise shooting.ShootingFailed(f"{err}; frame {first} already creases a joint flat that the inputs did not: "
                                      "the motion has left the bodies the basis can make", frames=err.frames) from None
    return continuation(path, report)


#: Why an extrapolated frame is refused (``extrapolate``).
CREASED_MOTION = ("it creases a joint flat that the inputs did not: the motion has left the bodies the basis "
                  "can make")
#: An extrapolated frame is refused (``creased``) when triangles that keep less than ``floor`` of their quality in
#: the inputs (``input_quality``) cover more than ``share`` of the template's surface (a patch a user sees, not
#: a sliver of a finger), or when one keeps less than ``flat`` of it (flattened). Real motions at full flexion
#: go far below random bodies' CREASE_QUALITY; the measurements behind the values are in
#: docs/decisions/023-motion-metric-fit.md.
MOTION_CREASE = {"floor": 0.01, "share": 1e-4, "flat": 1e-3}


def distances(basis, items, options=Options(), callback=None, cancel=None):
    """Geodesic distance between every two inputs (their codes, then one geodesic per pair):
    -> (n, n) symmetric, zero diagonal."""
    monitor = Monitor("distances", callback, cancel)
    lo = _scan_share(items)
    codes = [c.code for c in codes_of(basis, items, options, monitor.scaled(0.0, lo), cancel)]
    template, faces, fields = options.tensors(basis)
    weights = options.metric(basis)
    n = len(codes)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    d = np.zeros((n, n))
    for k, (i, j) in enumerate(pairs):
        sub = monitor.scaled(lo + (1 - lo) * k / len(pairs), lo + (1 - lo) * (k + 1) / len(pairs))
        d[i, j] = d[j, i] = geodesics.geodesic(template, faces, fields, codes[i], codes[j], weights,
                                               steps=options.steps, max_iter=options.max_iter, callback=sub,
                                               cancel=cancel).distance
    return d


# ------------------------------------------------------------------------------------ statistics


@dataclass
class Transfer:
    """Motion on another identity: motion (T, P); identity the Code of the identity input
    (with its registration when it was a scan); detail (T, N, 3) the identity's off-basis detail on every
    frame (None when it has none)."""

    motion: np.ndarray
    identity: Code

    @property
    def detail(self):
        """The identity's detail carried onto every frame: (T, N, 3), or None."""
        if self.identity.detail is None:
            return None
        return np.broadcast_to(self.identity.detail, (len(self.motion),) + self.identity.detail.shape)


def transfer(basis, frames, identity, group, options=Options(), callback=None, cancel=None):
    """The motion of the frame inputs with the identity group's coefficients of ``identity``
    (``statistics.transfer_motion``): -> Transfer."""
    identity_slice = basis.group_slice(group)
    codes = codes_of(basis, [*frames, identity], options, callback, cancel)
    motion = statistics.transfer_motion(np.stack([c.code for c in codes[:-1]]), codes[-1].code, identity_slice)
    return Transfer(motion=motion, identity=codes[-1])


#: A random body whose geodesic cannot be shot is retried with twice the steps, then replaced by a
#: further draw; at most this many draws per requested body (about half the ``human`` draws crease a
#: joint: with 10, one body asked for is not found once in a thousand seeds).
DRAWS_PER_BODY = 10
#: A random body is replaced by a further draw when one of its triangles keeps less than this share of
#: its shape quality on the template (``mesh.triangle_quality``): a joint creased flat. Measured on 50
#: random ``human`` bodies drawn without it (seeds 0 and 1): 16 of the 17 bodies with self-intersecting
#: faces had a triangle under 0.1 of its template quality, against 5 of the 33 without; 25 ``deformables``
#: bodies kept 0.52 or more.
CREASE_QUALITY = 0.1


def creased(template, faces, verts, floor=CREASE_QUALITY, reference=None, share=0.0, flat=0.0):
    """Whether a body (N, 3) in the template's topology has triangles under ``floor`` of their quality on the
    template (N, 3), faces (F, 3) (a joint creased flat, where limbs run through each other) covering more
    than ``share`` of the template's surface (0: any one triangle), or one triangle under ``flat`` of it
    (flattened: refused alone); reference (F,): the qualities to judge against instead of the template's (e.g.
    ``input_quality`` of a motion's frames: did the motion crease a triangle its inputs did not?)."""
    reference = triangle_quality(template, faces) if reference is None else np.asarray(reference, dtype=np.float64)
    ratio = np.divide(triangle_quality(verts, faces), reference, out=np.ones_like(reference), where=reference > 0)
    below = ratio < floor
    if not below.any():
        return False
    if not share or ratio.min() < flat:  # any one triangle counts, or one is flattened
        return True
    area = face_geometry(template, faces)[1]
    return bool(area[below].sum() > share * area.sum())


def input_quality(basis, codes):
    """Each triangle's quality in the worst of the bodies of codes (K, P), and never above the template's:
    what a motion through them is judged against -> (F,)."""
    quality = triangle_quality(basis.template, basis.faces)
    for code in np.atleast_2d(codes):
        quality = np.minimum(quality, triangle_quality(basis.template + np.tensordot(code, basis.fields, axes=1),
                                                       basis.faces))
    return quality


def first_creased(basis, codes, inputs=None, floor=CREASE_QUALITY, share=0.0, flat=0.0):
    """The number (1-based) of the first of codes (K, P) whose body is ``creased`` (at ``floor``, over more than
    ``share`` of the surface, or one triangle under ``flat``), or None (also
    for codes None); inputs (J, P): the motion's input codes, judged against (a registered person's triangles
    may be thinner than the template's already: only what the motion creased counts), else the template."""
    if codes is None:
        return None
    reference = None if inputs is None else input_quality(basis, inputs)
    for k, code in enumerate(codes):
        if creased(basis.template, basis.faces, basis.template + np.tensordot(code, basis.fields, axes=1),
                   floor=floor, reference=reference, share=share, flat=flat):
            return k + 1
    return None


def stored_distribution(basis):
    """The Gaussian mixture a basis stores (its ``gmm_*`` extras): -> dict, empty when it has none."""
    return {k: v for k, v in basis.extras.items() if k.startswith("gmm_")}


def sample_bodies(template, faces, fields, distribution, groups, weights, n, seed, steps, callback=None,
                  cancel=None):
    """n random codes: initial velocities drawn from ``distribution``, shot from the template.

    Like ``statistics.sample_codes`` (the same first n draws for a seed), except that a
    draw whose geodesic does not converge is shot again with 2 x steps and, failing that,
    replaced by a draw from a second stream of the same seed, and so is a draw whose body is
    ``creased`` or has more crossing faces than the template (``mesh.self_intersections``: a limb
    through the body); a shot stops at its first creased frame (its end would be creased too, and the
    steps near a crease are refined and cost most). -> (codes (n, P), replaced draws).
    """
    monitor = Monitor("sample", callback, cancel)
    velocities = list(statistics.sample_velocities(distribution, groups, n, seed))
    spares = iter(statistics.sample_velocities(distribution, groups, (DRAWS_PER_BODY - 1) * n, [seed, 1]))
    codes, replaced, error = [], 0, None
    template_np, faces_np = template.detach().cpu().double().numpy(), faces.detach().cpu().numpy()
    fields_np = fields.detach().cpu().double().numpy()
    allowed = len(self_intersections(template_np, faces_np))  # a template's own touching parts are not the draw's

    def crease_check(code):
        """Why a frame of the shot is refused: a joint creased flat stays creased to the end of the path
        (every creased human shot measured), where the steps are refined and cost most."""
        if creased(template_np, faces_np, template_np + np.tensordot(code, fields_np, axes=1)):
            return "the body creases a joint flat"
        return None

    while len(codes) < n:
        v = velocities.pop(0) if velocities else next(spares, None)
        if v is None:
            raise shooting.ShootingFailed(f"only {len(codes)} of {n} random bodies could be shot from the basis' "
                                          f"distribution ({error}); use more shooting steps or fit the "
                                          "distribution to shapes of your own")
        for k in (steps, 2 * steps):
            monitor.report(len(codes) / n, f"body {len(codes) + 1}/{n}" + (f" ({k} steps)" if k > steps else ""))
            try:
                code = shooting.shoot(template, faces, fields, np.zeros_like(v), v, weights, steps=k, cancel=cancel,
                                      frame_check=crease_check)[-1]
            except FrameRejected:
                error = "their bodies crease a joint flat"
                replaced += 1
                break
            except shooting.ShootingFailed as err:
                error = err
                continue
            body = template_np + np.tensordot(code, fields_np, axes=1)
            if creased(template_np, faces_np, body):
                error = "their bodies crease a joint flat"
                replaced += 1
            elif len(self_intersections(body, faces_np)) > allowed:
                error = "their limbs run through their bodies"
                replaced += 1
            else:
                codes.append(code)
            break
        else:
            replaced += 1
    return np.stack(codes), replaced


@dataclass
class RandomBodies:
    """Random codes (n, P) and how many draws could not be shot and were replaced by further draws."""

    codes: np.ndarray
    replaced: int = 0


def random_bodies(basis, n, seed, options=Options(), fit=None, components=1, shoot_steps=8, callback=None,
                  cancel=None):
    """n seeded random bodies (``sample_bodies``: retried, replaced draws counted), shot from the
    template in the basis' ``shape_metric``, from its stored distribution or from a mixture of
    ``components`` per group fitted to the initial velocities (``statistics.log_map``) of the codes of
    the inputs ``fit``: -> RandomBodies."""
    monitor = Monitor("random bodies", callback, cancel)
    template, faces, fields = options.tensors(basis)
    weights = options.shape_metric(basis)  # the metric the stored distribution was fitted in
    if fit is None:
        distribution, lo = stored_distribution(basis), 0.0
        if not distribution:
            raise InputError(f"basis '{basis.name}' stores no distribution: fit one to two or more shapes")
    else:
        mid = _scan_share(fit, 0.25)
        codes = np.stack([c.code for c in codes_of(basis, fit, options, monitor.scaled(0.0, mid), cancel)])
        velocities = statistics.log_map(template, faces, fields, codes, weights, callback=monitor.scaled(mid, 0.5),
                                        cancel=cancel)
        distribution = statistics.fit_distribution(velocities, basis.groups, {g: components for g in basis.groups},
                                                   seed=seed)
        lo = 0.5
    codes, replaced = sample_bodies(template, faces, fields, distribution, basis.groups, weights, n, seed,
                                    shoot_steps, monitor.scaled(lo, 1.0), cancel)
    return RandomBodies(codes=codes, replaced=replaced)
