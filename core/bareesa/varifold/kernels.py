"""The varifold kernels, the option checks and the rule of ``backend="auto"``."""

import contextlib
import io
import math
import os
import platform

import torch

from ..errors import InputError

#: Orientation kernels kappa(t) = c0 + c1 t + c2 t^2 of t = n . n' (unit normals): (c0, c1, c2)
KERNELS = {"binet": (0.0, 0.0, 1.0), "linear": (0.0, 1.0, 0.0), "constant": (1.0, 0.0, 0.0)}
#: Dimension K of the features that make each orientation kernel a dot product (binned measures)
FEATURE_DIMS = {"binet": 9, "linear": 3, "constant": 1}
BACKENDS = ("auto", "dense", "keops", "truncated")
DEFAULT_TOL = 1e-6
DENSE_MAX_PAIRS = 2e7
#: ... but with pykeops a cutoff below a quarter of the extent is truncated from this many pairs on: below
#: it dense sums are as fast, above it KeOps' block-sparse sums skip most pairs (see
#: docs/decisions/002-varifold-backends-and-cells.md). The torch fallback of the truncated sums is no faster than dense.
TRUNCATE_MIN_PAIRS = 1.5e6

#: Whether pykeops imports (None: not tried yet); set it to False to force the torch code paths.
_KEOPS = None
#: Environment variable that turns KeOps off ("1"): for a machine where its compiled code crashes
#: (a crash cannot be caught; seen with pykeops 2.3 on a CUDA 13 GPU).
NO_KEOPS_ENV = "BAREESA_NO_KEOPS"
#: C++ flags KeOps compiles its CPU kernels with on Linux x86_64 when the environment sets no CXXFLAGS
#: (KeOps' own: -O3): the machine's vector instructions, no errno or trap semantics to keep for exp, and
#: the loop over j vectorised: its sums reassociated (-fassociative-math) and exp taken from glibc's
#: vector math library (libmvec, within 4 ulp), which glibc's headers declare only under __FAST_MATH__.
#: Not -ffast-math itself: GCC 12 then links crtfastmath into the kernel, which flushes denormals to zero
#: in the whole process (Blender's too) once it loads, and assumes no NaN. The sums stay within rounding of
#: IEEE's (see docs/decisions/003-keops-cpu-flags.md). KeOps keeps its binaries per host
#: name and per flags, so a cluster's nodes each build their own.
KEOPS_CPU_FLAGS = ("-march=native -fno-math-errno -fno-trapping-math -fno-signed-zeros -fassociative-math "
                   "-D__FAST_MATH__")


@contextlib.contextmanager
def _keops_cpu_flags():
    """CXXFLAGS = KEOPS_CPU_FLAGS while pykeops imports (it reads them then), on Linux x86_64 when unset."""
    own = "CXXFLAGS" not in os.environ and platform.system() == "Linux" and platform.machine() == "x86_64"
    if own:
        os.environ["CXXFLAGS"] = KEOPS_CPU_FLAGS
    try:
        yield
    finally:
        if own:
            del os.environ["CXXFLAGS"]


def keops_available():
    """True when pykeops imports (its LazyTensor is then used by "keops" and "truncated"), unless
    ``$BAREESA_NO_KEOPS`` is 1."""
    global _KEOPS
    if _KEOPS is None and os.environ.get(NO_KEOPS_ENV, "") == "1":
        _KEOPS = False
    if _KEOPS is None:
        try:
            # KeOps prints its banner and compile messages on stdout, which would corrupt
            # the CLI's JSON output: keep its import quiet and turn its verbosity off.
            with contextlib.redirect_stdout(io.StringIO()), _keops_cpu_flags():
                import pykeops
                import pykeops.torch  # noqa: F401
            pykeops.set_verbose(False)
            _KEOPS = True
        except Exception:  # ImportError, or a broken compiler setup at import time
            _KEOPS = False
    return _KEOPS


def disable_keops():
    """Turn KeOps off for this process (``keops_available`` False from now on: the torch code paths)."""
    global _KEOPS
    _KEOPS = False


def is_oriented(kernel):
    """Whether a kernel tells a face from its flipped copy (an odd term c1 t): then the scan's faces
    must be wound consistently with the template's."""
    return KERNELS[kernel][1] != 0.0


def default_cutoff(sigma, tol=DEFAULT_TOL):
    """Cutoff radius beyond which the spatial kernel is <= tol: sigma * sqrt(log(1/tol))."""
    return float(sigma) * math.sqrt(math.log(1.0 / tol))


def choose_backend(n_source, n_target, sigma, extent, device, cutoff=None):
    """Backend for "auto": see the package docstring. extent = bounding-box diagonal of both meshes."""
    device = torch.device(device)
    cutoff = default_cutoff(sigma) if cutoff is None else float(cutoff)
    if device.type == "cuda":
        return "keops" if keops_available() else "dense"
    truncates = cutoff < 0.25 * float(extent)
    if truncates and keops_available() and max(n_source, n_target) ** 2 >= TRUNCATE_MIN_PAIRS:
        return "truncated"
    if max(n_source, n_target) ** 2 < DENSE_MAX_PAIRS:
        return "dense"
    if truncates:
        return "truncated"
    return "keops" if keops_available() else "dense"


def resolve_backend(backend, points, other_points, sigma, cutoff=None):
    """``backend``, or for "auto" ``choose_backend``'s choice for two point sets (N, 3), (M, 3)."""
    if backend != "auto":
        return backend
    pts = torch.cat([points, other_points]).detach()
    extent = float((pts.max(0).values - pts.min(0).values).norm())
    return choose_backend(points.shape[0], other_points.shape[0], sigma, extent, points.device, cutoff)


def check_options(sigma, kernel, backend, cutoff):
    """InputError unless the kernel (None: not checked), backend, sigma and cutoff are valid: -> sigma."""
    if kernel is not None and kernel not in KERNELS:
        raise InputError(f"unknown varifold kernel {kernel!r}; choose one of {sorted(KERNELS)}")
    if backend not in BACKENDS:
        raise InputError(f"unknown varifold backend {backend!r}; choose one of {list(BACKENDS)}")
    if backend == "keops" and not keops_available():
        raise InputError("backend 'keops' needs pykeops, which is not importable here; "
                         "install pykeops or use backend='dense' / 'truncated' / 'auto'")
    try:
        sigma = float(sigma)
    except (TypeError, ValueError):
        raise InputError(f"sigma must be a positive number, got {sigma!r}") from None
    if not (sigma > 0 and math.isfinite(sigma)):
        raise InputError(f"sigma must be a positive finite number, got {sigma}")
    if cutoff is not None and not (float(cutoff) > 0 and math.isfinite(float(cutoff))):
        raise InputError(f"cutoff must be a positive finite number or None, got {cutoff}")
    return sigma
