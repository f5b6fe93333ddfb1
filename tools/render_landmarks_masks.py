"""Render the README's landmark and mask pictures from the meshes ``bench/landmarks_masks.py`` kept.

    .venv/bin/python tools/render_landmarks_masks.py [--meshes bench/out/landmarks_masks] [--out docs/images]

``landmarks_sphere.png``: a held-out +60 sphere frame's scan, its registration without landmarks
(the red cap, the template's +Z end, lands at the wrong end: mirrored) and with three. ``landmarks_arm.png``:
a held-out human scan with a raised arm, registered without and with eight landmarks (the left hand
red). ``mask_floor.png``: a scan on a floor plate with a wall behind (the ignore mask red), registered
with and without the mask, and the clean scan's registration. Workbench, in a child process with a
timeout (the bpy module can hang at exit after a render, see bareesa_addon/demo.py).
"""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.render_child import finish_child, render_parser, run_child  # noqa: E402
sys.path.insert(0, str(ROOT / "core"))

GREY = (0.72, 0.72, 0.74, 1.0)
BLUE = (0.35, 0.55, 0.85, 1.0)
GREEN = (0.4, 0.72, 0.45, 1.0)
ORANGE = (0.92, 0.6, 0.3, 1.0)


def render(meshes, out, width):
    import bpy
    import numpy as np

    from bareesa.basis_io import load_basis
    from bareesa.mesh import load_mesh
    from bareesa_addon import demo

    bpy.ops.wm.read_factory_settings(use_empty=True)
    out.mkdir(parents=True, exist_ok=True)

    def mesh(name):
        """A kept mesh in the template frame (its part's right registration's transform): -> verts, faces."""
        verts, faces = load_mesh(meshes / f"{name}.ply")
        m = np.load(meshes / f"{name.split('_')[0]}_transform.npy")
        return verts @ m[:3, :3].T + m[:3, 3], faces

    sheets = {}
    if (meshes / "sphere_scan.ply").exists():
        from bench.common import shared_data

        template, faces = load_mesh(shared_data("render_landmarks_masks") / "deformed_sphere" / "template.ply")
        cap = template[faces].mean(1)[:, 2] > 0.6 * template[:, 2].max()  # the template's +Z end
        sheets["landmarks_sphere"] = demo.Row("A +60 bend: mirrored without landmarks", [
            demo.Item(*mesh("sphere_scan"), GREY, "scan"),
            demo.Item(*mesh("sphere_free"), BLUE, "no landmarks", highlight=cap),
            demo.Item(*mesh("sphere_landmarks"), GREEN, "3 landmarks", highlight=cap)])
    human = load_basis("human")
    names = [str(n) for n in human.extras["part_names"]]
    hand = human.extras["part_weights"][names.index("hand.L")][human.faces].mean(1) > 0.5
    if (meshes / "arm_scan.ply").exists():
        sheets["landmarks_arm"] = demo.Row("A held-out scan with a raised arm (left hand red)", [
            demo.Item(*mesh("arm_scan"), GREY, "scan"),
            demo.Item(*mesh("arm_free"), BLUE, "no landmarks", highlight=hand),
            demo.Item(*mesh("arm_landmarks"), GREEN, "8 landmarks", highlight=hand)])
    if (meshes / "floor_scan.ply").exists():
        ignored = np.load(meshes / "floor_scan.weights.npy") == 0
        sheets["mask_floor"] = demo.Row("A scan on a floor with a wall behind (ignore mask red)", [
            demo.Item(*mesh("floor_scan"), GREY, "scan + floor + wall", highlight=ignored),
            demo.Item(*mesh("floor_masked"), GREEN, "with the mask"),
            demo.Item(*mesh("floor_unmasked"), ORANGE, "without the mask"),
            demo.Item(*mesh("floor_clean"), BLUE, "clean scan")])
    for name, row in sheets.items():
        rotation = demo.view_rotation(row.items[1].verts)
        png = demo.render_sheet([row], out / f"{name}.png", width=width, rotation=rotation)
        print(f"wrote {png}", flush=True)


def main(argv=None):
    parser = render_parser(__doc__, width=1400, timeout=600.0)
    parser.add_argument("--meshes", type=Path, default=ROOT / "bench" / "out" / "landmarks_masks")
    args = parser.parse_args(argv)
    if args.child:
        finish_child(render, args.meshes.resolve(), args.out.resolve(), args.width)
    if not args.meshes.is_dir():
        sys.exit(f"render_landmarks_masks: no meshes in {args.meshes}: run python -m bench.landmarks_masks first")
    return run_child(__file__, ["--meshes", args.meshes, "--out", args.out, "--width", args.width],
                     args.timeout, "render_landmarks_masks")


if __name__ == "__main__":
    sys.exit(main())
