"""Build the installable Blender extension .zip: the add-on, the vendored solver, the bundled bases.

    python tools/build_extension.py [--out dist] [--no-bases]

Layout of the zip (its root is the extension package):
    blender_manifest.toml, __init__.py, operators.py, ...   (bareesa_addon/)
    bareesa/**.py                                           (the solver package, imported relatively)
    bareesa/bases/*.npz, bareesa/bases/*.json               (bundled bases, as in an installed wheel)
Install it with Blender's Preferences > Get Extensions > Install from Disk, or
``blender --command extension install-file -r user_default -e <zip>``.
"""

import argparse
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _files(folder, patterns):
    for pattern in patterns:
        for path in sorted(folder.glob(pattern)):
            if path.is_file() and "__pycache__" not in path.parts:
                yield path


def build(out_dir=ROOT / "dist", bases=True):
    """Write dist/bareesa-<version>.zip: -> its Path."""
    manifest_path = ROOT / "blender_manifest.toml"
    manifest = tomllib.loads(manifest_path.read_text())
    if manifest.get("id") != "bareesa" or manifest.get("type") != "add-on":
        raise SystemExit(f"{manifest_path}: expected an add-on with id 'bareesa'")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"bareesa-{manifest['version']}.zip"
    entries = [(manifest_path, "blender_manifest.toml")]
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
    tmp = target.with_suffix(".zip.tmp")
    with zipfile.ZipFile(tmp, "w") as zf:
        for src, name in entries:
            # .npz are already compressed; Python sources deflate well
            zf.write(src, name, compress_type=zipfile.ZIP_STORED if src.suffix == ".npz" else zipfile.ZIP_DEFLATED)
    tmp.replace(target)
    return target


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "dist", help="output folder (default: dist/)")
    parser.add_argument("--no-bases", action="store_true", help="leave the bundled bases out (a small zip)")
    args = parser.parse_args(argv)
    path = build(args.out, bases=not args.no_bases)
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
    n_bases = sum(n.startswith("bases/") and n.endswith(".npz") for n in names)
    print(f"{path}  ({path.stat().st_size / 1e6:.1f} MB, {len(names)} files, {n_bases} bundled bases)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
