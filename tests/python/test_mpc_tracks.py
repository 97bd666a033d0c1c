"""`ddyn mpc tracks`: the C MPC on a seeded random track against the track's own optimal lap."""
from __future__ import annotations

import pytest

from ddyn.control import mpc_lap, mpc_tracks
from ddyn.control import raceline as R
from ddyn.control.mpc_setup import MpcSettings
from ddyn.errors import DdynError


def test_parse_seeds():
    assert mpc_tracks.parse_seeds("0-2,9,100-101") == [0, 1, 2, 9, 100, 101]
    with pytest.raises(DdynError, match="--seeds"):
        mpc_tracks.parse_seeds("a-b")


def test_mpc_drives_a_random_track_near_its_optimum(tmp_path, monkeypatch):
    """Tuning track 3: the line is computed for it (~20 s), the C MPC's first lap is clean and within 5 %."""
    if not mpc_lap.DEFAULT_TOOL.is_file():
        pytest.fail(f"{mpc_lap.DEFAULT_TOOL} missing: build the C side first (scripts/test.sh does)")
    monkeypatch.setattr(R, "USER_RACELINE_DIR", tmp_path)
    (row,) = mpc_tracks.evaluate("orca_1_43", [3], MpcSettings())
    assert (tmp_path / "orca_1_43_random3.npz").is_file()
    assert row["violation_steps"] == 0 and row["lap_s"] is not None
    assert 1.0 <= row["ratio"] <= 1.05
    s = mpc_tracks.summary([row, dict(row, violation_steps=2)])
    assert s["clean"] == 1 and s["within_5pct"] == 1 and s["tracks"] == 2
