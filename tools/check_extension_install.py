"""Install a built extension zip into a fresh Blender user folder and use it: the self-contained check.

    BLENDER_USER_RESOURCES=/tmp/fresh-user PYTHON_WITH_ONLY_BPY tools/check_extension_install.py \
        dist/bareesa-<version>-linux-x64.zip REPO_DIR OUT.json

Run it with a Python whose environment has only ``bpy`` (e.g. ``python3.11 -m venv /tmp/bpyonly &&
/tmp/bpyonly/bin/pip install 'bpy==4.5.*'``): the zip is installed through
``bpy.ops.extensions.package_install_files`` into a new user repository, the solver's dependencies
must then import from the extension's own wheels, and a scan (a stretched icosphere) is registered
onto the bundled ``deformables`` basis, then two at once in two worker processes (Dask's, from the wheels). OUT.json says where each module came from and how it went.
"""
import json
import sys
import time


def main():
    import bpy

    zip_path, repo_dir, out = sys.argv[1:4]
    repos = bpy.context.preferences.extensions.repos
    repos.new(name="check", module="bareesa_check", custom_directory=repo_dir, source="USER")
    t0 = time.time()
    result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="bareesa_check", enable_on_install=True)
    t_install = time.time() - t0
    import importlib
    info = {"install": sorted(result), "seconds": round(t_install, 1)}
    for mod in ("torch", "scipy", "trimesh", "sklearn", "distributed"):
        try:
            m = importlib.import_module(mod); info[mod] = getattr(m, "__file__", "")
        except Exception as e:
            info[mod] = f"ERR {e}"
    info["enabled"] = "bl_ext.bareesa_check.bareesa" in bpy.context.preferences.addons
    try:
        bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=3, radius=0.3)
        scan = bpy.context.active_object
        scan.scale = (1.0, 0.6, 3.0)
        s = bpy.context.scene.bareesa
        s.basis = "deformables"; s.schedule = "FAST"
        t0 = time.time()
        info["register"] = sorted(bpy.ops.bareesa.register_scan())
        info["register_s"] = round(time.time() - t0, 1)
        info["registered"] = [o.name for o in bpy.data.objects if o.name.endswith("_registered")]
        # two scans at once: Register Scans runs them in two worker processes that import the bundled solver
        bpy.ops.object.select_all(action="DESELECT")
        scans = []
        for k in range(2):
            bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=3, radius=0.3, location=(2.0 + k, 0.0, 0.0))
            scans.append(bpy.context.active_object)
            scans[-1].scale = (1.0, 0.7 + 0.2 * k, 2.5)
        for obj in scans:
            obj.select_set(True)
        t0 = time.time()
        info["register_processes"] = sorted(bpy.ops.bareesa.register_scan(processes=2))
        info["register_processes_s"] = round(time.time() - t0, 1)
        info["registered"] = [o.name for o in bpy.data.objects if o.name.endswith("_registered")]
    except Exception as e:
        info["register"] = f"ERR {e}"
    json.dump(info, open(out, "w"), indent=1)
    import os; os._exit(0)


if __name__ == "__main__":  # worker processes (spawned) import this file again: only the parent checks
    main()
