"""The headless demo runs end to end (on the tiny test basis, so it is quick) and renders its pictures.

The README's demo (``tools/demo_blender.py``) runs the same code on the bundled default, `human`.
"""

import struct

import numpy as np
import pytest

from tests.addon.support import bpy


def png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_demo_registers_interpolates_transfers_bakes_saves_and_renders(tiny, tmp_path):
    import bareesa_addon
    from bareesa_addon.demo import FIGURES, run_demo

    try:
        result = run_demo(tmp_path / "demo", basis_name=str(tiny[1]), frames=6, figures=True, width=600,
                          figure_width=400)
        width, height = png_size(result["png"])
        assert width == 600 and 300 < height < 1200  # four rows of bodies
        assert [p.stem for p in result["figures"]] == list(FIGURES)
        for path in result["figures"]:
            w, h = png_size(path)
            assert w == 400 and h < w  # one row each
        assert {"register 2 scans", "interpolate", "transfer motion", "random bodies", "render", "total"} <= set(
            result["times"])
        objects = bpy.data.objects  # demo.blend is loaded again at the end
        for name in ("scan_A", "scan_B", "scan_A_registered", "scan_B_registered", "actor",
                     "scan_A_registered_to_scan_B_registered"):
            assert name in objects
        assert sum("_random_" in o.name for o in objects) == 6
        assert "ContactSheet" not in bpy.data.scenes and not any(o.name.startswith("sheet_") for o in objects)
    finally:
        bareesa_addon.unregister()


def test_contact_sheet_scene_is_removed_after_rendering(tiny, tmp_path):
    import numpy as np

    from bareesa_addon.demo import Item, Row, render_sheet

    basis = tiny[0]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    counts = (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.curves), len(bpy.data.scenes))
    rows = [Row("a row", [Item(basis.template, basis.faces, (1, 0, 0, 1), "one"),
                          Item(basis.template * np.array([1.0, 1.0, 1.5]), basis.faces, (0, 0, 1, 1), "two")],
                arrows=True)]
    w, h = png_size(render_sheet(rows, tmp_path / "row.png", width=300))
    assert w == 300 and 50 < h < 300
    assert (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.curves), len(bpy.data.scenes)) == counts


def test_demo_basis_choice_rejects_an_unknown_name_and_keeps_the_default():
    import pytest

    from bareesa_addon.demo import pick_basis
    from bareesa.errors import InputError

    with pytest.raises(InputError, match="no bundled basis named 'nosuch'"):
        pick_basis("nosuch")
    assert pick_basis("human") == "human" and pick_basis("deformables") == "deformables"


def test_front_ends_default_to_the_solver_default_basis():
    from bareesa.basis_io import DEFAULT_BASIS
    from bareesa.cli import build_parser

    from bareesa_addon import demo, properties

    assert demo.DEFAULT_BASIS == DEFAULT_BASIS
    assert properties.BareEsaSettings.__annotations__["basis"].keywords["default"] == DEFAULT_BASIS
    assert build_parser().parse_args(["register", "scan.ply", "-o", "out.ply"]).basis == DEFAULT_BASIS


def test_demo_scans_show_two_clearly_different_poses():
    from bareesa.basis_io import load_basis

    from bareesa_addon.demo import demo_codes

    basis = load_basis("human")
    a, b = demo_codes(basis, seed=0)
    pose = basis.group_slice("pose")
    protos = basis.extras["pose_prototypes"][:, pose]
    norms = np.linalg.norm(protos, axis=1)
    assert np.linalg.norm(a[pose]) == pytest.approx(norms.min())  # A: the prototype nearest rest
    assert np.linalg.norm(b[pose]) <= np.percentile(norms, 75) + 1e-12  # B: not one of the most extreme
    gaps = np.linalg.norm(protos - a[pose], axis=1)
    assert np.linalg.norm(b[pose] - a[pose]) > np.median(gaps)  # ... but far from A
    moved = np.linalg.norm(np.tensordot(a - b, basis.fields, axes=1), axis=1)
    assert moved.max() > 0.1 * basis.scale  # a limb moves by a tenth of the body's size or more
