"""Headless Blender demo: scans -> registration -> keyframed geodesic -> motion transfer -> random bodies.

Run from a source checkout with the bpy module or Blender itself::

    python tools/demo_blender.py --out bareesa_demo
    blender -b --factory-startup -P tools/demo_blender.py -- --out bareesa_demo

Everything goes through the add-on's operators (``bpy.ops.bareesa.*``), as an
artist's clicks would. Writes ``demo.blend`` and ``contact_sheet.png`` (a
Workbench render of the registrations, the geodesic path, the transferred
motion and six random bodies) and, with ``--figures``, one picture per step.
"""

import argparse
import colorsys
import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

from . import convert, solver

#: Scan simulator settings (lengths are fractions of the body size, see bareesa.scan_simulator).
SCAN_OPTIONS = dict(resolution=0.03, holes=2, noise=0.001, rigid=True, scale=0.1)
#: Object colours of the contact sheet (linear RGBA).
SCAN_COLOR = (0.50, 0.52, 0.56, 1.0)
END_COLORS = ((0.90, 0.42, 0.16, 1.0), (0.13, 0.42, 0.80, 1.0))  # registered A, B (the path blends them)
MOTION_COLORS = ((0.60, 0.82, 0.42, 1.0), (0.10, 0.45, 0.22, 1.0))
TEXT_COLOR = (0.05, 0.05, 0.06, 1.0)
CAPTION_COLOR = (0.25, 0.25, 0.28, 1.0)
FIGURES = ("registration", "geodesic", "transfer", "random")
#: The demo's basis: the solver's default (``bareesa.basis_io``, the vendored copy first).
DEFAULT_BASIS = solver.module("basis_io").DEFAULT_BASIS


def log(message):
    print(f"[demo] {message}", flush=True)


@contextmanager
def stage(times, name):
    """Time a demo stage into ``times[name]`` (seconds) and log it."""
    t0 = time.perf_counter()
    yield
    times[name] = time.perf_counter() - t0
    log(f"{name}: {times[name]:.1f} s")


def ensure_addon():
    """Register the add-on when the demo runs from a source checkout."""
    if not hasattr(bpy.types.Scene, "bareesa"):
        from . import register

        register()


def pick_basis(requested):
    """The requested basis (bundled name or .npz path): -> reference. Only the default, ``human``,
    falls back to ``deformables`` (a checkout whose human basis was not built); any other name that
    does not resolve raises InputError."""
    basis_io, errors = solver.module("basis_io"), solver.module("errors")
    candidates = (requested, "deformables") if requested == DEFAULT_BASIS else (requested,)
    for name in candidates:
        try:
            basis_io.resolve_basis_path(name)
        except errors.InputError as err:
            if name == candidates[-1]:
                raise
            log(f"{err}")
            continue
        return name


def sample_code(basis, seed, scale=1.0):
    """A plausible code (P,): a draw from the basis' stored distribution of initial velocities (the
    code reached along the straight latent line), else a small Gaussian."""
    if any(k.startswith("gmm_") for k in basis.extras):
        code = solver.module("statistics").sample_velocities(basis.extras, basis.groups, 1, seed)[0]
    else:
        code = np.random.default_rng(seed).normal(scale=0.5, size=basis.n_fields)
    return scale * code


def demo_codes(basis, seed):
    """Codes (2, P) of the demo's two bodies: two identities from the stored distribution in two
    clearly different poses, when the basis has pose prototypes: the one nearest the rest pose
    and, of the three quarters nearest rest (the most extreme poses, arms overhead, are where
    registration can still fall into a wrong minimum), the one farthest from it."""
    codes = np.stack([sample_code(basis, seed + 100 + i) for i in range(2)])
    protos = basis.extras.get("pose_prototypes")
    if protos is None or "pose" not in basis.groups:
        return codes
    pose = basis.group_slice("pose")
    p = np.asarray(protos, dtype=np.float64)[:, pose]
    norms = np.linalg.norm(p, axis=1)
    i = int(np.argmin(norms))
    usable = np.flatnonzero(norms <= np.percentile(norms, 75))
    j = int(usable[np.argmax(np.linalg.norm(p[usable] - p[i], axis=1))])
    codes[:, pose] = p[[i, j]]
    return codes


def simulate_scan(verts, faces, seed):
    """An unregistered scan of a mesh (remeshed, noisy, with holes, rigidly moved and rescaled): -> verts, faces."""
    v, f, _ = solver.module("scan_simulator").simulate_scan(verts, faces, seed=seed, **SCAN_OPTIONS)
    return v, f


def add_object(name, verts, faces, collection, location=(0, 0, 0)):
    obj = convert.new_mesh_object(name, verts, faces, collection)
    obj.location = location
    return obj


def run_demo(out, basis_name=DEFAULT_BASIS, schedule="FAST", frames=24, seed=0, figures=False, width=1800,
             figure_width=1000):
    """Build the demo scene, save demo.blend and render contact_sheet.png into ``out``.

    figures: also render each row alone (``FIGURES``.png, ``figure_width`` pixels wide).
    -> dict: blend, png (paths), figures (paths, with ``figures``), times (seconds per stage).
    """
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    times = {}
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ensure_addon()
    scene = bpy.context.scene
    s = scene.bareesa
    s.basis = pick_basis(basis_name)
    s.schedule = schedule
    s.frame_start, s.frame_end = 1, frames
    s.steps, s.geodesic_iterations, s.shoot_steps = 5, 40, 8  # a quick demo; the panel defaults are finer
    scene.frame_start, scene.frame_end = 1, frames
    basis, _ = solver.load_basis(s.basis)
    log(f"basis '{basis.name}': {basis.template.shape[0]} vertices, {basis.n_fields} fields "
        f"({', '.join(f'{g} {b - a}' for g, (a, b) in basis.groups.items())}); schedule {schedule.lower()}")

    # 1. two simulated scans of two different bodies in two different poses
    scans = []
    with stage(times, "simulate 2 scans"):
        for i, (name, code) in enumerate(zip(("scan_A", "scan_B"), demo_codes(basis, seed))):
            truth = basis.template + np.tensordot(code, basis.fields, axes=1)
            v, f = simulate_scan(truth, basis.faces, seed=seed + i + 1)
            scans.append(add_object(name, v, f, scene.collection, location=(0, 0, 0)))
            log(f"{name}: {len(v)} vertices, {len(f)} faces (remeshed, holes, rigidly moved)")

    # 2. register them (one operator call, as with both scans selected in the viewport)
    bpy.context.view_layer.update()
    for o in bpy.context.view_layer.objects:
        o.select_set(o in scans)
    bpy.context.view_layer.objects.active = scans[-1]
    with stage(times, "register 2 scans"):
        assert bpy.ops.bareesa.register_scan() == {"FINISHED"}
    reg_a, reg_b = bpy.data.objects["scan_A_registered"], bpy.data.objects["scan_B_registered"]
    for r in (reg_a, reg_b):
        log(f"{r.name}: varifold {r[convert.PROP_VARIFOLD]:.3g}, Chamfer {r[convert.PROP_CHAMFER]:.3g}")

    # 3. the geodesic between them, keyframed on every frame
    with stage(times, "interpolate"):
        assert bpy.ops.bareesa.interpolate(object_a=reg_a.name, object_b=reg_b.name) == {"FINISHED"}
    path_obj = bpy.data.objects[f"{reg_a.name}_to_{reg_b.name}"]
    log(f"geodesic keyframed on frames 1-{frames}, distance {s.distance:.4g}")

    # 4. transfer that motion onto a third body (its identity from the basis' distribution)
    with stage(times, "transfer motion"):
        bpy.ops.bareesa.load_template()
        actor = bpy.context.active_object
        actor.name = "actor"
        code = np.zeros(basis.n_fields)
        ident = basis.group_slice("shape") if "shape" in basis.groups else slice(0, basis.n_fields)
        code[ident] = sample_code(basis, seed + 10, 1.2)[ident]
        convert.set_code(actor, solver.field_names(basis), code)
        s.identity_group = "shape" if "shape" in basis.groups else next(iter(basis.groups))
        assert bpy.ops.bareesa.transfer_motion(source=path_obj.name, target=actor.name) == {"FINISHED"}
        actor = bpy.context.active_object  # the motion is a new object; the identity is left as it was

    # 5. six random bodies
    s.count, s.seed = 6, seed
    if not any(k.startswith("gmm_") for k in basis.extras):
        fit = bpy.data.collections.new("registered")
        scene.collection.children.link(fit)
        for r in (reg_a, reg_b):
            fit.objects.link(r)
        s.fit_collection = fit
    with stage(times, "random bodies"):
        assert bpy.ops.bareesa.generate_random() == {"FINISHED"}
    randoms = sorted((o for o in bpy.data.objects if "_random_" in o.name), key=lambda o: o.name)
    log(f"{len(randoms)} random bodies baked")

    blend = out / "demo.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    log(f"saved {blend}")
    with stage(times, "render"):
        rows = sheet_rows(scans, (reg_a, reg_b), path_obj, actor, randoms, frames)
        png = render_sheet(rows, out / "contact_sheet.png", width=width)
        made = [render_sheet([row], out / f"{name}.png", width=figure_width)
                for name, row in zip(FIGURES, rows)] if figures else []
    times["total"] = time.perf_counter() - t0
    log(f"rendered {png} ({times['total']:.0f} s in all)")
    bpy.ops.wm.open_mainfile(filepath=str(blend))  # leave the saved scene loaded, not the contact sheet
    return {"blend": blend, "png": png, "figures": made, "times": times}


# ------------------------------------------------------------------------------------ contact sheet


@dataclass
class Item:
    """One body of the sheet: a mesh in its own (local) frame, its colour and caption."""

    verts: np.ndarray  # (N, 3)
    faces: np.ndarray  # (F, 3)
    color: tuple
    caption: str = ""
    highlight: np.ndarray | None = None  # (F,) bool: faces drawn in highlight_color instead
    highlight_color: tuple = (0.85, 0.2, 0.15, 1.0)


@dataclass
class Row:
    title: str
    items: list = field(default_factory=list)
    arrows: bool = False  # draw arrows between consecutive bodies (a sequence)


def _mesh_at(obj, frame, frame_of=None):
    """Local vertices of an object as evaluated at a frame: -> (N, 3), (F, 3).

    With ``frame_of``, the vertices are expressed in that object's local frame
    (a scan shown in the frame of its registration).
    """
    bpy.context.scene.frame_set(frame)
    verts, faces = convert.evaluated_mesh(obj, bpy.context.evaluated_depsgraph_get())
    if frame_of is not None:
        m = np.array(frame_of.matrix_world.inverted() @ obj.matrix_world)
        verts = verts @ m[:3, :3].T + m[:3, 3]
    return verts, faces


def _mix(c0, c1, t):
    return tuple((1 - t) * a + t * b for a, b in zip(c0, c1))


def sheet_rows(scans, registered, path_obj, actor, randoms, frames, n_path=7):
    """The demo's results as rows of a contact sheet (evaluated meshes, colours, captions): -> list of Row."""
    scene = bpy.context.scene
    current = scene.frame_current
    picks = np.unique(np.linspace(1, frames, n_path).round().astype(int))
    ts = (picks - 1) / max(frames - 1, 1)
    try:
        rows = [
            Row("1  Register scans: raw scan (grey) → template fitted to it", [
                Item(*_mesh_at(scans[0], 1, registered[0]), SCAN_COLOR, "scan A"),
                Item(*_mesh_at(registered[0], 1), END_COLORS[0], "registered A"),
                Item(*_mesh_at(scans[1], 1, registered[1]), SCAN_COLOR, "scan B"),
                Item(*_mesh_at(registered[1], 1), END_COLORS[1], "registered B")]),
            Row(f"2  Interpolate: geodesic A → B keyframed on frames 1-{frames}",
                [Item(*_mesh_at(path_obj, int(f)), _mix(*END_COLORS, t), f"frame {f}") for f, t in zip(picks, ts)],
                arrows=True),
            Row("3  Transfer motion: the same motion on another body",
                [Item(*_mesh_at(actor, int(f)), _mix(*MOTION_COLORS, t), f"frame {f}") for f, t in zip(picks, ts)],
                arrows=True),
            Row(f"4  Random bodies: {len(randoms)} samples of the basis' distribution",
                [Item(*_mesh_at(o, 1), _random_color(i, len(randoms)), f"#{i + 1}") for i, o in enumerate(randoms)]),
        ]
    finally:
        scene.frame_set(current)
    return rows


def _random_color(i, n):
    r, g, b = colorsys.hsv_to_rgb((0.08 + i / max(n, 1)) % 1.0, 0.55, 0.85)
    return (r, g, b, 1.0)


def view_rotation(template, yaw_degrees=-25.0):
    """Rotation (3, 3) that stands the template up (longest axis -> Z, thinnest -> depth Y), then turns it by yaw."""
    ext = template.max(0) - template.min(0)
    up, depth = int(np.argmax(ext)), int(np.argmin(ext))
    side = 3 - up - depth
    m = np.zeros((3, 3))
    m[0, side], m[1, depth], m[2, up] = 1.0, 1.0, 1.0
    if np.linalg.det(m) < 0:
        m[1] *= -1
    a = math.radians(yaw_degrees)
    yaw = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return yaw @ m


def _text(collection, name, body, size, location, align="LEFT", color=TEXT_COLOR):
    curve = bpy.data.curves.new(name, type="FONT")
    curve.body, curve.size, curve.align_x, curve.align_y = body, size, align, "TOP"
    obj = bpy.data.objects.new(name, curve)
    obj.location = location
    obj.rotation_euler = (math.pi / 2, 0.0, 0.0)  # facing the camera (which looks along +Y)
    obj.color = color
    collection.objects.link(obj)
    return obj


def _text_halfwidth(body, size):
    """Rough half width of a line of text in Blender's default font (for spacing only)."""
    return 0.29 * size * len(body)


def _arrow(collection, name, x0, x1, z, size, color=CAPTION_COLOR):
    """A flat arrow from x0 to x1 at height z, in the sheet's plane."""
    shaft, head = 0.12 * size, 0.45 * size
    xh = x1 - 0.9 * head
    verts = [(x0, 0, z - shaft), (xh, 0, z - shaft), (xh, 0, z + shaft), (x0, 0, z + shaft),
             (xh, 0, z - head), (x1, 0, z), (xh, 0, z + head)]
    faces = [(0, 1, 2), (0, 2, 3), (4, 5, 6)]
    obj = convert.new_mesh_object(name, np.array(verts, dtype=float), np.array(faces), collection, smooth=False)
    obj.location.y = 0.3 * size  # just behind the bodies' plane: never in front of a body
    obj.color = color
    return obj


def render_sheet(rows, png, width=1800, rotation=None):
    """One Workbench render of rows of bodies (titled, captioned, sequences with arrows): -> png Path.

    Bodies are turned by ``rotation`` (default: :func:`view_rotation` of the first body),
    stand on a common baseline per row and are centred in equal cells. The render
    happens in a temporary scene that is removed afterwards.
    """
    rot = view_rotation(rows[0].items[0].verts) if rotation is None else rotation
    shown = [[(it.verts - it.verts.mean(0)) @ rot.T for it in row.items] for row in rows]
    lo = np.array([v.min(0) for vs in shown for v in vs])
    hi = np.array([v.max(0) for vs in shown for v in vs])
    body_w, body_h = float((hi - lo)[:, 0].max()), float((hi - lo)[:, 2].max())
    cell = 1.12 * body_w
    title, caption = 0.075 * body_h, 0.055 * body_h
    band = body_h + title * 2.4 + caption * 2.4  # title line, bodies, caption line, gap
    n_cols = max(len(r.items) for r in rows)
    margin = 0.25 * title
    left, right = -margin, n_cols * cell + margin

    sheet = bpy.data.scenes.new("ContactSheet")
    coll = sheet.collection
    for r, (row, bodies) in enumerate(zip(rows, shown)):
        top = -r * band
        _text(coll, f"title_{r}", row.title, title, (0.0, 0.0, top - 0.2 * title))
        base = top - 1.9 * title - body_h  # feet on this line
        for c, (item, v) in enumerate(zip(row.items, bodies)):
            vmin, vmax = v.min(0), v.max(0)
            x = (c + 0.5) * cell - 0.5 * (vmin[0] + vmax[0])
            where = (x, 0.0, base - vmin[2])
            marked = np.zeros(len(item.faces), bool) if item.highlight is None else np.asarray(item.highlight, bool)
            obj = add_object(f"sheet_{r}_{c}", v, item.faces[~marked], coll, location=where)
            obj.color = item.color
            if marked.any():
                add_object(f"sheet_{r}_{c}_highlight", v, item.faces[marked], coll, location=where).color = \
                    item.highlight_color
            if item.caption:
                _text(coll, f"caption_{r}_{c}", item.caption, caption, ((c + 0.5) * cell, 0.0, base - 0.45 * caption),
                      align="CENTER", color=CAPTION_COLOR)
            if row.arrows and c:  # between the captions of this body and the previous one
                gap = 0.6 * caption
                x0 = (c - 0.5) * cell + _text_halfwidth(row.items[c - 1].caption, caption) + gap
                x1 = (c + 0.5) * cell - _text_halfwidth(item.caption, caption) - gap
                _arrow(coll, f"arrow_{r}_{c}", x0, x1, base - 0.8 * caption, 0.5 * caption)
    top, bottom = margin, -len(rows) * band + 0.8 * caption
    span_x, span_z = right - left, top - bottom

    cam_data = bpy.data.cameras.new("sheet_camera")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = max(span_x, span_z)  # Blender fits the larger side of the image
    cam_data.clip_end = 40 * span_x
    cam = bpy.data.objects.new("sheet_camera", cam_data)
    cam.location = Vector(((left + right) / 2, -10 * span_x, (top + bottom) / 2))
    cam.rotation_euler = (math.pi / 2, 0.0, 0.0)
    coll.objects.link(cam)
    sheet.camera = cam

    render = sheet.render
    render.engine = "BLENDER_WORKBENCH"
    render.resolution_x = width
    render.resolution_y = int(round(width * span_z / span_x))
    render.resolution_percentage = 100
    render.film_transparent = False
    settings = render.image_settings
    settings.file_format, settings.color_mode, settings.color_depth, settings.compression = "PNG", "RGB", "8", 100
    render.filepath = str(png)
    sheet.display.render_aa = "16"
    shading = sheet.display.shading
    shading.light, shading.color_type = "STUDIO", "OBJECT"
    shading.show_cavity, shading.cavity_type = True, "BOTH"
    shading.cavity_ridge_factor, shading.cavity_valley_factor = 0.6, 1.0
    shading.show_object_outline, shading.object_outline_color = True, (0.15, 0.15, 0.17)
    shading.show_specular_highlight = True
    sheet.view_settings.view_transform = "Standard"
    world = bpy.data.worlds.new("sheet_world")
    world.color = (1.0, 1.0, 1.0)
    sheet.world = world
    try:
        with bpy.context.temp_override(scene=sheet):
            bpy.ops.render.render(write_still=True, scene=sheet.name)
    finally:
        _remove_scene(sheet, world, cam_data)
    return Path(png)


def _remove_scene(sheet, world, cam_data):
    """Delete the temporary sheet scene and everything made for it."""
    objects = list(sheet.collection.objects)
    data = [o.data for o in objects]
    for o in objects:
        bpy.data.objects.remove(o)
    for d in data:
        if isinstance(d, bpy.types.Mesh):
            bpy.data.meshes.remove(d)
        elif isinstance(d, bpy.types.Curve):
            bpy.data.curves.remove(d)
    if cam_data.name in bpy.data.cameras:
        bpy.data.cameras.remove(cam_data)
    bpy.data.scenes.remove(sheet)
    bpy.data.worlds.remove(world)


def main(argv=None):
    parser = argparse.ArgumentParser(description="BaRe-ESA headless Blender demo")
    parser.add_argument("--out", type=Path, default=Path("bareesa_demo"), help="output folder")
    parser.add_argument("--basis", default=DEFAULT_BASIS, help="bundled basis name or .npz path")
    parser.add_argument("--schedule", choices=["fast", "paper"], default="fast")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--width", type=int, default=1800, help="contact sheet width in pixels")
    parser.add_argument("--figures", action="store_true",
                        help="also render one picture per step (registration, geodesic, transfer, random)")
    args = parser.parse_args(argv)
    result = run_demo(args.out, args.basis, args.schedule.upper(), args.frames, args.seed, args.figures, args.width)
    print(f"demo written: {result['blend']} and {result['png']}")
    print("times (s): " + ", ".join(f"{k} {v:.1f}" for k, v in result["times"].items()))
    return 0


def console_main(argv=None):
    """Entry point of ``bareesa-demo`` (Python with the bpy module): ``main``, then exit at once.

    After a GPU render the bpy module (4.5) can hang at interpreter exit, in a C++ static
    destructor that waits for its GPU worker thread; by then everything is written and flushed,
    so the process ends without running those destructors. Inside the Blender binary
    (``bpy.app.binary_path`` set) Blender exits as usual.
    """
    import os
    import sys
    import traceback

    try:
        code = main(argv)
    except solver.module("errors").BareEsaError as err:
        print(f"bareesa-demo: error: {err}", file=sys.stderr)
        code = 2
    except Exception:  # noqa: BLE001  (reported, then the same fast exit)
        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    if bpy.app.binary_path:
        return code
    os._exit(code or 0)
