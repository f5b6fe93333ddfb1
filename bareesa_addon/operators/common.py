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


def refuse(cls, reason):
    """For ``poll``: False with the reason shown in the greyed-out button's tooltip; True without one."""
    if reason:
        cls.poll_message_set(reason)
        return False
    return True


def selected_meshes(context):
    return [o for o in (getattr(context, "selected_objects", None) or ()) if o.type == "MESH"]


def has_pair_or_selection(context):
    """Whether the panel names two objects (From, To) or meshes are selected: what the path operators need."""
    s = context.scene.bareesa
    return bool((s.object_a and s.object_b) or selected_meshes(context))


def own_or_panel(op, context, name, setting=None):
    """An operator's own property when it was set (scripts, redo panel), else the panel's setting."""
    if op.properties.is_property_set(name):
        return getattr(op, name)
    return getattr(settings(context), setting or name)


def workflows():
    """The solver's ``workflows`` module (what the CLI calls too)."""
    return solver.module("workflows")


def basis_reference(reference):
    """Normalise a basis reference: file paths absolute (Blender's // relative paths too), names as is."""
    reference = (reference or "").strip()
    if reference.endswith(".npz") or "/" in reference or "\\" in reference:
        return str(Path(bpy.path.abspath(reference)).resolve())
    return reference


def output_path(path, what):
    """An absolute path to write to; a Blender-relative '//' path needs a saved .blend file."""
    path = (path or "").strip()
    if not path:
        raise cv.ConversionError(f"choose a file for the {what}")
    if path.startswith("//") and not bpy.data.filepath:
        raise cv.ConversionError(f"the {what} path '{path}' is relative to the .blend file, which is not saved: "
                                 "save the file first or choose an absolute path")
    return Path(bpy.path.abspath(path)).resolve()


def load_basis(reference):
    """-> (Basis, stored reference) for a bundled name, a user-saved name or a path."""
    ref = basis_reference(reference)
    basis, _ = solver.load_basis(ref, user_bases_dir())
    return basis, ref


def metric(context, basis):
    s = settings(context)
    return solver.metric(basis, s.metric, s.metric_custom)


def registration_settings(context):
    """The panel's registration settings beyond schedule and pre-alignment (pose search, retries, detail layer,
    the Settings field's KEY=VALUE items): -> dict of ``RegistrationConfig`` overrides."""
    s = settings(context)
    out = {"retry": bool(s.retry_poor_fits), "detail.enabled": bool(s.detail_layer)}
    if not s.pose_search:
        out["poses.candidates"] = None
    out.update(solver.module("registration.config").parse_settings(s.registration_settings))
    return out


def solve_options(context, basis):
    """The panel's metric, schedule, pre-alignment and registration settings, geodesic steps and iterations and
    device: -> workflows.Options (InputError naming a bad registration setting)."""
    s = settings(context)
    options = workflows().Options(weights=metric(context, basis), schedule=solver.schedule(basis, s.schedule),
                                  prealign=s.prealign, steps=s.steps, max_iter=s.geodesic_iterations,
                                  device=solver_device(context), registration=registration_settings(context))
    options.registration_config(basis)  # unknown or bad settings refused before any solve starts
    return options


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


def landmark_empties(scan):
    """The landmark Empties of a scan (children with ``PROP_LANDMARK``), visible or not: -> list."""
    return [o for o in scan.children if o.type == "EMPTY" and o.get(cv.PROP_LANDMARK)]


def scan_landmarks(scan):
    """Where the scan's visible landmark Empties are, in the scan's local frame: -> {name: (x, y, z)}.

    Hidden Empties (or Empties in a hidden collection) are not used; deleted ones are gone."""
    inverse = scan.matrix_world.inverted()
    points, where = {}, {}
    for empty in landmark_empties(scan):
        if not empty.visible_get():
            continue
        name = str(empty[cv.PROP_LANDMARK])
        if name in points:
            raise cv.ConversionError(f"scan '{scan.name}' has two visible '{name}' landmarks ('{where[name]}' and "
                                     f"'{empty.name}'): delete or hide one")
        points[name], where[name] = tuple(inverse @ empty.matrix_world.translation), empty.name
    return points


def scan_input(context, obj, basis):
    """A scan as the solver takes it: its evaluated mesh, the panel's ignore mask (vertex group) as face
    weights and its visible landmark Empties: -> workflows.Scan."""
    verts, tris, ignore = cv.evaluated_mesh_with_mask(obj, context.evaluated_depsgraph_get(),
                                                      settings(context).mask_group)
    weights = None if ignore is None else solver.module("masks").face_weights_from_ignore(ignore, tris)
    if weights is not None and not (weights > 0).any():
        raise cv.ConversionError(f"the ignore group '{settings(context).mask_group}' of '{obj.name}' covers the "
                                 "whole scan: nothing is left to register")
    points = scan_landmarks(obj)
    marks = None
    if points:
        try:
            marks = solver.module("landmarks").scan_landmarks(basis, points)
        except solver.module("errors").InputError as err:
            raise cv.ConversionError(f"'{obj.name}': {err}") from None
    return workflows().Scan(verts, tris, face_weights=weights, landmarks=marks)


def object_input(context, obj, basis):
    """The workflow input of an object as it is now: KnownCode if registered (checked against basis; with the
    detail its detail keys add, ``object_detail``), else Scan."""
    wf = workflows()
    if is_registered(obj):
        return wf.KnownCode(registered_code(obj, basis, solver.field_names(basis)), detail=object_detail(obj, basis))
    return scan_input(context, obj, basis)


def object_detail(obj, basis):
    """The off-basis detail (N, 3) a registered object adds with its detail keys as they are now
    (``convert.detail_of``): its ``KnownCode``'s detail; None for a scan or an object without."""
    if not is_registered(obj):
        return None
    detail = cv.detail_of(obj)
    return None if detail is None or detail.shape != basis.template.shape else detail


#: The training range of a code: mean +- this many standard deviations of the basis' training codes
TRAINING_STDS = 4.0


def training_stats(basis):
    """Mean and standard deviation of each coefficient under the basis' stored distribution (its
    ``gmm_<group>_*`` extras, the mixture of its training codes): -> (mean (P,), std (P,)), NaN
    for coefficients of a group without one."""
    mean, std = np.full(basis.n_fields, np.nan), np.full(basis.n_fields, np.nan)
    for group, (a, b) in basis.groups.items():
        means, covs = basis.extras.get(f"gmm_{group}_means"), basis.extras.get(f"gmm_{group}_covariances")
        if means is None or covs is None:
            continue
        means = np.atleast_2d(np.asarray(means, dtype=np.float64))
        covs = np.asarray(covs, dtype=np.float64)
        var_k = np.diagonal(covs, axis1=-2, axis2=-1) if covs.ndim == 3 else np.broadcast_to(covs, means.shape)
        w = np.asarray(basis.extras.get(f"gmm_{group}_weights", np.full(len(means), 1 / len(means))), float)
        m = w @ means
        mean[a:b] = m
        std[a:b] = np.sqrt(np.clip(w @ (var_k + means ** 2) - m ** 2, 0, None))
    return mean, std


def training_excess(basis, codes):
    """How far codes (P,) or (T, P) go from the training codes: the largest |code - mean| / std over
    coefficients and frames (0 without a stored distribution). Beyond TRAINING_STDS a code leaves the
    training range. This is the one rule the add-on uses."""
    mean, std = training_stats(basis)
    ok = np.isfinite(std) & (std > 0)
    if not ok.any():
        return 0.0
    z = np.abs(np.atleast_2d(codes)[:, ok] - mean[ok]) / std[ok]
    return float(z.max(initial=0.0))


def key_layout(basis):
    """Key scale (one training std, 1 without a distribution) and slider range (the training range
    in slider units, +-10 without one) of each field key: -> scales (P,), ranges (P, 2)."""
    mean, std = training_stats(basis)
    ok = np.isfinite(std) & (std > 0)
    scales = np.where(ok, std, 1.0)
    centre = np.where(ok, mean, 0.0) / scales
    ranges = np.stack([centre - TRAINING_STDS, centre + TRAINING_STDS], 1)
    ranges[~ok] = (-cv.SLIDER_LIMIT, cv.SLIDER_LIMIT)
    return scales, ranges


def template_object(context, basis, ref, name, collection=None, code=None, hint=None):
    """A new object: the template with 'Basis' + one shape key per field, values = code, the basis' UV map and
    its named parts as vertex groups (if it has them).

    Keys follow ``key_layout``; their range is widened (or scale enlarged) to fit ``code`` and ``hint``.
    """
    names = solver.field_names(basis)
    obj = cv.new_mesh_object(name, basis.template, basis.faces, collection or context.collection,
                             uv=basis.extras.get("template_uv"))
    cv.add_field_keys(obj, basis.template, basis.fields, names, *key_layout(basis))
    if "part_names" in basis.extras and "part_weights" in basis.extras:  # named body parts
        cv.add_vertex_groups(obj, basis.extras["part_names"], basis.extras["part_weights"])
    obj[cv.PROP_BASIS] = ref
    obj[cv.PROP_BASIS_NAME] = basis.name
    for c in (code, hint):
        if c is not None:
            cv.fit_range(obj, names, basis.template, basis.fields, cv.check_code(c))
    if code is not None:
        cv.set_code(obj, names, code)
    return obj


def write_code(obj, basis, code):
    """Set an object's field keys to a code (P,), enlarging its key scale first when needed."""
    names = solver.field_names(basis)
    cv.fit_range(obj, names, basis.template, basis.fields, cv.check_code(code))
    cv.set_code(obj, names, code)


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


def add_registered(context, basis, ref, scan, registration, collection=None, detail=None):
    """The registered object of a scan (registration: code, transform, varifold, chamfer; detail (N, 3) its
    detail layer, template frame, or None): template topology, keys = code, a 'Detail' key at 1 with the
    detail, placed over the scan (the template frame carried into the scan's by the inverse transform, so the
    object shows the registered mesh, detailed when there is detail, exactly where the solver put it)."""
    obj = template_object(context, basis, ref, f"{scan.name}_registered",
                          collection or (scan.users_collection[0] if scan.users_collection else None),
                          code=registration.code)
    if detail is not None:
        cv.set_detail_key(obj, basis.template, detail)
        report = getattr(registration, "detail_report", None) or {}
        if report.get("chamfer") is not None:
            obj[cv.PROP_DETAIL_CHAMFER] = float(report["chamfer"])
    obj.matrix_world = scan.matrix_world @ cv.similarity_inverse_matrix(registration.transform)
    obj[cv.PROP_SCAN] = scan.name
    obj[cv.PROP_VARIFOLD] = float(registration.varifold)
    obj[cv.PROP_CHAMFER] = float(registration.chamfer)
    if getattr(registration, "residual", None) is not None:
        obj[cv.PROP_RESIDUAL] = float(registration.residual)
    if getattr(registration, "poor_fit", None) is not None:
        obj[cv.PROP_POOR_FIT] = bool(registration.poor_fit)
    return obj


def check_codes(codes):
    """Refuse non-finite codes, registrations or detail (list of workflows.Code) before anything is written."""
    for code in codes:
        cv.check_code(code.code)
        if code.registration is not None and not np.isfinite(code.registration.vertices).all():
            raise cv.ConversionError("the registration diverged (non-finite vertices); nothing was written")
        if code.detail is not None and not np.isfinite(code.detail).all():
            raise cv.ConversionError("the detail layer diverged (non-finite displacements); nothing was written")


def first_frame(context):
    """The first frame of ``frame_range`` (the scene's start, or the panel's override)."""
    s = settings(context)
    return s.frame_start if s.use_frame_range else context.scene.frame_start


def frame_range(context):
    """The frames to key or read: the scene's frame range, or the panel's when its override is on."""
    s, scene = settings(context), context.scene
    start, end = (s.frame_start, s.frame_end) if s.use_frame_range else (scene.frame_start, scene.frame_end)
    if end <= start:
        where = "the panel's override" if s.use_frame_range else "the scene's (Output properties)"
        raise cv.ConversionError(f"frame range {start}..{end} of {where} is empty: End must be after Start")
    return np.arange(start, end + 1)


def new_collection(context, name):
    coll = bpy.data.collections.new(name)
    context.scene.collection.children.link(coll)
    return coll
