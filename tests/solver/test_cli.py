import dataclasses
import json

import numpy as np
import pytest
import torch

from bareesa import cli, h2_metric, synthetic
from bareesa.evaluation import chamfer, hausdorff
from bareesa.mesh import save_mesh
from bareesa.varifold import varifold_distance


@pytest.fixture
def meshes(tmp_path):
    v, f = synthetic.blob_mesh(2, seed=0)
    w, _ = synthetic.blob_mesh(2, seed=1)
    s, sf = synthetic.blob_mesh(1, seed=1)
    paths = {}
    for name, (a, b) in {"a": (v, f), "b": (w, f), "scan": (s, sf)}.items():
        paths[name] = tmp_path / f"{name}.ply"
        save_mesh(paths[name], a, b)
    return paths, (v, w, f, s, sf)


def run(capsys, *argv):
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def test_metrics_json_reports_chamfer_hausdorff_and_squared_varifold(capsys, meshes):
    paths, (v, w, f, s, sf) = meshes
    rc, out, _ = run(capsys, "metrics", paths["a"], paths["scan"], "--sigma", "0.3", "--json")
    assert rc == 0
    res = json.loads(out)
    assert res["chamfer"] == pytest.approx(chamfer(v, s))
    assert res["hausdorff"] == pytest.approx(hausdorff(v, s))
    expected = varifold_distance(torch.tensor(v), torch.tensor(f), torch.tensor(s), torch.tensor(sf), sigma=0.3)
    assert res["varifold"] == pytest.approx(float(expected), rel=1e-6)
    assert res["sigma"] == 0.3


def test_metrics_default_sigma_and_kernel_choice(capsys, meshes):
    paths, _ = meshes
    rc, out, _ = run(capsys, "metrics", paths["a"], paths["b"], "--json")
    binet = json.loads(out)
    rc2, out2, _ = run(capsys, "metrics", paths["a"], paths["b"], "--json", "--kernel", "constant")
    assert rc == rc2 == 0
    assert binet["sigma"] > 0 and binet["varifold"] > 0
    assert json.loads(out2)["varifold"] != pytest.approx(binet["varifold"])


def test_path_energy_json_matches_core(capsys, meshes):
    paths, (v, w, f, _, _) = meshes
    mid = tmp = paths["a"].with_name("mid.ply")
    save_mesh(tmp, (v + w) / 2 + 0.01, f)
    rc, out, _ = run(capsys, "path-energy", paths["a"], mid, paths["b"], "--metric", "face", "--json")
    assert rc == 0
    res = json.loads(out)
    path = torch.tensor(np.stack([v, (v + w) / 2 + 0.01, w]))
    expected = h2_metric.path_energy(path, torch.tensor(f), h2_metric.PRESETS["face"])
    assert res["energy"] == pytest.approx(float(expected), rel=1e-10)
    assert len(res["steps"]) == 2 and res["metric"] == [1, 10, 10, 10, 1, 1]


@pytest.mark.parametrize("argv, message", [
    (["metrics", "{a}", "{missing}"], "missing.ply"),
    (["path-energy", "{a}", "{scan}"], "vertices"),
    (["path-energy", "{a}", "{b}", "--metric", "1,2"], "six metric weights"),
    (["metrics", "{a}", "{b}", "--sigma", "-1"], "sigma"),
])
def test_errors_print_one_line_without_traceback_and_exit_nonzero(capsys, meshes, argv, message):
    paths, _ = meshes
    names = {**{k: str(p) for k, p in paths.items()}, "missing": str(paths["a"].with_name("missing.ply"))}
    rc, out, err = run(capsys, *[a.format(**names) for a in argv])
    assert rc == 2
    assert message in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.fixture
def sequences(tmp_path):
    """A template and two registered 'motions' (sequences of frames) written to disk."""
    v, f = synthetic.blob_mesh(2, seed=0)
    rng = np.random.default_rng(0)
    dirs = [0.2 * np.sin(v @ rng.normal(size=(3, 3))) for _ in range(3)]
    save_mesh(tmp_path / "template.ply", v, f)
    seqs = {}
    for name, (d, n) in {"bend": (dirs[0] + 0.5 * dirs[1], 4), "twist": (dirs[1] - dirs[2], 3)}.items():
        seqs[name] = []
        for k in range(n):
            p = tmp_path / f"{name}_{k}.ply"
            save_mesh(p, v + k / (n - 1) * d, f)
            seqs[name].append(p)
    return tmp_path, v, f, seqs


def load_mesh_v(path):
    from bareesa.mesh import load_mesh

    return load_mesh(path)[0]


def test_build_basis_then_distance_and_interpolate_on_registered_meshes(capsys, sequences):
    from bareesa.basis_io import load_basis
    from bareesa.latent import project_to_basis

    tmp, v, f, seqs = sequences
    out = tmp / "b.npz"
    rc, text, err = run(capsys, "build-basis", tmp / "template.ply",
                        "--sequence", "pose:" + ",".join(map(str, seqs["bend"])),
                        "--sequence", "pose:" + ",".join(map(str, seqs["twist"])),
                        "--components", "pose=4", "--metric", "face", "-o", out)
    assert rc == 0, err
    basis = load_basis(out)
    assert basis.n_fields == 2  # two independent motion directions, rank-limited
    assert basis.groups == {"pose": (0, 2)} and basis.weights == h2_metric.PRESETS["face"]
    # pose prototypes for registration: k-means centres of the pose frames' codes
    frames = np.stack([load_mesh_v(p) for p in seqs["bend"] + seqs["twist"]])
    protos = basis.extras["pose_prototypes"]
    distinct = np.unique(project_to_basis(basis, frames)[0].round(9), axis=0)
    assert protos.shape == distinct.shape  # fewer distinct frames than the 24 centres: each its own
    assert np.allclose(sorted(protos.tolist()), sorted(distinct.tolist()), atol=1e-8)
    # ... and the constants every registration would compute (registration.prepare_basis) are in the file
    assert np.array_equal(basis.extras["template_metric_weights"], basis.weights.as_tuple())
    assert np.array_equal(basis.extras["pose_prototype_moments_codes"], protos)
    end = seqs["bend"][-1]
    rc, text, err = run(capsys, "distance", tmp / "template.ply", end, "--basis", out, "--json")
    assert rc == 0, err
    dist = json.loads(text)["distance"]
    assert dist > 0
    rc, text, err = run(capsys, "interpolate", tmp / "template.ply", end, "--basis", out, "--steps", "5",
                        "-o", tmp / "interp", "--json")
    assert rc == 0, err
    res = json.loads(text)
    assert res["distance"] == pytest.approx(dist, rel=1e-3)
    frames = sorted((tmp / "interp").glob("frame_*.ply"))
    assert len(frames) == 5
    codes = np.load(tmp / "interp" / "codes.npy")
    from bareesa.mesh import load_mesh
    first, last = load_mesh(frames[0])[0], load_mesh(frames[-1])[0]
    assert np.abs(first - v).max() < 1e-8
    # the end code is the ridge-regularised projection (bareesa.latent.PROJECTION_RIDGE): close, not exact
    assert np.abs(last - load_mesh(end)[0]).max() < 5e-3 * np.ptp(v, axis=0).max()
    # --no-anchor writes the geodesic as solved: same ends (this basis spans no translation, so
    # anchoring changes nothing either way)
    rc, text, err = run(capsys, "interpolate", tmp / "template.ply", end, "--basis", out, "--steps", "5",
                        "--no-anchor", "-o", tmp / "free")
    assert rc == 0, err
    assert np.allclose(np.load(tmp / "free" / "codes.npy"), codes, atol=1e-6)
    assert np.allclose(codes[-1], project_to_basis(basis, load_mesh(end)[0])[0])


def test_build_basis_fits_the_motion_metric_by_default_when_a_group_has_two_sequences(capsys, sequences):
    from bareesa.basis_io import load_basis

    tmp, v, f, seqs = sequences
    two = ["--sequence", "pose:" + ",".join(map(str, seqs["bend"])),
           "--sequence", "pose:" + ",".join(map(str, seqs["twist"]))]
    rc, text, err = run(capsys, "build-basis", tmp / "template.ply", *two, "-o", tmp / "fit.npz")
    assert rc == 0, err
    basis = load_basis(tmp / "fit.npz")
    fit = basis.provenance["metric_fit"]
    assert set(fit["held_out_frame_error"]) == {"fit", "body", "face"}
    assert min(fit["held_out_frame_error"], key=fit["held_out_frame_error"].get) == fit["chosen"]
    assert list(basis.weights.as_tuple()) == fit["weights"] and basis.shape_metric == h2_metric.PRESETS["body"]
    assert f"({fit['chosen']}; held-out frame error" in text
    # one sequence per group: nothing to hold out, the paper's weights
    rc, text, err = run(capsys, "build-basis", tmp / "template.ply", two[0], two[1], "-o", tmp / "one.npz")
    assert rc == 0, err
    one = load_basis(tmp / "one.npz")
    assert one.weights == h2_metric.PRESETS["body"] and "metric_fit" not in one.provenance
    # asking for a fit that cannot be made says why, and writes nothing
    rc, _, err = run(capsys, "build-basis", tmp / "template.ply", two[0], two[1], "--metric", "fit",
                     "-o", tmp / "none.npz")
    assert rc == 2 and "needs at least two training sequences" in err and not (tmp / "none.npz").exists()


def test_build_basis_rejects_unregistered_frames(capsys, sequences, tmp_path):
    tmp, v, f, seqs = sequences
    s, sf = synthetic.blob_mesh(1)
    save_mesh(tmp / "raw.ply", s, sf)
    rc, _, err = run(capsys, "build-basis", tmp / "template.ply", "--sequence",
                     f"pose:{seqs['bend'][0]},{tmp / 'raw.ply'}", "-o", tmp / "x.npz")
    assert rc == 2 and "not in the template's topology" in err
    assert not (tmp / "x.npz").exists()
    rc, _, err = run(capsys, "build-basis", tmp / "template.ply", "--sequence", "pose", "-o", tmp / "x.npz")
    assert rc == 2 and "GROUP:F1,F2" in err


@pytest.fixture
def built(capsys, sequences):
    tmp, v, f, seqs = sequences
    out = tmp / "b.npz"
    rc, _, err = run(capsys, "build-basis", tmp / "template.ply",
                     "--sequence", "pose:" + ",".join(map(str, seqs["bend"])),
                     "--sequence", "shape:" + ",".join(map(str, seqs["twist"])), "--metric", "face", "-o", out)
    assert rc == 0, err
    return tmp, out, seqs


def test_build_basis_stores_distribution_and_sample_is_reproducible(capsys, built):
    from bareesa.basis_io import load_basis
    from bareesa.mesh import load_mesh

    tmp, out, _ = built
    basis = load_basis(out)
    assert {"gmm_pose_weights", "gmm_shape_means"} <= set(basis.extras)
    results = []
    for name in ("s1", "s2"):
        rc, _, err = run(capsys, "sample", "--basis", out, "-n", "2", "--seed", "4", "-o", tmp / name)
        assert rc == 0, err
        results.append(np.load(tmp / name / "codes.npy"))
        assert len(list((tmp / name).glob("sample_*.ply"))) == 2
    assert np.array_equal(results[0], results[1]) and np.abs(results[0]).max() > 0
    v0 = load_mesh(tmp / "s1" / "sample_0.ply")[0]
    assert np.allclose(v0, basis.template + np.tensordot(results[0][0], basis.fields, 1), atol=1e-9)


def test_extrapolate_and_transfer_on_registered_meshes(capsys, built):
    from bareesa.basis_io import load_basis
    from bareesa.latent import project_to_basis
    from bareesa.mesh import load_mesh

    tmp, out, seqs = built
    basis = load_basis(out)
    rc, text, err = run(capsys, "extrapolate", seqs["bend"][0], seqs["bend"][1], "--basis", out, "--steps", "2",
                        "-o", tmp / "ex", "--json")
    assert rc == 0, err
    codes = np.load(tmp / "ex" / "codes.npy")
    assert codes.shape == (4, basis.n_fields) and json.loads(text)["frames"] == 4
    # the bend sequence is a straight line in the pose group: the continuation follows it closely
    true3 = project_to_basis(basis, load_mesh(seqs["bend"][3])[0])[0]
    assert np.abs(codes[3] - true3).max() < 0.05 * np.abs(true3).max()
    rc, _, err = run(capsys, "transfer", *seqs["bend"][:3], "--identity", seqs["twist"][2], "--basis", out,
                     "-o", tmp / "tr")
    assert rc == 0, err
    moved = np.load(tmp / "tr" / "codes.npy")
    ident = project_to_basis(basis, load_mesh(seqs["twist"][2])[0])[0]
    sl = basis.group_slice("shape")
    assert np.allclose(moved[:, sl], ident[sl])
    for k in range(3):
        pose = project_to_basis(basis, load_mesh(seqs["bend"][k])[0])[0]
        assert np.allclose(moved[k, basis.group_slice("pose")], pose[basis.group_slice("pose")])


def test_an_extrapolation_stopped_at_a_creased_frame_keeps_the_frames_before_it(capsys, built, monkeypatch):
    from bareesa import workflows

    tmp, out, seqs = built
    ends = [seqs["bend"][0], seqs["bend"][1], "--basis", out]
    rc, _, err = run(capsys, "extrapolate", *ends, "--steps", "4", "-o", tmp / "all")
    assert rc == 0, err
    real, seen = workflows.creased, []

    def creased(template, faces, verts, **kwargs):  # the third new frame creases a joint
        seen.append(verts)
        return len(seen) == 3 or real(template, faces, verts, **kwargs)

    monkeypatch.setattr(workflows, "creased", creased)
    rc, _, err = run(capsys, "extrapolate", *ends, "--steps", "4", "-o", tmp / "part")
    assert rc == 2 and "frame 3 of 4" in err and "ask for at most 2 frames" in err
    assert f"the inputs and the 2 frames before it are written to {tmp / 'part'}" in err
    assert np.allclose(np.load(tmp / "part" / "codes.npy"), np.load(tmp / "all" / "codes.npy")[:4], atol=1e-9)
    written = sorted(p.name for p in (tmp / "part").glob("*.ply"))
    assert len(written) == 4 and written == sorted(p.name for p in (tmp / "all").glob("*.ply"))[:4]
    # a first frame already refused leaves nothing to keep: no folder is written
    seen.clear()
    monkeypatch.setattr(workflows, "creased", lambda *a, **k: True)
    rc, _, err = run(capsys, "extrapolate", *ends, "--steps", "4", "-o", tmp / "none")
    assert rc == 2 and "frame 1 of 4" in err and "start from closer inputs" in err and not (tmp / "none").exists()


def test_extrapolate_from_two_scans_says_whether_the_second_was_registered_in_the_firsts_frame(capsys, built,
                                                                                               monkeypatch):
    from bareesa import workflows

    tmp, out, seqs = built
    real = workflows.extrapolate

    for same in (True, False):
        def two_scans(*args, same=same, **kwargs):  # (the bend frames stand for two scans of one capture)
            return dataclasses.replace(real(*args, **kwargs), same_frame=same)

        monkeypatch.setattr(cli, "extrapolate", two_scans)
        rc, text, err = run(capsys, "extrapolate", seqs["bend"][0], seqs["bend"][1], "--basis", out, "--steps", "1",
                            "-o", tmp / f"frame{same}")
        assert rc == 0, err
        line = next(t for t in text.splitlines() if "second scan in the first's frame" in t)
        said = " ".join(line.split("frame", 1)[1].split())
        assert said == ("yes" if same else "no (fitted there it was far from the scan: registered apart)")
        rc, text, err = run(capsys, "extrapolate", seqs["bend"][0], seqs["bend"][1], "--basis", out, "--steps", "1",
                            "-o", tmp / f"json{same}", "--json")
        assert rc == 0 and json.loads(text)["same_frame"] is same
    monkeypatch.setattr(cli, "extrapolate", real)
    rc, text, err = run(capsys, "extrapolate", seqs["bend"][0], seqs["bend"][1], "--basis", out, "--steps", "1",
                        "-o", tmp / "meshes", "--json")
    assert rc == 0 and "same_frame" not in json.loads(text)  # (meshes of the template: no registration)


def test_interpolate_and_extrapolate_keep_the_inputs_off_basis_detail(capsys, built):
    from bareesa.basis_io import load_basis
    from bareesa.mesh import load_mesh

    tmp, out, seqs = built
    basis = load_basis(out)
    rng = np.random.default_rng(5)
    inputs = []
    for k in (0, 1):  # registered meshes with detail the basis cannot express (a random bump each)
        v = load_mesh(seqs["bend"][k])[0] + 0.01 * rng.normal(size=basis.template.shape)
        save_mesh(tmp / f"detailed_{k}.ply", v, basis.faces)
        inputs.append(v)

    def frames(folder):
        return np.stack([load_mesh(p)[0] for p in sorted((tmp / folder).glob("frame_*.ply"))])

    def decoded(folder):
        return basis.template + np.tensordot(np.load(tmp / folder / "codes.npy"), basis.fields, axes=1)

    a, b = tmp / "detailed_0.ply", tmp / "detailed_1.ply"
    rc, text, err = run(capsys, "interpolate", a, b, "--basis", out, "--steps", "5", "-o", tmp / "kept", "--json")
    assert rc == 0, err
    res = json.loads(text)
    assert res["detail_kept"] and 0.005 < res["off_basis_rms"] < 0.05
    kept = frames("kept")
    assert np.abs(kept[0] - inputs[0]).max() < 1e-8 and np.abs(kept[-1] - inputs[1]).max() < 1e-8
    gap = kept - decoded("kept")  # the detail, blended linearly from one input's to the other's
    assert np.allclose(gap[2], (gap[0] + gap[-1]) / 2, atol=1e-8)
    rc, text, err = run(capsys, "interpolate", a, b, "--basis", out, "--steps", "5", "--no-detail",
                        "-o", tmp / "bare", "--json")
    assert rc == 0, err
    assert not json.loads(text)["detail_kept"]
    bare = frames("bare")
    assert np.allclose(bare, decoded("bare"), atol=1e-8)
    assert np.abs(bare[-1] - inputs[1]).max() > 0.02  # F(code) alone misses the bump
    rc, text, err = run(capsys, "extrapolate", a, b, "--basis", out, "--steps", "2", "-o", tmp / "ex", "--json")
    assert rc == 0, err
    ex = frames("ex")
    assert len(ex) == 4 and json.loads(text)["detail_kept"]
    assert np.abs(ex[0] - inputs[0]).max() < 1e-8 and np.abs(ex[1] - inputs[1]).max() < 1e-8
    gap = ex - decoded("ex")  # continued linearly, as the straight latent line would be
    assert np.allclose(gap[3], gap[0] + 3 * (gap[1] - gap[0]), atol=1e-8)


def test_interpolate_keeps_the_default_body_planted_unless_no_anchor(capsys, tmp_path):
    """Rest -> the pose prototype whose feet are highest (a jump, feet ~18 cm up) on the bundled basis: the
    CLI's frames lift the lowest point steadily between the ends' heights; --no-anchor writes the
    geodesic as solved, whose body sits a few millimetres off that line mid-jump (the H2 metric's L2 term
    keeps the centroid still; ``geodesics.anchor_path`` puts the body back where the line has it)."""
    from bareesa.geodesics import decode_path
    from bareesa.basis_io import DEFAULT_BASIS, load_basis
    from bareesa.mesh import load_mesh

    b = load_basis(DEFAULT_BASIS)  # what the CLI uses without --basis
    t, _, h = b.tensors()
    bodies = decode_path(t, h, b.extras["pose_prototypes"])
    up = bodies[np.argmax(bodies[:, :, 2].min(1))]  # the lowest point highest: feet off the ground
    save_mesh(tmp_path / "rest.ply", b.template, b.faces)
    save_mesh(tmp_path / "up.ply", up, b.faces)
    ends = np.array([b.template[:, 2].min(), up[:, 2].min()])
    lowest = {}
    for name, extra in (("planted", []), ("free", ["--no-anchor"])):
        rc, _, err = run(capsys, "interpolate", tmp_path / "rest.ply", tmp_path / "up.ply", "--steps", "5",
                         "-o", tmp_path / name, *extra)
        assert rc == 0, err
        frames = np.stack([load_mesh(p)[0] for p in sorted((tmp_path / name).glob("frame_*.ply"))])
        lowest[name] = frames[:, :, 2].min(1)
    assert np.all(np.diff(lowest["planted"]) > 0)  # lifts steadily, within the ends' heights
    assert lowest["planted"].max() <= ends.max() + 1e-4 and lowest["planted"].min() >= ends.min() - 1e-4
    assert np.abs(lowest["free"] - lowest["planted"]).max() > 0.001  # ~2 mm with the basis' motion weights


def test_simulate_scan_writes_a_differently_meshed_scan(capsys, meshes, tmp_path):
    from bareesa.mesh import load_mesh

    paths, (v, w, f, s, sf) = meshes
    rc, out, err = run(capsys, "simulate-scan", paths["a"], "-o", tmp_path / "scan.ply", "--seed", "2", "--json")
    assert rc == 0, err
    sv, sfaces = load_mesh(tmp_path / "scan.ply")
    assert json.loads(out)["faces"] == len(sfaces)
    assert len(sv) != len(v) or not np.allclose(sv, v)
    rc2, _, _ = run(capsys, "simulate-scan", paths["a"], "-o", tmp_path / "scan2.ply", "--seed", "2")
    assert rc2 == 0 and np.array_equal(load_mesh(tmp_path / "scan2.ply")[0], sv)  # seeded


def test_register_command_writes_registered_mesh_and_json(capsys, tmp_path):
    from bareesa.basis_io import save_basis
    from bareesa.mesh import load_mesh

    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    save_basis(tmp_path / "s.npz", basis)
    alpha = 0.5 * np.random.default_rng(4).normal(size=6)
    u, faces = synthetic.resampled_sphere(2, seed=5)
    rot = synthetic.random_rotation(2)
    save_mesh(tmp_path / "scan.ply", 1.5 * surface(u, alpha) @ rot.T, faces)
    (tmp_path / "lm.csv").write_text("# vertex, x, y, z\n")
    rc, out, err = run(capsys, "register", tmp_path / "scan.ply", "--basis", tmp_path / "s.npz",
                       "-o", tmp_path / "reg.ply", "--landmarks", tmp_path / "lm.csv", "--json")
    assert rc == 0, err
    res = json.loads(out)
    assert set(res) >= {"code", "varifold", "chamfer", "seconds", "levels"}
    assert np.abs(np.array(res["code"]) - alpha).max() < 0.05
    reg, reg_faces = load_mesh(tmp_path / "reg.ply")
    truth = 1.5 * surface(synthetic.icosphere(2)[0], alpha) @ rot.T
    assert np.array_equal(reg_faces, basis.faces)
    assert np.abs(reg - truth).max() < 0.05 * np.abs(truth).max()
    (tmp_path / "bad.csv").write_text("1, 2, 3\n")
    rc, _, err = run(capsys, "register", tmp_path / "scan.ply", "--basis", tmp_path / "s.npz",
                     "-o", tmp_path / "r2.ply", "--landmarks", tmp_path / "bad.csv")
    assert rc == 2 and "landmark 1" in err and not (tmp_path / "r2.ply").exists()
    assert [lv["kernel"] for lv in res["levels"]] == ["binet", "binet"] and res["normal_spread"] < 0.05
    rc, out, err = run(capsys, "register", tmp_path / "scan.ply", "--basis", tmp_path / "s.npz",
                       "-o", tmp_path / "r3.ply", "--kernel", "linear", "--json")
    assert rc == 0, err
    linear = json.loads(out)
    assert [lv["kernel"] for lv in linear["levels"]] == ["linear", "linear"]
    assert np.abs(np.array(linear["code"]) - alpha).max() < 0.1


def test_demo_registers_two_simulated_scans_and_writes_an_evenly_paced_geodesic(capsys, tmp_path):
    import re

    from bareesa.latent import Level

    from bareesa.basis_io import save_basis
    from bareesa.mesh import load_mesh

    basis, _ = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    basis.schedule = (Level(0.15, 1e3, 2, 40),)
    save_basis(tmp_path / "s.npz", basis)
    rc, out, err = run(capsys, "demo", "--basis", tmp_path / "s.npz", "--steps", "4", "-o", tmp_path / "demo")
    assert rc == 0, err
    for name in ("scan_A", "scan_B"):
        scan_v, scan_f = load_mesh(tmp_path / "demo" / f"{name}.ply")
        reg_v, reg_f = load_mesh(tmp_path / "demo" / f"{name}_registered.ply")
        assert np.array_equal(reg_f, basis.faces) and not np.array_equal(scan_f.shape, basis.faces.shape)
        assert chamfer(reg_v, scan_v) < 0.1 * np.ptp(scan_v, axis=0).max()  # overlays the scan (which has holes)
    errors = [float(e) for e in re.findall(r"vertex error ([0-9.e+-]+)", out)]
    assert len(errors) == 2 and max(errors) < 0.1  # unit sphere, one coarse level: under 10 % of the radius
    frames = sorted((tmp_path / "demo" / "geodesic").glob("frame_*.ply"))
    assert len(frames) == 4 and np.load(tmp_path / "demo" / "geodesic" / "codes.npy").shape == (4, 6)
    rc, _, err = run(capsys, "demo", "--basis", tmp_path / "s.npz", "--steps", "1", "-o", tmp_path / "d2")
    assert rc == 2 and "--steps" in err and not (tmp_path / "d2").exists()


def test_extrapolate_that_cannot_be_shot_names_the_frame_and_keeps_only_the_frames_before_it(capsys, built):
    import re

    from bareesa.mesh import load_mesh

    tmp, out, seqs = built
    v0, f = load_mesh(seqs["bend"][0])
    far = tmp / "far.ply"  # a step 40x the bend's: the decoded meshes fold over within a few frames
    save_mesh(far, v0 + 40 * (load_mesh(seqs["bend"][1])[0] - v0), f)
    rc, _, err = run(capsys, "extrapolate", seqs["bend"][0], far, "--basis", out, "--steps", "6",
                     "-o", tmp / "refused")
    assert rc == 2 and " of 6: " in err and "frame" in err and len(err.strip().splitlines()) == 1, err
    frame = int(re.search(r"frame (\d+) of 6", err).group(1))
    written = sorted((tmp / "refused").glob("*.ply")) if (tmp / "refused").exists() else []
    # the inputs and the frames before the refused one, or nothing when the first is refused
    assert len(written) == (frame + 1 if frame > 1 else 0), err


@pytest.mark.parametrize("device, message", [("cuda:99", "cuda:99"), ("tpu", "'tpu'")])
def test_solving_verbs_refuse_a_device_torch_does_not_have_and_write_nothing(capsys, built, device, message):
    tmp, out, seqs = built
    a, b = seqs["bend"][0], seqs["bend"][1]
    for argv in (["interpolate", a, b, "--steps", "3", "-o", tmp / "dev"],
                 ["extrapolate", a, b, "--steps", "2", "-o", tmp / "dev"],
                 ["distance", a, b],
                 ["register", a, "-o", tmp / "dev" / "r.ply"],
                 ["register-batch", a, "-o", tmp / "dev"],
                 ["transfer", a, b, "--identity", b, "-o", tmp / "dev"],
                 ["sample", "-n", "1", "-o", tmp / "dev"]):
        rc, _, err = run(capsys, *argv, "--basis", out, "--device", device)
        assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, (argv[0], err)
        assert not (tmp / "dev").exists()


def test_the_device_of_the_command_line_reaches_the_workflows(capsys, built, monkeypatch):
    """--device is checked, then handed to the solver in workflows.Options (a pretend GPU here)."""
    tmp, out, seqs = built
    seen = []
    monkeypatch.setattr(cli, "check_device", lambda device: seen.append(device) or device)

    def path_between(basis, a, b, n_frames, options, **kwargs):
        seen.append(options.device)
        raise cli.InputError("stop here")

    monkeypatch.setattr(cli, "path_between", path_between)
    rc, _, err = run(capsys, "interpolate", *seqs["bend"][:2], "--basis", out, "-o", tmp / "x", "--device", "cuda:3")
    assert rc == 2 and "stop here" in err and seen == ["cuda:3", "cuda:3"]


def _scan_on_a_plate(surface, alpha, seed=5):
    """F(alpha) sampled on a resampled sphere, standing on a square plate 0.05 below it (one mesh):
    -> (verts, faces, number of the sphere's vertices, number of its faces)."""
    u, faces = synthetic.resampled_sphere(2, seed=seed)
    verts = surface(u, alpha)
    g = np.linspace(-2.5, 2.5, 6)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    plate = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, verts[:, 2].min() - 0.05)], 1)
    a = (np.arange(5)[:, None] * 6 + np.arange(5)[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 6, a + 7], 1), np.stack([a, a + 7, a + 1], 1)]) + len(verts)
    return np.concatenate([verts, plate]), np.concatenate([faces, tris]), len(verts), len(faces)


def test_register_ignores_what_its_mask_file_says_and_bad_masks_are_one_line_errors(capsys, tmp_path, monkeypatch):
    from bareesa.basis_io import save_basis

    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    save_basis(tmp_path / "s.npz", basis)
    alpha = 0.5 * np.random.default_rng(4).normal(size=6)
    verts, faces, n_sphere, n_faces = _scan_on_a_plate(surface, alpha)
    save_mesh(tmp_path / "scan.ply", verts, faces)
    ignore = (np.arange(len(verts)) >= n_sphere).astype(float)
    (tmp_path / "mask.txt").write_text("# 1 = the plate\n" + "\n".join(f"{w:g}" for w in ignore))
    seen = []
    real = cli.code_of
    monkeypatch.setattr(cli, "code_of", lambda basis, item, *a, **k: (seen.append(item), real(basis, item, *a, **k))[1])
    rc, out, err = run(capsys, "register", tmp_path / "scan.ply", "--basis", tmp_path / "s.npz",
                       "-o", tmp_path / "reg.ply", "--ignore", tmp_path / "mask.txt", "--json")
    assert rc == 0, err
    weights = seen[0].face_weights
    assert np.all(weights[:n_faces] == 1.0) and np.all(weights[n_faces:] == 0.0)
    assert np.abs(np.array(json.loads(out)["code"]) - alpha).max() < 0.05
    np.save(tmp_path / "short.npy", ignore[:-1])
    np.save(tmp_path / "all.npy", np.ones(len(verts)))
    (tmp_path / "range.txt").write_text(" ".join(["2"] * len(verts)))
    for mask, message in (("short.npy", f"expected {len(verts)} numbers"), ("all.npy", "ignores every face"),
                          ("range.txt", "between 0 (keep) and 1 (ignore)"), ("none.txt", "does not exist")):
        rc, out, err = run(capsys, "register", tmp_path / "scan.ply", "--basis", tmp_path / "s.npz",
                           "-o", tmp_path / "bad.ply", "--ignore", tmp_path / mask)
        assert rc == 2 and message in err and mask in err, (mask, err)
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "bad.ply").exists()


def test_pair_verbs_give_each_raw_scan_its_own_mask_and_landmarks(capsys, tmp_path, monkeypatch):
    from types import SimpleNamespace

    from bareesa.basis_io import save_basis

    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    save_basis(tmp_path / "s.npz", basis)
    verts, faces, n_sphere, n_faces = _scan_on_a_plate(surface, np.zeros(6))
    save_mesh(tmp_path / "a.ply", verts, faces)
    save_mesh(tmp_path / "b.ply", verts[:n_sphere] + 0.1, faces[:n_faces])
    save_mesh(tmp_path / "t.ply", basis.template, basis.faces)
    np.save(tmp_path / "mask.npy", (np.arange(len(verts)) >= n_sphere).astype(float))
    (tmp_path / "lm.csv").write_text(f"3, {', '.join(f'{x:g}' for x in verts[7])}\n")
    seen = []
    monkeypatch.setattr(cli, "geodesic_between", lambda basis, a, b, *args, **kw: (seen.append((a, b)),
                                                                                    SimpleNamespace(distance=1.0))[1])
    rc, out, err = run(capsys, "distance", tmp_path / "a.ply", tmp_path / "b.ply", "--basis", tmp_path / "s.npz",
                       "--ignore-a", tmp_path / "mask.npy", "--landmarks-b", tmp_path / "lm.csv", "--json")
    assert rc == 0, err
    a, b = seen[0]
    assert np.all(a.face_weights[:n_faces] == 1.0) and np.all(a.face_weights[n_faces:] == 0.0) and a.landmarks is None
    assert b.face_weights is None and b.landmarks[0][0] == 3 and np.allclose(b.landmarks[0][1], verts[7])
    # a mesh in the template's topology is projected, not registered: a mask for it is refused
    rc, _, err = run(capsys, "interpolate", tmp_path / "t.ply", tmp_path / "b.ply", "--basis", tmp_path / "s.npz",
                     "--ignore-a", tmp_path / "mask.npy", "-o", tmp_path / "frames")
    assert rc == 2 and "--ignore-a applies to raw scans only" in err and not (tmp_path / "frames").exists()


def test_register_writes_the_detailed_mesh_the_basis_fit_beside_it_and_no_detail_on_request(capsys, tmp_path):
    from bareesa.basis_io import save_basis
    from bareesa.mesh import load_mesh

    basis, surface = synthetic.smooth_sphere_basis(subdivisions=3, n_fields=6, seed=0)
    save_basis(tmp_path / "s.npz", basis)
    alpha = 0.5 * np.random.default_rng(1).normal(size=6)
    u, faces = synthetic.resampled_sphere(4, seed=3)
    bump = 0.06 * np.exp(-((u - np.array([0.0, 0.6, 0.8])) ** 2).sum(1) / 0.15)[:, None] * u
    save_mesh(tmp_path / "scan.ply", surface(u, alpha) + bump, faces)
    sphere_detail = ["--set", "detail.sigmas=[0.05]", "--set", "detail.weights=[1000]"]
    rc, out, err = run(capsys, "register", tmp_path / "scan.ply", "--basis", tmp_path / "s.npz", "-o",
                       tmp_path / "reg.ply", "--json", *sphere_detail)
    assert rc == 0, err
    res = json.loads(out)
    assert res["detail"]["kept"] and res["detail"]["chamfer"] < res["chamfer"]
    detailed, detailed_faces = load_mesh(tmp_path / "reg.ply")
    fit, _ = load_mesh(tmp_path / "reg.basis.ply")
    detail = np.load(tmp_path / "reg.detail.npy")
    assert np.array_equal(detailed_faces, basis.faces) and detail.shape == basis.template.shape
    assert np.abs(detailed - fit).max() > 0.02  # the bump, which only the detailed mesh has
    rc, out, err = run(capsys, "register", tmp_path / "scan.ply", "--basis", tmp_path / "s.npz", "-o",
                       tmp_path / "plain.ply", "--no-detail", *sphere_detail)
    assert rc == 0, err
    assert (tmp_path / "plain.ply").exists() and not (tmp_path / "plain.basis.ply").exists()
    assert not (tmp_path / "plain.detail.npy").exists() and "detailed" not in out
