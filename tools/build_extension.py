"""Build the installable Blender extension .zip: the add-on, the vendored solver, the bundled bases.

    python tools/build_extension.py [--out dist] [--no-bases]
    python tools/build_extension.py --platform linux-x64 [--wheels DIR] [--cache DIR] [--extra-index-url URL]

Layout of the zip (its root is the extension package):
    blender_manifest.toml, __init__.py, operators.py, ...   (bareesa_addon/)
    bareesa/**.py                                           (the solver package, imported relatively)
    bareesa/bases/*.npz, bareesa/bases/*.json               (bundled bases, as in an installed wheel)
    wheels/*.whl                                            (--platform only: the solver's dependencies)
Without --platform the zip is platform independent (``dist/bareesa-<version>.zip``) and the add-on
pip-installs the dependencies on request. With --platform it is ``dist/bareesa-<version>-<platform>.zip``:
its manifest lists ``wheels`` and ``platforms`` and Blender installs the wheels itself. The wheels come
from --wheels DIR, or are fetched with ``pip download`` into --cache (default dist/wheel-cache).
Install it with Blender's Preferences > Get Extensions > Install from Disk, or
``blender --command extension install-file -r user_default -e <zip>``.
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CACHE = ROOT / "dist" / "wheel-cache"

#: Blender 4.5's Python: the wheels must be for it.
PYTHON_VERSION = "3.11"
#: The numpy Blender 4.5 ships (bpy 4.5 pins it): never bundled, every bundled wheel must accept it.
BLENDER_NUMPY = "1.26.4"
#: The solver's runtime dependencies (pyproject.toml) pinned to releases that import beside numpy 1.26 on
#: Python 3.11; pip adds what they need in turn (torch: typing_extensions, sympy, networkx, ...), since
#: bundled wheels must be complete. Not numpy (Blender's), pykeops (optional, compiles at run time), bpy.
#: Dask's distributed (the ``batch`` extra) is bundled too: Register Scans runs several scans in worker processes.
WHEEL_REQUIREMENTS = ("torch==2.13.0", "scipy==1.17.1", "trimesh==5.2.0", "scikit-learn==1.9.1",
                      "joblib==1.6.0", "threadpoolctl==3.8.0", "tqdm==4.70.1", "dask==2026.8.0",
                      "distributed==2026.8.0")
#: Runtime dependencies of pyproject.toml that are deliberately not bundled.
NOT_BUNDLED = {"numpy", "pykeops"}
#: Blender platform -> (pip --platform tag, local version label torch needs there).
#: Linux: PyPI's torch is the CUDA build (GBs, with nvidia-* wheels); the CPU build is ``+cpu``
#: (https://download.pytorch.org/whl/cpu, or a local wheel folder). Windows' PyPI torch is CPU only.
#: macOS arm64: torch 2.13 wheels are tagged macOS 14. macOS x64: torch stopped at 2.2.
PLATFORMS = {
    "linux-x64": ("manylinux_2_28_x86_64", "+cpu"),
    "windows-x64": ("win_amd64", ""),
    "macos-arm64": ("macosx_14_0_arm64", ""),
    "macos-x64": ("macosx_11_0_x86_64", ""),
}
CPU_TORCH_INDEX = "https://download.pytorch.org/whl/cpu"


def _files(folder, patterns):
    for pattern in patterns:
        for path in sorted(folder.glob(pattern)):
            if path.is_file() and "__pycache__" not in path.parts:
                yield path


def _packaging():
    try:
        from packaging.requirements import Requirement
        from packaging.version import Version
    except ImportError:  # pip always carries a copy
        from pip._vendor.packaging.requirements import Requirement
        from pip._vendor.packaging.version import Version
    return Requirement, Version


def platform_requirements(platform):
    """The pinned requirements pip fetches for ``platform`` (torch with its CPU label where needed): -> list."""
    if platform not in PLATFORMS:
        raise SystemExit(f"unknown platform {platform!r}: choose one of {', '.join(PLATFORMS)}")
    label = PLATFORMS[platform][1]
    return [req + label if req.startswith("torch==") else req for req in WHEEL_REQUIREMENTS]


def check_pins_match_pyproject(pyproject=ROOT / "pyproject.toml"):
    """SystemExit unless WHEEL_REQUIREMENTS covers pyproject's runtime dependencies within their ranges."""
    Requirement, Version = _packaging()
    dependencies = tomllib.loads(pyproject.read_text())["project"]["dependencies"]
    declared = {Requirement(r).name: Requirement(r) for r in dependencies}
    pinned = {Requirement(r).name: Requirement(r) for r in WHEEL_REQUIREMENTS}
    missing = sorted(set(declared) - NOT_BUNDLED - set(pinned))
    if missing:
        raise SystemExit(f"{pyproject.name} declares {', '.join(missing)} but WHEEL_REQUIREMENTS does not bundle it")
    for name, req in pinned.items():
        version = Version(next(iter(req.specifier)).version)
        if name in declared and not declared[name].specifier.contains(version, prereleases=True):
            raise SystemExit(f"bundled {name}=={version} is outside {pyproject.name}'s {declared[name]}")


def platform_tags(platform):
    """pip's --platform arguments for a Blender platform (Linux: manylinux_2_28 and the older glibc tags
    it runs, which e.g. numpy 1.26's wheels carry): -> list of strings."""
    tag = PLATFORMS[platform][0]
    tags = [tag] + (["manylinux_2_17_x86_64", "manylinux2014_x86_64"] if tag.startswith("manylinux") else [])
    return [arg for t in tags for arg in ("--platform", t)]


def _pip_error(output):
    """The line of pip's output that says what went wrong."""
    errors = [line.removeprefix("ERROR: ") for line in output.splitlines() if line.startswith("ERROR:")]
    return (errors or output.strip().splitlines()[-1:] or ["no output"])[-1]


def _pip_download(requirements, platform, dest, find_links=None, extra_index_urls=()):
    """``pip download`` the wheels of ``requirements`` and of everything they need for ``platform`` into
    ``dest`` (pip resolves the dependencies, with numpy held at Blender's); SystemExit on failure.

    With ``find_links`` pip looks only there (no index, no pip configuration): the offline selection.
    """
    cmd = [sys.executable, "-m", "pip", "download", "--disable-pip-version-check", "--no-input",
           "--only-binary=:all:", *platform_tags(platform), "--python-version", PYTHON_VERSION,
           "-d", str(dest)]
    env = dict(os.environ)
    if find_links is not None:
        cmd[3:3] = ["--isolated"]
        cmd += ["--no-index", "--find-links", str(find_links)]
        env["PIP_CONFIG_FILE"] = os.devnull
    for url in extra_index_urls:
        cmd += ["--extra-index-url", url]
    pinned = list(requirements) + [f"numpy=={BLENDER_NUMPY}"]  # resolve against Blender's numpy
    proc = subprocess.run(cmd + pinned, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        error = _pip_error(proc.stdout + proc.stderr)
        where = f"in {find_links}" if find_links is not None else "on the package index"
        found = re.search(r"No matching distribution found for (\S+)", error)
        if found:
            hint = (f" (the CPU torch build: add --extra-index-url {CPU_TORCH_INDEX})"
                    if found.group(1).startswith("torch") and PLATFORMS[platform][1] and find_links is None else "")
            raise SystemExit(f"no {platform} wheel for {found.group(1)} (Python {PYTHON_VERSION}) {where}{hint}")
        raise SystemExit(f"pip download for {platform} failed: {error}")


def _numpy_requirement_error(wheel):
    """Why ``wheel`` cannot import beside Blender's numpy, or None."""
    Requirement, Version = _packaging()
    with zipfile.ZipFile(wheel) as zf:
        metadata = next((n for n in zf.namelist() if n.count("/") == 1 and n.endswith(".dist-info/METADATA")), None)
        if metadata is None:
            return f"{wheel.name} has no .dist-info/METADATA"
        text = zf.read(metadata).decode("utf-8", "replace")
    environment = {"extra": "", "python_version": PYTHON_VERSION, "python_full_version": PYTHON_VERSION + ".0"}
    for line in text.split("\n\n", 1)[0].splitlines():
        if not line.startswith("Requires-Dist:"):
            continue
        req = Requirement(line.split(":", 1)[1].strip())
        if req.name == "numpy" and (req.marker is None or req.marker.evaluate(environment)):
            if not req.specifier.contains(BLENDER_NUMPY, prereleases=True):
                return f"{wheel.name} requires {req}, Blender ships numpy {BLENDER_NUMPY}"
    return None


def platform_wheels(platform, dest, wheels_dir=None, cache_dir=DEFAULT_CACHE, extra_index_urls=()):
    """Put the wheels for ``platform`` into the empty folder ``dest``: -> sorted list of their Paths.

    From ``wheels_dir`` when given; else downloaded into ``cache_dir`` first (pip skips files already there).
    """
    requirements = platform_requirements(platform)
    if wheels_dir is None:
        check_pins_match_pyproject()
        wheels_dir = Path(cache_dir)
        wheels_dir.mkdir(parents=True, exist_ok=True)
        _pip_download(requirements, platform, wheels_dir, extra_index_urls=extra_index_urls)
    elif not Path(wheels_dir).is_dir():
        raise SystemExit(f"--wheels {wheels_dir}: not a folder")
    _pip_download(requirements, platform, dest, find_links=Path(wheels_dir).resolve())
    wheels = sorted(w for w in Path(dest).glob("*.whl") if not w.name.lower().startswith("numpy-"))  # Blender's
    for wheel in wheels:
        if error := _numpy_requirement_error(wheel):
            raise SystemExit(error)
    return wheels


def _manifest_text(manifest_path, platform=None, wheels=()):
    """The manifest for the zip: the repo's, plus ``platforms`` and ``wheels`` for a platform build."""
    text = manifest_path.read_text()
    if platform is None:
        return text
    manifest = tomllib.loads(text)
    if "wheels" in manifest or "platforms" in manifest:
        raise SystemExit(f"{manifest_path}: 'wheels' and 'platforms' are written by the build, remove them")
    lines = [f'platforms = ["{platform}"]', "wheels = ["] + [f'  "./wheels/{w.name}",' for w in wheels] + ["]"]
    head, sep, tail = text.partition("\n[")  # top-level keys go before the first table
    text = head.rstrip("\n") + "\n\n" + "\n".join(lines) + "\n" + (sep + tail if sep else "")
    written = tomllib.loads(text)
    assert written["wheels"] == [f"./wheels/{w.name}" for w in wheels] and written["platforms"] == [platform]
    return text


def build(out_dir=ROOT / "dist", bases=True, platform=None, wheels_dir=None, cache_dir=DEFAULT_CACHE,
          extra_index_urls=()):
    """Write dist/bareesa-<version>.zip, or dist/bareesa-<version>-<platform>.zip with its wheels: -> its Path."""
    manifest_path = ROOT / "blender_manifest.toml"
    manifest = tomllib.loads(manifest_path.read_text())
    if manifest.get("id") != "bareesa" or manifest.get("type") != "add-on":
        raise SystemExit(f"{manifest_path}: expected an add-on with id 'bareesa'")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    suffix = f"-{platform}" if platform else ""
    target = out_dir / f"bareesa-{manifest['version']}{suffix}.zip"
    entries = []
    addon, solver = ROOT / "bareesa_addon", ROOT / "core" / "bareesa"
    entries += [(p, p.relative_to(addon).as_posix()) for p in _files(addon, ["**/*.py"])]
    entries += [(p, "bareesa/" + p.relative_to(solver).as_posix()) for p in _files(solver, ["**/*.py"])]
    if bases:
        entries += [(p, "bareesa/bases/" + p.name) for p in _files(ROOT / "bases", ["*.npz", "*.json"])]
    for src, name in entries:
        if name.startswith("bareesa/") and src.suffix == ".py":
            text = src.read_text()
            if "\nimport bareesa" in text or "\nfrom bareesa" in text:
                raise SystemExit(f"{src}: the vendored solver must use relative imports only")
    with tempfile.TemporaryDirectory(prefix="bareesa-wheels-") as wheel_tmp:
        wheels = []
        if platform is not None:
            wheels = platform_wheels(platform, Path(wheel_tmp), wheels_dir, cache_dir, extra_index_urls)
            entries += [(w, f"wheels/{w.name}") for w in wheels]
        tmp = target.with_suffix(".zip.tmp")
        with zipfile.ZipFile(tmp, "w") as zf:
            zf.writestr("blender_manifest.toml", _manifest_text(manifest_path, platform, wheels),
                        compress_type=zipfile.ZIP_DEFLATED)
            for src, name in entries:
                # .npz and .whl are already compressed; Python sources deflate well
                stored = src.suffix in (".npz", ".whl")
                zf.write(src, name, compress_type=zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED)
        tmp.replace(target)
    return target


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "dist", help="output folder (default: dist/)")
    parser.add_argument("--no-bases", action="store_true", help="leave the bundled bases out (a small zip)")
    parser.add_argument("--platform", choices=sorted(PLATFORMS),
                        help="bundle the dependencies' wheels for this Blender platform")
    parser.add_argument("--wheels", type=Path, help="take the wheels from this folder (no download)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                        help="where pip downloads the wheels (default: dist/wheel-cache)")
    parser.add_argument("--extra-index-url", action="append", default=[], metavar="URL",
                        help=f"another index for pip download, e.g. {CPU_TORCH_INDEX} for Linux' CPU torch")
    args = parser.parse_args(argv)
    if (args.wheels or args.extra_index_url) and not args.platform:
        parser.error("--wheels and --extra-index-url need --platform")
    path = build(args.out, bases=not args.no_bases, platform=args.platform, wheels_dir=args.wheels,
                 cache_dir=args.cache, extra_index_urls=args.extra_index_url)
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
    n_bases = sum(n.startswith("bareesa/bases/") and n.endswith(".npz") for n in names)
    n_wheels = sum(n.startswith("wheels/") for n in names)
    print(f"{path}  ({path.stat().st_size / 1e6:.1f} MB, {len(names)} files, {n_bases} bundled bases, "
          f"{n_wheels} wheels)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
