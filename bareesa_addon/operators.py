"""One operator per user action. Each gathers inputs as arrays, calls the core, writes results, reports.

The idnames (``bareesa.load_template``, ``bareesa.register_scan``, ``bareesa.interpolate``,
``bareesa.extrapolate``, ``bareesa.transfer_motion``, ``bareesa.generate_random``,
``bareesa.build_basis``, ``bareesa.distance``) are a public scripting interface. String
arguments left empty fall back to the scene settings of the panel (``scene.bareesa``).
"""

import csv
import math
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from . import convert as cv
from . import solver
from .jobs import SolveOperator, Task, scaled_callback
from .preferences import solver_device, user_bases_dir

# ------------------------------------------------------------------------------------ helpers


def settings(context):
    return context.scene.bareesa


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


def code_source(context, obj, basis_ref_hint=None):
    """How to get a code for ``obj``: ('code', basis, ref, code) if registered, else ('scan', verts, faces)."""
    if is_registered(obj):
        basis, ref = object_basis(obj)
        return ("code", basis, ref, registered_code(obj, basis, solver.field_names(basis)))
    verts, faces = cv.evaluated_mesh(obj, context.evaluated_depsgraph_get())
    return ("scan", verts, faces)


def common_basis(context, sources):
    """The basis shared by the registered sources (else the panel's): -> (Basis, ref)."""
    refs = {}
    for src in sources:
        if src[0] == "code":
            refs[solver.load_basis(src[2], user_bases_dir())[1]] = src[1:3]
    if len(refs) > 1:
        raise cv.ConversionError("the objects were registered with different bases: register them with one basis")
    if refs:
        return next(iter(refs.values()))
    return load_basis(settings(context).basis)


def register_options(context, basis):
    s = settings(context)
    return dict(schedule=solver.schedule(basis, s.schedule), prealign=s.prealign, metric=metric(context, basis),
                device=solver_device(context))


def solve_codes(basis, sources, options, callback, cancel, lo=0.0, hi=1.0):
    """Codes of mixed sources, registering the raw scans (thread side): -> list of (code, result or None)."""
    register = solver.module("registration").register
    scans = [i for i, s in enumerate(sources) if s[0] == "scan"]
    out = []
    for i, src in enumerate(sources):
        if src[0] == "code":
            out.append((src[3], None))
            continue
        k = scans.index(i)
        span = (hi - lo) / len(scans)
        res = register(basis, src[1], src[2], callback=scaled_callback(callback, lo + k * span, lo + (k + 1) * span),
                       cancel=cancel, **options)
        out.append((res.code, res))
    return out


def matched_end(basis, matching, k, scan_verts):
    """(code, registration-like result) of end k of a symmetric matching (thread side)."""
    from types import SimpleNamespace

    code = matching.path[0 if k == 0 else -1]
    verts = matching.transforms[k].invert(basis.template + np.tensordot(code, basis.fields, axes=1))
    chamfer = solver.module("evaluation").chamfer(verts, scan_verts)
    return code, SimpleNamespace(code=code, transform=matching.transforms[k], vertices=verts,
                                 varifold=matching.varifold[k], chamfer=chamfer)


def add_registered(context, basis, ref, scan, result, collection=None):
    """The registered object of a scan: template topology, keys = code, placed over the scan."""
    obj = template_object(context, basis, ref, f"{scan.name}_registered",
                          collection or (scan.users_collection[0] if scan.users_collection else None),
                          code=result.code)
    obj.matrix_world = scan.matrix_world @ cv.similarity_inverse_matrix(result.transform)
    obj[cv.PROP_SCAN] = scan.name
    obj[cv.PROP_VARIFOLD] = float(result.varifold)
    obj[cv.PROP_CHAMFER] = float(result.chamfer)
    return obj


def check_results(results):
    for code, res in results:
        cv.check_code(code)
        if res is not None and not np.isfinite(res.vertices).all():
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


# ------------------------------------------------------------------------------------ basis


class BAREESA_OT_load_template(bpy.types.Operator):
    """Add the template of a basis with one shape key per basis field"""

    bl_idname = "bareesa.load_template"
    bl_label = "Load Template"
    bl_options = {"REGISTER", "UNDO"}

    basis: StringProperty(name="Basis", default="", description="Bundled name or .npz path (empty: the panel's)")

    def execute(self, context):
        try:
            basis, ref = load_basis(self.basis or settings(context).basis)
            obj = template_object(context, basis, ref, f"{basis.name}_template")
        except Exception as err:
            if not _user_error(err):
                raise
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        select_only(context, [obj])
        self.report({"INFO"}, f"added '{obj.name}': {basis.n_fields} shape keys "
                              f"({', '.join(f'{g} {b - a}' for g, (a, b) in basis.groups.items())})")
        return {"FINISHED"}


def _user_error(err):
    from .jobs import is_user_error

    return is_user_error(err)


# ------------------------------------------------------------------------------------ register


class BAREESA_OT_register_scan(SolveOperator, bpy.types.Operator):
    """Register each selected scan (any mesh): a new object in template topology whose shape keys are its code"""

    bl_idname = "bareesa.register_scan"
    bl_label = "Register Scans"

    basis: StringProperty(name="Basis", default="", description="Bundled name or .npz path (empty: the panel's)")

    def prepare(self, context):
        scans = list(context.selected_objects)
        if not scans:
            raise cv.ConversionError("select one or more scan meshes to register")
        for o in scans:
            cv.require_mesh(o, "selected object")
        basis, ref = load_basis(self.basis or settings(context).basis)
        depsgraph = context.evaluated_depsgraph_get()
        sources = [("scan", *cv.evaluated_mesh(o, depsgraph)) for o in scans]
        names = [o.name for o in scans]
        options = register_options(context, basis)

        def solve(callback, cancel):
            return solve_codes(basis, sources, options, callback, cancel)

        def apply(context, results):
            check_results(results)
            scan_objects = [find_object(n) for n in names]
            made = [add_registered(context, basis, ref, scan, res) for scan, (_, res) in zip(scan_objects, results)]
            select_only(context, made)
            return "; ".join(f"{o.name}: varifold {r.varifold:.3g}, Chamfer {r.chamfer:.3g}"
                             for o, (_, r) in zip(made, results))

        return Task(f"register {len(scans)} scan{'s' * (len(scans) > 1)}", solve, apply)


# ------------------------------------------------------------------------------------ paths


class BAREESA_OT_interpolate(SolveOperator, bpy.types.Operator):
    """Geodesic between two registered objects (or scans) keyframed on every frame, evenly paced"""

    bl_idname = "bareesa.interpolate"
    bl_label = "Interpolate"

    object_a: StringProperty(name="From", default="")
    object_b: StringProperty(name="To", default="")
    anchor: BoolProperty(name="Keep Body Planted", default=True,
                         description="Keep the body's unmoving part where the straight line between the ends puts it "
                                     "(the metric's L2 term otherwise lets the body sink ~1 cm when a limb moves)")

    def prepare(self, context):
        s = settings(context)
        a, b = pick_pair(context, self.object_a, self.object_b)
        anchor = self.anchor
        sources = [code_source(context, o) for o in (a, b)]
        basis, ref = common_basis(context, sources)
        frames = frame_range(context)
        weights, steps, options = metric(context, basis), s.steps, register_options(context, basis)
        max_iter = s.geodesic_iterations
        device, make_meshes = solver_device(context), s.make_collection
        names_ab = (a.name, b.name)
        geo = solver.module("geodesics")
        registration = solver.module("registration")

        def solve(callback, cancel):
            template, faces, fields = basis.tensors(device=device)
            if all(src[0] == "scan" for src in sources):  # two raw scans: symmetric matching
                m = registration.symmetric_match(basis, sources[0][1:], sources[1][1:], steps=steps,
                                        schedule=options["schedule"], callback=scaled_callback(callback, 0, 0.95),
                                        cancel=cancel)
                codes = [matched_end(basis, m, k, sources[k][1]) for k in (0, 1)]
                raw_path, distance = m.path, m.distance
            else:
                raw = any(src[0] == "scan" for src in sources)
                codes = solve_codes(basis, sources, options, callback, cancel, 0.0, 0.5 if raw else 0.0)
                g = geo.geodesic(template, faces, fields, codes[0][0], codes[1][0], weights, steps=steps,
                                 max_iter=max_iter, callback=scaled_callback(callback, 0.5 if raw else 0.0, 0.95),
                                 cancel=cancel)
                raw_path, distance = g.path, g.distance
            path = geo.keyframe_path(template, faces, fields, raw_path, weights, len(frames), anchor=anchor)
            return codes, path, distance

        def apply(context, result):
            codes, path, distance = result
            check_results(codes)
            cv.check_code(path, "the geodesic")
            a_obj, b_obj = (find_object(n) for n in names_ab)
            made = []
            ends = []
            for obj, (code, res) in zip((a_obj, b_obj), codes):
                if res is not None:
                    made.append(add_registered(context, basis, ref, obj, res))
                    ends.append(made[-1].matrix_world.copy())
                else:
                    ends.append(obj.matrix_world.copy())
            name = f"{a_obj.name}_to_{b_obj.name}"
            obj = template_object(context, basis, ref, name, code=path[0], hint=path)
            write_keys(obj, basis, frames, path)
            ts = np.linspace(0.0, 1.0, len(frames))
            matrices = [cv.blend_matrices(ends[0], ends[1], t) for t in ts]
            cv.keyframe_transforms(obj, frames, matrices)
            settings(context).distance = distance
            settings(context).distance_pair = f"{a_obj.name} - {b_obj.name}"
            if make_meshes:
                coll = new_collection(context, f"{name}_frames")
                verts = basis.template + np.tensordot(path, basis.fields, axes=1)
                for f, v, m in zip(frames, verts, matrices):
                    frame_obj = cv.new_mesh_object(f"{name}_{int(f):04d}", v, basis.faces, coll)
                    frame_obj.matrix_world = m
            select_only(context, made + [obj])
            return (f"'{name}': geodesic keyframed on frames {frames[0]}-{frames[-1]}, "
                    f"distance {distance:.4g}")

        return Task("interpolate", solve, apply)


class BAREESA_OT_extrapolate(SolveOperator, bpy.types.Operator):
    """Continue a motion along the geodesic: from two objects (other -> active) or the last two keyframes"""

    bl_idname = "bareesa.extrapolate"
    bl_label = "Extrapolate"

    source: EnumProperty(name="Direction from", items=(
        ("AUTO", "Auto", "Two objects when two are chosen or selected, else the active object's keyframes"),
        ("OBJECTS", "Two objects", "From the start object to the end object"),
        ("KEYFRAMES", "Keyframes", "The last two shape-key keyframes of the active registered object")),
        default="AUTO")
    object_a: StringProperty(name="From", default="")
    object_b: StringProperty(name="To", default="")
    anchor: BoolProperty(name="Keep Body Planted", default=True,
                         description="Keep the body's unmoving part where the straight latent line puts it")

    def prepare(self, context):
        s = settings(context)
        mode = self.source
        if mode == "AUTO":
            two = (self.object_a and self.object_b) or (s.object_a and s.object_b) or len(
                context.selected_objects) == 2
            mode = "OBJECTS" if two else "KEYFRAMES"
        if mode == "OBJECTS":
            a, b = pick_pair(context, self.object_a, self.object_b)
            for o in (a, b):
                if not is_registered(o):
                    raise cv.ConversionError(f"'{o.name}' is not registered: register it first")
            basis, ref = common_basis(context, [code_source(context, o) for o in (a, b)])
            names = solver.field_names(basis)
            alpha0, alpha1 = registered_code(a, basis, names), registered_code(b, basis, names)
            target_name = None
            frames = s.frame_start + s.extrapolate_spacing * np.arange(s.extrapolate_steps + 2)
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
            target_name = obj.name
            frames = f1 + (f1 - f0) * np.arange(-1, s.extrapolate_steps + 1)
            label = obj.name
        weights, device, n_new = metric(context, basis), solver_device(context), s.extrapolate_steps
        shooting = solver.module("shooting")
        anchor = self.anchor

        def solve(callback, cancel):
            template, faces, fields = basis.tensors(device=device)
            return shooting.extrapolate(template, faces, fields, alpha0, alpha1, weights, n_new,
                                        callback=callback, cancel=cancel, anchor=anchor)

        def apply(context, path):
            cv.check_code(path, "the extrapolated motion")
            if target_name is None:
                obj = template_object(context, basis, ref, label, code=path[0], hint=path)
                write_keys(obj, basis, frames, path)
                select_only(context, [obj])
            else:
                obj = find_object(target_name)
                write_keys(obj, basis, frames[2:], path[2:], replace=False)
            return f"'{obj.name}': {n_new} extrapolated keyframes up to frame {int(frames[-1])}"

        return Task("extrapolate", solve, apply)


# ------------------------------------------------------------------------------------ motion


def motion_frames(context, source, collection):
    """Source motion as a list of ('code', ...) / ('scan', ...) per frame, and the frame numbers.

    An object is evaluated on every frame of the range (shape keys, caches, modifiers: whatever
    Blender evaluates); a collection gives one frame per object, ordered by name.
    """
    scene = context.scene
    if collection is not None:
        objects = sorted((o for o in collection.all_objects if o.type == "MESH"), key=lambda o: cv.natural_key(o.name))
        if len(objects) < 2:
            raise cv.ConversionError(f"collection '{collection.name}' holds {len(objects)} meshes: a motion needs two")
        frames = settings(context).frame_start + np.arange(len(objects))
        return [code_source(context, o) for o in objects], frames
    cv.require_mesh(source, "motion source")
    frames = frame_range(context)
    current = scene.frame_current
    out = []
    try:
        for f in frames:
            scene.frame_set(int(f))
            out.append(code_source(context, source))
    finally:
        scene.frame_set(current)
    return out, frames


def project_or_keep(basis, src):
    """A frame already in template topology is projected (fast, exact in the span); others are scans."""
    if src[0] == "scan" and src[1].shape == basis.template.shape and np.array_equal(src[2], basis.faces):
        code, _ = solver.module("latent").project_to_basis(basis, src[1])
        return ("code", basis, None, code)
    return src


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
        frames_src, frames = motion_frames(context, source, collection)
        target_src = code_source(context, target)
        basis, ref = common_basis(context, frames_src + [target_src])
        identity = basis.group_slice(s.identity_group)
        frames_src = [project_or_keep(basis, f) for f in frames_src]
        options = register_options(context, basis)
        target_name = target.name
        statistics = solver.module("statistics")

        def solve(callback, cancel):
            codes = solve_codes(basis, frames_src + [target_src], options, callback, cancel)
            frame_codes = np.stack([c for c, _ in codes[:-1]])
            return statistics.transfer_motion(frame_codes, codes[-1][0], identity), codes[-1]

        def apply(context, result):
            motion, (code, res) = result
            cv.check_code(motion, "the transferred motion")
            check_results([(code, res)])
            obj = find_object(target_name)
            if res is not None:
                obj = add_registered(context, basis, ref, obj, res)
                select_only(context, [obj])
            write_keys(obj, basis, frames, motion)
            return f"'{obj.name}': {len(frames)} frames of motion keyframed ({frames[0]}-{frames[-1]})"

        return Task("transfer motion", solve, apply)


# ------------------------------------------------------------------------------------ statistics


#: A random body whose geodesic cannot be shot is retried with twice the steps, then replaced by a
#: further draw; at most this many draws per requested body.
DRAWS_PER_BODY = 4


def sample_bodies(template, faces, fields, distribution, groups, weights, n, seed, steps, callback=None,
                  cancel=None):
    """n random codes: initial velocities drawn from ``distribution``, shot from the template (thread side).

    Like ``bareesa.statistics.sample_codes`` (the same first n draws for a seed), except that a
    draw whose geodesic does not converge is shot again with 2 x steps and, failing that,
    replaced by a draw from a second stream of the same seed. -> (codes (n, P), replaced draws).
    """
    statistics, shooting = solver.module("statistics"), solver.module("shooting")
    velocities = list(statistics.sample_velocities(distribution, groups, n, seed))
    spares = iter(statistics.sample_velocities(distribution, groups, (DRAWS_PER_BODY - 1) * n, [seed, 1]))
    codes, replaced, error = [], 0, None
    while len(codes) < n:
        v = velocities.pop(0) if velocities else next(spares, None)
        if v is None:
            raise shooting.ShootingFailed(f"only {len(codes)} of {n} random bodies could be shot from the basis' "
                                          f"distribution ({error}); raise Shooting steps or fit the "
                                          "distribution to a collection")
        for k in (steps, 2 * steps):
            if callback is not None:
                progress = solver.module("progress")
                callback(progress.ProgressEvent("sample", len(codes) / n,
                                                f"body {len(codes) + 1}/{n}" + (f" ({k} steps)" if k > steps else "")))
            try:
                codes.append(shooting.shoot(template, faces, fields, np.zeros_like(v), v, weights, steps=k,
                                            cancel=cancel)[-1])
                break
            except shooting.ShootingFailed as err:
                error = err
        else:
            replaced += 1
    return np.stack(codes), replaced


class BAREESA_OT_generate_random(SolveOperator, bpy.types.Operator):
    """Random bodies (seeded) from the basis' distribution or one fitted to a collection, in a grid"""

    bl_idname = "bareesa.generate_random"
    bl_label = "Generate Random Bodies"

    count: IntProperty(name="Count", default=0, min=0, description="0: the panel's count")
    seed: IntProperty(name="Seed", default=-1, min=-1, description="-1: the panel's seed")

    def prepare(self, context):
        s = settings(context)
        n = self.count or s.count
        seed = s.seed if self.seed < 0 else self.seed
        fit = s.fit_collection
        if fit is not None:
            objects = [o for o in fit.all_objects if is_registered(o)]
            if len(objects) < 2:
                raise cv.ConversionError(f"collection '{fit.name}' holds {len(objects)} registered objects: "
                                         "fitting a distribution needs two or more")
            basis, ref = common_basis(context, [code_source(context, o) for o in objects])
            names = solver.field_names(basis)
            fit_codes = np.stack([registered_code(o, basis, names) for o in objects])
            distribution = None
        else:
            basis, ref = load_basis(s.basis)
            distribution = {k: v for k, v in basis.extras.items() if k.startswith("gmm_")}
            if not distribution:
                raise cv.ConversionError(f"basis '{basis.name}' stores no distribution: choose a collection of "
                                         "registered objects to fit one")
            fit_codes = None
        weights, device, steps = metric(context, basis), solver_device(context), s.shoot_steps
        statistics = solver.module("statistics")
        cursor = context.scene.cursor.location.copy()

        def solve(callback, cancel):
            template, faces, fields = basis.tensors(device=device)
            dist = distribution
            if dist is None:
                velocities = statistics.log_map(template, faces, fields, fit_codes, weights,
                                                callback=scaled_callback(callback, 0.0, 0.5), cancel=cancel)
                dist = statistics.fit_distribution(velocities, basis.groups, {g: 1 for g in basis.groups}, seed)
            return sample_bodies(template, faces, fields, dist, basis.groups, weights, n, seed, steps,
                                 scaled_callback(callback, 0.5 if distribution is None else 0.0, 1.0), cancel)

        def apply(context, result):
            codes, replaced = result
            cv.check_code(codes, "the random codes")
            coll = new_collection(context, f"{basis.name}_random_seed{seed}")
            extent = basis.template.max(0) - basis.template.min(0)
            cols = math.ceil(math.sqrt(n))
            made = []
            for i, code in enumerate(codes):
                obj = template_object(context, basis, ref, f"{basis.name}_random_{i:03d}", coll, code, hint=codes)
                obj.location = cursor + type(cursor)((1.3 * extent[0] * (i % cols), -1.3 * extent[1] * (i // cols),
                                                      0.0))
                made.append(obj)
            select_only(context, made)
            note = f"; {replaced} draw{'s' * (replaced > 1)} could not be shot and were replaced" if replaced else ""
            return f"{n} random bodies (seed {seed}) in collection '{coll.name}'{note}"

        return Task("random bodies", solve, apply)


class BAREESA_OT_build_basis(SolveOperator, bpy.types.Operator):
    """Build a basis from an animated mesh's frames or a collection of same-topology meshes, save and load it"""

    bl_idname = "bareesa.build_basis"
    bl_label = "Build Basis"

    filepath: StringProperty(name="File", subtype="FILE_PATH", default="",
                             description="Where to save the .npz (empty: <name>.npz in the user's bases directory)")

    def prepare(self, context):
        s = settings(context)
        name = s.build_name.strip()
        if not name or not name.replace("_", "").replace("-", "").isalnum():
            raise cv.ConversionError(f"basis name '{name}' must be letters, digits, '_' or '-'")
        group = s.build_group.strip() or "pose"
        source = s.build_source or (None if s.build_collection else context.view_layer.objects.active)
        if s.build_collection is None and source is None:
            raise cv.ConversionError("choose an animated mesh or a collection of same-topology meshes")
        depsgraph = context.evaluated_depsgraph_get
        if s.build_collection is not None:
            objects = sorted((o for o in s.build_collection.all_objects if o.type == "MESH"),
                             key=lambda o: cv.natural_key(o.name))
            meshes = [cv.evaluated_mesh(o, depsgraph()) for o in objects]
            what = f"collection '{s.build_collection.name}'"
        else:
            cv.require_mesh(source, "animated mesh")
            scene, current, meshes = context.scene, context.scene.frame_current, []
            try:
                for f in frame_range(context):
                    scene.frame_set(int(f))
                    meshes.append(cv.evaluated_mesh(source, depsgraph()))
            finally:
                scene.frame_set(current)
            what = f"'{source.name}' frames {s.frame_start}-{s.frame_end}"
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
            basis_io.save_basis(path, basis)
            return basis

        def apply(context, basis):
            s = settings(context)
            s.basis = str(path)
            obj = template_object(context, basis, str(path.resolve()), f"{basis.name}_template")
            select_only(context, [obj])
            return f"basis '{basis.name}' ({basis.n_fields} fields) saved to {path} and loaded"

        return Task("build basis", solve, apply)


class BAREESA_OT_distance(SolveOperator, bpy.types.Operator):
    """Geodesic distance between two objects, or a distance matrix of a collection written to CSV"""

    bl_idname = "bareesa.distance"
    bl_label = "Geodesic Distance"

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
            objects = sorted((o for o in coll.all_objects if o.type == "MESH"), key=lambda o: cv.natural_key(o.name))
            if len(objects) < 2:
                raise cv.ConversionError(f"collection '{coll.name}' holds {len(objects)} meshes: need two or more")
            csv_path = Path(bpy.path.abspath(self.filepath or s.distance_csv))
        else:
            objects, csv_path = list(pick_pair(context, self.object_a, self.object_b)), None
        sources = [code_source(context, o) for o in objects]
        basis, _ = common_basis(context, sources)
        weights, steps, device = metric(context, basis), s.steps, solver_device(context)
        options, max_iter = register_options(context, basis), s.geodesic_iterations
        labels = [o.name for o in objects]
        geo = solver.module("geodesics")

        def solve(callback, cancel):
            raw = any(src[0] == "scan" for src in sources)
            codes = [c for c, _ in solve_codes(basis, sources, options, callback, cancel, 0.0, 0.5 if raw else 0.0)]
            template, faces, fields = basis.tensors(device=device)
            n = len(codes)
            pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
            d = np.zeros((n, n))
            lo = 0.5 if raw else 0.0
            for k, (i, j) in enumerate(pairs):
                sub = scaled_callback(callback, lo + (1 - lo) * k / len(pairs), lo + (1 - lo) * (k + 1) / len(pairs))
                d[i, j] = d[j, i] = geo.geodesic(template, faces, fields, codes[i], codes[j], weights, steps=steps,
                                                 max_iter=max_iter, callback=sub, cancel=cancel).distance
            return d

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


CLASSES = (BAREESA_OT_load_template, BAREESA_OT_register_scan, BAREESA_OT_interpolate, BAREESA_OT_extrapolate,
           BAREESA_OT_transfer_motion, BAREESA_OT_generate_random, BAREESA_OT_build_basis, BAREESA_OT_distance)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
