"""What the operators share: settings, bases, template objects, keys, selection, and objects read
into workflow inputs (``bareesa.workflows``: ``KnownCode`` of a registered object, ``Scan`` of any mesh)."""

from pathlib import Path

import bpy
import numpy as np

from .. import convert as cv
from .. import solver
from ..preferences import solver_device, user_bases_dir


def settings(context):
    return context.scene.bareesa


def workflows():
    """The solver's ``workflows`` module (what the CLI calls too)."""
    return solver.module("workflows")


def basis_reference(reference):
    """Normalise a basis reference: file paths absolute (Blender's // relative paths too), names as is."""
    reference = (reference or "").strip()
    if reference.endswith(".npz") or "/" in reference or "\\" in reference:
        return str(Path(bpy.path.abspath(reference)).resolve())
    return reference


def load_basis(reference):
    """-> (Basis, stored reference) for a bundled name, a user-saved name or a path."""
    ref = basis_reference(reference)
    basis, _ = solver.load_basis(ref, user_bases_dir())
    return basis, ref


def metric(context, basis):
    s = settings(context)
    return solver.metric(basis, s.metric, s.metric_custom)


def solve_options(context, basis):
    """The panel's metric, schedule, pre-alignment, geodesic steps and iterations and device: -> workflows.Options."""
    s = settings(context)
    return workflows().Options(weights=metric(context, basis), schedule=solver.schedule(basis, s.schedule),
                               prealign=s.prealign, steps=s.steps, max_iter=s.geodesic_iterations,
                               device=solver_device(context))


def is_registered(obj):
    return obj is not None and obj.type == "MESH" and cv.PROP_BASIS in obj


def registered_code(obj, basis, names):
    """Code of a registered object, after checking it still matches its basis: -> (P,)."""
    if not cv.has_field_keys(obj, names):
        raise cv.ConversionError(f"'{obj.name}' lacks the shape keys of basis '{basis.name}' "
                                 f"(expected e.g. '{names[0]}'): load the template or register again")
    verts, tris = cv.rest_mesh(obj)
    if verts.shape != basis.template.shape or tris.shape != basis.faces.shape or not np.array_equal(
            tris, basis.faces):
        raise cv.ConversionError(f"'{obj.name}' no longer has the topology of basis '{basis.name}' "
                                 f"({verts.shape[0]} vertices / {tris.shape[0]} triangles, basis: "
                                 f"{basis.template.shape[0]} / {basis.faces.shape[0]}): it was edited; "
                                 "register the scan again")
    code = cv.get_code(obj, names)
    return cv.check_code(code, f"the code of '{obj.name}'")


def object_basis(obj):
    """Basis of a registered object: -> (Basis, reference)."""
    return load_basis(obj[cv.PROP_BASIS])


def common_basis(context, objects):
    """The basis shared by the registered objects (else the panel's): -> (Basis, ref)."""
    refs = {}
    for obj in objects:
        if is_registered(obj):
            basis, ref = object_basis(obj)
            refs[solver.load_basis(ref, user_bases_dir())[1]] = (basis, ref)
    if len(refs) > 1:
        raise cv.ConversionError("the objects were registered with different bases: register them with one basis")
    if refs:
        return next(iter(refs.values()))
    return load_basis(settings(context).basis)


def object_input(context, obj, basis):
    """The workflow input of an object as it is now: KnownCode if registered (checked against basis), else Scan."""
    wf = workflows()
    if is_registered(obj):
        return wf.KnownCode(registered_code(obj, basis, solver.field_names(basis)))
    return wf.Scan(*cv.evaluated_mesh(obj, context.evaluated_depsgraph_get()))


def typical_code_size(basis):
    """Largest code magnitude the basis' stored distribution makes likely (mean + 3 std); 0 without one."""
    size = 0.0
    for group in basis.groups:
        means, covs = basis.extras.get(f"gmm_{group}_means"), basis.extras.get(f"gmm_{group}_covariances")
        if means is not None and covs is not None:
            std = np.sqrt(np.clip(np.diagonal(np.asarray(covs), axis1=-2, axis2=-1), 0, None))
            size = max(size, float((np.abs(means) + 3 * std).max()))
    return size


def template_object(context, basis, ref, name, collection=None, code=None, hint=None):
    """A new object: the template with 'Basis' + one shape key per field, values = code.

    The key scale fits ``code`` and the codes in ``hint`` (else the basis' typical codes).
    """
    names = solver.field_names(basis)
    sizes = [np.abs(cv.check_code(c)).max(initial=0.0) for c in (code, hint) if c is not None]
    scale = cv.needed_scale(max(sizes) if sizes else typical_code_size(basis))
    obj = cv.new_mesh_object(name, basis.template, basis.faces, collection or context.collection)
    cv.add_field_keys(obj, basis.template, basis.fields, names, scale)
    obj[cv.PROP_BASIS] = ref
    obj[cv.PROP_BASIS_NAME] = basis.name
    if code is not None:
        cv.set_code(obj, names, code)
    return obj


def write_keys(obj, basis, frames, codes, replace=True):
    """Keyframe codes (T, P) on frames (T,), enlarging the object's key scale first when needed."""
    names = solver.field_names(basis)
    cv.fit_range(obj, names, basis.template, basis.fields, cv.check_code(codes))
    cv.keyframe_codes(obj, names, frames, codes, replace=replace)


def select_only(context, objects):
    for o in context.selected_objects:
        o.select_set(False)
    for o in objects:
        o.select_set(True)
    if objects:
        context.view_layer.objects.active = objects[-1]


def find_object(name):
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise cv.ConversionError(f"object '{name}' no longer exists (it was removed during the solve)")
    return obj


def pick_pair(context, name_a, name_b):
    """Two objects: operator names, else the panel's From/To, else the selection (other -> active)."""
    s = settings(context)
    a = bpy.data.objects.get(name_a) if name_a else s.object_a
    b = bpy.data.objects.get(name_b) if name_b else s.object_b
    if name_a and a is None or name_b and b is None:
        raise cv.ConversionError(f"no object named '{name_a if a is None else name_b}'")
    if a is None or b is None:
        selected = list(context.selected_objects)
        active = context.view_layer.objects.active
        if len(selected) != 2 or active not in selected:
            raise cv.ConversionError("choose two objects: set From and To in the panel, or select two meshes "
                                     "(the active one is the end)")
        b = active
        a = selected[0] if selected[1] is active else selected[1]
    for o, role in ((a, "start"), (b, "end")):
        cv.require_mesh(o, role)
    if a == b:
        raise cv.ConversionError("start and end are the same object")
    return a, b


def sorted_meshes(collection):
    """The mesh objects of a collection (nested ones too), in natural name order."""
    return sorted((o for o in collection.all_objects if o.type == "MESH"), key=lambda o: cv.natural_key(o.name))


def add_registered(context, basis, ref, scan, registration, collection=None):
    """The registered object of a scan (registration: code, transform, varifold, chamfer): template
    topology, keys = code, placed over the scan."""
    obj = template_object(context, basis, ref, f"{scan.name}_registered",
                          collection or (scan.users_collection[0] if scan.users_collection else None),
                          code=registration.code)
    obj.matrix_world = scan.matrix_world @ cv.similarity_inverse_matrix(registration.transform)
    obj[cv.PROP_SCAN] = scan.name
    obj[cv.PROP_VARIFOLD] = float(registration.varifold)
    obj[cv.PROP_CHAMFER] = float(registration.chamfer)
    return obj


def check_codes(codes):
    """Refuse non-finite codes or registrations (list of workflows.Code) before anything is written."""
    for code in codes:
        cv.check_code(code.code)
        if code.registration is not None and not np.isfinite(code.registration.vertices).all():
            raise cv.ConversionError("the registration diverged (non-finite vertices); nothing was written")


def frame_range(context):
    s = settings(context)
    if s.frame_end <= s.frame_start:
        raise cv.ConversionError(f"frame range {s.frame_start}..{s.frame_end} is empty: End must be after Start")
    return np.arange(s.frame_start, s.frame_end + 1)


def new_collection(context, name):
    coll = bpy.data.collections.new(name)
    context.scene.collection.children.link(coll)
    return coll
