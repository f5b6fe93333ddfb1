"""Register many scans on a Dask ``distributed`` cluster: a registered mesh and a JSON record per scan.

``register_batch`` (``cluster``) runs ``registration.register`` on a ``LocalCluster`` or on an existing
scheduler, writing as each scan finishes ``NAME.ply`` (the registered template in the scan's frame) and
``NAME.json`` (code, alignment, varifold / Chamfer / fit residuals, seconds, worker, input and basis
hashes), and at the end ``summary.csv`` / ``summary.json`` (``records``). A scan's ignore mask and
landmarks are files next to it (``SIDECARS``). A rerun skips the scans whose record matches the
input's (mesh and sidecar files) and the basis' sha256; a scan that fails (a ``BareEsaError``) is
recorded with its one-line error and the others go on.

With ``sequence=True`` the scans are the frames of one 4D capture, in order, cut into chunks that run
in parallel, each frame warm-started from the previous one, the seams between chunks checked for jumps
(``frames``). ``register_scans`` (``in_memory``) is the same on scans in memory, for the add-on; the
workers import the solver as ``bareesa`` from its own folder, so a copy vendored inside another package
(the Blender extension) runs on them as well (``vendored``).
Dask is an optional dependency (``pip install 'bareesa[batch]'``), imported only when a batch runs.
"""

from ..errors import BareEsaError, InputError, SolveCancelled
from ..registration import WARM_LEVELS, warm_schedule
from .cluster import MISSING_DASK, register_batch
from .frames import SEAM_FACTOR, chunks_of, register_one
from .in_memory import POLL_EVERY, PROGRESS_EVERY, PROGRESS_TOPIC, plain_options, register_array, register_scans
from .records import (RECORD_VERSION, SIDECARS, SUMMARY_COLUMNS, SUMMARY_CSV, SUMMARY_JSON, BatchReport, file_hash,
                      input_hash, output_names, registered_meshes, scan_sidecars, write_atomic, write_summary)

__all__ = ["BareEsaError", "BatchReport", "InputError", "MISSING_DASK", "POLL_EVERY", "PROGRESS_EVERY",
           "PROGRESS_TOPIC", "RECORD_VERSION", "SEAM_FACTOR", "SIDECARS", "SUMMARY_COLUMNS", "SUMMARY_CSV",
           "SUMMARY_JSON", "SolveCancelled", "WARM_LEVELS", "chunks_of", "file_hash", "input_hash", "output_names",
           "plain_options", "register_array", "register_batch", "register_one", "register_scans",
           "registered_meshes", "scan_sidecars", "warm_schedule", "write_atomic", "write_summary"]
