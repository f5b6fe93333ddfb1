"""Interpolate, Extrapolate and (Geodesic) Distance.

The off-basis detail of the inputs goes along a path as the solver carries it (``workflows.path_between``,
``extrapolate``: linearly in time, ``latent.detail_along``, when both ends have some). An input's detail is
its detail keys as they are now (a registered object: ``convert.detail_of``) or its detail layer (a scan
registered by the solve). On the new object it is two keys (``convert.write_detail``): 'Detail' = the first
frame's at 1 and 'Detail Change' = the last frame's minus the first's, keyed from 0 to 1 with linear keys,
which is the carried detail exactly on every frame. Extrapolating an object's keyframes keys its animated
detail keys on the new frames along the line through their values at the last two keyframes
(``convert.continue_detail``): the same linear continuation; static ones hold, as a constant detail does.
"""

import csv

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, StringProperty

from .. import convert as cv
from .. import solver
from ..jobs import SolveOperator, Task
from ..properties import EXTRAPOLATE_SOURCES
from .common import (add_registered, check_codes, common_basis, find_object, first_frame, frame_range,
                     has_pair_or_selection, is_registered, new_collection, object_basis, object_detail, object_input,
                     output_path, own_or_panel, pick_pair, refuse, registered_code, select_only, settings,
                     solve_options, sorted_meshes, template_object, workflows, write_keys)


def detail_note(detail, ends, names):
    """What a path's report says of the detail it carries (detail (T, N, 3) or None; the Codes and names of
    its two inputs)."""
    if detail is not None:
        return "; with the inputs' detail (Detail keys)"
    has = [end.detail is not None for end in ends]
    if any(has):
        return f"; without detail: only '{names[has.index(True)]}' has some"
    return ""


class BAREESA_OT_interpolate(SolveOperator, bpy.types.Operator):
    """Geodesic between two registered objects (or scans) keyframed on every frame, evenly paced, with their
    detail carried along"""

    bl_idname = "bareesa.interpolate"
    bl_label = "Interpolate"

    @classmethod
    def poll(cls, context):
        return refuse(cls, None if has_pair_or_selection(context) else
                      "choose two objects: set From and To in the panel, or select two meshes")

    object_a: StringProperty(name="From", default="")
    object_b: StringProperty(name="To", default="")
    anchor: BoolProperty(name="Keep Body Planted", default=True,
                         description="Keep the body's unmoving part where the straight line between the ends puts it "
                                     "(not set: the panel's setting)")

    def prepare(self, context):
        a, b = pick_pair(context, self.object_a, self.object_b)
        basis, ref = common_basis(context, (a, b))
        inputs = [object_input(context, o, basis) for o in (a, b)]  # (a registered one's with its detail)
        frames = frame_range(context)
        options, anchor = solve_options(context, basis), own_or_panel(self, context, "anchor")
        make_meshes = settings(context).make_collection
        names_ab = (a.name, b.name)
        wf = workflows()

        def solve(callback, cancel):
            return wf.path_between(basis, *inputs, len(frames), options, anchor=anchor, callback=callback,
                                   cancel=cancel)

        def apply(context, found):
            check_codes(found.ends)
            path = found.frames
            cv.check_code(path, "the geodesic")
            a_obj, b_obj = (find_object(n) for n in names_ab)
            ts = np.linspace(0.0, 1.0, len(frames))  # path_between's times of the frames
            detail = found.detail
            made = []
            ends = []
            for obj, end in zip((a_obj, b_obj), found.ends):
                if end.registration is not None:
                    made.append(add_registered(context, basis, ref, obj, end.registration, detail=end.detail))
                    ends.append(made[-1].matrix_world.copy())
                else:
                    ends.append(obj.matrix_world.copy())
            name = f"{a_obj.name}_to_{b_obj.name}"
            obj = template_object(context, basis, ref, name, code=path[0], hint=path)
            write_keys(obj, basis, frames, path)
            if detail is not None:
                cv.write_detail(obj, basis.template, frames, detail, ts)
            matrices = [cv.blend_matrices(ends[0], ends[1], t) for t in ts]
            cv.keyframe_transforms(obj, frames, matrices)
            settings(context).distance = found.distance
            settings(context).distance_pair = f"{a_obj.name} - {b_obj.name}"
            if make_meshes:
                coll = new_collection(context, f"{name}_frames")
                verts = basis.template + np.tensordot(path, basis.fields, axes=1)
                if detail is not None:
                    verts = verts + detail
                for f, v, m in zip(frames, verts, matrices):
                    frame_obj = cv.new_mesh_object(f"{name}_{int(f):04d}", v, basis.faces, coll,
                                                   uv=basis.extras.get("template_uv"))
                    frame_obj.matrix_world = m
            select_only(context, made + [obj])
            return (f"'{name}': geodesic keyframed on frames {frames[0]}-{frames[-1]}, "
                    f"distance {found.distance:.4g}{detail_note(detail, found.ends, names_ab)}")

        return Task("interpolate", solve, apply)


class BAREESA_OT_extrapolate(SolveOperator, bpy.types.Operator):
    """Continue a motion along the geodesic: from two objects (other -> active) or the last two keyframes, with
    its detail continued"""

    bl_idname = "bareesa.extrapolate"
    bl_label = "Extrapolate"

    @classmethod
    def poll(cls, context):
        return refuse(cls, None if has_pair_or_selection(context) else
                      "choose two registered objects, or select one with shape-key keyframes")

    source: EnumProperty(name="Direction From", items=EXTRAPOLATE_SOURCES, default="AUTO",
                         description="What gives the direction (not set: the panel's setting)")
    object_a: StringProperty(name="From", default="")
    object_b: StringProperty(name="To", default="")
    anchor: BoolProperty(name="Keep Body Planted", default=True,
                         description="Keep the body's unmoving part where the straight latent line puts it "
                                     "(not set: the panel's setting)")

    def prepare(self, context):
        s = settings(context)
        mode = own_or_panel(self, context, "source", "extrapolate_source")
        if mode == "AUTO":
            two = (self.object_a and self.object_b) or (s.object_a and s.object_b) or len(
                context.selected_objects) == 2
            mode = "OBJECTS" if two else "KEYFRAMES"
        if mode == "OBJECTS":
            a, b = pick_pair(context, self.object_a, self.object_b)
            for o in (a, b):
                if not is_registered(o):
                    raise cv.ConversionError(f"'{o.name}' is not registered: register it first")
            basis, ref = common_basis(context, (a, b))
            names = solver.field_names(basis)
            alpha0, alpha1 = registered_code(a, basis, names), registered_code(b, basis, names)
            details = [object_detail(o, basis) for o in (a, b)]
            names_ab = (a.name, b.name)
            target_name = None
            frames = first_frame(context) + s.extrapolate_spacing * np.arange(s.extrapolate_steps + 2)
            label = f"{a.name}_{b.name}_extrapolated"
        else:
            obj = bpy.data.objects.get(self.object_b) if self.object_b else context.view_layer.objects.active
            if not is_registered(obj):
                raise cv.ConversionError("select a registered object with at least two shape-key keyframes "
                                         "(or choose two registered objects)")
            basis, ref = object_basis(obj)
            names = solver.field_names(basis)
            registered_code(obj, basis, names)
            keyed = cv.keyed_frames(obj, names)
            if len(keyed) < 2:
                raise cv.ConversionError(f"'{obj.name}' has {len(keyed)} shape-key keyframes: need two to "
                                         "give a direction")
            f0, f1 = keyed[-2], keyed[-1]
            alpha0, alpha1 = cv.code_at_frame(obj, names, f0), cv.code_at_frame(obj, names, f1)
            details, names_ab = [None, None], None
            target_name = obj.name
            frames = f1 + (f1 - f0) * np.arange(-1, s.extrapolate_steps + 1)
            label = obj.name
        options, n_new = solve_options(context, basis), s.extrapolate_steps
        anchor = own_or_panel(self, context, "anchor")
        wf = workflows()
        ends = (wf.KnownCode(alpha0, detail=details[0]), wf.KnownCode(alpha1, detail=details[1]))

        def solve(callback, cancel):
            return wf.extrapolate(basis, *ends, n_new, options, anchor=anchor, callback=callback, cancel=cancel)

        def apply(context, motion):
            path = motion.path
            cv.check_code(path, "the extrapolated motion")
            relaxed = motion.shooting.speed_relaxed if motion.shooting is not None else []
            if relaxed:
                self.report({"WARNING"}, f"the motion's speed varied at new frame{'s' * (len(relaxed) > 1)} "
                                         f"{', '.join(map(str, relaxed))}: the body passes a creased, almost flat "
                                         "joint there (kept at the finest time step)")
            frozen = motion.shooting.frozen if motion.shooting is not None else []
            if frozen:
                self.report({"WARNING"}, f"no geodesic step converged at new frame{'s' * (len(frozen) > 1)} "
                                         f"{', '.join(map(str, frozen))}: continued there in the metric of the frame "
                                         "before")
            note = ""
            if target_name is None:
                times = np.arange(len(path), dtype=np.float64)  # extrapolate's: the inputs at 0 and 1
                detail = motion.detail
                obj = template_object(context, basis, ref, label, code=path[0], hint=path)
                write_keys(obj, basis, frames, path)
                if detail is not None:
                    cv.write_detail(obj, basis.template, frames, detail, times)
                note = detail_note(detail, motion.ends, names_ab)
                select_only(context, [obj])
            else:
                obj = find_object(target_name)
                write_keys(obj, basis, frames[2:], path[2:], replace=False)
                held = cv.continue_detail(obj, frames[0], frames[1], frames[2:])
                if held:
                    self.report({"WARNING"}, f"'{obj.name}': the detail was not continued: {', '.join(held)} "
                                             f"would pass Blender's slider limit ({cv.SLIDER_LIMIT:g}); it holds "
                                             "its last keyed value")
            return f"'{obj.name}': {n_new} extrapolated keyframes up to frame {int(frames[-1])}{note}"

        return Task("extrapolate", solve, apply)


class BAREESA_OT_distance(SolveOperator, bpy.types.Operator):
    """Geodesic distance between two objects, or a distance matrix of a collection written to CSV"""

    bl_idname = "bareesa.distance"
    bl_label = "Geodesic Distance"

    @classmethod
    def poll(cls, context):
        some = context.scene.bareesa.distance_collection or has_pair_or_selection(context)
        return refuse(cls, None if some else "choose a collection, or two objects (From and To, or select two)")

    collection: StringProperty(name="Collection", default="", description="Pairwise distances of its objects")
    filepath: StringProperty(name="CSV", subtype="FILE_PATH", default="")
    object_a: StringProperty(name="From", default="")
    object_b: StringProperty(name="To", default="")

    def prepare(self, context):
        s = settings(context)
        coll = bpy.data.collections.get(self.collection) if self.collection else s.distance_collection
        if self.collection and coll is None:
            raise cv.ConversionError(f"no collection named '{self.collection}'")
        if coll is not None:
            objects = sorted_meshes(coll)
            if len(objects) < 2:
                raise cv.ConversionError(f"collection '{coll.name}' holds {len(objects)} meshes: need two or more")
            csv_path = output_path(self.filepath or s.distance_csv, "distance CSV")
        else:
            objects, csv_path = list(pick_pair(context, self.object_a, self.object_b)), None
        basis, _ = common_basis(context, objects)
        inputs = [object_input(context, o, basis) for o in objects]
        options = solve_options(context, basis)
        labels = [o.name for o in objects]
        wf = workflows()

        def solve(callback, cancel):
            return wf.distances(basis, inputs, options, callback, cancel)

        def apply(context, d):
            if not np.isfinite(d).all():
                raise cv.ConversionError("a distance is not finite (the solve diverged); nothing was written")
            s = settings(context)
            if csv_path is None:
                s.distance, s.distance_pair = float(d[0, 1]), f"{labels[0]} - {labels[1]}"
                return f"geodesic distance {labels[0]} - {labels[1]}: {d[0, 1]:.6g}"
            csv_path.parent.mkdir(parents=True, exist_ok=True)
            with open(csv_path, "w", newline="") as fh:
                writer = csv.writer(fh)
                writer.writerow([""] + labels)
                for label, row in zip(labels, d):
                    writer.writerow([label] + [f"{x:.9g}" for x in row])
            return f"{len(labels)}x{len(labels)} distance matrix written to {csv_path}"

        return Task("distance", solve, apply)
