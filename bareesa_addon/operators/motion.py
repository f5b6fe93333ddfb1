"""Transfer Motion."""

import bpy
import numpy as np
from bpy.props import StringProperty

from .. import convert as cv
from ..jobs import SolveOperator, Task
from .common import (add_registered, check_codes, common_basis, find_object, frame_range, is_registered,
                     object_input, select_only, settings, solve_options, sorted_meshes, workflows, write_keys)


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
        return [frame_input(context, o, basis) for o in objects], settings(context).frame_start + np.arange(
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
    """Give the motion of an animated mesh (no armature needed) to another body's identity"""

    bl_idname = "bareesa.transfer_motion"
    bl_label = "Transfer Motion"

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
        target_in = object_input(context, target, basis)
        options = solve_options(context, basis)
        target_name = target.name
        wf = workflows()

        def solve(callback, cancel):
            return wf.transfer(basis, frames_in, target_in, group, options, callback, cancel)

        def apply(context, result):
            cv.check_code(result.motion, "the transferred motion")
            check_codes([result.identity])
            obj = find_object(target_name)
            if result.identity.registration is not None:
                obj = add_registered(context, basis, ref, obj, result.identity.registration)
                select_only(context, [obj])
            write_keys(obj, basis, frames, result.motion)
            return f"'{obj.name}': {len(frames)} frames of motion keyframed ({frames[0]}-{frames[-1]})"

        return Task("transfer motion", solve, apply)
