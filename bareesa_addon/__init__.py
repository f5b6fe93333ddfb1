"""BaRe-ESA for Blender: the Blender side (operators, N-panel, conversions, background jobs).

Thin by design: all mathematics lives in the solver package ``bareesa``, which
never imports bpy (vendored as ``<extension>/bareesa`` in the installable extension).
Modules: ``convert`` (bpy <-> arrays), ``operators`` (one per user action),
``jobs`` (solves off the main thread), ``panels`` (the sidebar), ``properties``
(scene settings), ``preferences`` (dependencies, device), ``solver`` (access to the solver).
"""

from . import operators, panels, preferences, properties
from .panels import BAREESA_PT_main
from .preferences import SOLVER_MODULES, dependency_status

__all__ = ["BAREESA_PT_main", "SOLVER_MODULES", "dependency_status", "register", "unregister"]

MODULES = (preferences, properties, operators, panels)


def register():
    for module in MODULES:
        module.register()


def unregister():
    for module in reversed(MODULES):
        module.unregister()
