"""BaRe-ESA for Blender: the Blender side (operators, N-panel, conversions).

Thin by design: all mathematics lives in the solver ``core``, which never
imports bpy. For now the add-on registers an N-panel that reports which
solver dependencies import; operators arrive with the Blender issue.
"""

import importlib.util

import bpy

SOLVER_MODULES = ("torch", "scipy", "numpy", "trimesh", "pykeops", "sklearn")


def dependency_status():
    """{module name: importable?} for the solver's dependencies (no import is executed)."""
    return {name: importlib.util.find_spec(name) is not None for name in SOLVER_MODULES}


class BAREESA_PT_main(bpy.types.Panel):
    """The BaRe-ESA sidebar tab in the 3D Viewport."""

    bl_label = "BaRe-ESA"
    bl_idname = "BAREESA_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "BaRe-ESA"

    def draw(self, context):
        layout = self.layout
        col = layout.column(align=True)
        col.label(text="Solver dependencies:")
        for name, ok in dependency_status().items():
            col.label(text=name, icon="CHECKMARK" if ok else "ERROR")


CLASSES = (BAREESA_PT_main,)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
