"""Render the README's filmstrips: an interpolation and a motion transfer, made with the add-on's operators.

    .venv/bin/python tools/render_filmstrip.py [--out docs/images] [--basis human] [--frames 24]

Two bodies of the basis' distribution (template objects with their codes) are interpolated on
frames 1..N (Interpolate), and that motion is transferred onto a third identity (Transfer Motion);
seven evaluated frames of each are rendered with Workbench into ``filmstrip_interpolate.png`` and
``filmstrip_transfer.png``. The render runs in a child process with a timeout, which leaves with
``os._exit`` (the bpy module can hang at exit after a render, see bareesa_addon/demo.py).
"""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.render_child import finish_child, render_parser, run_child  # noqa: E402


def render(out, basis_name, frames, width):
    import bpy
    import numpy as np

    from bareesa_addon import convert, demo, solver

    bpy.ops.wm.read_factory_settings(use_empty=True)
    demo.ensure_addon()
    scene = bpy.context.scene
    s = scene.bareesa
    s.basis = demo.pick_basis(basis_name)
    s.steps, s.geodesic_iterations = 5, 40
    scene.frame_start, scene.frame_end = 1, frames
    basis, _ = solver.load_basis(s.basis)
    names = solver.field_names(basis)

    def body(name, code):
        bpy.ops.bareesa.load_template()
        obj = bpy.context.active_object
        obj.name = name
        convert.fit_range(obj, names, basis.template, basis.fields, code)
        convert.set_code(obj, names, code)
        return obj

    a, b = body("A", demo.sample_code(basis, 100)), body("B", demo.sample_code(basis, 101))
    for o in bpy.context.view_layer.objects:
        o.select_set(o in (a, b))
    assert bpy.ops.bareesa.interpolate(object_a="A", object_b="B") == {"FINISHED"}
    path_obj = bpy.data.objects["A_to_B"]
    group = "shape" if "shape" in basis.groups else next(iter(basis.groups))
    identity = np.zeros(basis.n_fields)
    identity[basis.group_slice(group)] = demo.sample_code(basis, 10)[basis.group_slice(group)]
    actor = body("actor", identity)
    s.identity_group = group
    assert bpy.ops.bareesa.transfer_motion(source=path_obj.name, target=actor.name) == {"FINISHED"}
    moved = bpy.context.active_object

    picks = np.unique(np.linspace(1, frames, 7).round().astype(int))
    ts = (picks - 1) / max(frames - 1, 1)
    rows = {
        "filmstrip_interpolate": demo.Row(
            f"Interpolate: A → B keyframed on frames 1-{frames}",
            [demo.Item(*demo._mesh_at(path_obj, int(f)), demo._mix(*demo.END_COLORS, t), f"frame {f}")
             for f, t in zip(picks, ts)], arrows=True),
        "filmstrip_transfer": demo.Row(
            "Transfer Motion: the same motion on another body (a new object)",
            [demo.Item(*demo._mesh_at(moved, int(f)), demo._mix(*demo.MOTION_COLORS, t), f"frame {f}")
             for f, t in zip(picks, ts)], arrows=True),
    }
    rotation = demo.view_rotation(basis.template)
    out.mkdir(parents=True, exist_ok=True)
    for name, row in rows.items():
        png = demo.render_sheet([row], out / f"{name}.png", width=width, rotation=rotation)
        print(f"wrote {png}", flush=True)


def main(argv=None):
    parser = render_parser(__doc__, width=1400, timeout=900.0)
    parser.add_argument("--basis", default="human")
    parser.add_argument("--frames", type=int, default=24)
    args = parser.parse_args(argv)
    if args.child:
        finish_child(render, args.out.resolve(), args.basis, args.frames, args.width)
    argv = ["--out", args.out, "--basis", args.basis, "--frames", args.frames, "--width", args.width]
    return run_child(__file__, argv, args.timeout, "render_filmstrip")


if __name__ == "__main__":
    sys.exit(main())
