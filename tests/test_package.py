"""Tests of the bareesa package as a whole: import layering, the curated API, a non-editable install."""

import ast
import functools
import graphlib
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import bareesa

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "core" / "bareesa"
#: Top-level names no solver module may import: Blender, the add-on, the pre-package source root.
FORBIDDEN = {"bpy", "bmesh", "bareesa_addon", "core"}


# ------------------------------------------------------------------------------ import graph


def _module_names(package_dir):
    """Dotted name of every .py below package_dir (a package's __init__ is the package): -> {name: Path}."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = (package_dir.name, *path.relative_to(package_dir).with_suffix("").parts)
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


def _known(name, modules):
    """The longest prefix of a dotted name that is a module of the package, or None."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in modules:
            return ".".join(parts[:n])
    return None


def _imports(name, path, modules):
    """Every import of a module (top level and function-local): -> (package modules, other top-level names)."""
    inside, outside = set(), set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                assert node.level <= len(parts), f"{path}:{node.lineno}: relative import above the package"
                base = ".".join(p for p in (".".join(parts[:len(parts) - node.level + 1]), node.module) if p)
            else:
                base = node.module
            # ``from base import y``: y is a submodule when the package has one of that name
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                       for alias in node.names]
        else:
            continue
        for target in targets:
            found = _known(target, modules)
            if found is not None:
                inside.add(found)
            else:
                outside.add(target.split(".")[0])
    return inside, outside


@functools.cache
def import_graph(package_dir=PACKAGE):
    """Intra-package imports and other top-level imports of each module: -> ({name: set}, {name: set})."""
    modules = _module_names(package_dir)
    graph, external = {}, {}
    for name, path in modules.items():
        graph[name], external[name] = _imports(name, path, modules)
    return graph, external


def test_import_graph_sees_relative_absolute_and_function_local_imports():
    graph, external = import_graph()
    assert "bareesa.registration" in graph["bareesa"]  # package __init__ -> subpackage __init__
    assert "bareesa.errors" in graph["bareesa.mesh"]  # from .errors import ...
    assert "bareesa.mesh" in graph["bareesa.scan_simulator"]
    assert "bareesa.latent" in graph["bareesa.registration.problem"]  # from ..latent import ...
    assert "torch" in external["bareesa.geometry"]


def test_solver_imports_have_no_cycle():
    graph, _ = import_graph()
    try:
        graphlib.TopologicalSorter(graph).prepare()
    except graphlib.CycleError as err:  # args[1]: each node is imported by the next one
        pytest.fail("import cycle in bareesa (each imports the next): " + " -> ".join(reversed(err.args[1])))


def test_solver_never_imports_blender_or_the_addon():
    _, external = import_graph()
    bad = {name: sorted(names & FORBIDDEN) for name, names in external.items() if names & FORBIDDEN}
    assert not bad, f"solver modules import {bad}; the solver must run without Blender and the add-on"


# ------------------------------------------------------------------------------- curated API


def test_every_name_in_all_is_importable_from_bareesa():
    missing = [name for name in bareesa.__all__ if not hasattr(bareesa, name)]
    assert not missing, f"bareesa.__all__ names these, which `from bareesa import ...` cannot: {missing}"
    namespace = {}
    exec("from bareesa import *", namespace)  # noqa: S102
    assert set(bareesa.__all__) <= set(namespace)


# --------------------------------------------------------------------- non-editable install


def _checkout_copy(dest):
    """Copy the checkout's files that git tracks or would track (no build/ leftovers, no .venv): -> dest."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for rel in filter(None, listed):
        if (ROOT / rel).is_file():  # a tracked file may be deleted in the working tree
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / rel, dest / rel)
    return dest


def _build_requirements_met():
    """Whether this interpreter already has the build backend pyproject.toml asks for."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        from packaging.requirements import Requirement
    except ImportError:
        return False
    for text in tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]:
        req = Requirement(text)
        try:
            if not req.specifier.contains(version(req.name), prereleases=True):
                return False
        except PackageNotFoundError:
            return False
    return True


def _pip(*args, cwd):
    """Run this interpreter's pip quietly; fail the test with its output if it fails."""
    proc = subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", "-q", *map(str, args)],
                          cwd=cwd, capture_output=True, text=True)
    assert proc.returncode == 0, f"pip {args[0]} failed:\n{proc.stdout}{proc.stderr}"


INSTALLED_CHECK = """
import sys
import bareesa
from bareesa import basis_io
print(bareesa.__file__)
for name in ("human", "deformables"):
    basis = bareesa.load_basis(name)
    assert basis.n_fields > 0, name
    print(basis_io.resolve_basis_path(name).resolve())
try:
    import core
except ModuleNotFoundError:
    print("no core")
else:
    sys.exit(f"import core found {core.__path__}: the wheel must not ship the source root")
"""


def test_wheel_installs_and_runs_without_the_checkout(tmp_path):
    """Build a wheel of the checkout, install it with --target and use it from outside the repository."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs a git checkout to list the source files")
    source = _checkout_copy(tmp_path / "source")
    # the declared backend either way; an isolated build env (from the index) only when this one lacks it
    isolation = ["--no-build-isolation"] if _build_requirements_met() else []
    _pip("wheel", "--no-deps", *isolation, "-w", tmp_path / "dist", source, cwd=tmp_path)
    (wheel,) = (tmp_path / "dist").glob("bareesa-*.whl")
    site = tmp_path / "site"
    _pip("install", "--no-deps", "--no-index", "--target", site, wheel, cwd=tmp_path)

    for package, folder in (("bareesa", source / "core" / "bareesa"), ("bareesa_addon", source / "bareesa_addon")):
        missing = sorted(str(p.relative_to(folder)) for p in folder.rglob("*.py")
                         if not (site / package / p.relative_to(folder)).is_file())
        assert not missing, f"the wheel's {package} lacks {missing}: list the subpackage in pyproject's packages"

    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "BAREESA_BASES_PATH")}
    env["PYTHONPATH"] = str(site)
    proc = subprocess.run([sys.executable, "-c", INSTALLED_CHECK], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    module_file, *basis_paths, last = proc.stdout.splitlines()
    print(module_file, *basis_paths, sep="\n")
    site = site.resolve()
    assert Path(module_file).resolve().is_relative_to(site / "bareesa")
    assert [Path(p) for p in basis_paths] == [site / "bareesa" / "bases" / f"{n}.npz"
                                             for n in ("human", "deformables")]
    assert last == "no core"
