"""The "BaRe-ESA" tab of the 3D Viewport sidebar: one sub-panel per workflow step."""

import bpy

from . import jobs
from .convert import PROP_BASIS, PROP_BASIS_NAME, PROP_CHAMFER, PROP_VARIFOLD
from .preferences import dependency_status


class _Section:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "BaRe-ESA"


class BAREESA_PT_main(_Section, bpy.types.Panel):
    """The BaRe-ESA sidebar tab in the 3D Viewport."""

    bl_label = "BaRe-ESA"
    bl_idname = "BAREESA_PT_main"

    def draw(self, context):
        layout = self.layout
        status = dependency_status()
        missing = [name for name, ok in status.items() if not ok and name != "pykeops"]
        if missing:
            col = layout.column(align=True)
            col.label(text="Missing: " + ", ".join(missing), icon="ERROR")
            col.operator("bareesa.install_dependencies", icon="IMPORT")
        for job in list(jobs.RUNNING):
            layout.progress(factor=job.fraction, type="BAR", text=f"{job.message} (Esc cancels)")
        obj = context.active_object
        if obj is not None and PROP_BASIS in obj:
            box = layout.box()
            box.label(text=f"{obj.name}: basis {obj.get(PROP_BASIS_NAME, obj[PROP_BASIS])}", icon="SHAPEKEY_DATA")
            if PROP_VARIFOLD in obj:
                box.label(text=f"varifold {obj[PROP_VARIFOLD]:.3g}   Chamfer {obj[PROP_CHAMFER]:.3g}")


class BAREESA_PT_basis(_Section, bpy.types.Panel):
    bl_label = "Basis"
    bl_parent_id = "BAREESA_PT_main"

    def draw(self, context):
        s = context.scene.bareesa
        col = self.layout.column(align=True)
        col.prop(s, "basis")
        col.prop(s, "metric")
        if s.metric == "CUSTOM":
            col.prop(s, "metric_custom")
        self.layout.operator("bareesa.load_template", icon="OUTLINER_OB_MESH")


class BAREESA_PT_register(_Section, bpy.types.Panel):
    bl_label = "Register"
    bl_parent_id = "BAREESA_PT_main"

    def draw(self, context):
        s = context.scene.bareesa
        col = self.layout.column(align=True)
        col.prop(s, "schedule")
        col.prop(s, "prealign")
        n = sum(o.type == "MESH" for o in context.selected_objects)
        row = self.layout.row()
        row.enabled = n > 0
        row.operator("bareesa.register_scan", text=f"Register {n} Selected" if n else "Select Scans",
                     icon="MOD_SHRINKWRAP")


class BAREESA_PT_paths(_Section, bpy.types.Panel):
    bl_label = "Interpolate / Extrapolate"
    bl_parent_id = "BAREESA_PT_main"

    def draw(self, context):
        s = context.scene.bareesa
        layout = self.layout
        col = layout.column(align=True)
        col.prop(s, "object_a")
        col.prop(s, "object_b")
        col = layout.column(align=True)
        row = col.row(align=True)
        row.prop(s, "steps")
        row.prop(s, "geodesic_iterations")
        row = col.row(align=True)
        row.prop(s, "frame_start")
        row.prop(s, "frame_end")
        col.prop(s, "make_collection")
        layout.operator("bareesa.interpolate", icon="IPO_EASE_IN_OUT")
        col = layout.column(align=True)
        row = col.row(align=True)
        row.prop(s, "extrapolate_steps")
        row.prop(s, "extrapolate_spacing")
        layout.operator("bareesa.extrapolate", icon="FORWARD")


class BAREESA_PT_motion(_Section, bpy.types.Panel):
    bl_label = "Motion Transfer"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        col = self.layout.column(align=True)
        col.prop(s, "motion_source")
        col.prop(s, "motion_collection")
        col.prop(s, "motion_target")
        col.prop(s, "identity_group")
        self.layout.operator("bareesa.transfer_motion", icon="ARMATURE_DATA")


class BAREESA_PT_random(_Section, bpy.types.Panel):
    bl_label = "Random Bodies"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        col = self.layout.column(align=True)
        row = col.row(align=True)
        row.prop(s, "count")
        row.prop(s, "seed")
        col.prop(s, "fit_collection")
        col.prop(s, "shoot_steps")
        self.layout.operator("bareesa.generate_random", icon="COMMUNITY")


class BAREESA_PT_build(_Section, bpy.types.Panel):
    bl_label = "Build Basis"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        col = self.layout.column(align=True)
        col.prop(s, "build_source")
        col.prop(s, "build_collection")
        col.prop(s, "build_name")
        row = col.row(align=True)
        row.prop(s, "build_group")
        row.prop(s, "build_components")
        self.layout.operator("bareesa.build_basis", icon="NODETREE")


class BAREESA_PT_distance(_Section, bpy.types.Panel):
    bl_label = "Distance"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        layout = self.layout
        if s.distance >= 0:
            layout.label(text=f"{s.distance_pair}: {s.distance:.4g}", icon="DRIVER_DISTANCE")
        col = layout.column(align=True)
        col.prop(s, "distance_collection")
        col.prop(s, "distance_csv")
        layout.operator("bareesa.distance", icon="DRIVER_DISTANCE")


CLASSES = (BAREESA_PT_main, BAREESA_PT_basis, BAREESA_PT_register, BAREESA_PT_paths, BAREESA_PT_motion,
           BAREESA_PT_random, BAREESA_PT_build, BAREESA_PT_distance)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
