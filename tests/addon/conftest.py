"""Fixtures shared by the headless Blender tests (helpers: tests/addon/support.py).

bpy is imported by the test modules through tests.addon.support, whose ``pytest.importorskip("bpy")``
skips each module where bpy is absent; the fixtures import it only when they run, so this file loads
without bpy.
"""

import pytest


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """(Basis, path of its .npz, surface map)."""
    from bareesa.basis_io import save_basis
    from tests.addon.support import tiny_basis

    basis, surface = tiny_basis()
    path = tmp_path_factory.mktemp("bases") / "tiny.npz"
    save_basis(path, basis)
    return basis, path, surface


@pytest.fixture
def scene(tiny, tmp_path, monkeypatch):
    """An empty scene with the add-on registered, the tiny basis chosen and fast settings."""
    import bareesa_addon
    from tests.addon.support import bpy

    monkeypatch.setenv("BAREESA_USER_BASES", str(tmp_path / "user_bases"))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bareesa_addon.register()
    s = bpy.context.scene.bareesa
    s.basis = str(tiny[1])
    s.schedule = "FAST"
    s.steps = 4
    s.use_frame_range = True  # the tests set the panel's own range (the default follows the scene's)
    s.frame_start, s.frame_end = 1, 6
    s.shoot_steps = 2
    yield bpy.context.scene
    bareesa_addon.unregister()
