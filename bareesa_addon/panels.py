"""The "BaRe-ESA" tab of the 3D Viewport sidebar: one sub-panel per workflow step."""

import bpy

from . import jobs
from .convert import (PROP_BASIS, PROP_BASIS_NAME, PROP_CHAMFER, PROP_DETAIL_CHAMFER, PROP_POOR_FIT, PROP_RANGE,
                      PROP_VARIFOLD)
from .operators.common import TRAINING_STDS
from .preferences import OPTIONAL_MODULES, dependency_status
from .properties import OTHER_BASIS


def length_text(context, value):
    """A length (metres, scene scale 1) in the scene's units, as Blender writes it (e.g. '2.3 mm')."""
    units = context.scene.unit_settings
    if units.system == "NONE":
        return f"{value:.3g}"
    return bpy.utils.units.to_string(units.system, "LENGTH", value / units.scale_length, precision=3,
                                     split_unit=units.use_separate)


def split(layout):
    """Blender's property layout: labels left of the fields, no animation decorators: -> layout."""
    layout.use_property_split = True
    layout.use_property_decorate = False
    return layout


class _Section:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "BaRe-ESA"


class BAREESA_PT_main(_Section, bpy.types.Panel):
    """The BaRe-ESA sidebar tab in the 3D Viewport."""

    bl_label = "BaRe-ESA"
    bl_idname = "BAREESA_PT_main"

    def draw(self, context):
        layout = split(self.layout)
        status = dependency_status()
        missing = [name for name, ok in status.items() if not ok and name not in OPTIONAL_MODULES]
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
            if PROP_CHAMFER in obj:
                box.label(text=f"Chamfer {length_text(context, obj[PROP_CHAMFER])}   "
                               f"varifold {obj.get(PROP_VARIFOLD, 0.0):.3g}")
            if PROP_DETAIL_CHAMFER in obj:
                box.label(text=f"With detail: Chamfer {length_text(context, obj[PROP_DETAIL_CHAMFER])}")
            if obj.get(PROP_POOR_FIT, False):
                box.label(text="Poor fit: far from the scan for this basis", icon="ERROR")
            if obj.get(PROP_RANGE, 0.0) > TRAINING_STDS:
                box.label(text=f"Outside the training range ({obj[PROP_RANGE]:.1f} std)", icon="ERROR")


class BAREESA_PT_basis(_Section, bpy.types.Panel):
    bl_label = "Basis"
    bl_parent_id = "BAREESA_PT_main"

    def draw(self, context):
        s = context.scene.bareesa
        layout = split(self.layout)
        col = layout.column()
        col.prop(s, "basis_choice")
        if s.basis_choice == OTHER_BASIS:
            col.prop(s, "basis_file")
            if s.basis and s.basis != s.basis_file:
                col.label(text=f"Now: {s.basis}", icon="FILE")
        col.prop(s, "metric")
        if s.metric == "CUSTOM":
            col.prop(s, "metric_custom")
        layout.operator("bareesa.load_template", icon="OUTLINER_OB_MESH")


class BAREESA_PT_register(_Section, bpy.types.Panel):
    bl_label = "Register"
    bl_parent_id = "BAREESA_PT_main"

    def draw(self, context):
        s = context.scene.bareesa
        layout = split(self.layout)
        col = layout.column()
        col.prop(s, "schedule")
        col.prop(s, "prealign")
        col.prop(s, "pose_search")
        col.prop(s, "retry_poor_fits")
        col.prop(s, "detail_layer")
        col.prop(s, "registration_settings")
        obj = context.active_object
        if obj is not None and obj.type == "MESH":
            col.prop_search(s, "mask_group", obj, "vertex_groups")
        else:
            col.prop(s, "mask_group")
        layout.operator("bareesa.add_landmarks", icon="EMPTY_AXIS")
        n = sum(o.type == "MESH" for o in context.selected_objects)
        layout.operator("bareesa.register_scan", text=f"Register {n} Selected" if n else "Register Selected",
                        icon="MOD_SHRINKWRAP")
        layout.operator("bareesa.transfer_texture", icon="TEXTURE")


class BAREESA_PT_paths(_Section, bpy.types.Panel):
    bl_label = "Interpolate / Extrapolate"
    bl_parent_id = "BAREESA_PT_main"

    def draw(self, context):
        s = context.scene.bareesa
        layout = split(self.layout)
        col = layout.column()
        col.prop(s, "object_a")
        col.prop(s, "object_b")
        col = layout.column()
        col.prop(s, "steps")
        col.prop(s, "geodesic_iterations")
        col.prop(s, "anchor")
        col = layout.column(heading="Frames")
        col.prop(s, "use_frame_range")
        sub = col.column(align=True)
        sub.enabled = s.use_frame_range
        sub.prop(s, "frame_start")
        sub.prop(s, "frame_end", text="End")
        col.prop(s, "make_collection")
        layout.operator("bareesa.interpolate", icon="IPO_EASE_IN_OUT")
        col = layout.column()
        col.prop(s, "extrapolate_source")
        col.prop(s, "extrapolate_steps")
        col.prop(s, "extrapolate_spacing")
        layout.operator("bareesa.extrapolate", icon="FORWARD")


class BAREESA_PT_motion(_Section, bpy.types.Panel):
    bl_label = "Motion Transfer"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        layout = split(self.layout)
        col = layout.column()
        col.prop(s, "motion_source")
        col.prop(s, "motion_collection")
        col.prop(s, "motion_target")
        col.prop(s, "identity_group")
        layout.operator("bareesa.transfer_motion", icon="ARMATURE_DATA")


class BAREESA_PT_random(_Section, bpy.types.Panel):
    bl_label = "Random Bodies"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        layout = split(self.layout)
        col = layout.column()
        col.prop(s, "count")
        col.prop(s, "seed")
        col.prop(s, "fit_collection")
        col.prop(s, "shoot_steps")
        layout.operator("bareesa.generate_random", icon="COMMUNITY")


class BAREESA_PT_build(_Section, bpy.types.Panel):
    bl_label = "Build Basis"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        layout = split(self.layout)
        col = layout.column()
        col.prop(s, "build_source")
        col.prop(s, "build_collection")
        col.prop(s, "build_name")
        col.prop(s, "build_group")
        col.prop(s, "build_components")
        layout.operator("bareesa.build_basis", icon="NODETREE")


class BAREESA_PT_distance(_Section, bpy.types.Panel):
    bl_label = "Distance"
    bl_parent_id = "BAREESA_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s = context.scene.bareesa
        layout = split(self.layout)
        if s.distance >= 0:
            layout.label(text=f"{s.distance_pair}: {s.distance:.4g}", icon="DRIVER_DISTANCE")
        col = layout.column()
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
