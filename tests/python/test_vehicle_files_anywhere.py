"""Issue 14, item 4: every command's --vehicle takes a JSON file outside train/vehicles, and a log made with
one finds that file again (it is embedded in the log), even after the file has moved."""
from __future__ import annotations

import json
import shutil

import pytest

from ddyn.cli import main
from ddyn.data import vehicle_ref
from ddyn.data.importers import load_any
from ddyn.errors import DdynError
from ddyn.model import vehicle as vehicles


@pytest.fixture(scope="module")
def car(tmp_path_factory, shared_data):
    """A vehicle file only this test knows: av21's numbers under a name train/vehicles does not hold, and a
    log of it (simulate with --vehicle PATH), 8 s of Putnam (200 rows)."""
    d = tmp_path_factory.mktemp("car")
    raw = json.loads((vehicles.VEHICLE_DIR / "av21.json").read_text())
    raw["name"] = "outside_car"
    path = d / "outside_car.json"
    path.write_text(json.dumps(raw, indent=1))
    assert "outside_car" not in vehicles.available()
    log = d / "log.csv"
    assert main(["simulate", "--vehicle", str(path), "--track", "putnam", "--duration", "8", "--noise", "1",
                 "--seed", "3", "-q", "-o", str(log)]) == 0
    return path, log


def test_simulate_records_the_vehicle_file(car):
    path, log = car
    ds = load_any(log)
    assert ds.vehicle == "outside_car"
    assert ds.metadata["vehicle_file"] == str(path)
    v = vehicle_ref.of_dataset(ds)
    assert v.name == "outside_car" and v.digest == vehicles.load(path).digest


def test_the_log_finds_its_vehicle_after_the_file_moved(car, tmp_path):
    path, log = car
    moved = tmp_path / "log.csv"
    shutil.copy(log, moved)
    shutil.move(path, tmp_path / "elsewhere.json")
    try:
        assert vehicle_ref.of_dataset(load_any(moved)).name == "outside_car"   # from the embedded copy
        # without the embedded copy and with the file gone, the name alone cannot find it: a clear error
        text = "\n".join(l for l in moved.read_text().splitlines() if not l.startswith("# vehicle_json_b64"))
        moved.write_text(text + "\n")
        with pytest.raises(DdynError, match="outside_car"):
            vehicle_ref.of_dataset(load_any(moved))
    finally:
        shutil.move(tmp_path / "elsewhere.json", path)


def test_diagnose_with_a_vehicle_file(car, tmp_path):
    path, log = car
    out = tmp_path / "diag"
    cfg = tmp_path / "c.toml"
    cfg.write_text('candidates = ["steer_delay", "mass_offset"]\n')
    assert main(["gap", "diagnose", "--vehicle", str(path), "--data", str(log), "--out", str(out), "--no-plots",
                 "--config", str(cfg)]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["nominal"]["vehicle"] == "outside_car"


def test_train_evaluate_and_diagnose_a_checkpoint_with_a_vehicle_file(car, tmp_path):
    path, log = car
    ck = tmp_path / "m.ckpt"
    assert main(["train", "--data", str(log), "--vehicle", str(path), "-o", str(ck), "--quiet", "--epochs", "1",
                 "--lbfgs-iterations", "0", "--hidden", "8"]) == 0
    # the dataset's own record is enough too (no --vehicle)
    ck2 = tmp_path / "m2.ckpt"
    assert main(["train", "--data", str(log), "-o", str(ck2), "--quiet", "--epochs", "1",
                 "--lbfgs-iterations", "0", "--hidden", "8"]) == 0
    assert main(["evaluate", "--model", str(ck), "--data", str(log)]) == 0
    cfg = tmp_path / "c.toml"
    cfg.write_text('candidates = ["steer_delay"]\nmax_effects = 1\n')
    assert main(["gap", "diagnose", "--model", str(ck), "--data", str(log), "--out", str(tmp_path / "d"), "--no-plots",
                 "--config", str(cfg)]) == 0


def test_a_wrong_vehicle_file_is_refused(car, tmp_path):
    path, log = car
    raw = json.loads(path.read_text())
    raw["name"] = "another_car"
    other = tmp_path / "another.json"
    other.write_text(json.dumps(raw))
    assert main(["diagnose", "--vehicle", str(other), "--data", str(log), "--out", str(tmp_path / "x"),
                 "--no-plots"]) == 2
