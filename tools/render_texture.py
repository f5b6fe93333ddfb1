"""Render the README's Transfer Texture picture: a coloured scan and its registration textured by the bake.

    .venv/bin/python tools/render_texture.py [--out docs/images] [--timeout 900]

A body of the bundled ``human`` basis is scanned (``bareesa_addon.demo.simulate_scan``) and painted
with a procedural colour pattern (vertex colours); the add-on registers it (Register, Fast schedule)
and bakes the colours onto the registered object's UVs (Transfer Texture); Workbench renders the scan
(its vertex colours, left) beside the registered object (its baked texture, right) into
``texture_transfer.png``.
"""

import math
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.render_child import finish_child, render_parser, run_child  # noqa: E402


def pattern(points):
    """RGB in [0, 1] of a smooth pattern of position: bands along the height, hue around the body: (N, 3)."""
    import numpy as np

    x, y, z = points.T
    return np.stack([0.5 + 0.5 * np.sin(14 * z), 0.5 + 0.5 * np.cos(9 * x + 3 * z),
                     0.5 + 0.5 * np.sin(11 * y - 5 * x)], 1)


def render(out, width):
    import bpy
    import numpy as np
    from mathutils import Matrix, Vector

    from bareesa_addon import demo, solver

    bpy.ops.wm.read_factory_settings(use_empty=True)
    demo.ensure_addon()
    scene = bpy.context.scene
    scene.bareesa.basis, scene.bareesa.schedule = "human", "FAST"
    basis, _ = solver.load_basis("human")
    truth = basis.template + np.tensordot(demo.demo_codes(basis, 0)[0], basis.fields, 1)
    verts, faces = demo.simulate_scan(truth, basis.faces, 3)[:2]
    scan = demo.add_object("scan", verts, faces, scene.collection)
    colours = scan.data.color_attributes.new("Col", "FLOAT_COLOR", "POINT")
    rgba = np.concatenate([pattern(verts), np.ones((len(verts), 1))], 1).astype(np.float32)
    colours.data.foreach_set("color", rgba.ravel())
    for o in scene.objects:
        o.select_set(o == scan)
    bpy.context.view_layer.objects.active = scan
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    registered = bpy.data.objects["scan_registered"]
    for o in scene.objects:
        o.select_set(o in (scan, registered))
    bpy.context.view_layer.objects.active = registered
    png = Path(tempfile.mkdtemp()) / "baked.png"
    assert bpy.ops.bareesa.transfer_texture(filepath=str(png), resolution=1024) == {"FINISHED"}
    # both in the template frame (the scan moved by the registration's inverse placement), facing the camera
    scan.matrix_world = registered.matrix_world.inverted() @ scan.matrix_world
    registered.matrix_world = Matrix.Identity(4)
    height = float(truth[:, 2].max() - truth[:, 2].min())
    cam_data = bpy.data.cameras.new("camera")
    cam_data.type, cam_data.ortho_scale = "ORTHO", 1.1 * height
    cam = bpy.data.objects.new("camera", cam_data)
    cam.location = Vector((float(truth[:, 0].mean()), -10.0, float(truth[:, 2].mean())))
    cam.rotation_euler = (math.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    r = scene.render
    r.engine, r.resolution_x, r.resolution_y = "BLENDER_WORKBENCH", width // 2, width // 2
    r.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    shading = scene.display.shading
    shading.light = "STUDIO"
    world = bpy.data.worlds.new("white")
    world.color = (1.0, 1.0, 1.0)
    scene.world = world
    halves = []
    for obj, mode in ((scan, "VERTEX"), (registered, "TEXTURE")):  # its colours; the baked texture
        for o in (scan, registered):
            o.hide_render = o is not obj
        shading.color_type = mode
        part = Path(tempfile.mkdtemp()) / "half.png"
        r.filepath = str(part)
        bpy.ops.render.render(write_still=True)
        image = bpy.data.images.load(str(part))
        halves.append(np.array(image.pixels[:], dtype=np.float32).reshape(image.size[1], image.size[0], 4))
    sheet = np.concatenate(halves, axis=1)
    target = bpy.data.images.new("texture_transfer", sheet.shape[1], sheet.shape[0], alpha=True)
    target.pixels.foreach_set(sheet.ravel())
    out.mkdir(parents=True, exist_ok=True)
    target.filepath_raw, target.file_format = str(out / "texture_transfer.png"), "PNG"
    target.save()
    print(f"wrote {out / 'texture_transfer.png'}", flush=True)


def main(argv=None):
    parser = render_parser(__doc__, width=1200, timeout=900.0)
    args = parser.parse_args(argv)
    if args.child:
        finish_child(render, args.out.resolve(), args.width)
    return run_child(__file__, ["--out", args.out, "--width", args.width], args.timeout, "render_texture")


if __name__ == "__main__":
    sys.exit(main())
