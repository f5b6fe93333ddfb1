"""Helpers shared by the headless Blender tests (tests/addon/): the tiny test basis, scene helpers and the
stand-ins that drive a modal solve operator. Plain functions; the fixtures (``tiny``, ``scene``) are in
tests/addon/conftest.py.

A tiny basis (42-vertex smooth sphere, groups ``pose`` and ``shape`` of two
fields each, a fitted distribution, a fast two-level schedule) is built once
(the ``tiny`` fixture) and saved to a temporary .npz, so the tests never need the bundled bases.

Importing this module skips the importing test module where bpy is absent.
"""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from bareesa import synthetic  # noqa: E402
from bareesa.latent import Basis, Level  # noqa: E402
from bareesa.statistics import fit_distribution  # noqa: E402

TINY_SCHEDULE = (Level(0.25, 1e3, 1, 15), Level(0.15, 1e5, 1, 15))


def tiny_basis():
    """The test basis and its generating surface map ``surface(u, alpha)``."""
    b, surface = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=4, seed=0, schedule=TINY_SCHEDULE)
    rng = np.random.default_rng(0)
    groups = {"pose": (0, 2), "shape": (2, 4)}
    extras = fit_distribution(0.5 * rng.normal(size=(12, 4)), groups, {"pose": 1, "shape": 1}, seed=0)
    basis = Basis(template=b.template, faces=b.faces, fields=b.fields, groups=groups, weights=b.weights,
                  schedule=TINY_SCHEDULE, scale=b.scale, units="", name="tiny", extras=extras)
    return basis, surface


def add_mesh(name, verts, faces, location=(0.0, 0.0, 0.0), quads=None):
    """A mesh object in the scene's collection, selected and active."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(np.asarray(verts).tolist(), [], (np.asarray(faces).tolist() if quads is None else quads))
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = location
    bpy.context.view_layer.update()
    return obj


def select(*objects, active=None):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in objects:
        o.select_set(True)
    bpy.context.view_layer.objects.active = active or (objects[-1] if objects else None)


def mesh_verts(obj):
    v = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", v)
    return v.reshape(-1, 3)


def key_values(obj, names):
    """The code an object's field keys hold (values times the per-key scales, bareesa_addon.convert.get_code)."""
    from bareesa_addon import convert

    return convert.get_code(obj, names)


def snapshot():
    """A comparable summary of the scene: objects, their vertices, transforms, keys and animation."""
    out = {}
    for o in bpy.data.objects:
        keys = o.data.shape_keys if o.type == "MESH" else None
        anim = keys.animation_data if keys is not None else None
        out[o.name] = (mesh_verts(o).round(9).tobytes() if o.type == "MESH" else None,
                       tuple(tuple(r) for r in o.matrix_world),
                       tuple((k.name, round(k.value, 9)) for k in keys.key_blocks) if keys else (),
                       anim.action.name if anim is not None and anim.action is not None else None)
    out["__collections__"] = tuple(sorted(c.name for c in bpy.data.collections))
    return out


def code_surface(surface, alpha, subdivisions=1, seed=3):
    """F(alpha) sampled on another triangulation of the sphere: -> verts, faces (a raw 'scan')."""
    u, faces = synthetic.resampled_sphere(subdivisions, seed=seed)
    return surface(u, np.asarray(alpha, dtype=np.float64)), faces


# --------------------------------------------------------------------------- a modal solve, driven by hand


class FakeWindowManager:
    def __init__(self):
        self.progress, self.timers, self.handlers = [], 0, []

    def event_timer_add(self, step, window=None):
        self.timers += 1
        return object()

    def event_timer_remove(self, timer):
        self.timers -= 1

    def modal_handler_add(self, op):
        self.handlers.append(op)

    def progress_begin(self, lo, hi):
        self.progress.append("begin")

    def progress_update(self, value):
        self.progress.append(value)

    def progress_end(self):
        self.progress.append("end")


class FakeWorkspace:
    def __init__(self):
        self.status = []

    def status_text_set(self, text):
        self.status.append(text)


def fake_context():
    return SimpleNamespace(window_manager=FakeWindowManager(), window=object(), workspace=FakeWorkspace(),
                           screen=None)


def make_operator(solve, applied):
    from bareesa_addon.jobs import SolveOperator, Task

    class Op(SolveOperator):
        def __init__(self):
            self.reports = []

        def report(self, kind, message):
            self.reports.append((set(kind), message))

        def prepare(self, context):
            def apply(context, result):
                applied.append((result, threading.current_thread() is threading.main_thread()))
                return f"applied {result}"

            return Task("test solve", solve, apply)

    return Op()


def drive(op, context, events=(), timeout=60.0):
    """Send TIMER events (and the given ones first) until the operator finishes: -> its return value."""
    for ev in events:
        result = op.modal(context, SimpleNamespace(type=ev, value="PRESS"))
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        result = op.modal(context, SimpleNamespace(type="TIMER", value="NOTHING"))
        if result != {"RUNNING_MODAL"}:
            return result
        time.sleep(0.02)
    raise AssertionError("the job did not finish")
