"""Headless Blender demo: scans -> registration -> keyframed geodesic -> motion transfer -> random bodies.

Run from a source checkout with the bpy module or Blender itself::

    python tools/demo_blender.py --out bareesa_demo
    blender -b --factory-startup -P tools/demo_blender.py -- --out bareesa_demo

Everything goes through the add-on's operators (``bpy.ops.bareesa.*``), as an
artist's clicks would. Writes ``demo.blend`` and ``contact_sheet.png``
(Workbench render: registration, the geodesic path, the transferred motion and
six random bodies).
"""

import argparse
import math
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

from . import convert, solver

COLORS = {"scan": (0.55, 0.55, 0.58, 1.0), "registered": (0.95, 0.55, 0.25, 1.0), "path": (0.30, 0.60, 0.90, 1.0),
          "motion": (0.45, 0.75, 0.40, 1.0), "random": (0.85, 0.45, 0.65, 1.0)}


def log(message):
    print(f"[demo] {message}", flush=True)


def ensure_addon():
    """Register the add-on when the demo runs from a source checkout."""
    if not hasattr(bpy.types.Scene, "bareesa"):
        from . import register

        register()


def synthetic_basis(path):
    """A stand-in basis (smooth deformations of a sphere, groups pose/shape, a fitted distribution)."""
    synthetic, latent, statistics = (solver.module(m) for m in ("synthetic", "latent", "statistics"))
    b, _ = synthetic.smooth_sphere_basis(subdivisions=3, n_fields=6, seed=0, amplitude=0.15)
    groups = {"pose": (0, 3), "shape": (3, 6)}
    rng = np.random.default_rng(0)
    extras = statistics.fit_distribution(0.3 * rng.normal(size=(40, 6)), groups, {"pose": 1, "shape": 1}, seed=0)
    basis = latent.Basis(template=b.template, faces=b.faces, fields=b.fields, groups=groups, weights=b.weights,
                         schedule=b.schedule, scale=b.scale, name="synthetic_blob", extras=extras)
    latent.save_basis(path, basis)
    return str(path)


def pick_basis(requested, out):
    """The requested bundled basis, or (when no basis is bundled yet) a generated stand-in."""
    latent, errors = solver.module("latent"), solver.module("errors")
    for name in dict.fromkeys((requested, "humanoid", "deformables")):
        try:
            latent.resolve_basis_path(name)
        except errors.InputError as err:
            log(f"{err}")
            continue
        return name
    log("no basis is bundled yet: using a generated stand-in basis")
    return synthetic_basis(out / "synthetic_blob.npz")


def sample_code(basis, rng, scale=1.0):
    """A plausible code: from the basis' stored distribution when it has one, else small Gaussian."""
    code = np.zeros(basis.n_fields)
    for group, (a, b) in basis.groups.items():
        means = basis.extras.get(f"gmm_{group}_means")
        covs = basis.extras.get(f"gmm_{group}_covariances")
        weights = basis.extras.get(f"gmm_{group}_weights")
        if means is not None:
            c = rng.choice(len(means), p=np.asarray(weights) / np.sum(weights)) if weights is not None else 0
            code[a:b] = rng.multivariate_normal(means[c], covs[c])
        else:
            code[a:b] = rng.normal(scale=0.5, size=b - a)
    return scale * code


def simulate_scan(verts, faces, seed):
    """An unregistered scan of a mesh: the core's scan simulator when present, else remesh + rigid motion."""
    try:
        simulator = solver.module("scan_simulator")
    except solver.DependencyError:
        simulator = None
    if simulator is not None and hasattr(simulator, "simulate_scan"):
        v, f, _ = simulator.simulate_scan(verts, faces, seed=seed, resolution=0.07, holes=2, noise=0.001,
                                          rigid=True, scale=0.1)
        return v, f
    synthetic = solver.module("synthetic")
    v, f = synthetic.remesh_same_surface(verts, faces, seed=seed)
    return v @ synthetic.random_rotation(seed).T + seed * 0.1, f


def add_object(name, verts, faces, collection, location=(0, 0, 0)):
    obj = convert.new_mesh_object(name, verts, faces, collection)
    obj.location = location
    return obj


def run_demo(out, basis_name="humanoid", schedule="FAST", frames=24, seed=0):
    """Build the demo scene, save demo.blend and render contact_sheet.png into ``out``: -> dict of paths."""
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ensure_addon()
    scene = bpy.context.scene
    s = scene.bareesa
    s.basis = pick_basis(basis_name, out)
    s.schedule = schedule
    s.frame_start, s.frame_end = 1, frames
    s.steps, s.geodesic_iterations, s.shoot_steps = 5, 40, 4  # a quick demo; the panel defaults are finer
    scene.frame_start, scene.frame_end = 1, frames
    basis, _ = solver.load_basis(s.basis)
    log(f"basis '{basis.name}': {basis.template.shape[0]} vertices, {basis.n_fields} fields "
        f"({', '.join(f'{g} {b - a}' for g, (a, b) in basis.groups.items())})")
    rng = np.random.default_rng(seed)

    # 1. two simulated scans of two different bodies in two different poses
    scans = []
    for i, name in enumerate(("scan_A", "scan_B")):
        truth = basis.template + np.tensordot(sample_code(basis, rng), basis.fields, axes=1)
        v, f = simulate_scan(truth, basis.faces, seed=seed + i + 1)
        scans.append(add_object(name, v, f, scene.collection, location=(0, 0, 0)))
        log(f"{name}: {len(v)} vertices, {len(f)} faces (remeshed, holes, rigidly moved)")

    # 2. register them (one operator call, as with both scans selected in the viewport)
    bpy.context.view_layer.update()
    for o in bpy.context.view_layer.objects:
        o.select_set(o in scans)
    bpy.context.view_layer.objects.active = scans[-1]
    assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    reg_a, reg_b = bpy.data.objects["scan_A_registered"], bpy.data.objects["scan_B_registered"]
    for r in (reg_a, reg_b):
        log(f"{r.name}: varifold {r[convert.PROP_VARIFOLD]:.3g}, Chamfer {r[convert.PROP_CHAMFER]:.3g}")

    # 3. the geodesic between them, keyframed on every frame
    assert bpy.ops.bareesa.interpolate(object_a=reg_a.name, object_b=reg_b.name) == {"FINISHED"}
    path_obj = bpy.data.objects[f"{reg_a.name}_to_{reg_b.name}"]
    log(f"geodesic keyframed on frames 1-{frames}, distance {s.distance:.4g}")

    # 4. transfer that motion onto a third body (its identity from the basis' distribution)
    bpy.ops.bareesa.load_template()
    actor = bpy.context.active_object
    actor.name = "actor"
    code = np.zeros(basis.n_fields)
    ident = basis.group_slice("shape") if "shape" in basis.groups else slice(0, basis.n_fields)
    code[ident] = sample_code(basis, np.random.default_rng(seed + 10), 1.2)[ident]
    convert.set_code(actor, solver.field_names(basis), code)
    s.identity_group = "shape" if "shape" in basis.groups else next(iter(basis.groups))
    assert bpy.ops.bareesa.transfer_motion(source=path_obj.name, target=actor.name) == {"FINISHED"}
    log("motion transferred onto 'actor'")

    # 5. six random bodies
    s.count, s.seed = 6, seed
    if not any(k.startswith("gmm_") for k in basis.extras):
        fit = bpy.data.collections.new("registered")
        scene.collection.children.link(fit)
        for r in (reg_a, reg_b):
            fit.objects.link(r)
        s.fit_collection = fit
    assert bpy.ops.bareesa.generate_random() == {"FINISHED"}
    randoms = sorted((o for o in bpy.data.objects if "_random_" in o.name), key=lambda o: o.name)
    log(f"{len(randoms)} random bodies baked")

    blend = out / "demo.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    log(f"saved {blend}")
    png = render_contact_sheet(out / "contact_sheet.png", scans, (reg_a, reg_b), path_obj, actor, randoms, frames)
    log(f"rendered {png} ({time.perf_counter() - t0:.0f} s in all)")
    bpy.ops.wm.open_mainfile(filepath=str(blend))  # leave the saved scene loaded, not the contact sheet
    return {"blend": blend, "png": png}


# ------------------------------------------------------------------------------------ contact sheet


def _snapshot(obj, frame, frame_of=None):
    """World-free vertices of an object at a frame (template frame for template objects): -> (N, 3), (F, 3)."""
    bpy.context.scene.frame_set(frame)
    verts, faces = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    if frame_of is not None:  # a scan shown in the frame of its registered object
        m = np.array(frame_of.matrix_world.inverted() @ obj.matrix_world)
        verts = verts @ m[:3, :3].T + m[:3, 3]
    return verts, faces


def _upright(template):
    """Rotation that shows the template's longest axis vertically (Z) and its thinnest towards the camera."""
    ext = template.max(0) - template.min(0)
    up, depth = int(np.argmax(ext)), int(np.argmin(ext))
    side = 3 - up - depth
    m = np.zeros((3, 3))
    m[0, side], m[1, depth], m[2, up] = 1.0, 1.0, 1.0
    if np.linalg.det(m) < 0:
        m[1] *= -1
    return m


def render_contact_sheet(png, scans, registered, path_obj, actor, randoms, frames, width=1800):
    """One Workbench render of the results laid out in labelled rows: -> png path."""
    source_scene = bpy.context.scene
    template = registered[0].data.shape_keys.key_blocks["Basis"].data
    co = np.empty(len(template) * 3)
    template.foreach_get("co", co)
    rot = _upright(co.reshape(-1, 3))
    ext = (co.reshape(-1, 3) @ rot.T).ptp(axis=0)
    dx, dz = 1.35 * max(ext[0], 0.45 * ext[2]), 1.45 * ext[2]
    path_frames = np.linspace(1, frames, 7).round().astype(int)
    rows = [("scans and registrations", [(_snapshot(scans[0], 1, registered[0]), "scan"),
                                         (_snapshot(registered[0], 1), "registered"),
                                         (_snapshot(scans[1], 1, registered[1]), "scan"),
                                         (_snapshot(registered[1], 1), "registered")]),
            ("geodesic A -> B, frames " + " ".join(map(str, path_frames)),
             [(_snapshot(path_obj, int(f)), "path") for f in path_frames]),
            ("motion transferred to a new body", [(_snapshot(actor, int(f)), "motion") for f in path_frames]),
            ("six random bodies", [(_snapshot(o, 1), "random") for o in randoms])]
    source_scene.frame_set(1)

    sheet = bpy.data.scenes.new("ContactSheet")
    n_cols = max(len(items) for _, items in rows)
    for r, (label, items) in enumerate(rows):
        z = -r * dz
        for c, ((verts, faces), kind) in enumerate(items):
            centre = verts.mean(0)
            v = (verts - centre) @ rot.T
            obj = add_object(f"sheet_{r}_{c}", v, faces, sheet.collection, location=(c * dx, 0.0, z))
            obj.color = COLORS[kind]
        text = bpy.data.curves.new(f"label_{r}", type="FONT")
        text.body, text.size, text.align_x = label, 0.09 * dz, "LEFT"
        label_obj = bpy.data.objects.new(f"label_{r}", text)
        label_obj.location = (-0.5 * dx, -0.1, z + 0.47 * dz)
        label_obj.rotation_euler = (math.pi / 2, 0.0, 0.0)
        label_obj.color = (0.1, 0.1, 0.1, 1.0)
        sheet.collection.objects.link(label_obj)

    # the sheet's extent (labels included) and a camera framing it exactly
    left, right = -0.6 * dx, (n_cols - 0.45) * dx
    top, bottom = 0.62 * dz, -(len(rows) - 0.4) * dz
    span_x, span_z = right - left, top - bottom
    cam_data = bpy.data.cameras.new("sheet_camera")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = max(span_x, span_z)  # covers the larger side of the image
    cam = bpy.data.objects.new("sheet_camera", cam_data)
    cam.location = Vector(((left + right) / 2, -10 * span_x, (top + bottom) / 2))
    cam.rotation_euler = (math.pi / 2, 0.0, 0.0)
    sheet.collection.objects.link(cam)
    sheet.camera = cam

    render = sheet.render
    render.engine = "BLENDER_WORKBENCH"
    render.resolution_x = width
    render.resolution_y = int(round(width * span_z / span_x))
    render.resolution_percentage = 100
    render.film_transparent = False
    render.image_settings.file_format = "PNG"
    render.filepath = str(png)
    shading = sheet.display.shading
    shading.light, shading.color_type = "STUDIO", "OBJECT"
    shading.show_cavity, shading.cavity_type = True, "WORLD"
    world = bpy.data.worlds.new("sheet_world")
    world.color = (0.96, 0.96, 0.96)
    sheet.world = world
    cam_data.clip_end = 40 * span_x
    sheet.view_settings.view_transform = "Standard"
    bpy.context.window_manager  # noqa: B018 (touch the window manager so the scene is valid headless)
    with bpy.context.temp_override(scene=sheet):
        bpy.ops.render.render(write_still=True, scene=sheet.name)
    return Path(png)


def main(argv=None):
    parser = argparse.ArgumentParser(description="BaRe-ESA headless Blender demo")
    parser.add_argument("--out", type=Path, default=Path("bareesa_demo"), help="output folder")
    parser.add_argument("--basis", default="humanoid", help="bundled basis name or .npz path")
    parser.add_argument("--schedule", choices=["fast", "paper"], default="fast")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    result = run_demo(args.out, args.basis, args.schedule.upper(), args.frames, args.seed)
    print(f"demo written: {result['blend']} and {result['png']}")
    return 0
