"""The headless demo runs end to end (on the tiny test basis, so it is quick) and renders its contact sheet."""

import struct

from tests.addon_support import bpy, tiny  # noqa: F401


def test_demo_registers_interpolates_transfers_bakes_saves_and_renders(tiny, tmp_path):
    import bareesa_addon
    from bareesa_addon.demo import run_demo

    try:
        result = run_demo(tmp_path / "demo", basis_name=str(tiny[1]), frames=6)
        png = result["png"].read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        width, height = struct.unpack(">II", png[16:24])
        assert width == 1800 and height > 1000
        objects = bpy.data.objects  # demo.blend is loaded again at the end
        for name in ("scan_A", "scan_B", "scan_A_registered", "scan_B_registered", "actor",
                     "scan_A_registered_to_scan_B_registered"):
            assert name in objects
        assert sum("_random_" in o.name for o in objects) == 6
        assert "ContactSheet" not in bpy.data.scenes
    finally:
        bareesa_addon.unregister()
