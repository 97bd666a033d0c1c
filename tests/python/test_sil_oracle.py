"""`ddyn study sil-oracle` (ddyn.sil.oracle): the controller told the true effect, scored as the loop scores its
runs. One small case in process (ETHZMobil, a 40 ms steering delay, noise seed 1); the summary's counting; bad input
is one line."""
from __future__ import annotations

import json

import pytest

from ddyn.cli import main
from ddyn.sil import oracle
from ddyn.sil import run as sil


def test_the_oracle_study_drives_the_told_controller_and_counts(tmp_path, capsys):
    sil.build_binaries(None)
    out = tmp_path / "o"
    assert main(["study", "sil-oracle", "--tracks", "ethzMobil", "--cases", "steer_delay=0.04", "--seeds", "1",
                 "--out", str(out)]) == 0
    doc = json.loads((out / "oracle.json").read_text())
    assert doc["line"] == "flying" and doc["seeds"] == [1] and len(doc["runs"]) == 1
    r = doc["runs"][0]
    # the controller was told the plant's delay: its configuration says so
    cfg = json.loads((out / "seed1" / "ethzMobil" / "steer_delay_0.04" / "controller.json").read_text())
    assert cfg["control"]["delay"]["steering"] == 0.04
    # scored as the loop scores: four laps, the median of the flying ones, against the car without the effect
    assert len(r["oracle"]["lap_times"]) == 4 and r["reference"]["lap_completed"]
    assert r["vs_reference_pct"] == pytest.approx(100.0 * (r["oracle"]["lap_s"] / r["reference"]["lap_s"] - 1.0))
    assert r["clean"] and r["clean_within"] and 0.0 < r["vs_reference_pct"] < 2.0
    assert doc["summary"]["all"] == doc["summary"]["steer_delay"] == {
        "runs": 1, "clean": 1, "clean_within": 1, "worst_vs_reference_pct": r["vs_reference_pct"],
        "best_vs_reference_pct": r["vs_reference_pct"]}
    assert "1 of 1 runs clean and within 2 %" in (out / "oracle.md").read_text()


def test_the_summary_counts_clean_and_within():
    def row(effect, clean, vs):
        return {"effect": effect, "clean": clean, "vs_reference_pct": vs,
                "clean_within": bool(clean and vs is not None and vs <= oracle.WITHIN_PCT)}
    s = oracle.summarise([row("steer_delay", True, 0.5), row("steer_delay", True, 2.5), row("steer_delay", False, None),
                          row("steer_lag", True, -0.2)])
    assert s["steer_delay"] == {"runs": 3, "clean": 2, "clean_within": 1, "worst_vs_reference_pct": 2.5,
                                "best_vs_reference_pct": 0.5}
    assert s["all"]["runs"] == 4 and s["all"]["clean_within"] == 2 and s["all"]["best_vs_reference_pct"] == -0.2


def test_bad_input_is_one_line(tmp_path, capsys):
    assert main(["study", "sil-oracle", "--cases", "yaw_rate_bias=0.01", "--out", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cases yaw_rate_bias: no oracle for it here" in err[0]
    assert main(["study", "sil-oracle", "--seeds", "1,x", "--out", str(tmp_path)]) != 0
    assert "--seeds: expected comma-separated integers" in capsys.readouterr().err


def test_a_told_mass_offset_laps_clean_where_the_nominal_controller_leaves_the_track(tmp_path):
    """random:304, a car 20 % heavier than the model (noise seed 1): the nominal controller leaves the track; told
    the offset (its coefficients scaled, the line's speeds times 1 / sqrt(1.2)) it laps clean, about 9.5 % slower
    than the car without the offset (the heavier car's bound)."""
    sil.build_binaries(None)
    # `ddyn sil run --line flying` makes a random track's flying line when it is not there yet (a fresh clone)
    assert main(["sil", "run", "--where", "inprocess", "--coeffs", "true", "--track", "random:304", "--line", "flying",
                 "--laps", "4", "--effects", "mass_offset=0.2", "--out", str(tmp_path / "nominal")]) == 0
    nominal = json.loads((tmp_path / "nominal" / "sil_metrics.json").read_text())
    assert "mass_offset" not in json.loads((tmp_path / "nominal" / "controller.json").read_text())["control"]
    assert not (nominal["lap_completed"] and nominal["violations"] == 0)
    out = tmp_path / "told"
    assert main(["study", "sil-oracle", "--tracks", "random:304", "--cases", "mass_offset=0.2", "--seeds", "1",
                 "--out", str(out)]) == 0
    r = json.loads((out / "oracle.json").read_text())["runs"][0]
    cfg = json.loads((out / "seed1" / "random_304" / "mass_offset_0.2" / "controller.json").read_text())
    assert cfg["control"]["mass_offset"] == 0.2
    assert r["clean"] and 7.0 < r["vs_reference_pct"] < 11.0


def test_a_told_downforce_laps_clean_where_the_nominal_controller_leaves_the_track(tmp_path):
    """ETHZMobil with downforce in the plant (k = 0.04 s^2/m^2: 1.36 times the tyre load at 3 m/s; noise seed 1):
    the nominal controller, expecting less grip than the car has, leaves the track; told the downforce (every model
    evaluation at the tyre load of its own speed, ddyn_model_downforce) it laps clean and no slower than the car
    without it."""
    sil.build_binaries(None)
    assert main(["sil", "run", "--where", "inprocess", "--coeffs", "true", "--line", "flying", "--laps", "4",
                 "--effects", "downforce=0.04", "--out", str(tmp_path / "nominal")]) == 0
    nominal = json.loads((tmp_path / "nominal" / "sil_metrics.json").read_text())
    assert "downforce" not in json.loads((tmp_path / "nominal" / "controller.json").read_text())["control"]
    assert nominal["plant"]["effects"]["downforce"] == 0.04      # the plant drove it
    assert not (nominal["lap_completed"] and nominal["violations"] == 0)
    out = tmp_path / "told"
    assert main(["study", "sil-oracle", "--tracks", "ethzMobil", "--cases", "downforce=0.04", "--seeds", "1",
                 "--out", str(out)]) == 0
    r = json.loads((out / "oracle.json").read_text())["runs"][0]
    cfg = json.loads((out / "seed1" / "ethzMobil" / "downforce_0.04" / "controller.json").read_text())
    assert cfg["control"]["downforce"] == 0.04
    assert r["clean"] and r["vs_reference_pct"] < 0.0
