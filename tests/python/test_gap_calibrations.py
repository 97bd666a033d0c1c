"""The calibrations that ship with the package (train/gap/calibrations/*.json): each loads, names what it covers, and
was made by the fitting and plant code of this version. A change to what the diagnosis or the plant computes makes
this test fail until the calibration is made again with the command it records (`made.command`)."""
from __future__ import annotations

import pytest

from ddyn.gap import calibration as CAL
from ddyn.gap.config import ANY_OTHER, DiagnosisConfig


def test_at_least_one_calibration_ships():
    assert CAL.shipped_names(), "no calibration in train/gap/calibrations/"


@pytest.mark.parametrize("name", CAL.shipped_names())
def test_a_shipped_calibration_was_made_by_the_current_code(name):
    cal = CAL.load(name)
    assert cal.stale() is None, cal.stale()
    assert cal.made["command"].startswith("ddyn gap calibrate")


@pytest.mark.parametrize("name", CAL.shipped_names())
def test_a_shipped_calibration_describes_what_it_covers_and_claims(name):
    cal = CAL.load(name)
    lo, hi = cal.length_range
    assert lo < cal.duration < hi and cal.sample_time > 0 and cal.seeds and cal.cases >= 8 * len(cal.seeds)
    assert cal.covers(cal.duration, cal.sample_time)[0]
    assert not cal.covers(2 * cal.duration, cal.sample_time)[0]
    assert not cal.covers(cal.duration, 2 * cal.sample_time)[0]
    # shipped calibrations put nothing into a user's nominal
    assert not cal.diagnosis.get("steer_servo") and not cal.diagnosis.get("nominal_effects")
    applied = cal.applied()
    assert isinstance(applied, DiagnosisConfig) and applied.min_evidence == pytest.approx(cal.margin)
    # claimed: only effects with a decision level; every other effect reported, never claimed
    assert applied.detection_limits[ANY_OTHER] is None
    for effect, level in cal.decision_levels.items():
        assert (level is None) == (cal.thresholds.get(effect) is None)
    assert set(cal.claim_record.get("withdrawn", [])) <= {e for e, t in cal.thresholds.items() if t is None}


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
