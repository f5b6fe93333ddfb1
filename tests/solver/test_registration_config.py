"""RegistrationConfig: every registration setting in one frozen object, defaulted from the basis card and
overridden in one place (API keywords, dotted keys, the CLI's --config / --set, the add-on's panel)."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from bareesa import basis_io, cli, registration, synthetic, workflows
from bareesa.errors import InputError
from bareesa.registration import RegistrationConfig
from bareesa.registration.config import parse_settings


@pytest.fixture(scope="module")
def basis():
    return synthetic.smooth_sphere_basis(subdivisions=2, n_fields=4, seed=0)[0]


def test_a_config_from_the_basis_carries_its_schedule_and_the_cards_overrides(basis):
    card = dataclasses.replace(basis, registration={"retry": False, "poses": {"finalists": 3}})
    config = RegistrationConfig.from_basis(card)
    assert config.schedule == tuple(basis.schedule)
    assert config.retry is False and config.poses.finalists == 3
    assert config.poses.tie == registration.PoseSearch().tie  # the rest keeps its defaults
    later = RegistrationConfig.from_basis(card, {"poses.finalists": 1}, retry=True)  # the caller's win
    assert later.poses.finalists == 1 and later.retry is True


def test_dotted_and_nested_overrides_agree_and_the_original_is_unchanged():
    base = RegistrationConfig()
    a = base.with_overrides({"poses.finalists": 4, "solve.memory": 20})
    b = base.with_overrides(poses={"finalists": 4}, solve={"memory": 20})
    assert a.to_dict() == b.to_dict()
    assert base.poses.finalists == registration.PoseSearch().finalists and base.solve.memory == 100
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.retry = False


@pytest.mark.parametrize("key, value, message", [
    ("poses.finalist", 3, "unknown registration setting 'poses.finalist'"),
    ("nonsense", 1, "unknown registration setting 'nonsense'"),
    ("nowhere.x", 1, "unknown registration setting section 'nowhere'"),
    ("retry", "maybe", "retry: expected true or false"),
    ("poses.finalists", 2.5, "expected a whole number"),
    ("solve.memory", "many", "expected a number"),
    ("dtype", "float16", "a dtype is one of"),
    ("binning", "sometimes", "binning must be"),
    ("landmark_weight", -1.0, "landmark_weight must be"),
    ("schedule", [], "the registration schedule is empty"),
])
def test_a_bad_setting_is_refused_in_one_line_naming_it(key, value, message):
    with pytest.raises(InputError, match=message) as err:
        RegistrationConfig().with_overrides({key: value})
    assert "\n" not in str(err.value)


def test_settings_given_as_text_are_parsed_like_json():
    config = RegistrationConfig().with_overrides(parse_settings(
        "retry=false; poses.finalists=3\nsolve.plateau=1e-4; dtype=float32; poses.candidates=null; kernel=linear"))
    assert config.retry is False and config.poses.finalists == 3 and config.solve.plateau == 1e-4
    assert config.dtype is torch.float32 and config.poses.candidates is None and config.kernel == "linear"
    with pytest.raises(InputError, match="expected KEY=VALUE"):
        parse_settings("retry")


def test_to_dict_is_json_and_from_dict_gives_the_same_settings(basis):
    config = RegistrationConfig.from_basis(basis, {"dtype": "float32", "poses.skip": float("inf"),
                                                   "metric": "body", "kernel": ("binet", "linear")})
    text = config.describe()
    again = RegistrationConfig.from_dict(json.loads(text))
    assert again.to_dict() == config.to_dict() and again.dtype is torch.float32
    assert again.schedule == config.schedule and again.kernel == ("binet", "linear")


def test_register_keywords_override_the_config_and_unknown_ones_are_refused(basis):
    code = np.array([0.6, -0.5, 0.4, 0.5])
    scan = basis.template + np.tensordot(code, basis.fields, axes=1)
    seen = []
    config = RegistrationConfig.from_basis(basis, prealign=False, backend="dense", retry=False)
    res = registration.register(basis, scan, basis.faces, config, callback=lambda e: seen.append(e.message),
                                **{"solve.preview_every": 7})
    assert np.abs(res.code - code).max() < 0.1
    assert not any("pre-aligning" in m for m in seen)  # the config's prealign=False reached the solve
    with pytest.raises(InputError, match="unknown registration setting 'no_such'"):
        registration.register(basis, scan, basis.faces, no_such=1)


def test_a_level_solve_reads_its_stops_from_the_config(basis, monkeypatch):
    from bareesa.registration import problem as level_problem

    seen = []
    real = level_problem.minimize_lbfgs
    monkeypatch.setattr(level_problem, "minimize_lbfgs",
                        lambda *a, **k: (seen.append((k["ftol"], k["plateau"], k["memory"])), real(*a, **k))[1])
    code = np.array([0.3, -0.2, 0.1, 0.2])
    scan = basis.template + np.tensordot(code, basis.fields, axes=1)
    registration.register(basis, scan, basis.faces, prealign=False, backend="dense", retry=False,
                          **{"solve.ftol": 1e-7, "solve.plateau_window": 3, "solve.plateau": 2e-3, "solve.memory": 7})
    assert seen and all(s == (1e-7, (3, lv_plateau), 7) for s, lv_plateau in
                        zip(seen, [lv.plateau or 2e-3 for lv in basis.schedule]))


def test_the_card_keeps_registration_overrides_through_save_and_load(basis, tmp_path):
    own = dataclasses.replace(basis, registration={"poses": {"finalists": 1}})
    basis_io.save_basis(tmp_path / "own.npz", own)
    loaded = basis_io.load_basis(tmp_path / "own.npz")
    assert loaded.registration == {"poses": {"finalists": 1}}
    assert RegistrationConfig.from_basis(loaded).poses.finalists == 1
    assert json.loads((tmp_path / "own.json").read_text())["registration"] == {"poses": {"finalists": 1}}


def test_workflow_options_build_the_config_with_their_fields_and_overrides(basis):
    options = workflows.Options(prealign=False, kernel="linear", dtype=torch.float32,
                                registration={"retry": False, "poses.realign": 2})
    config = options.registration_config(basis)
    assert (config.prealign, config.kernel, config.dtype, config.retry, config.poses.realign) == (
        False, "linear", torch.float32, False, 2)
    assert config.schedule == tuple(basis.schedule)


def test_cli_show_config_prints_the_merged_settings_and_refuses_bad_ones(tmp_path, capsys):
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps({"retry": False, "poses": {"finalists": 3}}))
    code = cli.main(["register", "scan.ply", "--basis", "deformables", "--show-config", "--config", str(settings),
                     "--set", "poses.finalists=1", "--set", "solve.memory=30"])
    shown = json.loads(capsys.readouterr().out)
    assert code in (None, 0)
    assert shown["retry"] is False and shown["poses"]["finalists"] == 1 and shown["solve"]["memory"] == 30
    assert len(shown["schedule"]) == len(basis_io.load_basis("deformables").schedule)
    assert cli.main(["register", "scan.ply", "--basis", "deformables", "--show-config", "--set", "poses.x=1"]) == 2
    assert "unknown registration setting 'poses.x'" in capsys.readouterr().err
    settings.write_text("{not json")
    assert cli.main(["register", "scan.ply", "--basis", "deformables", "--show-config", "--config",
                     str(settings)]) == 2
    assert "not JSON" in capsys.readouterr().err
    assert cli.main(["register", "scan.ply", "--basis", "deformables"]) == 2
    assert "-o/--output is required" in capsys.readouterr().err
