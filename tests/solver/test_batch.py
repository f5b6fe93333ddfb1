"""Batch registration on a Dask LocalCluster (bareesa.batch, ``bareesa register-batch``): tiny sphere scans."""

import json
import os
import sys
import time

import numpy as np
import pytest
import torch

distributed = pytest.importorskip("distributed")
psutil = pytest.importorskip("psutil")  # a dependency of distributed

from bareesa import batch, registration, synthetic  # noqa: E402
from bareesa.basis_io import load_basis, save_basis  # noqa: E402
from bareesa.cli import main  # noqa: E402
from bareesa.errors import SolveCancelled  # noqa: E402
from bareesa.latent import Level  # noqa: E402
from bareesa.mesh import load_mesh, save_mesh  # noqa: E402
from bareesa.progress import CancelToken  # noqa: E402
from bareesa.synthetic import random_rotation  # noqa: E402

TINY_SCHEDULE = (Level(0.25, 1e3, 1, 15), Level(0.15, 1e5, 1, 15))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(path of the tiny basis' .npz, its surface map ``surface(u, alpha)``)."""
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=4, seed=0, schedule=TINY_SCHEDULE)
    path = tmp_path_factory.mktemp("bases") / "tiny.npz"
    save_basis(path, basis)
    return path, surface


def _alive(pid):
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


@pytest.fixture(scope="module")
def client():
    """One LocalCluster of two single-threaded worker processes for the whole module (shut down after)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as cluster, distributed.Client(cluster) as c:
        pids = list(c.run(os.getpid).values())
        assert len(pids) == 2 and os.getpid() not in pids
        yield c
    deadline = time.monotonic() + 30
    while any(map(_alive, pids)):
        assert time.monotonic() < deadline, f"worker processes {pids} still run after the cluster closed"
        time.sleep(0.2)


def write_scan(path, surface, code, seed, rotation=None, shift=(0.0, 0.0, 0.0)):
    """F(code) sampled on a resampled sphere (another triangulation), moved rigidly, saved: -> path."""
    u, faces = synthetic.resampled_sphere(2, seed=seed)
    v = surface(u, np.asarray(code))
    if rotation is not None:
        v = v @ rotation.T
    save_mesh(path, v + np.asarray(shift), faces)
    return path


@pytest.fixture(scope="module")
def scans(tiny, tmp_path_factory):
    folder = tmp_path_factory.mktemp("scans")
    rng = np.random.default_rng(0)
    return [write_scan(folder / f"scan{k}.ply", tiny[1], 0.5 * rng.normal(size=4), seed=k,
                       rotation=random_rotation(k), shift=(0.3 * k, 0.0, -0.1)) for k in range(3)]


@pytest.fixture(scope="module")
def done(tiny, scans, client, tmp_path_factory):
    """The three scans registered by a batch: (report, output folder)."""
    out = tmp_path_factory.mktemp("batch")
    return batch.register_batch(tiny[0], scans, out, client=client), out


def test_batch_writes_every_output_equal_to_single_process_registration(tiny, scans, done):
    report, out = done
    assert report.counts == {"ok": 3, "failed": 0, "skipped": 0, "pending": 0}
    basis = load_basis(tiny[0])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as on a worker
    try:
        for scan, row in zip(scans, report.rows):
            record = json.loads((out / f"{scan.stem}.json").read_text())
            ref = registration.register(basis, *load_mesh(scan))
            np.testing.assert_allclose(record["code"], ref.code, rtol=1e-7, atol=1e-9)
            # the mesh is the registered one as `register` writes it: detailed when the detail layer was kept
            np.testing.assert_allclose(load_mesh(out / record["mesh"])[0], ref.output_vertices, rtol=1e-7, atol=1e-9)
            assert record["detail"]["kept"] == (ref.detail is not None)
            if ref.detail is not None:
                np.testing.assert_allclose(np.load(out / record["detail_layer"]), ref.detail, rtol=1e-7, atol=1e-9)
                assert record["chamfer"] == pytest.approx(ref.detail_report["chamfer"], rel=1e-6)
            for key, value in ref.transform.to_dict().items():
                np.testing.assert_allclose(record["transform"][key], value, rtol=1e-7, atol=1e-9)
            assert record["varifold"] == pytest.approx(ref.varifold, rel=1e-6)
            assert record["basis_fit_chamfer"] == pytest.approx(ref.chamfer, rel=1e-6)
            assert record["input_hash"] == batch.file_hash(scan)
            assert record["basis_hash"] == batch.file_hash(tiny[0])
            assert record["worker"].startswith("tcp://127.0.0.1")
            assert record["seconds"] > 0 and row["status"] == "ok"
            assert [lv["iterations"] for lv in record["levels"]] == [lv["iterations"] for lv in ref.levels]
    finally:
        torch.set_num_threads(threads)
    summary = json.loads((out / batch.SUMMARY_JSON).read_text())
    assert [r["name"] for r in summary["rows"]] == ["scan0", "scan1", "scan2"]
    csv_lines = (out / batch.SUMMARY_CSV).read_text().splitlines()
    assert csv_lines[0].split(",") == list(batch.SUMMARY_COLUMNS) and len(csv_lines) == 4
    assert batch.registered_meshes(out) == [out / f"scan{k}.ply" for k in range(3)]
    assert batch.registered_meshes(out / batch.SUMMARY_CSV) == batch.registered_meshes(out)


def test_rerun_skips_finished_scans_and_redoes_a_changed_one(tiny, scans, done, client, tmp_path):
    _, out = done
    import shutil

    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    again = batch.register_batch(tiny[0], scans, copy, client=client)
    assert again.counts == {"ok": 0, "failed": 0, "skipped": 3, "pending": 0}
    # the second scan's file changes: only it runs again
    moved = tmp_path / "scans"
    moved.mkdir()
    new = [shutil.copy(s, moved / s.name) for s in scans]
    write_scan(moved / "scan1.ply", tiny[1], [0.3, -0.2, 0.1, 0.4], seed=11)
    before = json.loads((copy / "scan1.json").read_text())
    third = batch.register_batch(tiny[0], new, copy, client=client)
    assert third.counts == {"ok": 1, "failed": 0, "skipped": 2, "pending": 0}
    assert [r["status"] for r in third.rows] == ["skipped", "ok", "skipped"]
    after = json.loads((copy / "scan1.json").read_text())
    assert after["input_hash"] == batch.file_hash(moved / "scan1.ply") != before["input_hash"]
    assert not list(copy.glob(".*tmp*")), "atomic writes leave no temp files"


def test_a_broken_scan_is_recorded_and_the_others_finish(tiny, scans, client, tmp_path):
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"this is not a mesh")
    save_mesh(tmp_path / "piece.ply", np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
              np.array([[0, 1, 2], [0, 2, 3]]))  # two faces: too few to register (InputError)
    report = batch.register_batch(tiny[0], [scans[0], garbage, tmp_path / "piece.ply"], tmp_path / "out",
                                  client=client)
    assert report.counts == {"ok": 1, "failed": 2, "skipped": 0, "pending": 0}
    rows = {r["name"]: r for r in report.rows}
    assert rows["scan0"]["status"] == "ok"
    for name, kind in (("garbage", "MeshError"), ("piece", "InputError")):
        assert rows[name]["status"] == "failed" and rows[name]["error"].startswith(kind)
        assert "\n" not in rows[name]["error"]
        record = json.loads((tmp_path / "out" / f"{name}.json").read_text())
        assert record["status"] == "failed" and not (tmp_path / "out" / f"{name}.ply").exists()
    assert "piece" in (tmp_path / "out" / batch.SUMMARY_CSV).read_text()
    with pytest.raises(batch.InputError, match="not registered"):
        batch.registered_meshes(tmp_path / "out")


def test_ctrl_c_keeps_what_finished_and_cancels_the_rest(tiny, scans, client, tmp_path):
    def interrupt(event):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        batch.register_batch(tiny[0], scans, tmp_path / "out", client=client, callback=interrupt)
    summary = json.loads((tmp_path / "out" / batch.SUMMARY_JSON).read_text())
    assert summary["interrupted"] and summary["counts"]["ok"] == 1
    assert len(list((tmp_path / "out").glob("scan*.json"))) == 1
    resumed = batch.register_batch(tiny[0], scans, tmp_path / "out", client=client)
    assert resumed.counts["skipped"] == 1 and resumed.counts["ok"] == 2


def test_a_cancel_token_stops_the_batch_like_ctrl_c(tiny, scans, client, tmp_path):
    token = CancelToken()
    token.cancel()
    with pytest.raises(SolveCancelled):
        batch.register_batch(tiny[0], scans[:2], tmp_path / "out", client=client, cancel=token)
    summary = json.loads((tmp_path / "out" / batch.SUMMARY_JSON).read_text())
    assert summary["interrupted"] and summary["counts"]["ok"] == 1 and summary["counts"]["pending"] == 1


@pytest.fixture(scope="module")
def motion(tiny, tmp_path_factory):
    """Four frames of one smooth capture (the code moves a little each frame, the scanner stays put)."""
    folder = tmp_path_factory.mktemp("motion")
    a, b = np.array([0.6, -0.4, 0.2, 0.5]), np.array([-0.3, 0.5, 0.6, -0.2])
    return [write_scan(folder / f"frame{k}.ply", tiny[1], a + k / 6 * (b - a), seed=20 + k,
                       rotation=random_rotation(3), shift=(0.5, 0.2, 0.0)) for k in range(4)]


def test_a_warm_frame_skips_the_coarsest_level_and_runs_at_most_the_two_finest():
    levels = [Level(sigma, 1e3, 2, 10) for sigma in (0.4, 0.2, 0.1, 0.05)]
    assert batch.warm_schedule(levels) == tuple(levels[2:])      # 4 levels: the middle and the finest
    assert batch.warm_schedule(levels[1:]) == tuple(levels[2:])  # 3 levels: all but the coarsest
    assert batch.warm_schedule(levels[2:]) == tuple(levels[3:])  # 2 levels: the finest
    assert batch.warm_schedule(levels[:1]) == tuple(levels[:1])  # one level: that one


def test_sequence_warm_starts_take_fewer_iterations_and_seams_are_checked(tiny, motion, client, tmp_path):
    cold = batch.register_batch(tiny[0], motion, tmp_path / "cold", client=client)
    warm = batch.register_batch(tiny[0], motion, tmp_path / "warm", client=client, sequence=True, chunk=2)
    assert warm.counts["ok"] == 4
    assert [r["warm_start"] for r in warm.rows] == [None, "frame0", None, "frame2"]
    for k in (1, 3):  # fewer iterations, the same registration (scan frame)
        assert warm.rows[k]["iterations"] < cold.rows[k]["iterations"]
        assert warm.rows[k]["chamfer"] < 1.5 * cold.rows[k]["chamfer"] + 1e-3
        record = json.loads((tmp_path / "warm" / f"frame{k}.json").read_text())
        assert [lv["iterations"] for lv in record["levels"]][-1] > 0
    (seam,) = warm.seams
    assert (seam["before"], seam["after"]) == ("frame1", "frame2")
    assert seam["jump"] > 0 and seam["median_motion"] > 0 and isinstance(seam["flagged"], bool)
    assert warm.rows[2]["seam_jump"] == seam["jump"]
    summary = json.loads((tmp_path / "warm" / batch.SUMMARY_JSON).read_text())
    assert summary["sequence"] and summary["chunk"] == 2 and len(summary["seams"]) == 1
    # a resumed sequence skips it all; a changed frame runs again, and so do the frames after it in its chunk
    frames = [tmp_path / p.name for p in motion]
    for src, dst in zip(motion, frames):
        dst.write_bytes(src.read_bytes())
    assert batch.register_batch(tiny[0], frames, tmp_path / "warm", client=client, sequence=True,
                                chunk=2).counts["skipped"] == 4
    write_scan(frames[0], tiny[1], [0.5, -0.3, 0.2, 0.4], seed=40, rotation=random_rotation(3),
               shift=(0.5, 0.2, 0.0))
    again = batch.register_batch(tiny[0], frames, tmp_path / "warm", client=client, sequence=True, chunk=2)
    assert [r["status"] for r in again.rows] == ["ok", "ok", "skipped", "skipped"]


def test_cli_register_batch_on_a_scheduler_then_build_basis_from_its_folder(tiny, motion, client, tmp_path,
                                                                            capsys):
    listing = tmp_path / "frames.txt"
    listing.write_text("# one frame a line\n" + "\n".join(str(p) for p in motion[:4]) + "\n")
    out = tmp_path / "batch"
    assert main(["register-batch", "--list", str(listing), "--basis", str(tiny[0]), "-o", str(out),
                 "--scheduler", client.scheduler.address, "--sequence", "--chunk", "2", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["counts"]["ok"] == 4 and len(printed["seams"]) == 1
    template = tmp_path / "template.ply"
    basis = load_basis(tiny[0])
    save_mesh(template, basis.template, basis.faces)
    assert main(["build-basis", str(template), "--sequence", f"pose:{out}", "--components", "pose=2",
                 "--no-distribution", "-o", str(tmp_path / "built.npz")]) == 0
    built = load_basis(tmp_path / "built.npz")
    assert built.n_fields == 2
    assert built.provenance["sequences"]["pose"] == [[str(out / f"frame{k}.ply") for k in range(4)]]


def test_cli_register_batch_errors_are_one_line(tiny, scans, tmp_path, capsys, monkeypatch):
    assert main(["register-batch", "--basis", str(tiny[0]), "-o", str(tmp_path / "o")]) == 2
    assert "no scans given" in capsys.readouterr().err
    assert main(["register-batch", str(scans[0]), "--basis", str(tiny[0]), "-o", str(tmp_path / "o"),
                 "--chunk", "2"]) == 2
    assert "--chunk only applies with --sequence" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask were not installed
    assert main(["register-batch", str(scans[0]), "--basis", str(tiny[0]), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "pip install 'bareesa[batch]'" in err and len(err.strip().splitlines()) == 1


# --------------------------------------------------------------- scans in memory, local processes


def _scan_inputs(scans, broken=None):
    from bareesa.workflows import Scan

    out = [Scan(*load_mesh(s)) for s in scans]
    if broken is not None:  # a one-triangle "scan": refused up front
        out[broken] = Scan(np.array([[0.0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0]]), np.array([[0, 1, 2]]))
    return out


def test_scans_in_memory_register_in_processes_like_in_this_one_with_one_progress_bar(tiny, scans):
    from bareesa.workflows import Options, codes_of

    inputs, options = _scan_inputs(scans[:2], broken=None), Options(schedule=TINY_SCHEDULE)
    events = []
    results = batch.register_scans(tiny[0], inputs, options, workers=2, callback=events.append, progress_every=0)
    serial = codes_of(load_basis(tiny[0]), inputs, options)
    for r, s in zip(results, serial):
        assert isinstance(r, registration.RegistrationResult)
        np.testing.assert_allclose(r.code, s.code, atol=1e-8)
        np.testing.assert_allclose(r.vertices, s.registration.vertices, atol=1e-8)
        np.testing.assert_allclose(r.transform.rotation, s.registration.transform.rotation, atol=1e-8)
        assert r.transform.scale == pytest.approx(s.registration.transform.scale)
    fractions = [e.fraction for e in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len(set(fractions)) > 2
    previews = [e.preview for e in events if e.preview is not None]
    assert {p["item"] for p in previews} <= {0, 1} and previews, "the workers' previews reach the client"
    assert all(p["code"].shape == (4,) and hasattr(p["transform"], "apply") for p in previews)


def test_a_scan_that_fails_in_a_process_is_returned_as_its_error_and_the_others_register(tiny, scans):
    from bareesa.errors import InputError
    from bareesa.workflows import Options

    results = batch.register_scans(tiny[0], _scan_inputs(scans[:2], broken=1), Options(schedule=TINY_SCHEDULE),
                                   workers=2)
    assert isinstance(results[0], registration.RegistrationResult)
    assert isinstance(results[1], InputError) and str(results[1]).startswith("scan 2: ")


def test_cancelling_scans_in_processes_stops_the_workers_and_raises(tiny, scans):
    from bareesa.workflows import Options

    token = CancelToken()
    seen = []

    def callback(event):
        seen.append(event)
        if len(seen) == 3:
            token.cancel()

    start = time.monotonic()
    with pytest.raises(SolveCancelled):
        batch.register_scans(tiny[0], _scan_inputs(scans), Options(schedule=(Level(0.15, 1e5, 2, 10_000),)),
                             workers=2, callback=callback, cancel=token)
    assert time.monotonic() - start < 120


def test_a_vendored_copy_of_the_solver_registers_scans_in_processes(tiny, scans, tmp_path):
    """The Blender extension vendors the solver as <extension>/bareesa (imported as <package>.bareesa): its
    workers import it as ``bareesa`` from that folder, not from the installed package, and the scheduler
    (in the client's process, where no top-level ``bareesa`` exists) unpickles the tasks: the installed
    extension failed so ("Error during deserialization of the task graph") before ``_alias_solver``."""
    import shutil
    import subprocess

    import bareesa

    ext = tmp_path / "my_extension"
    shutil.copytree(os.path.dirname(bareesa.__file__), ext / "bareesa",
                    ignore=shutil.ignore_patterns("__pycache__", "bases"))
    (ext / "__init__.py").write_text("")
    with open(ext / "bareesa" / "batch" / "__init__.py", "a") as f:  # a mark only the vendored copy leaves
        f.write("\n_unmarked = register_array\n\n\ndef register_array(*args, **kwargs):\n"
                "    return {**_unmarked(*args, **kwargs), 'levels': [{'vendored': True}]}\n")
    script = f"""
import sys, numpy as np


class HideInstalled:  # as in Blender: the client process has no top-level bareesa of its own
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "bareesa":
            raise ModuleNotFoundError("No module named " + repr(name))


sys.meta_path.insert(0, HideInstalled())
sys.path.insert(0, {str(tmp_path)!r})
import my_extension.bareesa.batch as vb
from my_extension.bareesa.mesh import load_mesh
from my_extension.bareesa.workflows import Scan, Options
from my_extension.bareesa.latent import Level
import distributed

res = vb.register_scans({str(tiny[0])!r}, [Scan(*load_mesh({str(scans[0])!r}))],
                        Options(schedule=(Level(0.25, 1e3, 1, 5),)), workers=1)
assert type(res[0]).__module__ == "my_extension.bareesa.registration.result", type(res[0])
assert res[0].levels == [{{"vendored": True}}], "the workers ran the installed solver, not the vendored one"
print("code", np.round(res[0].code, 6).tolist())
"""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": ""})
    assert run.returncode == 0, run.stderr[-3000:]
    assert "code" in run.stdout


def test_a_scans_mask_and_landmark_files_register_with_it_and_a_change_to_them_is_a_new_input(tiny, tmp_path):
    from bareesa.errors import InputError
    from bareesa.masks import face_weights_from_ignore
    from bareesa.transforms import Similarity

    basis = load_basis(tiny[0])
    u, faces = synthetic.resampled_sphere(2, seed=3)
    code = np.array([0.4, -0.3, 0.2, 0.1])
    sphere = tiny[1](u, code)
    mark = tiny[1](synthetic.icosphere(1)[0][:1], code)  # where template vertex 0 is on the scan
    g = np.linspace(-2.0, 2.0, 5)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    plate = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, sphere[:, 2].min() - 0.05)], 1)
    a = (np.arange(4)[:, None] * 5 + np.arange(4)[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 5, a + 6], 1), np.stack([a, a + 6, a + 1], 1)]) + len(sphere)
    verts, faces = np.concatenate([sphere, plate]), np.concatenate([faces, tris])
    scan = tmp_path / "s.ply"
    save_mesh(scan, verts, faces)
    plain_hash = batch.input_hash(scan)
    assert plain_hash == batch.file_hash(scan)  # no sidecar: the records of earlier batches stay valid
    ignore = (np.arange(len(verts)) >= len(sphere)).astype(float)
    np.save(tmp_path / "s.ignore.npy", ignore)
    (tmp_path / "s.landmarks.csv").write_text(f"0, {', '.join(f'{x!r}' for x in mark[0])}\n")
    masked_hash = batch.input_hash(scan)
    assert masked_hash != plain_hash
    threads = torch.get_num_threads()
    try:
        rec = batch.register_one(basis, scan)
        torch.set_num_threads(1)
        ref = registration.register(basis, verts, faces, scan_face_weights=face_weights_from_ignore(ignore, faces),
                                    landmarks=[(0, mark[0], 1.0)])
        # a warm start maps the scan, and so its landmarks, by the previous frame's alignment: the same scan
        # moved, with its files, starts from the first one's code and the motion back
        before = Similarity(random_rotation(4), 1.1, np.array([0.2, -0.1, 0.3]))
        moved = tmp_path / "m.ply"
        save_mesh(moved, before.invert(verts), faces)
        np.save(tmp_path / "m.ignore.npy", ignore)
        (tmp_path / "m.landmarks.csv").write_text(f"0, {', '.join(f'{x!r}' for x in before.invert(mark)[0])}\n")
        warm = batch.register_one(basis, moved, {"status": "ok", "name": "prev", "code": rec["code"],
                                                 "transform": before.to_dict()})
    finally:
        torch.set_num_threads(threads)
    assert rec["status"] == "ok" and rec["ignore"] == "s.ignore.npy" and rec["landmarks"] == "s.landmarks.csv"
    assert rec["input_hash"] == masked_hash
    np.testing.assert_allclose(rec["code"], ref.code, rtol=1e-7, atol=1e-9)
    assert warm["status"] == "ok" and warm["warm_start"] == "prev"
    np.testing.assert_allclose(warm["code"], rec["code"], atol=0.05)
    finest = batch.warm_schedule(basis.schedule)  # a warm start runs the finest levels only
    assert [lv["weight"] for lv in warm["levels"]] == [lv.weight for lv in finest] and len(finest) < len(rec["levels"])
    np.save(tmp_path / "s.ignore.npy", 0.5 * ignore)
    assert batch.input_hash(scan) not in (plain_hash, masked_hash)  # an edited mask registers the scan again
    (tmp_path / "s.ignore.txt").write_text("0\n")
    with pytest.raises(InputError, match="two ignore files"):
        batch.input_hash(scan)
    (tmp_path / "s.ignore.txt").unlink()
    np.save(tmp_path / "s.ignore.npy", np.ones(3))
    bad = batch.register_one(basis, scan)
    assert bad["status"] == "failed" and f"expected {len(verts)} numbers" in bad["error"]
