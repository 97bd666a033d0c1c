"""A diagnosed bank carried to the controller (issue 34, "From diagnosis to the car"; ddyn.sil.effects,
`ddyn sil run --effects-from D`): a claimed bank_profile becomes raceline.csv's 6th column, the profile at each
row's track position (the diagnosis's own knots and interpolation); a claimed bank_angle the constant on every
row; bank_from_roll is named and not applied (diagnosis.json has no roll along the track); control.bank is true
and controller.json's `effects` records it; the controller refuses the file once control.bank or the bank column
no longer matches the record; bad input is one line naming the file and the key.

Synthetic diagnosis files on the banked oval; the raceline is the centre line (no line to solve): fast."""
from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest

from ddyn.cli import main
from ddyn.errors import DdynError
from ddyn.gap.candidates import curvature_knots, profile_at
from ddyn.model.track_files import open_track
from ddyn.model.track_oval import bank_at
from ddyn.model.vehicle import load as load_vehicle
from ddyn.sil import run as sil
from ddyn.sil.effects import apply_to_config, bank_column, controller_effects


@pytest.fixture(scope="module")
def av21():
    return load_vehicle("av21")


@pytest.fixture(scope="module")
def oval(av21):
    return open_track("oval", av21.name)


@pytest.fixture(scope="module")
def table(oval):
    """A raceline of the oval: every second centre-line point at 20 m/s, the full width."""
    c = np.asarray(oval.center)[::2]
    return np.column_stack([c, np.full(len(c), 20.0), np.full(len(c), 7.0), np.full(len(c), 7.0)])


def _profile(oval, scale=0.9, track="oval", length=None):
    """A fitted bank profile as `ddyn gap diagnose` reports it (ddyn.gap.candidates.summary): the oval's
    curvature knots, the true bank there times `scale`."""
    knots = curvature_knots(oval)
    angle = scale * np.asarray(bank_at(oval, knots))
    return {"knots_m": knots.tolist(), "angle_rad": angle.tolist(), "std_rad": [0.01] * len(knots),
            "free": list(range(len(knots))), "periodic_length_m": float(length or oval.length),
            "position_from": f"track {track}, knots tied to its curvature"}


def _diagnosis(folder, effects):
    """diagnosis.json with these model.effects (effect, params, profile), all selected."""
    folder.mkdir(parents=True, exist_ok=True)
    d = {"schema": 1, "selected": [e["effect"] for e in effects], "model": {"effects": effects}, "candidates": []}
    (folder / "diagnosis.json").write_text(json.dumps(d))
    return folder


def _bank_profile(oval, **kw):
    prof = _profile(oval, **kw)
    peak = max(prof["angle_rad"], key=abs)
    return {"effect": "bank_profile", "params": {"peak": peak}, "profile": prof}


def test_a_bank_profile_is_the_raceline_column_at_the_rows_positions(tmp_path, oval, table):
    fx = controller_effects(_diagnosis(tmp_path / "D", [_bank_profile(oval)]))
    assert fx.applied == ["bank_profile"] and fx.not_applied == [] and fx.bank["track"] == "oval"
    col = bank_column(fx.summary(), oval, table)
    s, _ = oval.project(table[:, 0], table[:, 1])
    assert np.array_equal(col, profile_at(_profile(oval), s))
    # the profile is 0.9 of the track's bank at its knots: so is the column, up to the interpolation between them
    assert abs(np.max(np.abs(col)) - 0.9 * math.radians(20.0)) < 1e-9
    assert fx.lines()[0].startswith("bank_profile: applied as control.bank = true, raceline.csv's bank column the "
                                    "profile at each row's position on track oval")


def test_a_constant_bank_is_the_same_on_every_row(tmp_path, oval, table):
    fx = controller_effects(_diagnosis(tmp_path / "D", [{"effect": "bank_angle", "params": {"angle": 0.12}}]))
    assert fx.applied == ["bank_angle"] and fx.bank["kind"] == "constant"
    assert np.array_equal(bank_column(fx.summary(), oval, table), np.full(len(table), 0.12))
    cfg = apply_to_config({"vehicle": "av21", "control": {"period": 0.04}}, fx, np.full(len(table), 0.12))
    assert cfg["control"]["bank"] is True
    assert cfg["effects"]["bank"] is True and cfg["effects"]["bank_peak"] == 0.12
    assert cfg["effects"]["bank_from"].startswith("bank_angle: the constant 0.12 rad")
    with pytest.raises(DdynError, match="bank_angle: a diagnosed bank is raceline.csv's 6th column"):
        apply_to_config({"vehicle": "av21", "control": {}}, fx)
    # a configuration with a bank of its own and a diagnosis without one: refused, not silently dropped
    none = controller_effects(_diagnosis(tmp_path / "E", []))
    with pytest.raises(DdynError, match="control.bank: true in the configuration, but the diagnosis gives no bank"):
        apply_to_config({"vehicle": "av21", "control": {"bank": True}}, none)


def test_the_roll_channel_and_a_profile_off_the_track_are_named_not_applied(tmp_path, oval):
    roll = controller_effects(_diagnosis(tmp_path / "R", [{"effect": "bank_from_roll", "params": {"gain": 0.8}}]))
    assert roll.bank is None and roll.applied == []
    assert roll.not_applied == ["bank_from_roll: found gain 0.8, not applied: diagnosis.json carries the gain and "
                                "the roll channel's check, not the log's roll along the track, which a bank column "
                                "along the raceline needs"]
    lap = _bank_profile(oval)
    lap["profile"]["position_from"] = "laps from x, y (3 laps of 1228 m)"
    fx = controller_effects(_diagnosis(tmp_path / "L", [lap]))
    assert fx.bank is None and len(fx.not_applied) == 1
    assert fx.not_applied[0].startswith("bank_profile: peak 0.3142 rad, not applied: its positions are 'laps from")


@pytest.mark.parametrize("edit, says", [
    (lambda e: e["profile"].pop("knots_m"), "model.effects[0].profile.knots_m: expected a list of finite numbers"),
    (lambda e: e["profile"]["angle_rad"].pop(), "model.effects[0].profile.angle_rad: expected "),
    (lambda e: e["profile"]["angle_rad"].__setitem__(3, 0.9), "model.effects[0].profile.angle_rad: reaches 0.9 rad"),
    (lambda e: e["profile"]["knots_m"].reverse(), "model.effects[0].profile.knots_m: expected ascending"),
    (lambda e: e["profile"].__setitem__("periodic_length_m", "long"), "model.effects[0].profile.periodic_length_m"),
    (lambda e: e.pop("profile"), "model.effects[0].profile: expected the fitted profile"),
])
def test_a_bad_profile_is_one_line_naming_the_file_and_key(tmp_path, oval, edit, says):
    e = _bank_profile(oval)
    edit(e)
    with pytest.raises(DdynError) as err:
        controller_effects(_diagnosis(tmp_path / "D", [e]))
    assert says in str(err.value) and "diagnosis.json" in str(err.value) and "\n" not in str(err.value)


def test_a_profile_of_another_track_is_refused(tmp_path, oval, table):
    fx = controller_effects(_diagnosis(tmp_path / "D", [_bank_profile(oval, track="ethzMobil")]))
    with pytest.raises(DdynError, match=r"model.effects\[0\].profile.position_from: the profile lies along track "
                                        "'ethzMobil', but the controller drives 'oval'"):
        bank_column(fx.summary(), oval, table)
    fx = controller_effects(_diagnosis(tmp_path / "L", [_bank_profile(oval, length=1300.0)]))
    with pytest.raises(DdynError, match=r"periodic_length_m: 1300 m, but track 'oval' is"):
        bank_column(fx.summary(), oval, table)
    with pytest.raises(DdynError, match="model.effects.0..params.angle: 0.9 rad, beyond"):
        controller_effects(_diagnosis(tmp_path / "A", [{"effect": "bank_angle", "params": {"angle": 0.9}}]))


def _check(bins, path, cfg):
    path.write_text(json.dumps(cfg))
    return subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True,
                          timeout=30)


def test_the_controller_refuses_a_bank_its_effects_do_not_record(tmp_path, av21, oval, table):
    """The SIL's controller.json made from a diagnosed bank profile passes the controller's check; control.bank
    turned off, the raceline's column swapped for the track's true bank, or a bank added to a file made from a
    diagnosis without one: each refused in one line naming the effects key."""
    bins = sil.build_binaries(None)
    fx = controller_effects(_diagnosis(tmp_path / "D", [_bank_profile(oval)]))
    spec = sil.SilSpec.true_car(av21, oval, effects_from=fx.summary())
    path = sil.write_controller_files(spec, table, tmp_path, str(tmp_path))
    cfg = json.loads(path.read_text())
    assert cfg["control"]["bank"] is True and cfg["effects"]["bank"] is True
    col = np.loadtxt(tmp_path / "raceline.csv", delimiter=",", skiprows=1)[:, 5]
    assert np.array_equal(col, bank_column(fx.summary(), oval, table)) and cfg["effects"]["bank_peak"] == np.max(
        np.abs(col))
    ok = _check(bins, path, cfg)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["effects"]["bank"] is True
    off = json.loads(json.dumps(cfg))
    off["control"]["bank"] = False
    (tmp_path / "flat.csv").write_text(sil.raceline_csv(table))
    off["raceline"] = "flat.csv"
    bad = _check(bins, path, off)
    assert bad.returncode == 2 and "effects.bank: true from diagnosis" in bad.stderr, bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1
    (tmp_path / "true.csv").write_text(sil.raceline_csv(table, sil.raceline_bank(oval, table)))
    swapped = dict(cfg, raceline="true.csv")
    bad = _check(bins, path, swapped)
    assert bad.returncode == 2 and "effects.bank_peak: " in bad.stderr and "true.csv's bank column" in bad.stderr
    # a diagnosis without a bank, the track's true bank added: refused in Python and by the controller
    none = controller_effects(_diagnosis(tmp_path / "E", []))
    with pytest.raises(DdynError, match="--controller-bank with --effects-from D: give one"):
        sil.controller_config(sil.SilSpec.true_car(av21, oval, effects_from=none.summary(), controller_bank=True),
                              str(tmp_path), table=table)
    plain = sil.controller_config(sil.SilSpec.true_car(av21, oval, effects_from=none.summary()), str(tmp_path),
                                  table=table)
    assert "bank" not in plain["control"] and "bank" not in plain["effects"]
    plain["control"]["bank"] = True
    plain["raceline"] = "true.csv"
    bad = _check(bins, path, plain)
    assert bad.returncode == 2 and "effects.bank: false from diagnosis" in bad.stderr, bad.stderr


def test_the_command_writes_the_diagnosed_bank(tmp_path, capsys):
    """`ddyn sil run --vehicle av21 --track oval --effects-from D --config-only`: the diagnosed profile in
    raceline.csv, control.bank true, and --controller-bank beside it refused."""
    from ddyn.control import raceline as R
    av21, oval = load_vehicle("av21"), open_track("oval", "av21")
    if R.load_for(av21.name, oval) is None:
        pytest.skip("the AV-21's line of the oval is not computed (tests/python/test_sil_bank.py makes it)")
    d = _diagnosis(tmp_path / "D", [_bank_profile(oval)])
    out = tmp_path / "cfg"
    args = ["sil", "run", "--vehicle", "av21", "--track", "oval", "--effects-from", str(d), "--config-only",
            "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "bank_profile: applied as control.bank = true" in printed and "control.bank True" in printed
    cfg = json.loads((out / "controller.json").read_text())
    assert cfg["control"]["bank"] is True and cfg["effects"]["bank_from"].startswith("bank_profile: the profile")
    rows = np.loadtxt(out / "raceline.csv", delimiter=",", skiprows=1)
    s, _ = oval.project(rows[:, 0], rows[:, 1])
    assert np.allclose(rows[:, 5], profile_at(_profile(oval), s), atol=0, rtol=0)
    assert main(args + ["--controller-bank"]) == 2
    assert "give one" in capsys.readouterr().err
