"""Load Template and Build Basis."""

from pathlib import Path

import bpy
import numpy as np
from bpy.props import StringProperty

from .. import convert as cv
from .. import solver
from ..jobs import SolveOperator, Task, is_user_error
from ..preferences import user_bases_dir
from .common import frame_range, load_basis, refuse, select_only, settings, sorted_meshes, template_object


class BAREESA_OT_load_template(bpy.types.Operator):
    """Add the template of a basis with one shape key per basis field"""

    bl_idname = "bareesa.load_template"
    bl_label = "Load Template"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        s = getattr(context.scene, "bareesa", None)
        return refuse(cls, None if s is not None and s.basis.strip() else "choose a basis in the Basis section")

    basis: StringProperty(name="Basis", default="", description="Bundled name or .npz path (empty: the panel's)")

    def execute(self, context):
        try:
            basis, ref = load_basis(self.basis or settings(context).basis)
            obj = template_object(context, basis, ref, f"{basis.name}_template")
        except Exception as err:
            if not is_user_error(err):
                raise
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        select_only(context, [obj])
        self.report({"INFO"}, f"added '{obj.name}': {basis.n_fields} shape keys "
                              f"({', '.join(f'{g} {b - a}' for g, (a, b) in basis.groups.items())})")
        return {"FINISHED"}


def source_meshes(context, s):
    """The same-topology meshes a basis is built from: the panel's collection (one per object) or
    animated mesh (one per frame of the range): -> (list of (verts, faces), what they are)."""
    source = s.build_source or (None if s.build_collection else context.view_layer.objects.active)
    if s.build_collection is None and source is None:
        raise cv.ConversionError("choose an animated mesh or a collection of same-topology meshes")
    depsgraph = context.evaluated_depsgraph_get
    if s.build_collection is not None:
        meshes = [cv.evaluated_mesh(o, depsgraph()) for o in sorted_meshes(s.build_collection)]
        return meshes, f"collection '{s.build_collection.name}'"
    cv.require_mesh(source, "animated mesh")
    scene, current, meshes, frames = context.scene, context.scene.frame_current, [], frame_range(context)
    try:
        for f in frames:
            scene.frame_set(int(f))
            meshes.append(cv.evaluated_mesh(source, depsgraph()))
    finally:
        scene.frame_set(current)
    return meshes, f"'{source.name}' frames {frames[0]}-{frames[-1]}"


class BAREESA_OT_build_basis(SolveOperator, bpy.types.Operator):
    """Build a basis from an animated mesh's frames or a collection of same-topology meshes, save and load it"""

    bl_idname = "bareesa.build_basis"
    bl_label = "Build Basis"

    @classmethod
    def poll(cls, context):
        s, active = context.scene.bareesa, context.view_layer.objects.active
        some = s.build_source or s.build_collection or (active is not None and active.type == "MESH")
        return refuse(cls, None if some else "choose an animated mesh or a collection of same-topology meshes "
                                             "(or make an animated mesh active)")

    filepath: StringProperty(name="File", subtype="FILE_PATH", default="",
                             description="Where to save the .npz (empty: <name>.npz in the user's bases directory)")

    def prepare(self, context):
        s = settings(context)
        name = s.build_name.strip()
        if not name or not name.replace("_", "").replace("-", "").isalnum():
            raise cv.ConversionError(f"basis name '{name}' must be letters, digits, '_' or '-'")
        group = s.build_group.strip() or "pose"
        meshes, what = source_meshes(context, s)
        if len(meshes) < 2:
            raise cv.ConversionError(f"{what} gives {len(meshes)} meshes: a basis needs at least two frames")
        faces = meshes[0][1]
        for v, f in meshes[1:]:
            if v.shape != meshes[0][0].shape or not np.array_equal(f, faces):
                raise cv.ConversionError(f"{what}: the frames do not share one topology (vertex count or faces "
                                         "differ); register them first")
        frames = np.stack([v for v, _ in meshes])
        path = Path(bpy.path.abspath(self.filepath)) if self.filepath else user_bases_dir(create=True) / f"{name}.npz"
        building, basis_io = solver.module("basis_building"), solver.module("basis_io")
        weights = {"BASIS": "body", "CUSTOM": s.metric_custom}.get(s.metric, s.metric.lower())
        solver.module("h2_metric").H2Weights.parse(weights)  # a bad custom metric is reported now
        k = s.build_components

        def solve(callback, cancel):
            basis = building.build_basis(frames[0], faces, {group: [frames]}, {group: k}, weights=weights, name=name,
                                         provenance={"source": what, "tool": "BaRe-ESA for Blender"},
                                         callback=callback, cancel=cancel)
            if group == "pose":  # starting poses for registration (bareesa.registration, pose candidates)
                basis.extras["pose_prototypes"] = solver.module("statistics").pose_prototypes(basis, frames)
            solver.module("registration").prepare_basis(basis)  # what every registration would compute
            basis_io.save_basis(path, basis)
            return basis

        def apply(context, basis):
            s = settings(context)
            s.basis = str(path)
            obj = template_object(context, basis, str(path.resolve()), f"{basis.name}_template")
            select_only(context, [obj])
            report = basis.provenance.get("groups", {}).get(group, {})
            asked, built = report.get("requested", k), report.get("components", basis.n_fields)
            if built < asked:
                self.report({"WARNING"}, f"asked for {asked} components of '{group}', built {built}: the frames "
                                         f"hold no more independent motion (use more, or more varied, frames)")
            return f"basis '{basis.name}' ({basis.n_fields} fields) saved to {path} and loaded"

        return Task("build basis", solve, apply)
