"""Leave-a-condition-out splits of `ddyn study ddm real --holdout laps|speed` (issue 36): the held-out laps' rows
never reach training, and no window of either part reads across the cut."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ddyn.data import laps
from ddyn.data.dataset import Dataset
from ddyn.data.windows import make_windows, valid_end_rows
from ddyn.errors import DdynError
from ddyn.studies import ddm

DT = 0.04
TAU = 5


def _oval_log(n_laps: float = 3.6, gap_at: int | None = 300) -> Dataset:
    """A closed 100 m x 50 m ellipse driven n_laps times at a speed that varies along the log (so a speed band
    cuts it into many runs); a dropped-row gap (a new segment) at row gap_at, as a real log's vx < 5 m/s rows."""
    a, b = 100.0, 50.0
    perimeter = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))
    n = int(n_laps * perimeter / (15.0 * DT))
    t = np.arange(n) * DT
    vx = 15.0 + 5.0 * np.sin(2 * np.pi * t / 37.0)
    s = np.cumsum(vx) * DT                               # distance along the ellipse (approximately)
    th = 2 * np.pi * s / perimeter
    x, y = a * np.cos(th), b * np.sin(th)
    yaw = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    states = np.column_stack([x, y, yaw, vx, np.zeros(n), np.gradient(yaw, DT), np.full(n, 0.2), np.zeros(n)])
    segment = np.zeros(n, int)
    if gap_at is not None:
        segment[gap_at:] = 1
    return Dataset(t, segment, states, np.zeros((n, 2)), DT, vehicle="av21", source="synthetic oval")


def _original_rows(part: Dataset, ds: Dataset) -> np.ndarray:
    """Each row of a part as its row index in ds (the times are unique)."""
    idx = np.searchsorted(ds.time, part.time)
    assert np.array_equal(ds.time[idx], part.time)
    return idx


def _straddling_windows(part: Dataset, ds: Dataset, tau: int) -> int:
    """Windows of `part` (tau rows of history plus the target row) whose rows are not consecutive rows of one
    segment of ds: such a window steps across rows the part does not have."""
    orig = _original_rows(part, ds)
    k = valid_end_rows(part, tau)
    rows = orig[k[:, None] + np.arange(-tau + 1, 2)]
    bad = (np.diff(rows, axis=1) != 1).any(axis=1) | (ds.segment[rows] != ds.segment[rows[:, :1]]).any(axis=1)
    return int(bad.sum())


def test_laps_split_holds_out_whole_laps_and_no_window_straddles_the_cut():
    ds = _oval_log()
    lp = laps.from_dataset(ds)
    assert lp.circuit and set(np.unique(lp.lap)) == {0, 1, 2, 3}
    train, test, info = ddm.split_real(ds, "laps", (1,))
    assert info["test_laps"] == [1] and info["train_laps"] == [0, 2, 3]
    tr, te = _original_rows(train, ds), _original_rows(test, ds)
    # the held-out part is exactly lap 1's rows; training has none of them; together they are the log
    assert np.array_equal(te, np.flatnonzero(lp.lap == 1))
    assert not np.intersect1d(tr, te).size and len(tr) + len(te) == len(ds)
    assert np.all(lp.lap[tr] != 1)
    # no window of either part reads a row across the cut or across the log's own gap
    assert _straddling_windows(train, ds, TAU) == 0 and _straddling_windows(test, ds, TAU) == 0
    w = make_windows(train, TAU)
    assert not np.isin(_original_rows(train, ds)[w.end_row + 1], te).any()
    # the check has teeth: the same rows without renumbered segments give windows across the held-out lap
    naive = ds.subset(tr)
    assert _straddling_windows(naive, ds, TAU) > 0
    # the training part's segments: lap 0 split by the log's gap, then laps 2-3 after the held-out lap
    assert len(np.unique(train.segment)) == 3


def test_speed_split_and_refusals():
    ds = _oval_log()
    train, test, info = ddm.split_real(ds, "speed", speed=17.0)
    assert np.all(train.states[:, 3] < 17.0) and np.all(test.states[:, 3] >= 17.0)
    assert len(train) + len(test) == len(ds) and info["train_rows"] == len(train)
    assert _straddling_windows(train, ds, TAU) == 0 and _straddling_windows(test, ds, TAU) == 0
    with pytest.raises(DdynError, match="not among them"):
        ddm.split_real(ds, "laps", (7,))
    with pytest.raises(DdynError, match="every lap"):
        ddm.split_real(ds, "laps", (0, 1, 2, 3))
    with pytest.raises(DdynError, match="no rows on one side"):
        ddm.split_real(ds, "speed", speed=50.0)
    line = ds.subset(slice(0, 200))           # part of one lap: no laps to hold out
    with pytest.raises(DdynError, match="no laps"):
        ddm.split_real(line, "laps", (1,))
    # the time split is the study's split before issue 36: the first 80 % of the rows train
    train, test, _ = ddm.split_real(ds, "time")
    assert len(train) == int(0.8 * len(ds)) and train.time[-1] < test.time[0]


def test_split_rows_refuses_a_wrong_mask():
    with pytest.raises(DdynError, match="row mask"):
        ddm.split_rows(_oval_log(), np.ones(3, bool))


def test_study_holdout_laps_quick_on_the_real_log(tmp_path, shared_data):
    """A tiny `ddyn study ddm real --holdout laps --seeds 0 1`: the test part is the log's lap 1, whole; each run
    reports in-sample figures beside the held-out ones, and the summary spans both seeds."""
    from ddyn.cli import build_parser, commands_named

    out = tmp_path / "study"
    argv = ["study", "ddm", "real", "--quick", "--holdout", "laps", "--only", "ddm_putnam", "--seeds", "0", "1",
            "--out", str(out)]
    args = build_parser(commands_named("study")).parse_args(argv)
    assert args.func(args) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["holdout"]["holdout"] == "laps" and res["holdout"]["test_laps"] == [1]
    assert [r["seed"] for r in res["real"]] == [0, 1]
    for r in res["real"]:
        assert r["samples"] < res["holdout"]["test_rows"] and r["in_sample"]["samples"] > 0
        assert 0 <= r["test_any_bound"] <= 1
    (s,) = res["holdout_summary"]
    assert s["name"] == "ddm_putnam" and s["seeds"] == [0, 1]
    assert s["test"]["vx"]["min"] <= s["test"]["vx"]["mean"] <= s["test"]["vx"]["max"]
    assert (out / "real" / "seed1" / "ddm_putnam" / "model.ckpt").is_file()
    # "nothing changes" scored on the same held-out rows: its one-step vx error is the rms change of vx over
    # the held-out lap's steps, computed here from the log itself
    from ddyn.data.importers import load_any

    lap = ddm.split_real(load_any(shared_data / "real" / "Putnam_park2023_run4_2.csv", vehicle="av21"), "laps")[1]
    same = lap.segment[1:] == lap.segment[:-1]
    want = float(np.sqrt(np.mean(np.diff(lap.states[:, 3])[same] ** 2)))
    assert s["reference"]["test"]["vx"] == pytest.approx(want, rel=1e-12)
    assert 0 < s["reference"]["test"]["ade"] < s["reference"]["test"]["fde"]
    assert "| reference: nothing changes" in (out / "results.md").read_text()
    # --holdout-laps without --holdout laps is refused, not ignored
    args = build_parser(commands_named("study")).parse_args(
        ["study", "ddm", "real", "--quick", "--holdout-laps", "2", "--out", str(out)])
    with pytest.raises(DdynError, match="needs --holdout laps"):
        args.func(args)


def test_saturation_figure_is_the_worst_coefficient_on_either_bound():
    """results/ddm_real_putnam.json reads saturation_max_pct: the largest share (%) of samples one coefficient
    spends on its lower plus upper bound, not the sum over coefficients; None without a guard."""
    from ddyn.studies.ddm import _saturation_max_pct

    coeffs = {"Iz": {"at_lower_bound": 0.001, "at_upper_bound": 0.006}, "Cm1": {"at_lower_bound": 0.0,
                                                                                "at_upper_bound": 0.004}}
    assert _saturation_max_pct(coeffs) == pytest.approx(0.7)
    assert _saturation_max_pct({}) is None and _saturation_max_pct(None) is None
