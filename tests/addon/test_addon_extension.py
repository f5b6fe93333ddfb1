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

ROOT = Path(__file__).resolve().parents[2]

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
    from tests.addon.support import tiny_basis

    path = tmp_path / "tiny.npz"
    save_basis(path, tiny_basis()[0])
    return path


def _build_module():
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import build_extension
    finally:
        sys.path.pop(0)
    return build_extension


def fake_wheel(folder, requirement, requires=()):
    """A minimal pure-Python wheel 'name==version' (METADATA, WHEEL, RECORD), for tests without network."""
    name, version = requirement.split("==")
    stem = f"{name.replace('-', '_')}-{version}"
    path = folder / f"{stem}-py3-none-any.whl"
    meta = f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n" + "".join(
        f"Requires-Dist: {r}\n" for r in requires)
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(f"{name.replace('-', '_')}/__init__.py", "")
        zf.writestr(f"{stem}.dist-info/METADATA", meta)
        zf.writestr(f"{stem}.dist-info/WHEEL",
                    "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n")
        zf.writestr(f"{stem}.dist-info/RECORD", "")
    return path


def test_a_platform_zip_carries_exactly_its_wheels_in_its_manifest_and_no_numpy(tmp_path):
    import tomllib

    be = _build_module()
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    for req in be.platform_requirements("linux-x64"):
        fake_wheel(wheels, req, requires=["numpy>=1.23"] if req.startswith("scipy") else ())
    fake_wheel(wheels, "numpy==1.26.4")  # in the folder, never bundled
    path = be.build(tmp_path / "dist", bases=False, platform="linux-x64", wheels_dir=wheels)
    assert path.name.endswith("-linux-x64.zip")
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    bundled = sorted(n for n in names if n.startswith("wheels/"))
    assert manifest["platforms"] == ["linux-x64"]
    assert sorted(w.removeprefix("./") for w in manifest["wheels"]) == bundled
    assert len(bundled) == len(be.WHEEL_REQUIREMENTS) and not any("numpy" in n for n in bundled)
    assert any(n.startswith("wheels/torch-2.13.0+cpu") for n in bundled)
    assert "website" not in manifest
    assert tomllib.loads((ROOT / "blender_manifest.toml").read_text()).get("wheels") is None  # repo's untouched


def test_a_platform_zip_refuses_a_missing_wheel_and_one_that_needs_another_numpy(tmp_path):
    be = _build_module()
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    reqs = be.platform_requirements("linux-x64")
    for req in reqs[1:]:
        fake_wheel(wheels, req)
    with pytest.raises(SystemExit, match="no linux-x64 wheel for torch"):
        be.build(tmp_path / "dist", bases=False, platform="linux-x64", wheels_dir=wheels)
    fake_wheel(wheels, reqs[0], requires=["numpy>=2.0"])
    with pytest.raises(SystemExit, match="numpy"):  # pip cannot resolve it against numpy 1.26
        be.build(tmp_path / "dist", bases=False, platform="linux-x64", wheels_dir=wheels)
    assert not list((tmp_path / "dist").glob("*.zip"))
