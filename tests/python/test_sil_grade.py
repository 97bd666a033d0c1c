"""The road's grade in the SIL and a grade-aware controller (issue 34 item 1: grade as a profile along the track;
docs/sil.md "Road grade").

`ddyn.model.road_grade.graded` gives a track hills (Track.grade, the world's); the plant drives them (plant.json
road_grade: -g sin(grade) on dvx at the car's track position); the controller is told (`--controller-grade`,
controller.json control.grade, the raceline's grade column) or, from a diagnosis's grade or grade_profile
(`--effects-from D`), given the diagnosed one; the controller's configuration check refuses a grade column it was
not told of, one beyond 20 degrees, and a grade its recorded effects do not give. Synthetic diagnosis files; the
drive is in process on emulated time (deterministic)."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from ddyn.cli import main
from ddyn.errors import DdynError
from ddyn.gap.candidates import profile_at
from ddyn.model.road_grade import grade_at, graded
from ddyn.model.track_files import open_track
from ddyn.model.vehicle import load as load_vehicle
from ddyn.sil import run as sil
from ddyn.sil.effects import controller_effects, grade_column


@pytest.fixture(scope="module")
def orca():
    return load_vehicle("orca_1_43")


@pytest.fixture(scope="module")
def hills(orca):
    return graded(open_track("ethzMobil", orca.name), 0.05)


@pytest.fixture(scope="module")
def table(hills):
    """A raceline of the graded track: its centre line at 2 m/s, 0.1 m of room either side."""
    c = np.asarray(hills.center)
    return np.column_stack([c, np.full(len(c), 2.0), np.full(len(c), 0.1), np.full(len(c), 0.1)])


def _diagnosis(folder, effects):
    folder.mkdir(parents=True, exist_ok=True)
    d = {"schema": 1, "selected": [e["effect"] for e in effects], "model": {"effects": effects}, "candidates": []}
    (folder / "diagnosis.json").write_text(json.dumps(d))
    return folder


def _grade_profile(track, scale=0.9):
    """A fitted grade profile as `ddyn gap diagnose` reports one: 16 knots along the lap, the true grade there
    times `scale`."""
    knots = np.linspace(0.0, track.length, 16, endpoint=False)
    angle = scale * np.asarray(grade_at(track, knots))
    prof = {"knots_m": knots.tolist(), "angle_rad": angle.tolist(), "periodic_length_m": float(track.length),
            "position_from": f"track {track.name}, knots every {track.length / 16:.3g} m"}
    return {"effect": "grade_profile", "params": {"peak": float(max(angle, key=abs))}, "profile": prof}


def _check(bins, path, cfg):
    path.write_text(json.dumps(cfg))
    return subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True,
                          timeout=30)


def test_a_graded_track_climbs_as_much_as_it_descends_and_bad_amplitudes_are_refused(orca, hills):
    g = np.asarray(hills.grade)
    assert len(g) == len(hills.center) and 0.049 < np.max(g) <= 0.05 and -0.05 <= np.min(g) < -0.049
    # the height gained over a lap: the integral of sin(grade) ds, ~0 for a closed road
    ds = np.diff(np.r_[hills.s, hills.length])
    assert abs(np.sum(np.sin(g) * ds)) < 1e-3 * hills.length * 0.05
    assert hills.name == "ethzMobil" and getattr(open_track("ethzMobil", orca.name), "grade", None) is None
    for bad in (0.0, -0.1, 0.5, float("nan")):
        with pytest.raises(DdynError, match="road grade: amplitude"):
            graded(hills, bad)


def test_the_plant_and_the_raceline_carry_the_grade_only_when_told(orca, hills, table):
    plain = sil.controller_config(sil.SilSpec.true_car(orca, hills), "/out", table=table)
    assert "grade" not in plain["control"]
    cfg = sil.controller_config(sil.SilSpec.true_car(orca, hills, controller_grade=True), "/out", table=table)
    assert cfg["control"]["grade"] is True
    col = sil.raceline_grade(hills, table)
    s, _ = hills.project(table[:, 0], table[:, 1])
    assert np.allclose(col, grade_at(hills, s))
    rows = sil.raceline_csv(table, None, col).splitlines()
    assert rows[0].endswith(",grade") and len(rows[1].split(",")) == 6
    both = sil.raceline_csv(table, np.zeros(len(table)), col).splitlines()
    assert both[0].endswith(",bank,grade") and len(both[1].split(",")) == 7
    plant = sil.plant_config(sil.SilSpec.true_car(orca, hills), "/tracks", "/out", table)
    assert np.allclose(plant["road_grade"], hills.grade)
    level = sil.plant_config(sil.SilSpec.true_car(orca, hills, road_grade=False), "/tracks", "/out", table)
    assert "road_grade" not in level
    with pytest.raises(DdynError, match="control.grade.*has no grade profile"):
        sil.raceline_grade(open_track("ethzMobil", orca.name), table)


def test_the_controller_reads_the_grade_column_and_refuses_a_bad_one(tmp_path, orca, hills, table, sil_bins):
    cfg = sil.controller_config(sil.SilSpec.true_car(orca, hills, controller_grade=True), str(tmp_path),
                                table=table)
    col = sil.raceline_grade(hills, table)
    (tmp_path / "raceline.csv").write_text(sil.raceline_csv(table, None, col))
    ok = _check(sil_bins, tmp_path / "controller.json", cfg)
    assert ok.returncode == 0, ok.stderr
    # told, but the raceline has no grade column; a grade beyond 20 degrees; a 7th column after a bank untold
    (tmp_path / "level.csv").write_text(sil.raceline_csv(table))
    cases = [("level.csv", dict(cfg["control"]), "no finite 6th column (the grade"),
             ("steep.csv", dict(cfg["control"]), "grade 0.4 rad, beyond +-0.3491 rad (20 degrees)"),
             ("both.csv", dict(cfg["control"], grade=False, bank=True), "control.grade: false, but")]
    (tmp_path / "steep.csv").write_text(sil.raceline_csv(table, None, np.full(len(table), 0.4)))
    (tmp_path / "both.csv").write_text(sil.raceline_csv(table, np.zeros(len(table)), col))
    for name, control, says in cases:
        bad = _check(sil_bins, tmp_path / "controller.json", dict(cfg, raceline=name, control=control))
        assert bad.returncode == 2 and says in bad.stderr, (name, bad.stderr)
        assert len(bad.stderr.strip().splitlines()) == 1


def test_a_diagnosed_grade_becomes_the_grade_column_and_an_edited_one_is_refused(tmp_path, orca, hills, table,
                                                                                  sil_bins):
    fx = controller_effects(_diagnosis(tmp_path / "D", [_grade_profile(hills)]))
    assert fx.applied == ["grade_profile"] and fx.grade["kind"] == "profile"
    assert any(line.startswith("grade_profile: applied as control.grade = true") for line in fx.lines())
    col = grade_column(fx.summary(), hills, table)
    s, _ = hills.project(table[:, 0], table[:, 1])
    assert np.allclose(col, profile_at(fx.grade["profile"], s))
    assert np.max(np.abs(col - 0.9 * grade_at(hills, s))) < 0.01   # the 16 knots' linear profile
    spec = sil.SilSpec.true_car(orca, hills, effects_from=fx.summary())
    path = sil.write_controller_files(spec, table, tmp_path, str(tmp_path))
    cfg = json.loads(path.read_text())
    assert cfg["control"]["grade"] is True and cfg["effects"]["grade"] is True
    assert cfg["effects"]["grade_peak"] == float(np.max(np.abs(col)))
    ok = _check(sil_bins, path, cfg)
    assert ok.returncode == 0, ok.stderr
    (tmp_path / "true.csv").write_text(sil.raceline_csv(table, None, sil.raceline_grade(hills, table)))
    bad = _check(sil_bins, path, dict(cfg, raceline="true.csv"))
    assert bad.returncode == 2 and "effects.grade_peak: " in bad.stderr, bad.stderr
    off = dict(cfg, control=dict(cfg["control"], grade=False), raceline="level.csv")
    (tmp_path / "level.csv").write_text(sil.raceline_csv(table))
    bad = _check(sil_bins, path, off)
    assert bad.returncode == 2 and "effects.grade: true from diagnosis" in bad.stderr, bad.stderr
    with pytest.raises(DdynError, match="--controller-grade with --effects-from D: give one"):
        sil.controller_config(sil.SilSpec.true_car(orca, hills, effects_from=fx.summary(), controller_grade=True),
                              str(tmp_path), table=table)
    # a constant grade: on every row; a pitch channel's gain: named, not applied; beyond 20 degrees: refused
    fx = controller_effects(_diagnosis(tmp_path / "C", [{"effect": "grade", "params": {"angle": 0.02}}]))
    assert np.all(grade_column(fx.summary(), hills, table) == 0.02)
    fx = controller_effects(_diagnosis(tmp_path / "P", [{"effect": "grade_from_pitch", "params": {"gain": 0.8}}]))
    assert fx.grade is None and fx.not_applied[0].startswith("grade_from_pitch: found gain 0.8, not applied")
    with pytest.raises(DdynError, match=r"model.effects.0..params.angle: 0.4 rad, beyond the controller's"):
        controller_effects(_diagnosis(tmp_path / "S", [{"effect": "grade", "params": {"angle": 0.4}}]))


def test_a_diagnosed_delay_beyond_the_runtime_maximum_is_named_not_applied(tmp_path):
    """A false 0.18 s throttle delay (seen on a graded random:302 log) would make the controller refuse the whole
    configuration (6 periods of 20 ms at most): named, not applied."""
    d = _diagnosis(tmp_path / "D", [{"effect": "throttle_delay", "params": {"delay": 0.18}}])
    fx = controller_effects(d, period=0.02)
    assert fx.delays == {} and fx.applied == []
    assert fx.not_applied == ["throttle_delay: found 0.18 s, not applied: beyond the runtime's 6 control periods "
                              "(0.12 s; DDYN_CTRL_MAX_DELAY_STEPS)"]
    assert controller_effects(d).delays == {"throttle": 0.18}   # the period unknown: as estimated


def test_the_grade_aware_controller_laps_the_hills_faster(tmp_path, sil_bins):
    """ETHZMobil with hills of 0.2 rad (11 degrees), the flying line, 4 laps, noise seed 1: told the grade, the
    controller laps clean and faster than the one that does not know it."""
    runs = {}
    for told in (False, True):
        out = tmp_path / f"told_{told}"
        args = ["sil", "run", "--where", "inprocess", "--coeffs", "true", "--line", "flying", "--laps", "4",
                "--road-grade", "0.2", "--out", str(out)] + (["--controller-grade"] if told else [])
        assert main(args) == 0
        runs[told] = json.loads((out / "sil_metrics.json").read_text())
    nominal, aware = runs[False], runs[True]
    assert nominal["road_grade"] and aware["road_grade"] and aware["controller_grade"]
    assert aware["lap_completed"] and aware["violations"] == 0
    lap = {k: float(np.median(m["lap_times"][1:])) for k, m in runs.items()}
    assert lap[True] < 0.99 * lap[False], lap
    assert aware["tracking_error"]["mean"] < nominal["tracking_error"]["mean"]
