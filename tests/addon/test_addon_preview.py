"""Live preview of a registration run from the interface: the fit appears and updates before the solve
ends, goes away when the result lands, and a cancel leaves the scene as it was."""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from tests.addon.support import add_mesh, bpy, code_surface, fake_context, select, snapshot

NAMES = ["pose_000", "pose_001", "shape_000", "shape_001"]
ALPHA = np.array([0.6, -0.4, 0.5, 0.3])


class InterfaceContext:
    """bpy.context with the window parts of a running interface (headless Blender has none)."""

    def __init__(self):
        self._fake = fake_context()

    def __getattr__(self, name):
        if name in ("window_manager", "window", "workspace", "screen"):
            return getattr(self._fake, name)
        return getattr(bpy.context, name)


@pytest.fixture
def interface(monkeypatch):
    """The register operator as the interface runs it (modal, solve in a thread), each preview handed
    over before the solve goes on (so that the test sees every one, however fast the solve)."""
    from bareesa_addon import jobs
    from bareesa_addon.operators.register import BAREESA_OT_register_scan

    monkeypatch.setattr(jobs, "bpy", SimpleNamespace(app=SimpleNamespace(background=False)))
    handed = threading.Event()
    original = jobs.Job._callback

    def slow_callback(self, event):
        original(self, event)
        if event.preview is not None:
            handed.clear()
            handed.wait(5.0)  # until the main thread showed it

    monkeypatch.setattr(jobs.Job, "_callback", slow_callback)

    class Op(jobs.SolveOperator):
        basis = ""
        processes = -1
        prepare = BAREESA_OT_register_scan.prepare

        def __init__(self):
            self.reports = []
            self.properties = SimpleNamespace(is_property_set=lambda name: False)

        def report(self, kind, message):
            self.reports.append((set(kind), message))

    def start():
        op, context = Op(), InterfaceContext()
        assert op.invoke(context, None) == {"RUNNING_MODAL"}
        show = op._task.show

        def show_and_hand(ctx, preview):
            show(ctx, preview)
            handed.set()

        op._task.show = show_and_hand
        return op, context

    return start


def tick(op, context, event="TIMER"):
    return op.modal(context, SimpleNamespace(type=event, value="PRESS"))


def test_the_preview_object_updates_while_the_solve_runs_and_gives_way_to_the_result(scene, tiny, interface):
    from bareesa_addon import convert

    scene.bareesa.prealign = False
    scan = add_mesh("scan", *code_surface(tiny[2], ALPHA))
    select(scan)
    op, context = interface()
    seen, outcome, start = [], None, time.monotonic()
    while time.monotonic() - start < 120:
        outcome = tick(op, context)
        preview = bpy.data.objects.get("scan_registered (preview)")
        if preview is not None and not op._job.done:
            seen.append(convert.get_code(preview, NAMES).copy())
            assert preview.display_type == "WIRE" and bpy.data.objects.get("scan_registered") is None
        if outcome != {"RUNNING_MODAL"}:
            break
        time.sleep(0.01)
    assert outcome == {"FINISHED"}
    assert len(seen) >= 2 and not np.allclose(seen[0], seen[-1])  # it moved while the artist watched
    final = convert.get_code(bpy.data.objects["scan_registered"], NAMES)
    assert np.abs(seen[-1] - final).max() < np.abs(seen[0] - final).max()  # ... towards the result
    assert bpy.data.objects.get("scan_registered (preview)") is None
    assert not [m for m in bpy.data.meshes if m.name.startswith("scan_registered (preview)")]


def test_cancelling_after_a_preview_leaves_the_scene_as_it_was(scene, tiny, interface):
    scene.bareesa.prealign = False
    scan = add_mesh("scan", *code_surface(tiny[2], ALPHA))
    select(scan)
    before = snapshot()
    meshes = {m.name for m in bpy.data.meshes}
    op, context = interface()
    start = time.monotonic()
    while bpy.data.objects.get("scan_registered (preview)") is None and time.monotonic() - start < 60:
        assert tick(op, context) == {"RUNNING_MODAL"}
        time.sleep(0.01)
    assert bpy.data.objects.get("scan_registered (preview)") is not None
    tick(op, context, "ESC")
    outcome = {"RUNNING_MODAL"}
    while outcome == {"RUNNING_MODAL"} and time.monotonic() - start < 60:
        outcome = tick(op, context)
        time.sleep(0.01)
    assert outcome == {"CANCELLED"} and any("cancelled" in m for _, m in op.reports)
    assert snapshot() == before and {m.name for m in bpy.data.meshes} == meshes
