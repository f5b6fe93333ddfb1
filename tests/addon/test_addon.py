"""Headless Blender tests through the ``bpy`` module (skipped where bpy is absent)."""

import pytest

bpy = pytest.importorskip("bpy")


@pytest.fixture
def addon():
    import bareesa_addon

    bareesa_addon.register()
    yield bareesa_addon
    bareesa_addon.unregister()


def test_addon_registers_sidebar_panel_and_unregisters_cleanly(addon):
    panel = bpy.types.Panel.bl_rna_get_subclass_py("BAREESA_PT_main")
    assert panel is not None
    assert panel.bl_space_type == "VIEW_3D" and panel.bl_region_type == "UI"
    assert panel.bl_category == "BaRe-ESA"
    addon.unregister()
    assert bpy.types.Panel.bl_rna_get_subclass_py("BAREESA_PT_main") is None
    addon.register()  # the fixture unregisters again


def test_dependency_status_reports_installed_solver_modules(addon):
    status = addon.dependency_status()
    assert status["numpy"] and status["torch"]
    assert set(status) >= {"torch", "scipy", "pykeops", "sklearn"}


def test_manifest_declares_extension_id_and_minimum_blender():
    import tomllib
    from pathlib import Path

    manifest = tomllib.loads((Path(__file__).resolve().parents[2] / "blender_manifest.toml").read_text())
    assert manifest["schema_version"] == "1.0.0"
    assert manifest["id"] == "bareesa"
    assert tuple(int(x) for x in manifest["blender_version_min"].split(".")) >= (4, 2, 0)
    assert manifest["type"] == "add-on"
