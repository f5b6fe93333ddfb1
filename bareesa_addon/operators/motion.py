"""Transfer Motion.

The identity's off-basis detail goes onto the new object as ``workflows.Transfer.detail`` carries it (the
same on every frame): its detail keys as they are now (a registered object's ``KnownCode`` carries them,
``convert.detail_of``) or its detail layer (a scan registered by the solve), one 'Detail' key at 1. The
motion's own detail stays with the body that made it.
"""

import bpy
import numpy as np
from bpy.props import StringProperty

from .. import convert as cv
from ..jobs import SolveOperator, Task
from .common import (TRAINING_STDS, add_registered, check_codes, common_basis, find_object, first_frame, frame_range,
                     is_registered, object_input, refuse, select_only, selected_meshes, settings, solve_options,
                     sorted_meshes, template_object, training_excess, workflows, write_keys)


def motion_objects(source, collection):
    """The objects a motion is read from: a collection's meshes (two or more, by name) or the animated source."""
    if collection is not None:
        objects = sorted_meshes(collection)
        if len(objects) < 2:
            raise cv.ConversionError(f"collection '{collection.name}' holds {len(objects)} meshes: a motion needs two")
        return objects
    cv.require_mesh(source, "motion source")
    return [source]


def frame_input(context, obj, basis):
    """A frame of a motion as it is now: KnownCode if registered, a TemplateMesh (projected, fast and
    exact in the span) if in template topology, else a Scan."""
    if is_registered(obj):
        return object_input(context, obj, basis)
    return workflows().mesh_input(basis, *cv.evaluated_mesh(obj, context.evaluated_depsgraph_get()))


def motion_frames(context, objects, per_object, basis):
    """Source motion as one workflow input per frame, and the frame numbers.

    per_object: one frame per object (a collection, from the panel's Start); else the one object
    evaluated on every frame of the range (shape keys, caches, modifiers: whatever Blender evaluates).
    """
    if per_object:
        return [frame_input(context, o, basis) for o in objects], first_frame(context) + np.arange(
            len(objects))
    scene, frames = context.scene, frame_range(context)
    current = scene.frame_current
    out = []
    try:
        for f in frames:
            scene.frame_set(int(f))
            out.append(frame_input(context, objects[0], basis))
    finally:
        scene.frame_set(current)
    return out, frames


class BAREESA_OT_transfer_motion(SolveOperator, bpy.types.Operator):
    """Give the motion of an animated mesh (no armature needed) to another body's identity, as a new object
    with the identity's detail"""

    bl_idname = "bareesa.transfer_motion"
    bl_label = "Transfer Motion"

    @classmethod
    def poll(cls, context):
        s = context.scene.bareesa
        return refuse(cls, None if s.motion_target or selected_meshes(context) else
                      "choose the identity: set Identity in the panel or select the body")

    source: StringProperty(name="Motion", default="", description="Animated object (empty: the panel's)")
    source_collection: StringProperty(name="Frames", default="", description="Collection of per-frame objects")
    target: StringProperty(name="Identity", default="", description="Target body (empty: the panel's or active)")

    def prepare(self, context):
        s = settings(context)
        collection = bpy.data.collections.get(self.source_collection) if self.source_collection else None
        if self.source_collection and collection is None:
            raise cv.ConversionError(f"no collection named '{self.source_collection}'")
        source = bpy.data.objects.get(self.source) if self.source else s.motion_source
        if collection is None and source is None:
            collection = s.motion_collection
        if collection is None and source is None:
            raise cv.ConversionError("choose the motion: an animated mesh or a collection of per-frame meshes")
        target = bpy.data.objects.get(self.target) if self.target else (s.motion_target or
                                                                         context.view_layer.objects.active)
        cv.require_mesh(target, "identity target")
        if target == source:
            raise cv.ConversionError("the motion source and the identity target are the same object")
        objects = motion_objects(source, collection)
        basis, ref = common_basis(context, objects + [target])
        group = s.identity_group
        basis.group_slice(group)  # an unknown group is reported now
        frames_in, frames = motion_frames(context, objects, collection is not None, basis)
        target_in = object_input(context, target, basis)  # (a registered one's with its detail)
        options = solve_options(context, basis)
        target_name = target.name
        wf = workflows()

        def solve(callback, cancel):
            return wf.transfer(basis, frames_in, target_in, group, options, callback, cancel)

        def apply(context, result):
            cv.check_code(result.motion, "the transferred motion")
            check_codes([result.identity])
            body = find_object(target_name)
            made = []
            if result.identity.registration is not None:  # a scan: its fit is a new object too
                body = add_registered(context, basis, ref, body, result.identity.registration,
                                      detail=result.identity.detail)
                made.append(body)
            coll = body.users_collection[0] if body.users_collection else None
            obj = template_object(context, basis, ref, f"{body.name}_motion", coll, code=result.motion[0],
                                  hint=result.motion)
            obj.matrix_world = body.matrix_world
            write_keys(obj, basis, frames, result.motion)
            if result.identity.detail is not None:
                cv.set_detail_key(obj, basis.template, result.identity.detail)
            excess = training_excess(basis, result.motion)
            obj[cv.PROP_RANGE] = excess
            select_only(context, made + [obj])
            if excess > TRAINING_STDS:
                self.report({"WARNING"}, f"'{obj.name}': the motion on this identity reaches {excess:.1f} standard "
                                         f"deviations from the basis' training codes (range: {TRAINING_STDS:g}); "
                                         "expect implausible shapes")
            return (f"'{obj.name}': {len(frames)} frames of motion keyframed ({frames[0]}-{frames[-1]}) "
                    f"on a new object; '{body.name}' is unchanged")

        return Task("transfer motion", solve, apply)
