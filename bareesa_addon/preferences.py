"""Add-on preferences: solver dependency status, "Install dependencies" (pip), compute device.

Dependencies are pip-installed into the extension's own user directory
(``<extension user dir>/site-packages``), which is put on ``sys.path`` at
registration; Blender's bundled numpy is kept (pinned in a constraints file).
"""

import importlib.util
import os
import subprocess
import sys
import threading
from pathlib import Path

import bpy
from bpy.props import EnumProperty

PACKAGE = __package__ or "bareesa_addon"
SOLVER_MODULES = ("torch", "scipy", "numpy", "trimesh", "pykeops", "sklearn", "distributed")
#: Modules the solver runs without (pykeops: faster sums; distributed: scans in parallel processes).
OPTIONAL_MODULES = ("pykeops", "distributed")
#: pip requirement of each module the solver imports (numpy comes with Blender).
PIP_NAMES = {"torch": "torch", "scipy": "scipy", "trimesh": "trimesh", "sklearn": "scikit-learn",
             "pykeops": "pykeops", "distributed": "distributed"}
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def dependency_status():
    """{module name: importable?} for the solver's dependencies (no import is executed)."""
    return {name: importlib.util.find_spec(name) is not None for name in SOLVER_MODULES}


def _user_dir(sub, create):
    """A directory of the add-on's own in the user's Blender files (extension directory when installed)."""
    try:
        return Path(bpy.utils.extension_path_user(PACKAGE, path=sub, create=create))
    except ValueError:  # run from a source checkout, not as an installed extension
        path = Path(bpy.utils.user_resource("DATAFILES", path=f"bareesa/{sub}", create=create))
        return path


def user_bases_dir(create=False):
    """Where built bases are saved (``$BAREESA_USER_BASES`` overrides): -> Path."""
    env = os.environ.get("BAREESA_USER_BASES")
    if env:
        path = Path(env)
        if create:
            path.mkdir(parents=True, exist_ok=True)
        return path
    return _user_dir("bases", create)


def dependencies_dir(create=False):
    """The site-packages directory the dependencies are installed into: -> Path."""
    return _user_dir("site-packages", create)


def add_dependencies_to_path():
    path = dependencies_dir()
    if path.is_dir() and str(path) not in sys.path:
        sys.path.append(str(path))


def cuda_available():
    if importlib.util.find_spec("torch") is None:
        return False
    try:
        import torch

        return bool(torch.cuda.is_available())
    except Exception:  # a broken torch install: CPU only
        return False


_DEVICE_ITEMS = {}


def _device_items(_self, _context):
    cuda = cuda_available()
    if cuda not in _DEVICE_ITEMS:  # Blender needs the item strings to stay referenced
        items = [("cpu", "CPU", "Run the solver on the processor")]
        if cuda:
            items.append(("cuda", "CUDA", "Run the solver on the NVIDIA GPU"))
        _DEVICE_ITEMS[cuda] = items
    return _DEVICE_ITEMS[cuda]


def preferences(context=None):
    """The add-on's preferences, or None when it was registered without being enabled (tests)."""
    addon = (context or bpy.context).preferences.addons.get(PACKAGE)
    return addon.preferences if addon is not None else None


def solver_device(context=None):
    """'cpu' or 'cuda' as chosen in the preferences (CPU when CUDA is not available)."""
    prefs = preferences(context)
    device = prefs.device if prefs is not None else "cpu"
    return device if device == "cpu" or cuda_available() else "cpu"


def solver_processes(n_scans, context=None, asked=-1):
    """How many worker processes register n_scans scans: ``asked`` when >= 0 (an operator's own setting),
    else the preference (0: one per CPU core); at most one per scan. 1 means in Blender's own process
    (also when the add-on was registered without being enabled, or Dask's distributed is missing)."""
    if asked < 0:
        prefs = preferences(context)
        asked = prefs.processes if prefs is not None else 1
    n = min(asked or os.cpu_count() or 1, n_scans)
    if n > 1 and importlib.util.find_spec("distributed") is None:
        return 1
    return max(n, 1)


def pip_commands(target, modules, cuda=False):
    """The pip command lines that install ``modules`` into ``target`` (torch first, CPU wheel unless cuda)."""
    import numpy

    constraints = Path(target) / "blender-constraints.txt"
    base = [sys.executable, "-m", "pip", "install", "--upgrade", "--target", str(target), "--constraint",
            str(constraints), "--disable-pip-version-check", "--no-input"]
    commands = []
    wanted = [PIP_NAMES[m] for m in modules if m in PIP_NAMES]
    if "torch" in wanted:
        wanted.remove("torch")
        commands.append(base + ([] if cuda else ["--index-url", TORCH_CPU_INDEX]) + ["torch"])
    if wanted:
        commands.append(base + wanted)
    return commands, constraints, f"numpy=={numpy.__version__}\n"


class BAREESA_OT_install_dependencies(bpy.types.Operator):
    """Install the solver's missing Python packages (torch, scipy, ...) into the extension's directory"""

    bl_idname = "bareesa.install_dependencies"
    bl_label = "Install Dependencies"

    def _commands(self):
        missing = [m for m, ok in dependency_status().items() if not ok]
        prefs = preferences()
        target = dependencies_dir(create=True)
        commands, constraints, pins = pip_commands(target, missing, cuda=prefs is not None and prefs.cuda_wheels)
        constraints.write_text(pins)
        return commands, target

    def _run(self, commands):
        self._log, self._error = [], None
        try:
            subprocess.run([sys.executable, "-m", "ensurepip", "--default-pip"], capture_output=True, check=False)
            for cmd in commands:
                proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                for line in proc.stdout:
                    self._log.append(line.rstrip())
                if proc.wait() != 0:
                    tail = " | ".join(self._log[-3:])
                    self._error = f"pip failed (exit {proc.returncode}): {tail}"
                    return
        except OSError as err:
            self._error = f"cannot run pip: {err}"

    def _done(self, context, target):
        if self._error:
            self.report({"ERROR"}, f"{self._error}. Check the network connection, or install the packages into "
                                   f"{target} by hand")
            return {"CANCELLED"}
        add_dependencies_to_path()
        importlib.invalidate_caches()
        still = [m for m, ok in dependency_status().items() if not ok and m in PIP_NAMES]
        if still:
            self.report({"ERROR"}, f"installed, but {', '.join(still)} still do not import: restart Blender")
            return {"CANCELLED"}
        self.report({"INFO"}, f"dependencies installed into {target}")
        return {"FINISHED"}

    def execute(self, context):
        commands, target = self._commands()
        if not commands:
            self.report({"INFO"}, "all dependencies are already installed")
            return {"FINISHED"}
        self._run(commands)
        return self._done(context, target)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        self._commands_, self._target = self._commands()
        if not self._commands_:
            self.report({"INFO"}, "all dependencies are already installed")
            return {"FINISHED"}
        self._thread = threading.Thread(target=self._run, args=(self._commands_,), daemon=True)
        self._log = []
        self._thread.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.5, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        line = self._log[-1] if self._log else "starting pip..."
        context.workspace.status_text_set(f"BaRe-ESA: installing dependencies: {line[:120]}")
        if self._thread.is_alive():
            return {"RUNNING_MODAL"}
        context.window_manager.event_timer_remove(self._timer)
        context.workspace.status_text_set(None)
        return self._done(context, self._target)


class BareEsaPreferences(bpy.types.AddonPreferences):
    bl_idname = PACKAGE

    device: EnumProperty(name="Device", items=_device_items,
                         description="Where the solver runs (CUDA appears when torch sees an NVIDIA GPU)")
    processes: bpy.props.IntProperty(
        name="Worker Processes", default=0, min=0, max=256,
        description="Register several selected scans in parallel worker processes (Dask's distributed "
                    "scheduler, one solver thread each); 0: one per CPU core, 1: one scan at a time in Blender")
    cuda_wheels: bpy.props.BoolProperty(name="Install CUDA build of torch", default=False,
                                        description="Install the (large) CUDA build of torch instead of the CPU one")

    def draw(self, context):
        layout = self.layout
        status = dependency_status()
        box = layout.box()
        box.label(text="Solver dependencies")
        grid = box.grid_flow(columns=3, even_columns=True)
        for name, ok in status.items():
            grid.label(text=name, icon="CHECKMARK" if ok else "ERROR")
        row = box.row()
        row.operator(BAREESA_OT_install_dependencies.bl_idname, icon="IMPORT")
        row.prop(self, "cuda_wheels")
        box.label(text=f"Installed into: {dependencies_dir()}")
        layout.prop(self, "device")
        row = layout.row()
        row.prop(self, "processes")
        if importlib.util.find_spec("distributed") is None:
            row.label(text="needs Dask's distributed (Install dependencies)", icon="INFO")


CLASSES = (BAREESA_OT_install_dependencies, BareEsaPreferences)


def register():
    add_dependencies_to_path()
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
