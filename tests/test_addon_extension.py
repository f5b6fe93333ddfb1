"""The built extension .zip installs through Blender's own extension machinery, enables, and runs an operator."""

import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

pytest.importorskip("bpy")

ROOT = Path(__file__).resolve().parents[1]

INSTALL_SCRIPT = textwrap.dedent("""
    import json, sys
    import bpy

    zip_path, repo_dir, basis_path, out = sys.argv[1:5]
    repos = bpy.context.preferences.extensions.repos
    repos.new(name="BaRe-ESA test", module="bareesa_test", custom_directory=repo_dir, source="USER")
    result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="bareesa_test",
                                                      enable_on_install=True)
    module = "bl_ext.bareesa_test.bareesa"
    enabled = module in bpy.context.preferences.addons
    op = bpy.ops.bareesa.load_template(basis=basis_path)
    obj = bpy.context.active_object
    json.dump({"install": sorted(result), "enabled": enabled, "load_template": sorted(op),
               "keys": [k.name for k in obj.data.shape_keys.key_blocks],
               "vendored_core": f"{module}.bareesa.latent" in sys.modules,
               "repo_core": "core" in sys.modules}, open(out, "w"))
""")


def test_built_zip_contains_addon_vendored_core_and_manifest(tmp_path):
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from build_extension import build
    finally:
        sys.path.pop(0)
    path = build(tmp_path, bases=True)
    names = set(zipfile.ZipFile(path).namelist())
    assert {"blender_manifest.toml", "__init__.py", "operators/__init__.py", "convert.py", "jobs.py",
            "bareesa/latent.py", "bareesa/registration/__init__.py"} <= names
    bundled = {p.name for p in (ROOT / "bases").glob("*.npz")}
    assert {f"bareesa/bases/{n}" for n in bundled} <= names


def test_zip_installs_with_blender_extension_machinery_and_runs_an_operator(tmp_path, tiny_basis_file):
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from build_extension import build
    finally:
        sys.path.pop(0)
    zip_path = build(tmp_path / "dist", bases=False)
    script, out = tmp_path / "install.py", tmp_path / "out.json"
    script.write_text(INSTALL_SCRIPT)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "blender_user"))
    env.pop("PYTHONPATH", None)
    proc = subprocess.run([sys.executable, str(script), str(zip_path), str(tmp_path / "repo"), str(tiny_basis_file),
                           str(out)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["install"] == ["FINISHED"] and result["enabled"]
    assert result["load_template"] == ["FINISHED"]
    assert result["keys"] == ["Basis", "pose_000", "pose_001", "shape_000", "shape_001"]
    assert result["vendored_core"] and not result["repo_core"]
    assert (tmp_path / "repo" / "bareesa" / "bareesa" / "latent.py").exists()


@pytest.fixture
def tiny_basis_file(tmp_path):
    from bareesa.basis_io import save_basis
    from tests.addon_support import tiny_basis

    path = tmp_path / "tiny.npz"
    save_basis(path, tiny_basis()[0])
    return path
