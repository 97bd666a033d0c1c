"""The public Python API (ddyn.api, re-exported lazily as ddyn.<name>) and the scripts in examples/: each example
runs as a newcomer runs it (a subprocess of this venv's Python), and its printed numbers are checked against
what the project knows to be right. A missing build or shared-data folder fails these tests (never skips)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import ddyn
from ddyn.errors import DdynError
from ddyn.paths import BUILD, REPO, shared_data_dir

EXAMPLES = REPO / "examples"


def run_example(name: str, *args: str, timeout: float = 600) -> str:
    env = dict(os.environ, DDYN_BUILD_DIR=str(BUILD), OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, f"{name} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def number(pattern: str, text: str) -> float:
    m = re.search(pattern, text)
    assert m, f"no match for {pattern!r} in:\n{text}"
    return float(m.group(1))


# ----------------------------------------------------------------------------------------------- the API

def test_import_ddyn_imports_nothing_of_its_own():
    code = ("import sys, ddyn; mods = sorted(m for m in sys.modules if m.startswith('ddyn.') or m in "
            "('torch', 'casadi', 'numpy')); print(mods)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_public_names_are_the_api_and_documented():
    from ddyn import api

    assert ddyn.__all__ == api.__all__
    for name in ddyn.__all__:
        obj = getattr(ddyn, name)
        assert obj is getattr(api, name)
        assert (obj.__doc__ or "").strip(), f"ddyn.{name} has no docstring"
    with pytest.raises(AttributeError):
        ddyn.no_such_name  # noqa: B018


def _one_line(excinfo, *needles: str) -> str:
    msg = str(excinfo.value)
    assert "\n" not in msg, msg
    for n in needles:
        assert n in msg, msg
    return msg


def test_bad_input_is_one_line_naming_the_file_or_key(tmp_path):
    with pytest.raises(DdynError) as e:
        ddyn.load_log(tmp_path / "missing.csv")
    _one_line(e, "missing.csv")
    with pytest.raises(DdynError) as e:
        ddyn.load_log(REPO / "README.md")
    _one_line(e, "README.md", "unrecognised format")
    with pytest.raises(DdynError) as e:
        ddyn.load_vehicle("no_such_car")
    _one_line(e, "no_such_car", "orca_1_43")
    car = json.loads((REPO / "train" / "vehicles" / "orca_1_43.json").read_text())
    del car["sample_time"]
    (tmp_path / "car.json").write_text(json.dumps(car))
    with pytest.raises(DdynError) as e:
        ddyn.load_vehicle(tmp_path / "car.json")
    _one_line(e, "car.json", "sample_time")
    with pytest.raises(DdynError) as e:
        ddyn.load_checkpoint(REPO / "README.md")
    _one_line(e, "README.md", "not a ddyn checkpoint")
    (tmp_path / "zip.ckpt").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(DdynError) as e:
        ddyn.load_checkpoint(tmp_path / "zip.ckpt")
    _one_line(e, "zip.ckpt")
    with pytest.raises(DdynError) as e:
        ddyn.load_checkpoint(tmp_path / "none.ckpt")
    _one_line(e, "none.ckpt")
    with pytest.raises(DdynError) as e:
        ddyn.train(tmp_path / "log.csv", tmp_path / "m.ckpt", epoch=3)
    _one_line(e, "epoch")
    with pytest.raises(DdynError) as e:
        ddyn.generate_c(REPO / "c_src" / "generated")
    _one_line(e, "c_src/generated", "ddyn codegen model")
    with pytest.raises(DdynError) as e:
        ddyn.run_mpc_lap(tool=tmp_path / "ddyn_mpc_lap")
    _one_line(e, "ddyn_mpc_lap", "scripts/build.sh")


def test_diagnose_names_a_bad_config_key(tmp_path):
    log = ddyn.simulate("orca_1_43", track="ethzMobil", laps=0.5, seed=3)
    (tmp_path / "bad.toml").write_text("[diagnosis]\nno_such_setting = 1\n")
    with pytest.raises(DdynError) as e:
        ddyn.diagnose(log, "orca_1_43", config=tmp_path / "bad.toml")
    _one_line(e, "no_such_setting")
    with pytest.raises(DdynError) as e:
        ddyn.diagnose(log, "orca_1_43", config=3)
    _one_line(e, "config")


# ----------------------------------------------------------------------------------------------- the examples

def test_examples_have_a_header_saying_what_and_how():
    scripts = sorted(EXAMPLES.glob("[0-9][0-9]_*.py"))
    assert 5 <= len(scripts) <= 8, scripts
    tested = set(re.findall(r'run_example\("([^"]+)"', Path(__file__).read_text()))
    for s in scripts:
        head = s.read_text().split('"""')[1]
        assert f".venv/bin/python examples/{s.name}" in head, f"{s.name}: no 'Run:' line"
        assert "Shows:" in head, f"{s.name}: does not say what it shows"
        assert s.name in tested, f"{s.name} has no test here"


def test_01_simulate_a_log(tmp_path):
    out = run_example("01_simulate_a_log.py", "--out", str(tmp_path))
    rows = number(r"rows (\d+), sample time 0.02 s", out)
    assert 300 < rows < 600                         # one lap of ETHZMobil (12.8 m) at 1-2.5 m/s
    assert 2.0 < number(r"speed min [\d.]+ max ([\d.]+) m/s", out) < 5.0
    assert "identical: True" in out
    assert (tmp_path / "sim.csv").is_file() and (tmp_path / "sim.png").stat().st_size > 10_000


def test_02_step_the_model():
    out = run_example("02_step_the_model.py")
    assert "coeffs Bf, Cf, Df, Ef, Gf, Kf, Br, Cr, Dr, Er, Gr, Kr, Cm1, Cm2, Cr0, Cd, Iz" in out
    assert number(r"numpy-torch ([\d.e+-]+)", out) < 1e-12
    assert number(r"numpy-CasADi ([\d.e+-]+)", out) < 1e-12
    assert number(r"torch-CasADi ([\d.e+-]+)", out) < 1e-12
    assert 0.9 < number(r"d vx_next / d vx = ([\d.]+)", out) < 1.0   # drag and drivetrain slow the car down


def test_03_train_a_tiny_ddm(tmp_path):
    out = run_example("03_train_a_tiny_ddm.py", "--out", str(tmp_path))
    for ch in ("vx", "vy", "omega"):
        ddm = number(rf"RMSE {ch}\s+DDM ([\d.e+-]+)", out)
        still = number(rf"RMSE {ch}\s+DDM [\d.e+-]+\s+nothing-changes ([\d.e+-]+)", out)
        assert ddm < still / 5, f"{ch}: the DDM ({ddm}) is not clearly better than nothing-changes ({still})"
    for name in ("Df", "Dr", "Cm1", "Iz"):          # the guard's estimates near the truth after a few epochs
        assert abs(number(rf"coefficient {name}\s+mean .*error ([+-][\d.]+) %", out)) < 30, name
    ck = ddyn.load_checkpoint(tmp_path / "ddm.ckpt")
    assert ck.kind == "ddm" and ck.vehicle.name == "orca_1_43" and ck.tau == 1
    # the API's diagnosis against a checkpoint (its coefficients row by row), from the file and from the object
    for nominal in (tmp_path / "ddm.ckpt", ck):
        d = ddyn.diagnose(tmp_path / "test.csv", nominal)
        assert d["nominal"]["source"].startswith("DDM checkpoint ddm.ckpt"), d["nominal"]
        assert d["model"]["heldout"]["rmse_before"]["vx"] > 0


def test_04_diagnose_a_hidden_effect(tmp_path):
    out = run_example("04_diagnose_a_hidden_effect.py", "--out", str(tmp_path))
    assert re.search(r"^selected: throttle_delay \(", out, re.M), out
    assert abs(number(r"found throttle_delay: delay = ([\d.]+)", out) - 0.04) < 0.01
    assert number(r"gap closed: ([\d.]+) %", out) > 80
    d = json.loads((tmp_path / "diagnosis" / "diagnosis.json").read_text())
    assert d["selected"] == ["throttle_delay"]
    assert re.search(r"^calibration: ", out, re.M) and "calibration" in d


def test_05_generate_c():
    out = run_example("05_generate_c.py")
    assert "ddyn_orca_1_43_model.c identical to the committed c_src/generated/ddyn_orca_1_43_model.c: True" in out
    assert "no warnings" in out
    assert number(r"largest relative difference C vs numpy: ([\d.e+-]+)", out) < 1e-12


def test_06_c_mpc_lap(tmp_path):
    tool = BUILD / "c_src" / "ddyn_mpc_lap"
    assert tool.is_file(), f"{tool} missing: build with bash scripts/build.sh {BUILD} (scripts/test.sh does)"
    out = run_example("06_c_mpc_lap.py", "--out", str(tmp_path))
    assert number(r"violation steps (\d+)", out) == 0
    assert 5.0 < number(r"lap times ([\d.]+)", out) < 5.8     # the README's C MPC lap: 5.414 s
    assert json.loads((tmp_path / "mpc_lap.json").read_text())["c_mpc"]["violation_steps"] == 0


def test_07_putnam_roll(tmp_path):
    path = shared_data_dir() / "real" / "Putnam_park2023_run4_2.csv"
    assert path.is_file(), f"{path} missing: set DDYN_SHARED_DATA to the shared data folder"
    out = run_example("07_putnam_roll.py", "--out", str(tmp_path))
    assert "vehicle av21" in out and "roll" in out
    assert number(r"roll ([+-][\d.]+) to", out) < -1.5            # the shared data's README: -1.9 to 2.3 rad
    assert number(r"roll [+-][\d.]+ to ([+-][\d.]+) rad", out) > 2.0
    assert "roll plausible as bank + body roll: False (failed: range, rate" in out
