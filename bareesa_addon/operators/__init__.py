"""One operator per user action, grouped by workflow step. Each gathers inputs (main thread), calls
``bareesa.workflows`` (in the job's solve), writes the results (apply) and reports.

Modules: ``common`` (settings, bases, template objects, keys, selection, objects as workflow
inputs), ``basis`` (Load Template, Build Basis), ``register`` (Register Scans), ``paths``
(Interpolate, Extrapolate, Distance), ``motion`` (Transfer Motion), ``random`` (Generate Random),
``landmarks`` (Add Landmarks), ``texture`` (Transfer Texture).
The idnames (``bareesa.load_template``, ``bareesa.register_scan``, ``bareesa.interpolate``,
``bareesa.extrapolate``, ``bareesa.transfer_motion``, ``bareesa.generate_random``,
``bareesa.build_basis``, ``bareesa.distance``, ``bareesa.add_landmarks``, ``bareesa.transfer_texture``) are a
public scripting interface. String arguments left empty fall back to the scene settings of the panel
(``scene.bareesa``).
"""

import bpy

from .basis import BAREESA_OT_build_basis, BAREESA_OT_load_template
from .landmarks import BAREESA_OT_add_landmarks
from .motion import BAREESA_OT_transfer_motion
from .paths import BAREESA_OT_distance, BAREESA_OT_extrapolate, BAREESA_OT_interpolate
from .random import BAREESA_OT_generate_random
from .register import BAREESA_OT_register_scan
from .texture import BAREESA_OT_transfer_texture

CLASSES = (BAREESA_OT_load_template, BAREESA_OT_register_scan, BAREESA_OT_interpolate, BAREESA_OT_extrapolate,
           BAREESA_OT_transfer_motion, BAREESA_OT_generate_random, BAREESA_OT_build_basis, BAREESA_OT_distance,
           BAREESA_OT_add_landmarks, BAREESA_OT_transfer_texture)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
