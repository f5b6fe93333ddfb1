"""Named landmarks: the bundled bases' (rules on the template), files for the CLI, and what they fix."""

import json
from dataclasses import replace

import numpy as np
import pytest

from bareesa import cli, evaluation, synthetic
from bareesa.basis_io import load_basis, save_basis
from bareesa.errors import InputError
from bareesa.landmarks import read_scan_landmarks, read_template_landmarks, scan_landmarks
from bareesa.latent import Level
from bareesa.mesh import save_mesh
from bareesa.registration import register
from bareesa.registration.prealign import landmark_alignment
from bareesa.scan_simulator import apply_similarity, simulate_scan
from bases.build.landmarks import LANDMARK_RULES

#: What the human basis must name (issue: nose tip, chin, ear lobes, shoulder tips, elbows, wrists,
#: middle fingertips, navel, knees, ankles, heels, big-toe tips).
HUMAN_REQUIRED = {"nose_tip", "chin", "navel"} | {f"{p}_{s}" for s in "lr" for p in (
    "ear_lobe", "shoulder_tip", "elbow", "wrist", "middle_fingertip", "knee", "ankle", "heel", "big_toe_tip")}


@pytest.mark.parametrize("name", sorted(LANDMARK_RULES))
def test_shipped_landmarks_are_the_rules_on_the_shipped_template(name):
    basis = load_basis(name)
    assert basis.landmarks == LANDMARK_RULES[name](basis.template, basis.faces)
    assert "landmarks" in basis.provenance  # documented in the card


def test_human_landmarks_are_all_there_mirrored_and_in_anatomical_order():
    basis = load_basis("human")
    marks = basis.landmarks
    assert HUMAN_REQUIRED <= set(marks)
    p = {k: basis.template[v] for k, v in marks.items()}
    for k in [k for k in marks if k.endswith("_l")]:
        left, right = p[k], p[k[:-2] + "_r"]
        assert left[0] > 0.03 and np.abs(left * [-1, 1, 1] - right).max() < 0.005  # left is +X, right its mirror
    z = {k: v[2] for k, v in p.items()}
    assert z["heel_l"] < z["ankle_l"] < z["knee_l"] < z["navel"] < z["elbow_l"] < z["shoulder_tip_l"] \
        < z["chin"] < z["nose_tip"]
    assert z["middle_fingertip_l"] < z["wrist_l"] < z["elbow_l"]  # arms hang in the rest pose
    assert p["nose_tip"][1] == basis.template[:, 1][basis.template[:, 2] > z["chin"]].min()  # the face's front
    assert p["big_toe_tip_l"][1] < p["ankle_l"][1] < p["heel_l"][1]  # facing -Y
    assert len(set(marks.values())) == len(marks)


def test_landmarks_round_trip_through_a_basis_file_and_bad_ones_are_refused(tmp_path):
    basis, _ = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=2, seed=0)
    marked = replace(basis, landmarks={"north": 3, "tip": 7})
    save_basis(tmp_path / "m.npz", marked)
    assert load_basis(tmp_path / "m.npz").landmarks == {"north": 3, "tip": 7}
    assert json.loads((tmp_path / "m.json").read_text())["landmarks"] == {"north": 3, "tip": 7}
    for bad in ({"x": len(basis.template)}, {"x": -1}, {"": 2}, {"x": 1.5}):
        with pytest.raises(InputError, match="landmark"):
            replace(basis, landmarks=bad)


def test_scan_landmark_files_take_names_or_vertex_indices(tmp_path):
    basis, _ = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=2, seed=0)
    basis = replace(basis, landmarks={"north": 3, "tip": 7})
    (tmp_path / "a.json").write_text(json.dumps({"north": [0, 0, 1], "tip": {"point": [1, 2, 3], "weight": 2}}))
    assert read_scan_landmarks(tmp_path / "a.json", basis) == [(3, (0.0, 0.0, 1.0), 1.0), (7, (1.0, 2.0, 3.0), 2.0)]
    (tmp_path / "a.csv").write_text("# name, x, y, z, weight\nnorth, 0, 0, 1\n5, 1, 1, 1, 0.5\n")
    assert read_scan_landmarks(tmp_path / "a.csv", basis) == [(3, (0.0, 0.0, 1.0), 1.0), (5, (1.0, 1.0, 1.0), 0.5)]
    (tmp_path / "old.json").write_text(json.dumps([[4, [1, 2, 3]], [5, [0, 0, 0], 3]]))
    assert read_scan_landmarks(tmp_path / "old.json", basis) == [(4, (1.0, 2.0, 3.0), 1.0), (5, (0.0, 0.0, 0.0), 3.0)]
    for text, match in (("nose, 0, 0, 1\n", "no landmark 'nose' .*north, tip"), ("north, 0, 0\n", "must be"),
                        ("north, 0, x, 1\n", "3 finite"), ("north, 0, 0, 1, -2\n", "weight"),
                        ("999, 0, 0, 1\n", "template vertex 999")):
        (tmp_path / "b.csv").write_text(text)
        with pytest.raises(InputError, match=match):
            read_scan_landmarks(tmp_path / "b.csv", basis)
    with pytest.raises(InputError, match="does not exist"):
        read_scan_landmarks(tmp_path / "none.csv", basis)
    assert scan_landmarks(basis, {"tip": ((1, 1, 1), 0.5)}) == [(7, (1.0, 1.0, 1.0), 0.5)]


def test_template_landmark_files_for_build_basis(tmp_path):
    (tmp_path / "t.csv").write_text("# name, vertex\nnose, 12\nchin, 3\n")
    assert read_template_landmarks(tmp_path / "t.csv", 20) == {"nose": 12, "chin": 3}
    (tmp_path / "t.json").write_text(json.dumps({"nose": 12}))
    assert read_template_landmarks(tmp_path / "t.json", 20) == {"nose": 12}
    for text in ("nose, 20\n", "nose, 1.5\n", "nose\n"):
        (tmp_path / "bad.csv").write_text(text)
        with pytest.raises(InputError, match="nose"):
            read_template_landmarks(tmp_path / "bad.csv", 20)


def test_landmark_alignment_recovers_a_similarity_and_refuses_collinear_points():
    rng = np.random.default_rng(1)
    template = rng.normal(size=(4, 3))
    rot = synthetic.random_rotation(5)
    scan = 0.4 * template @ rot + [1.0, -2.0, 0.5]
    s = landmark_alignment(template, scan)
    assert np.abs(s.apply(scan) - template).max() < 1e-9
    line = np.outer(np.arange(4.0), [1.0, 2.0, 0.0])
    assert landmark_alignment(line, line + 1) is None and landmark_alignment(template[:2], scan[:2]) is None


def test_three_landmarks_fix_the_capsule_that_registers_upside_down_without_them():
    """The straight capsule turned over fits its surface equally well upside down (its ends swapped):
    without landmarks which way a scan lands is a toss-up decided by rounding (the scan of seed 1 landed
    upside down until the rotations' last digits changed, then right; seeds 2 and 3 land upside down), so
    the control asks only that some land wrong; its three landmarks (two ends, the seam) make every one
    register the right way round."""
    basis = load_basis("deformables")
    truth = basis.template
    schedule = (Level(0.25, 1e1, 1, 20), Level(0.08, 1e4, 1, 20))
    errors = {False: [], True: []}
    for seed in (1, 2, 3):
        sv, sf, info = simulate_scan(truth, basis.faces, seed=seed, holes=0, scale=0.3, resolution=0.08)
        truth_scan = apply_similarity(info, truth)
        rng = np.random.default_rng(0)
        for use in (False, True):
            marks = [(i, truth_scan[i] + rng.normal(scale=0.01 * info["scale"], size=3))  # placed to ~1 % of the length
                     for i in basis.landmarks.values()]
            res = register(basis, sv, sf, landmarks=marks if use else None, schedule=schedule, pose_candidates=None)
            errors[use].append(evaluation.vertex_error(res.vertices, truth_scan)["mean"] / info["scale"] / basis.scale)
    # mean vertex error as a share of the length: the controls land the labels wrong on some scans
    assert max(errors[True]) < 0.02 and max(errors[False]) > 0.1, errors


def test_cli_register_reads_named_landmarks_and_build_basis_stores_a_landmark_file(capsys, tmp_path):
    basis, surface = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=4, seed=0)
    t = basis.template
    save_mesh(tmp_path / "template.ply", t, basis.faces)
    frames = [t + a * basis.fields[0] for a in (0.0, 0.3, 0.6)]
    paths = []
    for k, f in enumerate(frames):
        paths.append(tmp_path / f"f{k}.ply")
        save_mesh(paths[-1], f, basis.faces)
    north, south = int(np.argmax(t[:, 2])), int(np.argmin(t[:, 2]))
    (tmp_path / "marks.csv").write_text(f"north, {north}\nsouth, {south}\n")
    out = tmp_path / "b.npz"
    rc = cli.main(["build-basis", str(tmp_path / "template.ply"), "--sequence", "pose:" + ",".join(map(str, paths)),
                   "--components", "pose=1", "--landmarks", str(tmp_path / "marks.csv"), "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    assert load_basis(out).landmarks == {"north": north, "south": south}
    (tmp_path / "bad.csv").write_text(f"north, {len(t)}\n")
    rc = cli.main(["build-basis", str(tmp_path / "template.ply"), "--sequence", "pose:" + ",".join(map(str, paths)),
                   "--landmarks", str(tmp_path / "bad.csv"), "-o", str(tmp_path / "c.npz")])
    assert rc == 2 and "landmark 'north'" in capsys.readouterr().err and not (tmp_path / "c.npz").exists()
    save_mesh(tmp_path / "scan.ply", frames[2], basis.faces)
    (tmp_path / "scan_marks.json").write_text(json.dumps({"north": frames[2][north].tolist(), "east": [1, 0, 0]}))
    rc = cli.main(["register", str(tmp_path / "scan.ply"), "--basis", str(out), "-o", str(tmp_path / "r.ply"),
                   "--landmarks", str(tmp_path / "scan_marks.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "no landmark 'east'" in err and "north, south" in err and not (tmp_path / "r.ply").exists()


def test_human_parts_cover_the_template_symmetrically_where_the_landmarks_say():
    basis = load_basis("human")
    names = [str(n) for n in basis.extras["part_names"]]
    w = basis.extras["part_weights"]
    assert set(names) == {"head", "body", "hand.L", "hand.R", "foot.L", "foot.R"}
    assert w.shape == (len(names), len(basis.template)) and np.allclose(w.sum(0), 1.0, atol=1e-6)
    t, marks = basis.template, basis.landmarks
    member = {n: w[k] > 0.5 for k, n in enumerate(names)}
    for part, inside, outside in (("head", "nose_tip", "shoulder_tip_l"), ("hand.L", "middle_fingertip_l", "elbow_l"),
                                  ("hand.R", "middle_fingertip_r", "middle_fingertip_l"),
                                  ("foot.L", "big_toe_tip_l", "knee_l"), ("foot.R", "heel_r", "heel_l")):
        assert member[part][marks[inside]] and not member[part][marks[outside]], part
    assert member["body"][marks["navel"]]
    mirror = t * [-1, 1, 1]
    left, right = t[member["hand.L"]], t[member["hand.R"]]
    assert len(left) == len(right) and np.abs(np.sort(mirror[member["hand.L"]], 0) - np.sort(right, 0)).max() < 0.01
    assert t[member["head"], 2].min() > t[marks["shoulder_tip_l"], 2]
