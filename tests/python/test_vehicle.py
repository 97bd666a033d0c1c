"""Vehicle files load, hold what the model needs, and bad files are refused by name."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ddyn.errors import DdynError
from ddyn.model import vehicle
from ddyn.model.single_track import COEFF_NAMES


@pytest.mark.parametrize("name", ["orca_1_43", "av21"])
def test_vehicle_files_are_complete(name):
    v = vehicle.load(name)
    lo, hi = v.range_arrays()
    truth = v.true_vector()
    assert truth.shape == (len(COEFF_NAMES),)
    assert np.all((lo <= truth) & (truth <= hi))
    assert v.sample_time in (0.02, 0.04)
    assert v.sources, "every vehicle file says where its numbers come from"


def test_orca_matches_shared_readme_table():
    v = vehicle.load("orca_1_43")
    assert (v.known.mass, v.known.lf, v.known.lr) == (0.041, 0.029, 0.033)
    assert v.true_coefficients["Bf"] == 5.579 and v.true_coefficients["Iz"] == 2.78e-5
    # drivetrain and Iz ranges are half to double the truth
    for k in ("Cm1", "Cm2", "Cr0", "Cd", "Iz"):
        assert v.ranges[k] == pytest.approx((v.true_coefficients[k] / 2, v.true_coefficients[k] * 2))


def _write(tmp_path, mutate):
    raw = json.loads(Path(vehicle.load("orca_1_43").source_path).read_text())
    mutate(raw)
    p = tmp_path / "car.json"
    p.write_text(json.dumps(raw))
    return p


def test_truth_outside_range_is_refused(tmp_path):
    p = _write(tmp_path, lambda r: r["true_coefficients"].update(Bf=99.0))
    with pytest.raises(DdynError, match="true Bf = 99.0 lies outside"):
        vehicle.load(p)


def test_missing_field_is_named(tmp_path):
    p = _write(tmp_path, lambda r: r["known"].pop("lf"))
    with pytest.raises(DdynError, match="missing field 'lf'"):
        vehicle.load(p)


def test_unknown_vehicle_lists_known_ones():
    with pytest.raises(DdynError, match="orca_1_43"):
        vehicle.load("no_such_car")
