"""bareesa.transfer_texture: a scan's colours baked onto its registered object's UVs (headless Cycles),
compared point by point with the colour pattern painted on the scan; refusals and a failed bake leave
the scene as it was."""

import dataclasses
import math

import numpy as np
import pytest

from tests.addon.support import add_mesh, bpy, code_surface, select, tiny_basis

from mathutils import Matrix  # noqa: E402 (after bpy)
from mathutils.bvhtree import BVHTree  # noqa: E402

ALPHA = np.array([0.6, -0.4, 0.5, 0.3])
RESOLUTION = 256  # small: the bake takes a fraction of a second


def atlas(n_faces, inset=0.12):
    """Per-face UVs: one right triangle per cell of a square grid, inset from the cell's sides: -> (F, 3, 2)."""
    n = math.ceil(math.sqrt(n_faces))
    cells = np.stack(np.divmod(np.arange(n_faces), n), 1)[:, ::-1].astype(float)  # (column, row)
    corners = np.array([[inset, inset], [1 - inset, inset], [inset, 1 - inset]])
    return ((cells[:, None, :] + corners[None]) / n).astype(np.float32)


@pytest.fixture(scope="session")
def uv_tiny(tmp_path_factory):
    """The tiny basis with template UVs (a per-face atlas): (Basis, path of its .npz)."""
    from bareesa.basis_io import save_basis

    basis, _ = tiny_basis()
    basis = dataclasses.replace(basis, name="tiny_uv",
                                extras={**basis.extras, "template_uv": atlas(len(basis.faces))})
    path = tmp_path_factory.mktemp("bases") / "tiny_uv.npz"
    save_basis(path, basis)
    return basis, path


def vertex_pattern(p):
    """The scan's vertex colours (sRGB), a smooth function of its local position: (N, 3) -> (N, 3)."""
    x, y, z = p.T
    return 0.5 + 0.35 * np.stack([np.sin(1.6 * x + 0.3), np.sin(1.4 * y - 0.6 + 0.5 * z), np.cos(1.5 * z + 0.4 * x)], 1)


def image_pattern(p):
    """The scan's image texture (sRGB), painted through a planar UV map, so a function of (x, y) only."""
    x, y = p[:, 0], p[:, 1]
    return 0.5 + 0.35 * np.stack([np.cos(2.0 * x), np.sin(2.0 * y + 0.5), np.sin(1.5 * (x + y))], 1)


PLANAR = 1.5  # the planar UV map: u = (x + PLANAR) / (2 PLANAR), v likewise from y


def add_scan():
    """A scan of F(ALPHA) (642 vertices), moved and turned, with vertex colours ``vertex_pattern``."""
    surface = tiny_basis()[1]
    verts, faces = code_surface(surface, ALPHA, subdivisions=3)
    scan = add_mesh("scan", verts, faces, location=(1.0, 0.5, 0.0))
    scan.rotation_euler = (0.0, 0.0, math.radians(30))
    bpy.context.view_layer.update()
    colours = np.hstack([vertex_pattern(verts), np.ones((len(verts), 1))])
    attr = scan.data.color_attributes.new("Scan Colour", "BYTE_COLOR", "POINT")
    attr.data.foreach_set("color_srgb", colours.ravel())
    return scan


def add_image_material(scan, metallic=0.6):
    """Give the scan an image texture (``image_pattern``) through its own UV map 'ScanUV' (not the active one)
    into a Principled BSDF that is partly metallic (its diffuse colour is no longer the image's)."""
    mesh = scan.data
    mesh.uv_layers.new(name="Other")
    uv = mesh.uv_layers.new(name="ScanUV")
    mesh.uv_layers.active = mesh.uv_layers["Other"]
    corners = np.empty(len(mesh.loops), dtype=np.int64)
    mesh.loops.foreach_get("vertex_index", corners)
    verts = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", verts)
    xy = verts.reshape(-1, 3)[corners, :2]
    uv.data.foreach_set("uv", ((xy + PLANAR) / (2 * PLANAR)).astype(np.float32).ravel())
    size = 256
    u, v = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size)  # rows from the bottom
    p = np.stack([u.ravel() * 2 * PLANAR - PLANAR, v.ravel() * 2 * PLANAR - PLANAR, np.zeros(u.size)], 1)
    image = bpy.data.images.new("scan_photo", size, size)
    image.pixels.foreach_set(np.hstack([image_pattern(p), np.ones((u.size, 1))]).astype(np.float32).ravel())
    image.pack()
    mat = bpy.data.materials.new("scan_skin")
    mat.use_nodes = True
    tree = mat.node_tree
    bsdf = tree.nodes["Principled BSDF"]
    bsdf.inputs["Metallic"].default_value = metallic
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    uvmap = tree.nodes.new("ShaderNodeUVMap")
    uvmap.uv_map = "ScanUV"
    tree.links.new(uvmap.outputs["UV"], tex.inputs["Vector"])
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    mesh.materials.append(mat)
    return mat


def register(scene, uv_path, scan):
    scene.bareesa.basis = str(uv_path)
    scene.bareesa.prealign = False
    select(scan)
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    return bpy.data.objects["scan_registered"]


def state(scene, scan=None):
    """What Transfer Texture must leave as it found it."""
    bake = scene.render.bake
    return {
        "objects": sorted(bpy.data.objects.keys()), "meshes": sorted(bpy.data.meshes.keys()),
        "materials": sorted(bpy.data.materials.keys()), "images": sorted(bpy.data.images.keys()),
        "node_groups": sorted(bpy.data.node_groups.keys()),
        "engine": scene.render.engine, "samples": scene.cycles.samples, "device": scene.cycles.device,
        "bake": (scene.cycles.bake_type, bake.use_selected_to_active, bake.cage_extrusion, bake.max_ray_distance,
                 bake.margin, bake.target, bake.use_clear, bake.use_cage),
        "selected": sorted(o.name for o in scene.objects if o.select_get()),
        "active": getattr(bpy.context.view_layer.objects.active, "name", None),
        "hidden": sorted(o.name for o in scene.objects if o.hide_get() or o.hide_viewport or o.hide_select),
        "scan slots": [(s.link, s.material.name if s.material else None) for s in scan.material_slots] if scan else [],
        "scan materials": ([len(s.material.node_tree.nodes) for s in scan.material_slots if s.material]
                           if scan else []),
    }


def baked_pixels(path):
    """The PNG as written (not Blender's copy in memory): -> (H, W, 3), row 0 at the bottom (v = 0)."""
    image = bpy.data.images.load(str(path), check_existing=False)
    try:
        w, h = image.size
        px = np.empty(w * h * 4, dtype=np.float32)
        image.pixels.foreach_get(px)
        return px.reshape(h, w, 4)[..., :3]
    finally:
        bpy.data.images.remove(image)


def bilinear(px, uv):
    h, w, _ = px.shape
    x, y = uv[:, 0] * w - 0.5, uv[:, 1] * h - 0.5
    x0, y0 = np.clip(np.floor(x).astype(int), 0, w - 2), np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fx) * (1 - fy) * px[y0, x0] + fx * (1 - fy) * px[y0, x0 + 1]
            + (1 - fx) * fy * px[y0 + 1, x0] + fx * fy * px[y0 + 1, x0 + 1])


def surface_samples(obj):
    """Points inside each face of the registered object (as shown: keys and transform), world frame, and their
    UVs: -> points (M, 3), uv (M, 2), face index (M,), barycentrics (M, 3)."""
    from bareesa_addon import convert

    verts, tris = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    m = np.array(obj.matrix_world)
    verts = verts @ m[:3, :3].T + m[:3, 3]
    uv = np.empty(len(obj.data.loops) * 2, dtype=np.float32)
    obj.data.uv_layers[convert.UV_MAP].data.foreach_get("uv", uv)
    uv = uv.reshape(len(tris), 3, 2)  # triangles: loops in face-corner order
    n = 10  # barycentrics on a grid, at least 0.2 from each edge (away from the texels that straddle an edge)
    bary = np.array([(i, j, n - i - j) for i in range(2, n) for j in range(2, n) if n - i - j >= 2]) / n
    face = np.repeat(np.arange(len(tris)), len(bary))
    b = np.tile(bary, (len(tris), 1))
    points = np.einsum("mk,mkd->md", b, verts[tris[face]])
    return points, np.einsum("mk,mkd->md", b, uv[face]), face, b, uv


def scan_truth(scan, points, pattern):
    """The pattern at the scan point nearest to each world point."""
    from bareesa_addon import convert

    verts, tris = convert.evaluated_mesh(scan, bpy.context.evaluated_depsgraph_get())
    m = np.array(scan.matrix_world)
    tree = BVHTree.FromPolygons((verts @ m[:3, :3].T + m[:3, 3]).tolist(), tris.tolist())
    nearest = np.array([tree.find_nearest(p)[0] for p in points.tolist()])
    return pattern((nearest - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T)


def colour_errors(reg, scan, path, pattern):
    """Mean absolute RGB error of the baked image against the scan's pattern: right UVs, and the UVs of the
    faces shuffled (a wrong mapping): -> (right, wrong)."""
    px = baked_pixels(path)
    points, uv, face, b, face_uv = surface_samples(reg)
    truth = scan_truth(scan, points, pattern)
    right = np.abs(bilinear(px, uv) - truth).mean()
    shuffled = face_uv[np.random.default_rng(0).permutation(len(face_uv))]
    wrong = np.abs(bilinear(px, np.einsum("mk,mkd->md", b, shuffled[face])) - truth).mean()
    return float(right), float(wrong)


def test_transfer_texture_bakes_the_scans_colours_onto_the_registered_uvs(scene, uv_tiny, tmp_path, capfd):
    from bareesa_addon import convert

    scan = add_scan()
    reg = register(scene, uv_tiny[1], scan)
    assert convert.UV_MAP in reg.data.uv_layers and reg["bareesa_scan"] == "scan"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scans.blend"))
    scene.render.engine = "BLENDER_WORKBENCH"
    scan.hide_set(True)  # the artist looks at the registered object: the bake shows the scan for itself
    select(reg)  # the scan is the one it names
    before = state(scene, scan)
    capfd.readouterr()
    assert bpy.ops.bareesa.transfer_texture.poll()
    assert bpy.ops.bareesa.transfer_texture(resolution=RESOLUTION) == {"FINISHED"}
    out = capfd.readouterr().out
    first = tmp_path / "textures" / "scan_registered_scan.png"
    assert first.exists() and "textures/scan_registered_scan.png" in out and "colour attribute 'Scan Colour'" in out
    after = state(scene, scan)
    assert after["materials"] == sorted(before["materials"] + ["scan_registered_scan"])
    assert after["images"] == sorted(before["images"] + ["scan_registered_scan"])
    assert {k: v for k, v in after.items() if k not in ("materials", "images")} == \
        {k: v for k, v in before.items() if k not in ("materials", "images")}
    # the registered object shows the image through its UV map
    mat = reg.material_slots[0].material
    tex = next(n for n in mat.node_tree.nodes if n.type == "TEX_IMAGE")
    assert len(reg.material_slots) == 1 and tex.image.name == "scan_registered_scan"
    assert tex.image.filepath == "//textures/scan_registered_scan.png" and tex.image.source == "FILE"
    assert tex.inputs["Vector"].links[0].from_node.uv_map == convert.UV_MAP
    assert tex.outputs["Color"].links[0].to_socket.name == "Base Color"
    right, wrong = colour_errors(reg, scan, first, vertex_pattern)
    with capfd.disabled():
        print(f"vertex colours: mean |RGB error| {right:.4f}, shuffled UVs {wrong:.4f}")
    assert right < 0.05 and wrong > 0.1 and wrong > 4 * right

    # an image texture through the scan's own (not active) UV map wins over its colour attribute, and comes
    # over exactly although the Principled BSDF is partly metallic; the first file is not overwritten
    add_image_material(scan)
    written = first.read_bytes()
    scan.hide_set(False)
    select(scan, reg, active=reg)
    before = state(scene, scan)
    capfd.readouterr()
    assert bpy.ops.bareesa.transfer_texture(resolution=RESOLUTION) == {"FINISHED"}
    second = tmp_path / "textures" / "scan_registered_scan.001.png"
    assert second.exists() and first.read_bytes() == written and "image 'scan_photo'" in capfd.readouterr().out
    after = state(scene, scan)
    assert after["scan slots"] == before["scan slots"] == [("DATA", "scan_skin")]
    assert after["scan materials"] == before["scan materials"]  # its node tree untouched
    assert after["selected"] == ["scan", "scan_registered"] and after["active"] == "scan_registered"
    assert [s.material.name for s in reg.material_slots] == ["scan_registered_scan.001"]
    right, wrong = colour_errors(reg, scan, second, image_pattern)
    with capfd.disabled():
        print(f"image texture: mean |RGB error| {right:.4f}, shuffled UVs {wrong:.4f}")
    assert right < 0.05 and wrong > 0.1 and wrong > 4 * right
    other, _ = colour_errors(reg, scan, second, vertex_pattern)  # a different pattern does not match either
    assert other > 0.1

    # overwrite on request
    assert bpy.ops.bareesa.transfer_texture(resolution=64, overwrite=True,
                                            filepath="//textures/scan_registered_scan.png") == {"FINISHED"}
    assert first.read_bytes() != written and not (tmp_path / "textures" / "scan_registered_scan.002.png").exists()


def refused(scene, scan, reason):
    """The operator is greyed out with ``reason`` and, run anyway, changes nothing."""
    before = state(scene, scan)
    with pytest.raises(RuntimeError, match=reason):
        bpy.ops.bareesa.transfer_texture(resolution=32)
    assert state(scene, scan) == before


def template(name, scan_name=None):
    """A template object of the panel's basis (no solve) that names a scan, placed at the origin."""
    bpy.ops.bareesa.load_template()
    obj = bpy.context.active_object
    obj.name = name
    if scan_name is not None:
        obj["bareesa_scan"] = scan_name
    return obj


def test_transfer_texture_refuses_with_a_reason_and_changes_nothing(scene, tiny, uv_tiny, tmp_path):
    scan = add_scan()
    plain = add_mesh("plain", *code_surface(tiny[2], ALPHA))  # no material, no colour attribute
    scene.render.engine = "BLENDER_WORKBENCH"

    select(scan)
    assert bpy.ops.bareesa.transfer_texture.poll() is False
    refused(scene, scan, "make a registered object active")

    no_uv = template("no_uv", "scan")  # the tiny basis has no template UVs
    select(no_uv)
    assert bpy.ops.bareesa.transfer_texture.poll() is False
    refused(scene, scan, "'no_uv' has no UV map: its basis has no template UVs")

    scene.bareesa.basis = str(uv_tiny[1])
    colourless = template("colourless", "plain")
    select(colourless)
    refused(scene, plain, "scan 'plain' has neither an image texture nor a colour attribute")
    gone = template("gone", "deleted scan")
    select(gone)
    refused(scene, scan, "the scan 'deleted scan' of 'gone' no longer exists")
    select(plain, scan, gone, active=gone)
    refused(scene, scan, "select only the scan and its registered object")

    ok = template("ok", "scan")
    select(ok)
    assert bpy.ops.bareesa.transfer_texture.poll() and not bpy.data.filepath
    refused(scene, scan, "is relative to the .blend file, which is not saved: save the file first or choose an "
                         "absolute path")
    assert not list(tmp_path.rglob("*.png"))


def test_a_failed_bake_puts_everything_back_and_leaves_no_file(scene, uv_tiny, tmp_path, monkeypatch):
    from bareesa_addon.operators import texture

    scene.bareesa.basis = str(uv_tiny[1])
    scan = add_scan()
    add_image_material(scan)
    reg = template("reg", "scan")
    old = bpy.data.materials.new("old look")
    reg.data.materials.append(old)
    scan.hide_set(True)
    scene.render.engine = "BLENDER_EEVEE_NEXT"
    other = bpy.data.objects.new("bystander", None)  # selected, not a mesh: the scan is the one reg names
    scene.collection.objects.link(other)
    select(other, reg, active=reg)
    seen = {}

    def broken(**options):
        seen["options"] = options
        seen["selected"] = sorted(o.name for o in bpy.context.selected_objects)
        seen["engine"] = scene.render.engine
        mat = scan.material_slots[0].material
        seen["emits"] = mat.node_tree.get_output_node("CYCLES").inputs["Surface"].links[0].from_node.type
        seen["target"] = reg.material_slots[0].material.node_tree.nodes.active.image.name
        raise RuntimeError("Error: Cycles ran out of memory\n")

    monkeypatch.setattr(texture, "bake", broken)
    path = tmp_path / "out" / "skin.png"  # an explicit path: no saved .blend needed
    before = state(scene, scan)
    before["reg slots"] = [s.material.name for s in reg.material_slots]
    with pytest.raises(RuntimeError, match="transfer texture: Cycles ran out of memory; nothing was changed"):
        bpy.ops.bareesa.transfer_texture(resolution=32, filepath=str(path))
    after = state(scene, scan)
    after["reg slots"] = [s.material.name for s in reg.material_slots]
    assert after == before and not path.exists()
    # what the bake was given: the scan (other selected mesh from the name) to the registered object, EMIT
    assert seen["selected"] == ["reg", "scan"] and seen["engine"] == "CYCLES" and seen["emits"] == "EMISSION"
    assert seen["target"] == "skin"
    o = seen["options"]
    assert o["type"] == "EMIT" and o["use_selected_to_active"] and o["uv_layer"] == "UVMap"
    assert o["max_ray_distance"] == pytest.approx(2 * o["cage_extrusion"]) and o["cage_extrusion"] > 0


def test_transfer_texture_bakes_onto_the_surface_with_its_detail_key(scene, uv_tiny, tmp_path):
    """The bake takes the registered object as shown (its shape keys mixed), so a 'Detail' key at 1 is the
    surface the scan's colours are baked onto: here a detail that turns the template 90 degrees about z, and
    a scan of the turned body; the colours match on the detailed surface and not on the basis fit."""
    from bareesa import synthetic
    from bareesa_addon import convert

    basis, uv_path = uv_tiny
    scene.bareesa.basis = str(uv_path)
    turn = np.array(Matrix.Rotation(math.radians(90), 3, "Z"))
    reg = template("reg", "scan")
    convert.set_detail_key(reg, basis.template, basis.template @ turn.T - basis.template)
    u, faces = synthetic.resampled_sphere(3, seed=3)
    verts = tiny_basis()[1](u) @ turn.T  # the template's surface, finely meshed, turned
    scan = add_mesh("scan", verts, faces)
    attr = scan.data.color_attributes.new("Scan Colour", "BYTE_COLOR", "POINT")
    attr.data.foreach_set("color_srgb", np.hstack([vertex_pattern(verts), np.ones((len(verts), 1))]).ravel())
    scene.render.engine = "BLENDER_WORKBENCH"
    select(reg)
    path = tmp_path / "detail.png"
    assert bpy.ops.bareesa.transfer_texture(resolution=RESOLUTION, filepath=str(path)) == {"FINISHED"}
    right, wrong = colour_errors(reg, scan, path, vertex_pattern)
    assert right < 0.05 and wrong > 0.1
    reg.data.shape_keys.key_blocks["Detail"].value = 0.0  # the same image read on the basis fit's surface
    basis_fit, _ = colour_errors(reg, scan, path, vertex_pattern)
    assert basis_fit > 0.1 and basis_fit > 4 * right
