"""Running the solver's tasks on Dask workers also when the solver is vendored inside another package.

The Blender extension vendors the solver as ``<extension>/bareesa`` (imported as ``<package>.bareesa``).
Its workers import it as ``bareesa`` from that folder (``solver_preload``); a task's function pickles
by name through ``bareesa.batch`` (``SolverFunction``), never by the copy's own module name; and the
client's process, where a LocalCluster's scheduler unpickles the tasks, can import the copy as
``bareesa`` too (``alias_solver``).
"""

import importlib
import sys
from pathlib import Path

#: The dotted name the solver runs under here: "bareesa", or e.g. "<extension>.bareesa" when vendored.
SOLVER = __package__.rpartition(".")[0]


class _Module:
    """Pickles as ``importlib.import_module(name)``."""

    def __init__(self, name):
        self.name = name

    def __reduce__(self):
        return importlib.import_module, (self.name,)


class SolverFunction:
    """A function of the batch package that pickles as ``bareesa.batch.<name>`` whatever the package's own
    name: the workers import the solver as ``bareesa`` (``solver_preload``), also when the client runs a
    copy vendored inside another package. Called, it runs the package's attribute of that name as it is
    then (so a function replaced on the package is the one that runs)."""

    def __init__(self, name):
        self.name = name

    def __call__(self, *args, **kwargs):
        return getattr(importlib.import_module(__package__), self.name)(*args, **kwargs)

    def __reduce__(self):  # by name only: never by this copy's own module name, also when a scheduler re-pickles
        return _Attribute("bareesa.batch.vendored", "SolverFunction"), (self.name,)


class _Attribute:
    """Pickles as ``getattr(importlib.import_module(module), name)``."""

    def __init__(self, module, name):
        self.module, self.name = module, name

    def __call__(self, *args):
        return getattr(importlib.import_module(self.module), self.name)(*args)

    def __reduce__(self):
        return getattr, (_Module(self.module), self.name)


def solver_preload():
    """Dask preload texts that let a worker import this solver as ``bareesa``: none when it is installed
    under that name, else its parent folder put first on the worker's sys.path."""
    if SOLVER == "bareesa":
        return []
    return [f"import sys\nsys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r})\n"]


def alias_solver():
    """Let this process import a vendored copy of the solver as ``bareesa`` too: a LocalCluster's scheduler
    runs here and unpickles the tasks, whose function is ``bareesa.batch.<name>`` (``SolverFunction``).
    Every loaded module of the copy is entered in sys.modules under its ``bareesa`` name as well (the same
    module objects, so the add-on's classes stay one), unless a ``bareesa`` is loaded already."""
    if SOLVER == "bareesa" or "bareesa" in sys.modules:
        return
    for name, module in list(sys.modules.items()):
        if name == SOLVER or name.startswith(SOLVER + "."):
            sys.modules.setdefault("bareesa" + name[len(SOLVER):], module)
