"""bpy data <-> numpy arrays: meshes, shape keys (latent codes), keyframes, transforms.

Nothing here knows about the mathematics; every function is a plain conversion.
Codes live on an object as the values of one shape key per basis field (named
``<group>_<index:03d>``, relative to ``Basis``), so that Blender's own shape-key
mix *is* the decoder F(alpha) = template + sum_i alpha_i h_i.

Each field key holds template + k_i h_i with a key scale k_i (custom property
``bareesa_key_scale``, one per key) and its value is alpha_i / k_i; the mix is the
same decoder. The operators choose k_i = one standard deviation of the basis'
training codes for that field, so a slider at 1 is one typical step, and the slider
range is the training range (Blender caps sliders at +-10: a key whose values would
pass that gets a larger scale).

What the basis cannot make, the off-basis *detail* (N, 3) in the template frame (a
registration's detail layer), is one more key ``Detail`` = template + detail at value
1 (slider 0-1), after the field keys; a path whose ends have different detail adds
``Detail Change`` = template + (last frame's detail - first frame's), keyed from 0 to
1. They are not field keys: codes are read from the field keys by name only, and the
detail an object adds is read from these keys (``detail_of``).
"""

import math

import bpy
import numpy as np
from mathutils import Matrix

#: Custom properties stored on objects made by the add-on (they survive save/reload).
PROP_BASIS = "bareesa_basis"            # the basis reference: bundled name or absolute .npz path
PROP_BASIS_NAME = "bareesa_basis_name"  # the basis' own name (for display)
PROP_SCAN = "bareesa_scan"              # the scan an object was registered from
PROP_VARIFOLD = "bareesa_varifold"
PROP_CHAMFER = "bareesa_chamfer"
PROP_DETAIL_CHAMFER = "bareesa_detail_chamfer"  # Chamfer of the detailed mesh (with its Detail key at 1)
PROP_RESIDUAL = "bareesa_fit_residual"  # mean scan-to-surface distance over the basis' size
PROP_POOR_FIT = "bareesa_poor_fit"      # the residual is far above the basis' own (its card's fit_check)
PROP_KEY_SCALE = "bareesa_key_scale"    # per field key: it holds template + k_i h_i; its value is code_i / k_i
PROP_RANGE = "bareesa_training_stds"    # how far a result's codes go from the training codes (in std)
PROP_LANDMARK = "bareesa_landmark"      # on an Empty parented to a scan: the basis landmark it marks
#: The detail keys (not field keys): the detail itself, and how it changes along a path.
DETAIL_KEY = "Detail"
DETAIL_CHANGE_KEY = "Detail Change"
DETAIL_KEYS = (DETAIL_KEY, DETAIL_CHANGE_KEY)
#: Blender limits shape-key sliders to [-10, 10]; larger codes use a key scale (see above).
SLIDER_LIMIT = 10.0
#: A code beyond this is a diverged solve, not a shape.
CODE_LIMIT = 1e6


class ConversionError(ValueError):
    """Blender data cannot be converted (message tells the user what to fix)."""


def require_mesh(obj, role="object"):
    """Raise ConversionError unless ``obj`` is a mesh object."""
    if obj is None:
        raise ConversionError(f"no {role} given")
    if obj.type != "MESH":
        raise ConversionError(f"{role} '{obj.name}' is a {obj.type.lower()}, not a mesh")
    return obj


def _read_mesh(mesh):
    mesh.calc_loop_triangles()
    verts = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", verts)
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return verts.reshape(-1, 3), tris.reshape(-1, 3).astype(np.int64)


def evaluated_mesh(obj, depsgraph):
    """Mesh as Blender shows it (modifiers, shape keys, caches), local frame: -> verts (N, 3), tris (F, 3).

    Quads and n-gons are triangulated (Blender's loop triangles).
    """
    verts, tris, _ = evaluated_mesh_with_mask(obj, depsgraph, None)
    return verts, tris


def add_vertex_groups(obj, names, weights):
    """Vertex groups ``names`` (K,) with per-vertex weights (K, N); vertices of weight 0 are left out."""
    for name, w in zip(names, np.asarray(weights, dtype=np.float64)):
        group = obj.vertex_groups.get(str(name)) or obj.vertex_groups.new(name=str(name))
        for value in np.unique(w[w > 0]):
            group.add(np.flatnonzero(w == value).tolist(), float(value), "REPLACE")


def evaluated_mesh_with_mask(obj, depsgraph, group):
    """``evaluated_mesh`` plus the per-vertex weights of the vertex group ``group`` (1 = ignore):
    -> verts (N, 3), tris (F, 3), ignore weights (N,) (0 where a vertex is not in it), or None without the group."""
    require_mesh(obj)
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        verts, tris = _read_mesh(mesh)
        vg = obj.vertex_groups.get(group) if group else None
        if vg is None:
            return verts, tris, None
        ignore = np.zeros(len(verts))
        for v in mesh.vertices:
            for g in v.groups:
                if g.group == vg.index:
                    ignore[v.index] = g.weight
        return verts, tris, ignore
    finally:
        evaluated.to_mesh_clear()


def rest_mesh(obj):
    """The mesh data itself (the ``Basis`` shape), local frame: -> verts (N, 3), tris (F, 3)."""
    require_mesh(obj)
    return _read_mesh(obj.data)


#: Name of the UV map a basis' template UVs (``extras["template_uv"]``) are given on every object.
UV_MAP = "UVMap"


def new_mesh_object(name, verts, faces, collection, smooth=True, uv=None):
    """A new object with a triangle mesh (N, 3), (F, 3), linked to ``collection``; ``uv`` (F, 3, 2),
    UVs per face corner (a basis' ``template_uv``), becomes its UV map."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(np.asarray(verts, dtype=np.float64).tolist(), [], np.asarray(faces).tolist())
    if uv is not None:
        uv = np.asarray(uv, dtype=np.float32)
        if uv.shape != (len(faces), 3, 2):
            raise ValueError(f"template UVs have shape {uv.shape}, expected ({len(faces)}, 3, 2)")
        mesh.uv_layers.new(name=UV_MAP).data.foreach_set("uv", uv.ravel())  # loops follow the faces' corners
    mesh.update()
    if smooth:
        mesh.shade_smooth()
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def key_scales(obj, n=None):
    """The object's key scales k_i, one per field key (values are code_i / k_i): -> (P,).

    Older files store one scale for all keys (a float); it is broadcast to ``n`` keys.
    """
    stored = obj.get(PROP_KEY_SCALE, 1.0)
    try:
        scales = np.array(list(stored), dtype=np.float64)
    except TypeError:
        scales = np.full(n if n is not None else 1, float(stored))
    return scales


def _set_slider(block, lo, hi):
    lo, hi = max(-SLIDER_LIMIT, float(lo)), min(SLIDER_LIMIT, float(hi))
    block.slider_max = SLIDER_LIMIT  # slider_min may not exceed slider_max: widen first
    block.slider_min = min(lo, hi - 1e-3)
    block.slider_max = hi


def add_field_keys(obj, template, fields, names, scales=1.0, ranges=None):
    """Shape keys 'Basis' (= template) and one per field (template + k_i h_i).

    scales: (P,) or a float, the key scales k_i (value = code / k_i); ranges: (P, 2) slider
    ranges in value units (None: +-SLIDER_LIMIT).
    """
    template = np.asarray(template, dtype=np.float64)
    fields = np.asarray(fields, dtype=np.float64)
    scales = np.broadcast_to(np.asarray(scales, dtype=np.float64), (len(names),))
    if ranges is None:
        ranges = np.tile([-SLIDER_LIMIT, SLIDER_LIMIT], (len(names), 1))
    basis_key = obj.shape_key_add(name="Basis", from_mix=False)
    basis_key.data.foreach_set("co", template.ravel())
    for name, field, k, (lo, hi) in zip(names, fields, scales, ranges):
        key = obj.shape_key_add(name=name, from_mix=False)
        key.data.foreach_set("co", (template + k * field).ravel())
        _set_slider(key, lo, hi)
        key.relative_key = basis_key
    obj.data.shape_keys.use_relative = True
    obj[PROP_KEY_SCALE] = [float(k) for k in scales]
    obj.data.update()


def needed_scale(codes):
    """Smallest power-of-two factor that keeps values within 90% of Blender's slider limit (1 when they fit)."""
    m = float(np.abs(np.asarray(codes, dtype=np.float64)).max(initial=0.0))
    limit = 0.9 * SLIDER_LIMIT
    return 1.0 if m <= limit else float(2.0 ** math.ceil(math.log2(m / limit)))


def fit_range(obj, names, template, fields, codes):
    """Make the field keys able to hold ``codes`` (P,) or (T, P): a slider range that covers the values
    (up to Blender's +-10), and a larger key scale for a key whose values would pass +-10 (its key,
    value and keyframes rescaled, so the mix is unchanged)."""
    codes = np.atleast_2d(np.asarray(codes, dtype=np.float64))
    blocks = obj.data.shape_keys.key_blocks
    scales = key_scales(obj, len(names))
    curves = fcurves(obj.data.shape_keys)
    fields = np.asarray(fields, dtype=np.float64)
    for j, name in enumerate(names):
        block = blocks[name]
        factor = needed_scale(codes[:, j] / scales[j])
        if factor > 1.0:
            ratio, value = 1.0 / factor, block.value
            scales[j] *= factor
            block.data.foreach_set("co", (np.asarray(template) + scales[j] * fields[j]).ravel())
            block.value = value * ratio
            fc = curves.get(_data_path(name))
            if fc is not None:
                for point in fc.keyframe_points:
                    point.co[1] *= ratio
                    point.handle_left[1] *= ratio
                    point.handle_right[1] *= ratio
                fc.update()
        values = codes[:, j] / scales[j]
        lo, hi = min(block.slider_min, math.floor(values.min())), max(block.slider_max, math.ceil(values.max()))
        if (lo, hi) != (block.slider_min, block.slider_max):
            _set_slider(block, lo, hi)
    obj[PROP_KEY_SCALE] = [float(k) for k in scales]
    obj.data.update()


def has_field_keys(obj, names):
    """True when ``obj`` carries a shape key for every field name."""
    keys = obj.data.shape_keys if obj is not None and obj.type == "MESH" else None
    return keys is not None and all(n in keys.key_blocks for n in names)


def check_code(code, what="the result"):
    """Raise ConversionError unless the code is finite and of a sane size (else the solve diverged)."""
    code = np.asarray(code, dtype=np.float64)
    if not np.isfinite(code).all():
        raise ConversionError(f"{what} contains NaN or infinite values (the solve diverged); nothing was written")
    if np.abs(code).max(initial=0.0) > CODE_LIMIT:
        raise ConversionError(f"{what} has a coefficient of {np.abs(code).max():.3g} (the solve diverged); "
                              "nothing was written")
    return code


def _values(obj, names, code):
    """Values (code / k_i) of codes (P,) or (T, P), widening a key's slider range to hold them
    (Blender clamps values to it); refused when a value would pass Blender's +-10 (see fit_range)."""
    code = check_code(code)
    values = code / key_scales(obj, len(names))
    if np.abs(values).max(initial=0.0) > SLIDER_LIMIT * (1 + 1e-6):
        raise ConversionError(f"a code of {np.abs(code).max():.3g} does not fit the shape keys of '{obj.name}' "
                              "(their key scales); nothing was written")
    blocks = obj.data.shape_keys.key_blocks
    flat = np.atleast_2d(values)
    for j, name in enumerate(names):
        lo, hi = flat[:, j].min(initial=0.0), flat[:, j].max(initial=0.0)
        block = blocks[name]
        if lo < block.slider_min or hi > block.slider_max:
            _set_slider(block, min(block.slider_min, math.floor(lo)), max(block.slider_max, math.ceil(hi)))
    return values


def set_code(obj, names, code):
    """Shape-key values <- code (P,) (divided by the keys' scales)."""
    blocks = obj.data.shape_keys.key_blocks
    for name, value in zip(names, _values(obj, names, code)):
        blocks[name].value = float(value)


def get_code(obj, names):
    """Shape-key values -> code (P,) (the current, possibly animated, values times the key scales)."""
    blocks = obj.data.shape_keys.key_blocks
    return key_scales(obj, len(names)) * np.array([blocks[n].value for n in names], dtype=np.float64)


def _data_path(name):
    return f'key_blocks["{bpy.utils.escape_identifier(name)}"].value'


def fcurves(id_data):
    """{data_path: FCurve} of the action assigned to an ID (one curve per path: for scalar properties)."""
    return {fc.data_path: fc for fc in all_fcurves(id_data)}


def all_fcurves(id_data):
    """Every FCurve of the action assigned to an ID (Blender 4.2 actions and 4.4+ slotted ones): -> list."""
    anim = id_data.animation_data
    if anim is None or anim.action is None:
        return []
    curves = None
    slot = getattr(anim, "action_slot", None)
    if slot is not None:
        try:
            from bpy_extras.anim_utils import action_get_channelbag_for_slot
        except ImportError:
            pass
        else:
            bag = action_get_channelbag_for_slot(anim.action, slot)
            curves = bag.fcurves if bag is not None else []
    if curves is None:
        curves = anim.action.fcurves
    return list(curves)


def keyframe_codes(obj, names, frames, codes, replace=True):
    """Keyframe the field shape keys: frames (T,), codes (T, P); linear interpolation between keys.

    replace=True rebuilds each curve from these keys only; otherwise keys are added to existing curves.
    """
    values = np.atleast_2d(_values(obj, names, np.asarray(codes, dtype=np.float64)))
    _keyframe_values(obj, names, frames, values, replace)


def _keyframe_values(obj, names, frames, values, replace=True):
    """Keyframe the values (T, K) of the shape keys ``names`` (K,) on frames (T,), linear between keys."""
    frames = np.asarray(frames, dtype=np.float64)
    key = obj.data.shape_keys
    blocks = key.key_blocks
    curves = fcurves(key)
    for name in names:
        if _data_path(name) not in curves:
            blocks[name].keyframe_insert("value", frame=float(frames[0]))
    curves = fcurves(key)
    for j, name in enumerate(names):
        fc = curves[_data_path(name)]
        if replace:
            fc.keyframe_points.clear()
            fc.keyframe_points.add(len(frames))
            fc.keyframe_points.foreach_set("co", np.stack([frames, values[:, j]], 1).ravel())
        else:
            for f, v in zip(frames, values[:, j]):
                fc.keyframe_points.insert(float(f), float(v), options={"FAST"})
        for point in fc.keyframe_points:
            point.interpolation = "LINEAR"
        fc.update()


def keyed_frames(obj, names):
    """Sorted frames at which any field shape key has a keyframe: -> (K,) float array."""
    if obj.data.shape_keys is None:
        return np.zeros(0)
    curves = fcurves(obj.data.shape_keys)
    frames = set()
    for name in names:
        fc = curves.get(_data_path(name))
        if fc is not None:
            frames.update(p.co[0] for p in fc.keyframe_points)
    return np.array(sorted(frames))


def code_at_frame(obj, names, frame):
    """Code of an object at a frame, from its shape-key animation (static values where not animated)."""
    curves = fcurves(obj.data.shape_keys)
    blocks = obj.data.shape_keys.key_blocks
    return key_scales(obj, len(names)) * np.array([curves[_data_path(n)].evaluate(frame) if _data_path(n) in curves
                                      else blocks[n].value for n in names], dtype=np.float64)


def set_detail_key(obj, template, detail, name=DETAIL_KEY, value=1.0):
    """The detail key ``name`` (a new one, or the one there) = template (N, 3) + detail (N, 3), template
    frame, relative to 'Basis', slider 0-1, at ``value``; the object must have its field keys already."""
    blocks = obj.data.shape_keys.key_blocks
    block = blocks.get(name) or obj.shape_key_add(name=name, from_mix=False)
    block.data.foreach_set("co", (np.asarray(template, dtype=np.float64) + np.asarray(detail, np.float64)).ravel())
    block.relative_key = blocks["Basis"]
    _set_slider(block, 0.0, 1.0)
    block.value = float(value)
    obj.data.update()
    return block


def detail_keys(obj):
    """The object's detail keys (``DETAIL_KEYS`` it has, muted ones left out): -> list of ShapeKey."""
    keys = obj.data.shape_keys if obj is not None and obj.type == "MESH" else None
    if keys is None:
        return []
    return [keys.key_blocks[n] for n in DETAIL_KEYS if n in keys.key_blocks and not keys.key_blocks[n].mute]


def _key_offset(block):
    """co - co of its relative key: -> (N, 3)."""
    co = np.empty(len(block.data) * 3)
    block.data.foreach_get("co", co)
    base = np.empty(len(block.relative_key.data) * 3)
    block.relative_key.data.foreach_get("co", base)
    return (co - base).reshape(-1, 3)


def detail_of(obj):
    """The off-basis detail (N, 3), template frame, that the object's detail keys add as they are now: the sum
    of (co - Basis co) x value over them; None when it has none or all are at 0."""
    detail = None
    for block in detail_keys(obj):
        if block.value != 0.0:
            detail = block.value * _key_offset(block) + (0.0 if detail is None else detail)
    return detail


def write_detail(obj, template, frames, detail, times):
    """Write detail (T, N, 3) carried along frames (T,) at path times (T,) as detail keys: 'Detail' = the
    first frame's detail at 1 and, when it changes, 'Detail Change' = the last frame's minus the first's,
    keyed (times - times[0]) / (times[-1] - times[0]) with linear keys. Exact on every frame for detail
    linear in time (``latent.detail_along``, how the solver carries it) and in between."""
    detail = np.asarray(detail, dtype=np.float64)
    set_detail_key(obj, template, detail[0])
    change = detail[-1] - detail[0]
    if len(detail) < 2 or not np.any(change):
        return
    times = np.asarray(times, dtype=np.float64)
    set_detail_key(obj, template, change, DETAIL_CHANGE_KEY, 0.0)
    _keyframe_values(obj, [DETAIL_CHANGE_KEY], frames, ((times - times[0]) / (times[-1] - times[0]))[:, None])


def continue_detail(obj, f0, f1, frames):
    """Keyframe the object's animated detail keys on frames (K,) after f1, their values continued along the
    straight line through their values at f0 and f1 (so the detail is continued linearly, as the solver's
    ``extrapolate`` continues it); widens their sliders. Returns the names of keys that would pass Blender's
    slider limit (+-10), left as they are; nothing is keyed then."""
    curves = fcurves(obj.data.shape_keys) if obj.data.shape_keys is not None else {}
    animated = [b for b in detail_keys(obj) if _data_path(b.name) in curves]
    frames = np.asarray(frames, dtype=np.float64)
    values = {}
    for block in animated:
        fc = curves[_data_path(block.name)]
        v0, v1 = fc.evaluate(f0), fc.evaluate(f1)
        values[block.name] = v1 + (frames - f1) / (f1 - f0) * (v1 - v0)
    too_far = [n for n, v in values.items() if np.abs(v).max(initial=0.0) > SLIDER_LIMIT]
    if too_far:
        return too_far
    for block in animated:
        v = values[block.name]
        _set_slider(block, min(block.slider_min, math.floor(v.min())), max(block.slider_max, math.ceil(v.max())))
        _keyframe_values(obj, [block.name], frames, v[:, None], replace=False)
    return []


def similarity_inverse_matrix(similarity):
    """4x4 Matrix of the inverse of x -> s R x + t (template frame -> scan frame)."""
    r, s, t = np.asarray(similarity.rotation), float(similarity.scale), np.asarray(similarity.translation)
    m = np.eye(4)
    m[:3, :3] = r.T / s
    m[:3, 3] = -(r.T @ t) / s
    return Matrix(m.tolist())


def blend_matrices(m0, m1, t):
    """Transform between two world matrices at t in [0, 1] (lerp location/scale, slerp rotation)."""
    l0, r0, s0 = m0.decompose()
    l1, r1, s1 = m1.decompose()
    loc, rot, scale = l0.lerp(l1, t), r0.slerp(r1, t), s0.lerp(s1, t)
    return Matrix.LocRotScale(loc, rot, scale)


def keyframe_transforms(obj, frames, matrices):
    """Keyframe location, quaternion rotation and scale of ``obj`` from world matrices (no parent),
    with linear interpolation (Blender's default Bezier easing would stall and snap per-frame keys)."""
    obj.rotation_mode = "QUATERNION"
    for frame, m in zip(frames, matrices):
        loc, rot, scale = m.decompose()
        obj.location, obj.rotation_quaternion, obj.scale = loc, rot, scale
        for path in ("location", "rotation_quaternion", "scale"):
            obj.keyframe_insert(path, frame=float(frame))
    for fc in all_fcurves(obj):
        if fc.data_path in ("location", "rotation_quaternion", "scale"):
            for point in fc.keyframe_points:
                point.interpolation = "LINEAR"
            fc.update()
    obj.matrix_world = matrices[0]


def natural_key(name):
    """Sort key that orders 'frame_2' before 'frame_10'."""
    import re

    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]
