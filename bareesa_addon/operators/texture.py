"""Transfer Texture: bake a scan's colours (image texture or colour attribute) onto its registered
object's UV map, as a PNG image next to the .blend and a material that shows it.

The bake is Cycles' EMIT pass, selected (the scan) to active (the registered object): each slot of
the scan temporarily gets a copy of its material whose surface is an Emission shader of strength 1
fed by the colour that reached its Base Color (image texture, colour attribute, their mapping and
mixing nodes). The emission pass is exactly that colour: no lights, no Fresnel, no metallic or
transmission weighting (which a DIFFUSE/COLOR bake of a Principled BSDF applies), and it works the
same for a scan whose colour attribute is not wired to any material. The bake runs on the main
thread (a few seconds at few samples); everything it changes is put back, also when it fails.

It bakes onto the registered object as Blender shows it (its shape keys mixed, as ``fit_distance``
measures it too): with its 'Detail' key at 1, onto the detailed surface.
"""

import re
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty, IntProperty, StringProperty

from .. import convert as cv
from .common import is_registered, output_path, refuse, selected_meshes

#: Nodes whose colour is scan data (what Transfer Texture carries over).
IMAGE_NODES = {"TEX_IMAGE"}
ATTRIBUTE_NODES = {"VERTEX_COLOR", "ATTRIBUTE"}
#: Shader nodes passed through on the way from the material output to the BSDF that holds the colour.
SHADER_MIXES = {"MIX_SHADER", "ADD_SHADER"}
COLOUR_INPUTS = ("Base Color", "Color")
TEMPORARY = "BaRe-ESA bake (temporary)"


def uv_map_name(obj):
    """The UV map to bake into: the template's ('UVMap'), else the active render one, else None."""
    layers = obj.data.uv_layers
    if cv.UV_MAP in layers:
        return cv.UV_MAP
    render = next((uv for uv in layers if uv.active_render), None)
    return render.name if render is not None else None


def colour_attribute_name(mesh):
    """The scan's colour attribute used for rendering (its default one), else the first, else None."""
    attrs = mesh.color_attributes
    if not len(attrs):
        return None
    index = attrs.render_color_index
    return attrs[index].name if 0 <= index < len(attrs) else attrs[0].name


def _linked_from(socket):
    """The socket feeding ``socket`` (through reroutes), or None."""
    while socket is not None and socket.is_linked:
        link = socket.links[0]
        if link.is_muted or not link.is_valid:
            return None
        socket = link.from_socket
        if socket.node.type != "REROUTE":
            return socket
        socket = socket.node.inputs[0]
    return None


def _colour_input(tree):
    """The Base Color (or Color) input of the shader at the material's Cycles output, or None."""
    out = tree.get_output_node("CYCLES")
    source = _linked_from(out.inputs["Surface"]) if out is not None else None
    seen = set()
    while source is not None and source.node.name not in seen:
        node = source.node
        seen.add(node.name)
        for name in COLOUR_INPUTS:
            if name in node.inputs:
                return node.inputs[name]
        if node.type not in SHADER_MIXES:
            return None
        shaders = [s for s in node.inputs if s.type == "SHADER" and s.is_linked]
        source = _linked_from(shaders[0]) if shaders else None
    return None


def _upstream(socket):
    """The scan data reaching ``socket``: -> ('image', image name), ('attribute', attribute name) or None.
    An image wins over an attribute."""
    found, stack, seen = {}, [socket.node], set()
    while stack:
        node = stack.pop()
        if node.as_pointer() in seen:
            continue
        seen.add(node.as_pointer())
        if node.type in IMAGE_NODES and node.image is not None:
            found.setdefault("image", node.image.name)
        elif node.type in ATTRIBUTE_NODES:
            found.setdefault("attribute", node.layer_name if node.type == "VERTEX_COLOR" else node.attribute_name)
        elif node.type == "GROUP" and node.node_tree is not None:
            stack.extend(node.node_tree.nodes)
        for s in node.inputs:
            src = _linked_from(s)
            if src is not None:
                stack.append(src.node)
    for kind in ("image", "attribute"):
        if kind in found:
            return kind, found[kind]
    return None


def colour_source(material, mesh):
    """Where one material slot of the scan takes its colour: -> (kind, detail), kind one of
    'chain' (what feeds the shader's Base Color: image or attribute nodes and whatever maps and mixes
    them; detail: the input socket), 'image' (an Image Texture node of the material; detail: node),
    'attribute' (the mesh's colour attribute; detail: its name) or 'constant' (no scan data; detail: RGBA)."""
    tree = material.node_tree if material is not None and material.use_nodes else None
    if tree is not None:
        socket = _colour_input(tree)
        if socket is not None and socket.is_linked and _upstream(socket) is not None:
            return "chain", socket
        images = [n for n in tree.nodes if n.type == "TEX_IMAGE" and n.image is not None]
        if images:
            return "image", tree.nodes.active if tree.nodes.active in images else images[0]
    name = colour_attribute_name(mesh)
    if name is not None:
        return "attribute", name
    if tree is not None:
        socket = _colour_input(tree)
        if socket is not None and not socket.is_linked:
            return "constant", tuple(socket.default_value)
    return "constant", tuple(material.diffuse_color) if material is not None else (0.8, 0.8, 0.8, 1.0)


def describe(kind, detail):
    """What a colour source carries, for the report: -> text, or None for a constant."""
    if kind == "chain":
        kind, detail = _upstream(detail)
        if kind == "attribute" and not detail:
            return "colour attribute"
    elif kind == "image":
        detail = detail.image.name
    if kind == "image":
        return f"image '{detail}'"
    return f"colour attribute '{detail}'" if kind == "attribute" else None


def scan_sources(scan):
    """The colour source of each material slot (one entry for a scan without slots): -> list of
    (material or None, kind, detail). Raises ConversionError when no slot has scan colours."""
    mats = [slot.material for slot in scan.material_slots] or [None]
    sources = [(m, *colour_source(m, scan.data)) for m in mats]
    if all(kind == "constant" for _, kind, _ in sources):
        raise cv.ConversionError(f"scan '{scan.name}' has neither an image texture nor a colour attribute: "
                                 "nothing to transfer")
    return sources


def find_scan(context, obj):
    """The scan of a registered object: the other selected mesh, else the one it names (PROP_SCAN)."""
    others = [o for o in selected_meshes(context) if o != obj]
    if len(others) > 1:
        raise cv.ConversionError("select only the scan and its registered object (the active one)")
    if others:
        scan = others[0]
    else:
        name = obj.get(cv.PROP_SCAN)
        if not name:
            raise cv.ConversionError(f"'{obj.name}' names no scan: select the scan too (the registered object "
                                     "active)")
        scan = bpy.data.objects.get(str(name))
        if scan is None:
            raise cv.ConversionError(f"the scan '{name}' of '{obj.name}' no longer exists: select the scan too")
        if scan.type != "MESH":
            raise cv.ConversionError(f"the scan '{name}' of '{obj.name}' is a {scan.type.lower()}, not a mesh")
    if is_registered(scan):
        raise cv.ConversionError(f"'{scan.name}' is a registered object, not a scan: select the scan")
    return scan


def check_target(obj):
    """Refuse an active object that cannot take a texture: -> its UV map name."""
    if not is_registered(obj):
        raise cv.ConversionError("make a registered object active (select its scan too, or keep the one it names)")
    uv = uv_map_name(obj)
    if uv is None:
        raise cv.ConversionError(f"'{obj.name}' has no UV map: its basis has no template UVs (unwrap it first "
                                 "or use a basis with UVs)")
    return uv


def default_path(obj, scan):
    clean = lambda name: re.sub(r"[^\w\-]+", "_", name).strip("_") or "texture"  # noqa: E731
    return f"//textures/{clean(obj.name)}_{clean(scan.name)}.png"


def free_path(path):
    """``path``, or the first free 'name.001.png', 'name.002.png', ... next to it."""
    stem, n = re.sub(r"\.\d{3}$", "", path.stem), 0
    while path.exists():
        n += 1
        path = path.with_name(f"{stem}.{n:03d}{path.suffix}")
    return path


#: Rays reach at least this many times the 95th percentile of the registered surface's distance to the scan.
REACH_MARGIN = 1.5


def fit_distance(context, obj, scan):
    """How far the registered surface is from the scan, in the world: the 95th percentile over its vertices and
    face centres of the distance to the nearest scan point."""
    from mathutils import Matrix
    from mathutils.bvhtree import BVHTree

    depsgraph = context.evaluated_depsgraph_get()
    verts, tris = cv.evaluated_mesh(obj, depsgraph)
    points = np.concatenate([verts, verts[tris].mean(1)]) if len(tris) else verts
    m = np.array(scan.matrix_world.inverted() @ obj.matrix_world)
    points = points @ m[:3, :3].T + m[:3, 3]  # in the scan's frame
    tree = BVHTree.FromObject(scan, depsgraph)
    found = [tree.find_nearest(p) for p in points.tolist()]
    local = np.array([f[3] for f in found if f[3] is not None])
    if not len(local):
        return 0.0
    scale = abs(Matrix(scan.matrix_world).to_3x3().determinant()) ** (1 / 3)  # scan frame -> world lengths
    return float(np.quantile(local, 0.95) * scale)


def bake(**options):
    """Cycles' bake of the selection onto the active object (a function of its own: tests replace it)."""
    return bpy.ops.object.bake(**options)


# ---------------------------------------------------------------------------------- state to restore


def _values(struct):
    """All writable plain (not pointer or collection) properties of an RNA struct: -> dict."""
    return {p.identifier: getattr(struct, p.identifier) for p in struct.bl_rna.properties
            if not p.is_readonly and p.type not in {"POINTER", "COLLECTION"} and p.identifier != "rna_type"}


def _restore(struct, values):
    for name, value in values.items():
        try:
            if getattr(struct, name) != value:
                setattr(struct, name, value)
        except (AttributeError, TypeError, ValueError):
            pass


class SceneState:
    """Render engine, Cycles and bake settings, selection, active object and hide flags: saved, then put back."""

    def __init__(self, context):
        self.scene, self.view_layer = context.scene, context.view_layer
        self.engine = self.scene.render.engine
        self.bake = _values(self.scene.render.bake)
        self.cycles = _values(self.scene.cycles) if hasattr(self.scene, "cycles") else {}
        self.selected = [o.name for o in self.view_layer.objects if o.select_get()]
        active = self.view_layer.objects.active
        self.active = active.name if active is not None else None
        self.hidden = {}

    def reveal(self, obj):
        """Unhide an object for the bake (it needs its selected objects visible and selectable)."""
        self.hidden[obj.name] = (obj.hide_get(), obj.hide_viewport, obj.hide_select)
        obj.hide_viewport = obj.hide_select = False
        obj.hide_set(False)

    def restore(self):
        for name, (hide, viewport, select) in self.hidden.items():
            obj = bpy.data.objects.get(name)
            if obj is not None:
                obj.hide_viewport, obj.hide_select = viewport, select
                obj.hide_set(hide)
        for obj in self.view_layer.objects:
            chosen = obj.name in self.selected
            if obj.select_get() != chosen:
                obj.select_set(chosen)
        self.view_layer.objects.active = bpy.data.objects.get(self.active) if self.active else None
        self.scene.render.engine = self.engine
        _restore(self.scene.render.bake, self.bake)
        if self.cycles:
            _restore(self.scene.cycles, self.cycles)


# ---------------------------------------------------------------------------------- temporary materials


def _emission_material(base, kind, detail):
    """A temporary material whose surface emits the colour of one scan slot (strength 1, nothing else)."""
    if kind in ("chain", "image"):
        mat = base.copy()
        tree = mat.node_tree
        if kind == "chain":  # the same input, found by node and socket name in the copy
            source = _linked_from(tree.nodes[detail.node.name].inputs[detail.name])
        else:
            source = tree.nodes[detail.name].outputs["Color"]
    else:
        mat = bpy.data.materials.new(TEMPORARY)
        mat.use_nodes = True
        tree = mat.node_tree
        if kind == "attribute":
            node = tree.nodes.new("ShaderNodeVertexColor")
            node.layer_name = detail
            source = node.outputs["Color"]
        else:
            source = None
    mat.name = TEMPORARY
    out = tree.get_output_node("CYCLES")
    if out is None:
        out = tree.nodes.new("ShaderNodeOutputMaterial")
        out.target = "CYCLES"
    for name in ("Volume", "Displacement"):  # nothing may tint the rays or move the surface
        for link in list(out.inputs[name].links):
            tree.links.remove(link)
    emit = tree.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    if source is not None:
        tree.links.new(source, emit.inputs["Color"])
    else:
        emit.inputs["Color"].default_value = detail
    tree.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return mat


class ScanMaterials:
    """The scan's slots switched to emission copies for the bake; ``restore`` puts its own back."""

    def __init__(self, scan, sources):
        self.scan, self.saved, self.temporary, self.appended = scan, [], [], False
        try:
            for (material, kind, detail) in sources:
                self.temporary.append(_emission_material(material, kind, detail))
            if not scan.material_slots:
                scan.data.materials.append(self.temporary[0])
                self.appended = True
            else:
                for slot, mat in zip(scan.material_slots, self.temporary):
                    self.saved.append(slot.material)
                    slot.material = mat
        except BaseException:
            self.restore()
            raise

    def restore(self):
        if self.appended:  # it had none (clear, unlike pop, also drops the object's slot)
            self.scan.data.materials.clear()
        for slot, material in zip(self.scan.material_slots, self.saved):
            slot.material = material
        for mat in self.temporary:
            bpy.data.materials.remove(mat)
        self.temporary = []


def texture_material(name, image, uv):
    """The registered object's material: the image to bake into through its UV map, beside a Principled BSDF
    (``show_texture`` connects them)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    tree = mat.node_tree
    bsdf = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    tex.location = (bsdf.location.x - 320, bsdf.location.y)
    uvmap = tree.nodes.new("ShaderNodeUVMap")
    uvmap.uv_map = uv
    uvmap.location = (tex.location.x - 220, tex.location.y - 120)
    tree.links.new(uvmap.outputs["UV"], tex.inputs["Vector"])
    tree.nodes.active = tex  # the bake writes into the active Image Texture node
    return mat


def show_texture(material):
    """Wire the baked image into the Base Color (after the bake: an image read by the material it is baked from
    is a circular dependency)."""
    tree = material.node_tree
    bsdf = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
    tex = next(n for n in tree.nodes if n.type == "TEX_IMAGE")
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])


class BAREESA_OT_transfer_texture(bpy.types.Operator):
    """Bake the scan's colours (its image texture or colour attribute) onto the active registered object's UV
    map: a PNG image in the textures folder next to the .blend and a material that shows it"""

    bl_idname = "bareesa.transfer_texture"
    bl_label = "Transfer Texture"
    bl_options = {"REGISTER", "UNDO"}

    resolution: IntProperty(name="Resolution", default=1024, min=16, max=16384, soft_min=256, soft_max=4096,
                            subtype="PIXEL", description="Width and height of the baked image (1024, 2048, ...)")
    filepath: StringProperty(name="File", default="", subtype="FILE_PATH", options={"PATH_SUPPORTS_BLEND_RELATIVE"},
                             description="Where the PNG goes (empty: //textures/<registered>_<scan>.png next to "
                                         "the saved .blend)")
    overwrite: BoolProperty(name="Overwrite", default=False,
                            description="Replace an existing image file (off: write name.001.png, ... instead)")
    extrusion: FloatProperty(name="Extrusion", default=0.01, min=0.0, soft_max=0.1, subtype="FACTOR",
                             description="How far outside the registered surface the rays start at least, as a "
                                         "share of its size (bounding-box diagonal); they reach as far inside. "
                                         "It widens by itself to 1.5 times the fit's 95th-percentile distance to "
                                         "the scan. Raise it for black patches, lower it where parts nearly touch")
    samples: IntProperty(name="Samples", default=4, min=1, soft_max=64,
                         description="Cycles samples per texel (anti-aliasing of colour edges)")

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        try:
            check_target(obj)
            scan_sources(find_scan(context, obj))
        except cv.ConversionError as err:
            return refuse(cls, str(err))
        return True

    def execute(self, context):
        obj = context.active_object
        try:
            uv = check_target(obj)
            scan = find_scan(context, obj)
            sources = scan_sources(scan)
            if not hasattr(context.scene, "cycles"):
                raise cv.ConversionError("Cycles is not available: enable the Cycles add-on to bake")
            path = output_path(self.filepath or default_path(obj, scan), "texture")
            if path.exists() and not self.overwrite:
                path = free_path(path)
            if scan.name not in context.view_layer.objects or obj.name not in context.view_layer.objects:
                raise cv.ConversionError(f"'{scan.name}' and '{obj.name}' must both be in the view layer to bake")
        except cv.ConversionError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        found = ", ".join(sorted({d for _, k, x in sources if (d := describe(k, x))}))
        try:
            image, material, replaced, reach = self.transfer(context, obj, scan, sources, uv, path)
        except (cv.ConversionError, RuntimeError, OSError) as err:
            self.report({"ERROR"}, f"transfer texture: {str(err).removeprefix('Error: ').strip()}; nothing was "
                                   "changed")
            return {"CANCELLED"}
        shown = bpy.path.relpath(str(path)) if bpy.data.filepath else str(path)
        note = f" (replaced material {', '.join(replaced)})" if replaced else ""
        self.report({"INFO"}, f"baked {found} of '{scan.name}' onto '{obj.name}': {self.resolution} px image "
                              f"written to {shown}, material '{material.name}'{note}; rays reach {reach:.3g} "
                              "either side")
        return {"FINISHED"}

    def transfer(self, context, obj, scan, sources, uv, path):
        """Bake, save, assign: -> (image, material, names of replaced materials). On any failure the scene is
        as before and no new data-block or file is left."""
        state = SceneState(context)
        wm = context.window_manager
        image = bpy.data.images.new(path.stem, self.resolution, self.resolution, alpha=False)
        material = texture_material(path.stem, image, uv)
        slots = [(slot, slot.material) for slot in obj.material_slots]
        appended = not slots
        existed, written, swapped = path.exists(), False, None
        try:
            if appended:
                obj.data.materials.append(material)
            for slot, _ in slots:
                slot.material = material
            swapped = ScanMaterials(scan, sources)
            for o in (scan, obj):
                state.reveal(o)
            for o in context.view_layer.objects:
                o.select_set(o in (scan, obj))
            context.view_layer.objects.active = obj
            if not scan.select_get():
                raise cv.ConversionError(f"scan '{scan.name}' is in a hidden or excluded collection: show it")
            scene = context.scene
            scene.render.engine = "CYCLES"
            scene.cycles.device = "CPU"
            scene.cycles.samples = self.samples
            scene.cycles.use_adaptive_sampling = False
            scene.cycles.use_denoising = False
            distance = max(self.extrusion * obj.dimensions.length, REACH_MARGIN * fit_distance(context, obj, scan),
                           1e-6)
            wm.progress_begin(0, 1)
            try:
                bake(type="EMIT", use_selected_to_active=True, use_cage=False, cage_extrusion=distance,
                     max_ray_distance=2 * distance, margin=max(2, self.resolution // 64), margin_type="EXTEND",
                     use_clear=True, target="IMAGE_TEXTURES", uv_layer=uv)
            finally:
                wm.progress_end()
            show_texture(material)
            path.parent.mkdir(parents=True, exist_ok=True)
            image.filepath_raw = str(path)
            image.file_format = "PNG"
            written = True
            image.save()
            if bpy.data.filepath:
                image.filepath = bpy.path.relpath(str(path))
            for other in bpy.data.images:  # others showing the file we replaced
                if other != image and other.source == "FILE" and other.filepath and \
                        Path(bpy.path.abspath(other.filepath)).resolve() == path:
                    other.reload()
        except BaseException:
            if appended:  # it had no slots
                obj.data.materials.clear()
            for slot, old in slots:
                slot.material = old
            bpy.data.materials.remove(material)
            bpy.data.images.remove(image)
            if written and not existed and path.exists():
                path.unlink()
            raise
        finally:
            if swapped is not None:
                swapped.restore()
            state.restore()
        replaced = sorted({old.name for _, old in slots if old is not None and old != material})
        return image, material, replaced, distance
