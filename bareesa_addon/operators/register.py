"""Register Scans."""

import bpy
from bpy.props import IntProperty, StringProperty

from .. import convert as cv
from .. import solver
from ..jobs import SolveOperator, Task
from ..preferences import solver_processes, user_bases_dir
from .common import (add_registered, check_codes, find_object, load_basis, refuse, scan_input, select_only,
                     selected_meshes, settings, solve_options, template_object, workflows, write_code)


def detail_note(registration):
    """What the report says of a registration's detail layer: its detailed Chamfer, why it was left out, or
    nothing (turned off, or a registration without one)."""
    report = getattr(registration, "detail_report", None) or {}
    if getattr(registration, "detail", None) is not None:
        return f", detailed Chamfer {report['chamfer']:.3g}" if report.get("chamfer") is not None else ""
    if report.get("skipped") and report["skipped"] != "turned off":
        return f", no detail layer ({report['skipped']})"
    return ""


class BAREESA_OT_register_scan(SolveOperator, bpy.types.Operator):
    """Register each selected scan (any mesh): a new object in template topology whose shape keys are its code,
    and a 'Detail' key with the scan's own detail the basis cannot make (the panel's Detail Layer)"""

    bl_idname = "bareesa.register_scan"
    bl_label = "Register Scans"

    @classmethod
    def poll(cls, context):
        return refuse(cls, None if selected_meshes(context) else "select one or more scan meshes to register")

    basis: StringProperty(name="Basis", default="", description="Bundled name or .npz path (empty: the panel's)")
    processes: IntProperty(name="Processes", default=-1, min=-1, max=256,
                           description="Worker processes for several scans (-1: the add-on preference, 0: one "
                                       "per CPU core, 1: one scan at a time in Blender)")

    def prepare(self, context):
        selected = list(context.selected_objects)
        scans = [o for o in selected if o.type == "MESH"]
        skipped = [o.name for o in selected if o.type != "MESH"]
        if not scans:
            raise cv.ConversionError("select one or more scan meshes to register"
                                     + (f" (not meshes: {', '.join(skipped)})" if skipped else ""))
        basis, ref = load_basis(self.basis or settings(context).basis)
        wf = workflows()
        inputs = [scan_input(context, o, basis) for o in scans]
        names = [o.name for o in scans]
        options = solve_options(context, basis)
        processes = solver_processes(len(inputs), context, self.processes)
        basis_file = solver.load_basis(ref, user_bases_dir())[1]  # worker processes load the basis by path

        notes = []

        def solve(callback, cancel):
            if processes > 1:
                # several scans at once in worker processes (Dask), one progress bar; a scan that fails is
                # reported and the others are still registered
                try:
                    results = solver.module("batch").register_scans(basis_file, inputs, options, workers=processes,
                                                                    callback=callback, cancel=cancel)
                    return [r if isinstance(r, Exception) else wf.Code(r.code, detail=r.detail, registration=r)
                            for r in results]
                except solver.module("errors").WorkersUnavailable as err:
                    notes.append(f"{err}: registered one at a time in Blender instead")
            return wf.codes_of(basis, inputs, options, callback, cancel)

        shown = {}  # input index -> name of its preview object

        def show(context, preview):
            """The fit so far as a '<scan>_registered (preview)' object over its scan."""
            item = preview.get("item", 0)
            scan = bpy.data.objects.get(names[item])
            if scan is None:
                return
            obj = bpy.data.objects.get(shown.get(item, ""))
            if obj is None:
                obj = template_object(context, basis, ref, f"{names[item]}_registered (preview)",
                                      scan.users_collection[0] if scan.users_collection else None)
                obj.display_type = "WIRE"
                obj.hide_select = True
                shown[item] = obj.name
            write_code(obj, basis, preview["code"])
            obj.matrix_world = scan.matrix_world @ cv.similarity_inverse_matrix(preview["transform"])

        def clear(context):
            for name in shown.values():
                obj = bpy.data.objects.get(name)
                if obj is not None:
                    mesh = obj.data
                    bpy.data.objects.remove(obj)
                    if mesh is not None and mesh.users == 0:
                        bpy.data.meshes.remove(mesh)
            shown.clear()

        def apply(context, results):
            failed = [(n, r) for n, r in zip(names, results) if isinstance(r, Exception)]
            if len(failed) == len(results):
                raise failed[0][1]
            kept = [(n, r) for n, r in zip(names, results) if not isinstance(r, Exception)]
            codes = [r for _, r in kept]
            check_codes(codes)
            scan_objects = [find_object(n) for n, _ in kept]
            made = [add_registered(context, basis, ref, scan, c.registration, detail=c.detail)
                    for scan, c in zip(scan_objects, codes)]
            for note in notes:
                self.report({"WARNING"}, note)
            for name, err in failed:
                self.report({"WARNING"}, f"'{name}' was not registered: {str(err).removeprefix('scan ')}")
            select_only(context, made)
            poor = [o.name for o, c in zip(made, codes) if getattr(c.registration, "poor_fit", False)]
            if poor:
                self.report({"WARNING"}, f"poor fit: {', '.join(poor)} {'are' if len(poor) > 1 else 'is'} far from "
                                         f"the scan, beyond what basis '{basis.name}' reaches on its own scans; check "
                                         "the selection, mask floors or add landmarks")
            retried = [o.name for o, c in zip(made, codes) if getattr(c.registration, "retried_alignments", 0)]
            if retried:
                self.report({"INFO"}, f"the first fit of {', '.join(retried)} was poor: registered again from other "
                                      "alignments, kept the better")
            if skipped:
                self.report({"WARNING"}, f"skipped {len(skipped)} selected object{'s' * (len(skipped) > 1)} that "
                                         f"{'are' if len(skipped) > 1 else 'is'} not a mesh: {', '.join(skipped)}")
            return "; ".join(f"{o.name}: varifold {c.registration.varifold:.3g}, Chamfer {c.registration.chamfer:.3g}"
                             f"{detail_note(c.registration)}" for o, c in zip(made, codes))

        return Task(f"register {len(scans)} scan{'s' * (len(scans) > 1)}", solve, apply, show, clear)
