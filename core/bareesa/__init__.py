"""BaRe-ESA: basis-restricted elastic shape analysis of surface meshes.

Pure Python on torch/scipy/numpy (pykeops where it pays); never imports bpy. The
modules, lowest first (each imports only modules above it in this list):

errors, progress, threads         exceptions; progress/cancel callbacks; BLAS pools held to one thread
optimize                          L-BFGS
geometry, transforms, mesh        discrete differential geometry; the similarity type; mesh I/O
h2_metric, varifold, evaluation   the H2 metric and path energy; the data term; metrics
latent, basis_io                  Basis, decoder, latent metric, projection; basis files
geodesics, shooting               boundary and initial value problems in the latent space
registration                      codes of raw scans (pre-alignment, levels, poses, two scans)
statistics, basis_building        motion transfer, log map, random bodies; bases from data
workflows                         what the CLI and the Blender add-on both call
cli                               the ``bareesa`` command
"""

__version__ = "0.1.0"

from .basis_io import load_basis, save_basis
from .errors import BareEsaError, InputError, MeshError, ShootingFailed, SolveCancelled, SolveDiverged
from .geodesics import Geodesic, geodesic
from .h2_metric import PRESETS, H2Weights
from .latent import Basis, Level, decode, project_to_basis
from .mesh import load_mesh, save_mesh
from .progress import CancelToken, ProgressEvent
from .registration import Matching, RegistrationResult, register, symmetric_match
from .shooting import extrapolate, shoot
from .transforms import Similarity
from .varifold import VarifoldLoss, varifold_distance

__all__ = ["BareEsaError", "Basis", "CancelToken", "Geodesic", "H2Weights", "InputError", "Level", "Matching",
           "MeshError", "PRESETS", "ProgressEvent", "RegistrationResult", "ShootingFailed", "Similarity",
           "SolveCancelled", "SolveDiverged", "VarifoldLoss", "decode", "extrapolate", "geodesic", "load_basis",
           "load_mesh", "project_to_basis", "register", "save_basis", "save_mesh", "shoot", "symmetric_match",
           "varifold_distance", "__version__"]
