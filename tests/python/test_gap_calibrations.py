"""The calibrations that ship with the package (train/gap/calibrations/*.json): each loads, names what it covers, and
was made by the fitting and plant code of this version. A change to what the diagnosis or the plant computes makes
this test fail until the calibration is made again with the command it records (`made.command`)."""
from __future__ import annotations

import json

import pytest

from ddyn.errors import DdynError
from ddyn.gap import calibration as CAL
from ddyn.gap.config import ANY_OTHER, DiagnosisConfig


def test_at_least_one_calibration_ships():
    assert CAL.shipped_names(), "no calibration in train/gap/calibrations/"


@pytest.mark.parametrize("name", CAL.shipped_names())
def test_a_shipped_calibration_was_made_by_the_current_code(name):
    cal = CAL.load(name)
    assert cal.stale() is None, cal.stale()
    command = cal.made["command"]
    assert command.startswith("ddyn gap calibrate") or command.startswith("ddyn gap lofo"), command


def _check_sweep_calibration(cal):
    lo, hi = cal.length_range
    assert lo < cal.duration < hi and cal.sample_time > 0 and cal.seeds and cal.cases >= 8 * len(cal.seeds)
    assert cal.covers(cal.duration, cal.sample_time)[0]
    assert not cal.covers(2 * cal.duration, cal.sample_time)[0]
    applied = cal.applied()
    assert applied.min_evidence == pytest.approx(cal.margin)
    # claimed: only effects with a decision level; every other effect reported, never claimed
    assert applied.detection_limits[ANY_OTHER] is None
    for effect, level in cal.decision_levels.items():
        assert (level is None) == (cal.thresholds.get(effect) is None)
    assert set(cal.claim_record.get("withdrawn", [])) <= {e for e, t in cal.thresholds.items() if t is None}


def _check_travelling_calibration(cal):
    # made on more than one plant family, logs of more than one length; it applies to any length at its rate
    assert len(cal.families) >= 2 and cal.durations[0] < cal.durations[1] and cal.logs >= 8 * len(cal.families)
    for length in (0.5 * cal.durations[0], cal.duration, 3 * cal.durations[1]):
        assert cal.covers(length, cal.sample_time)[0]
    applied = cal.applied()
    assert applied.decision_levels[ANY_OTHER] is None
    assert all(v >= 0 for v in applied.family_margins_per_row.values())
    # what it is worth on a plant it never saw is recorded with it
    assert cal.lofo.get("family") in cal.families


@pytest.mark.parametrize("name", CAL.shipped_names())
def test_a_shipped_calibration_describes_what_it_covers_and_claims(name):
    cal = CAL.load(name)
    assert not cal.covers(cal.duration, 2 * cal.sample_time)[0]
    # shipped calibrations put nothing into a user's nominal
    assert not cal.diagnosis.get("steer_servo") and not cal.diagnosis.get("nominal_effects")
    assert isinstance(cal.applied(), DiagnosisConfig)
    if isinstance(cal, CAL.TravellingCalibration):
        _check_travelling_calibration(cal)
    else:
        _check_sweep_calibration(cal)


def test_the_default_diagnosis_of_any_length_uses_a_shipped_calibration():
    """`ddyn gap diagnose` with no flags claims under a calibration on a 25 Hz log of any length."""
    for length in (45.0, 200.0, 900.0):
        cal, cfg, why = CAL.choose(length, 0.04)
        assert cal is not None, why
        assert cfg == cal.applied()


def test_the_code_version_follows_what_the_code_does_not_its_words(tmp_path, monkeypatch):
    """Comments and docstrings leave the version alone; a changed statement moves it."""
    import importlib.util
    import sys

    def version_of(text: str) -> str:
        (tmp_path / "probe_mod.py").write_text(text)
        monkeypatch.syspath_prepend(str(tmp_path))
        importlib.invalidate_caches()
        sys.modules.pop("probe_mod", None)
        assert importlib.util.find_spec("probe_mod") is not None
        return CAL.code_version(("probe_mod",))

    a = version_of('"""doc"""\nX = 1  # one\n\ndef f():\n    "words"\n    return X\n')
    b = version_of('"""other doc"""\nX = 1  # another comment\n\ndef f():\n    "other words"\n    return X\n')
    c = version_of('"""doc"""\nX = 2\n\ndef f():\n    "words"\n    return X\n')
    assert a == b != c


def _ddyn_imports(module: str) -> set[str]:
    """The ddyn modules `module` imports anywhere in its source (function-level imports too), by name."""
    import ast
    import importlib.util

    def is_module(name: str) -> bool:
        try:
            return importlib.util.find_spec(name) is not None
        except ModuleNotFoundError:
            return False

    out = set()
    tree = ast.parse(open(importlib.util.find_spec(module).origin).read())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("ddyn"):
            out |= {f"{node.module}.{a.name}" if is_module(f"{node.module}.{a.name}") else node.module
                    for a in node.names}
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("ddyn")}
    return out


def test_every_module_behind_a_calibration_is_hashed_or_said_not_to_matter():
    """A calibration goes stale when the code it measured changes: every ddyn module that a hashed module imports
    is hashed too, or named in NOT_MEASURED with the reason it cannot move what a calibration measures (the
    driver in ddyn.data.simulate once was neither)."""
    import importlib.util

    hashed = set(CAL.FITTING_MODULES) | {m for mods in CAL.PLANT_MODULES.values() for m in mods}
    assert "ddyn.data.simulate" in CAL.PLANT_MODULES["families"]
    for name in CAL.NOT_MEASURED:
        assert importlib.util.find_spec(name) is not None, name
    unhashed = {m: sorted(_ddyn_imports(m) - hashed - set(CAL.NOT_MEASURED)) for m in sorted(hashed)}
    assert not {m: u for m, u in unhashed.items() if u}


def test_the_plant_version_follows_the_plants_vehicle_files_values(tmp_path):
    """A changed value in a plant's vehicle file moves the data version; the same values re-indented do not."""
    (tmp_path / "vehicles" / "plants").mkdir(parents=True)
    car = tmp_path / "vehicles" / "plants" / "car.json"
    car.write_text(json.dumps({"name": "car", "mass": 790.0}))
    a = CAL.data_version(CAL.PLANT_FILES, root=tmp_path)
    car.write_text(json.dumps({"mass": 790.0, "name": "car"}, indent=4))
    b = CAL.data_version(CAL.PLANT_FILES, root=tmp_path)
    car.write_text(json.dumps({"name": "car", "mass": 800.0}))
    c = CAL.data_version(CAL.PLANT_FILES, root=tmp_path)
    assert a == b != c
    car.write_text("{not json")
    with pytest.raises(DdynError, match="car.json"):
        CAL.data_version(CAL.PLANT_FILES, root=tmp_path)
