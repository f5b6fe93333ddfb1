"""Per-basis constants a registration would otherwise compute in every process, kept in the basis."""

import numpy as np

from ..threads import with_one_blas_thread
from .config import RegistrationConfig
from .prealign import moment_table

#: ``Basis.extras`` key of the surface moments of the decoded pose prototypes (``prealign.moment_table``),
#: with the codes they are of under this key + "_codes"
PROTOTYPE_MOMENTS = "pose_prototype_moments"
#: The extras ``prepare_basis`` computes (a basis' own template metric, "template_metric", is the basis'
#: and stays as it was built)
PREPARED_EXTRAS = ("shape_template_metric", "shape_template_metric_weights", PROTOTYPE_MOMENTS,
                   PROTOTYPE_MOMENTS + "_codes")


@with_one_blas_thread
def prepare_basis(basis):
    """Compute the per-basis constants every registration would otherwise compute once per process and
    keep them in ``basis.extras`` (a basis saved afterwards carries them): the template metric of its shape
    weights (``Basis.template_metric``) and the surface moments of its decoded pose prototypes
    (``PROTOTYPE_MOMENTS``) -> basis; ``python -m bases.build --derived`` stores them in the bundled
    files."""
    basis.template_metric()  # (the basis' own weights first: the first metric asked for would take its key)
    basis.template_metric(basis.shape_metric)
    poses = RegistrationConfig().pose_candidates(basis)
    if poses is not None:
        reference_moments(basis, poses, basis.template + np.tensordot(poses, basis.fields, axes=1))
    return basis


def reference_moments(basis, poses, references):
    """The surface moments of the decoded pose candidates (K, N, 3) (``prealign.moment_table``): stored in
    ``basis.extras`` when they are the basis' own pose prototypes (PROTOTYPE_MOMENTS, with the codes they
    are of), else computed -> (K, 12)."""
    key = PROTOTYPE_MOMENTS
    stored, of = basis.extras.get(key), basis.extras.get(key + "_codes")
    if (stored is not None and of is not None and np.shape(stored) == (len(poses), 12)
            and np.isfinite(stored).all() and np.array_equal(of, poses)):
        return stored
    table = moment_table(references, basis.faces)
    if np.array_equal(poses, basis.extras.get("pose_prototypes")):
        basis.extras[key], basis.extras[key + "_codes"] = table, np.array(poses, dtype=np.float64)
    return table
