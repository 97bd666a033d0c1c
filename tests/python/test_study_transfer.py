"""`ddyn study transfer` (issue 36, items 1 and 3): the quick study end to end on the multi-body plant, the split's
honesty read from the datasets every fit receives, and the one-line refusals of bad options."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ddyn.errors import DdynError

pytest.importorskip("vehiclemodels")


def _args(argv):
    from ddyn.cli import build_parser, commands_named

    return build_parser(commands_named("study")).parse_args(["study", "transfer", *argv])


def test_quick_study_end_to_end_and_its_splits(tmp_path, monkeypatch):
    from ddyn.studies import transfer as T

    calls = []                     # (what, dataset(s)) in call order
    real_train, real_finetune = T.train, T.finetune

    def spy_train(ds, v, cfg, progress=True, validation=None):
        calls.append(("train", ds))
        return real_train(ds, v, cfg, progress=progress, validation=validation)

    def spy_finetune(base, train_ds, val_ds, cfg, **kw):
        calls.append(("finetune", train_ds, val_ds))
        return real_finetune(base, train_ds, val_ds, cfg, **kw)

    monkeypatch.setattr(T, "train", spy_train)
    monkeypatch.setattr(T, "finetune", spy_finetune)
    out = tmp_path / "transfer"
    args = _args(["--quick", "--quiet", "--out", str(out)])
    assert args.func(args) == 0

    res = json.loads((out / "results.json").read_text())
    assert (out / "results.md").is_file() and (out / "A.csv").is_file() and (out / "B.csv").is_file()
    s = res["summary"]
    for key in ("own", "other", "b_all", "ratio"):
        for c in T.CHANNELS:
            assert np.isfinite(s[key][c]["mean"]), (key, c)
    assert [f["fraction"] for f in s["fractions"]] == list(T.FRACTIONS)
    for f in s["fractions"]:
        for arm in ("fthd", "scratch"):
            assert all(np.isfinite(f[arm][c]["mean"]) for c in T.CHANNELS)
    run = res["runs"][0]
    assert run["base"]["ratio"]["vx"] == pytest.approx(run["base"]["other"]["vx"] / run["base"]["own"]["vx"])
    assert set(s["ratio_target"]["per_channel"]) == set(T.CHANNELS)
    md = (out / "results.md").read_text()
    assert "ratio other / own" in md and "FTHD (A model fine-tuned)" in md and "5%" in md
    # the recorded budget is the quick one
    assert res["settings"]["train"]["config"]["epochs"] == T.QUICK["epochs"]
    assert res["settings"]["train"]["origin"]["epochs"] == "--epochs"

    # honesty: the A model's fit saw only A's training part, and it came before any fine-tuning
    a_rows, b_rows = res["rows"]["a_train"], res["rows"]["b_test"]
    assert calls[0][0] == "train"
    base = calls[0][1]
    assert base.metadata["track"] == "putnam" and len(base) == a_rows[1] - a_rows[0]
    from ddyn.data.importers import load_any

    b = load_any(out / "B.csv")
    b_test_start_time = b.time[b_rows[0]]
    b_name = b.metadata["track"]
    assert b_name.startswith("random301")
    n_ft = 0
    for call in calls[1:]:
        for ds in call[1:]:
            # every later fit reads B's rows, never one of B's last 20 %
            assert ds.metadata["track"] == b_name
            assert ds.time.max() < b_test_start_time
            assert np.isin(ds.time, b.time[:b_rows[0]]).all()
        if call[0] == "finetune":
            n_ft += 1
            assert call[1].time.max() < call[2].time.min()   # its selection rows follow its fitting rows
            # the fraction is spread over B's training part (FRACTION_BLOCKS blocks), not its first rows
            rows = np.concatenate([call[1].time, call[2].time])
            assert len(np.unique(np.concatenate([call[1].segment, call[2].segment]))) == T.FRACTION_BLOCKS
            assert rows.max() > b.time[int(0.75 * b_rows[0])]
    assert n_ft == len(T.FRACTIONS)
    assert all(isinstance(f["fthd_kept_base"], bool) for f in run["fractions"])
    # the record counts the fraction's rows, the sum of its blocks (they are not one range from row 0)
    for f in run["fractions"]:
        assert f["rows"] == sum(e - a for a, e in f["blocks"]) == f["fit_rows"] + f["select_rows"]
        assert len(f["blocks"]) == T.FRACTION_BLOCKS and f["blocks"][-1][0] > 0


@pytest.mark.parametrize("argv, option", [
    (["--family", "commonroad-xx"], "--family"),
    (["--duration", "-5"], "--duration"),
    (["--speed", "50"], "--speed"),
    (["--fractions", "0.05", "1.5"], "--fractions"),
    (["--seeds", "1", "1"], "--seeds"),
    (["--epochs", "0"], "--epochs"),
    (["--ft-adam-steps", "-1"], "--ft-adam-steps"),
    (["--vehicle", "no_such_car"], "--vehicle"),
    (["--road-scale", "5"], "--road-scale"),
    (["--noise-scale", "-1"], "--noise-scale"),
    (["--fraction-blocks", "0"], "--fraction-blocks"),
])
def test_bad_options_are_one_line_errors_naming_the_option(argv, option, tmp_path):
    from ddyn.studies import transfer as T

    with pytest.raises(DdynError) as e:
        T.options(_args([*argv, "--out", str(tmp_path / "x")]))
    msg = str(e.value)
    assert option in msg and "\n" not in msg


def test_fraction_blocks_spread_over_the_pool_and_never_join_at_a_seam():
    from ddyn.data.dataset import Dataset
    from ddyn.studies import transfer as T

    n = 1000
    pool = Dataset(np.arange(n) * 0.04, np.zeros(n, dtype=np.int64), np.random.default_rng(0).normal(size=(n, 8)),
                   np.zeros((n, 2)), 0.04)
    part, ranges = T.fraction_blocks(pool, 0.1, 4)
    assert ranges == [[0, 25], [250, 275], [500, 525], [750, 775]]
    assert len(part) == 100 and np.array_equal(part.states, np.concatenate([pool.states[a:b] for a, b in ranges]))
    # one segment per block: no one-step pair reads across a seam, every pair inside a block is kept
    assert len(np.unique(part.segment)) == 4 and np.all(np.diff(part.segment) >= 0)
    assert len(part.transition_index()) == 4 * 24
    first, r1 = T.fraction_blocks(pool, 0.1, 1)
    assert r1 == [[0, 100]] and np.array_equal(first.time, pool.time[:100])
    with pytest.raises(DdynError, match="fraction 0.001 in 4 blocks"):
        T.fraction_blocks(pool, 0.001, 4)


def test_road_course_is_full_size_and_seeded():
    from ddyn.studies import transfer as T

    a, b = T.road_course(301), T.road_course(301)
    assert a.length == pytest.approx(b.length) and 1000 < a.length < 2000
    assert a.width == pytest.approx(T.ROAD_WIDTH, rel=0.01)


def test_transfer_compare_counts_beyond_the_seed_spread(tmp_path):
    """ddyn.studies.transfer_compare: a figure moves beyond the spread only when each mean lies outside the other's
    seed range."""
    from ddyn.studies.transfer_compare import compare, verdict

    r = lambda m, lo, hi: {"mean": m, "min": lo, "max": hi}  # noqa: E731
    assert verdict(r(1.0, 0.9, 1.1), r(0.5, 0.4, 0.6)) == "better"
    assert verdict(r(1.0, 0.9, 1.1), r(1.5, 1.4, 1.6)) == "worse"
    assert verdict(r(1.0, 0.9, 1.1), r(0.85, 0.5, 1.2)) == "within"    # below the old range, but spread wide
    figs = lambda m: {c: r(m, m, m) for c in ("vx", "vy", "omega", "ade", "fde")}  # noqa: E731
    for folder, m in (("old", 1.0), ("new", 0.5)):
        (tmp_path / folder / "transfer").mkdir(parents=True)
        summary = {"other": figs(m), "fractions": [{"fraction": 0.05, "fthd": figs(m), "scratch": figs(2 * m)}]}
        (tmp_path / folder / "transfer" / "results.json").write_text(json.dumps({"summary": summary}))
    lines, tally = compare(tmp_path / "old", tmp_path / "new")
    assert tally == {"better": 15, "within": 0, "worse": 0} and len(lines) == 3


def test_transfer_compare_finds_the_common_studies_and_counts_own_figures_when_asked(tmp_path):
    """Candidate folders of any study names: only those both hold are compared; --own adds the own-track figures, so
    a candidate that carries to the other track by fitting its own worse shows it."""
    from ddyn.studies.transfer_compare import compare, main

    r = lambda m: {"mean": m, "min": m, "max": m}  # noqa: E731
    figs = lambda m: {c: r(m) for c in ("vx", "vy", "omega", "ade", "fde")}  # noqa: E731
    for folder, own, other in (("base", 1.0, 2.0), ("cand", 3.0, 1.0)):
        for study in ("mb_fwd", "mb_swap"):
            (tmp_path / folder / study).mkdir(parents=True)
            summary = {"own": figs(own), "other": figs(other), "fractions": []}
            (tmp_path / folder / study / "results.json").write_text(json.dumps({"summary": summary}))
    (tmp_path / "cand" / "only_here").mkdir()
    (tmp_path / "cand" / "only_here" / "results.json").write_text(json.dumps({"summary": {}}))
    lines, tally = compare(tmp_path / "base", tmp_path / "cand")
    assert tally == {"better": 10, "within": 0, "worse": 0} and len(lines) == 2
    lines, tally = compare(tmp_path / "base", tmp_path / "cand", own=True)
    assert tally == {"better": 10, "within": 0, "worse": 10} and len(lines) == 4
    with pytest.raises(SystemExit):
        main([str(tmp_path / "base"), str(tmp_path / "nowhere")])


def test_candidate_settings_and_ranges_are_checked_and_recorded(tmp_path, monkeypatch):
    """--set KEY=VALUE reaches every training's config over the av21 profile, --ranges the guard the model trains
    with, --no-finetune leaves the FTHD fractions out; each is recorded in results.json."""
    from ddyn.studies import transfer as T

    seen = []
    real_train = T.train

    def spy_train(ds, v, cfg, progress=True, validation=None):
        seen.append((cfg, dict(v.ranges)))
        return real_train(ds, v, cfg, progress=progress, validation=validation)

    monkeypatch.setattr(T, "train", spy_train)
    ranges = tmp_path / "peak.json"
    ranges.write_text(json.dumps({"coefficients": {"Df": [4000.0, 8000.0]}}))
    out = tmp_path / "t"
    args = _args(["--quick", "--quiet", "--no-finetune", "--set", "guard_prior=0.01", "--set", "tau=2",
                  "--ranges", str(ranges), "--out", str(out)])
    assert args.func(args) == 0
    assert len(seen) == 1                       # the A model only: no fine-tuning, no model from scratch
    cfg, used = seen[0]
    assert cfg.guard_prior == 0.01 and cfg.tau == 2 and used["Df"] == (4000.0, 8000.0)
    res = json.loads((out / "results.json").read_text())
    assert res["settings"]["sets"] == {"guard_prior": 0.01, "tau": 2}
    assert res["settings"]["train"]["origin"]["guard_prior"] == "--guard-prior"
    assert res["settings"]["ranges"]["changed"]["Df"]["used"] == [4000.0, 8000.0]
    assert res["summary"]["fractions"] == [] and "--no-finetune" in (out / "results.md").read_text()


@pytest.mark.parametrize("argv, words", [
    (["--set", "foo=1"], "unknown key 'foo'"),
    (["--set", "guard_prior=-1"], "--set guard_prior"),
    (["--set", "seed=3"], "--seeds"),
    (["--set", "tau"], "KEY=VALUE"),
    (["--set", "tau=2", "--set", "tau=3"], "given twice"),
    (["--set", "kind=dpm", "--set", "guard_prior=0.1"], "--set"),
    (["--no-finetune", "--fractions", "0.1"], "--no-finetune"),
    (["--ranges", "/no/such/ranges.json"], "/no/such/ranges.json"),
    (["--set", "kind=dpm", "--ranges", "/no/such/ranges.json"], "--ranges"),
])
def test_bad_candidate_settings_are_one_line_errors(argv, words, tmp_path):
    from ddyn.studies import transfer as T

    with pytest.raises(DdynError) as e:
        T.options(_args([*argv, "--out", str(tmp_path / "x")]))
    assert words in str(e.value) and "\n" not in str(e.value)


def test_transfer_compare_pools_runs_of_other_seeds_and_refuses_a_mixed_study(tmp_path):
    """`defaults,more/defaults`: the runs of both folders are one study's seeds, summarised again (the worse verdict of
    three seeds can go away with five); a repeated seed or other settings are refused in one line."""
    from ddyn.errors import DdynError
    from ddyn.studies import transfer as T
    from ddyn.studies.transfer_compare import compare, main

    def write(folder, seeds_values, vehicle="av21"):
        runs = []
        for seed, own_omega in seeds_values:
            m = {c: 1.0 for c in T.CHANNELS} | {"omega": own_omega, "any_bound": 0.0}
            runs.append({"seed": seed, "base": {"own": m, "other": dict(m), "b_all": dict(m),
                                                "ratio": {c: 1.0 for c in T.CHANNELS}}, "fractions": []})
        d = tmp_path / folder / "mb_fwd"
        d.mkdir(parents=True)
        res = {"family": "commonroad-mb", "vehicle": vehicle, "duration": 180.0, "speed": 24.0, "swap": False,
               "noise_scale": 0.0, "settings": {"sets": {}, "ranges": None, "fractions": []}, "runs": runs,
               "summary": T.summarise(runs, ())}
        (d / "results.json").write_text(json.dumps(res))

    write("base", [(0, 1.0), (1, 1.1), (2, 1.2)])
    write("base_more", [(3, 1.3), (4, 2.0)])
    write("cand", [(0, 1.5), (1, 1.6), (2, 1.7)])
    write("cand_more", [(3, 0.9), (4, 1.0)])
    _, three = compare(tmp_path / "base", tmp_path / "cand", own=True)
    assert three["worse"] == 2                               # omega, own and other, on three seeds
    _, five = compare(f"{tmp_path / 'base'},{tmp_path / 'base_more'}", f"{tmp_path / 'cand'},{tmp_path / 'cand_more'}",
                      own=True)
    assert five == {"better": 0, "within": 10, "worse": 0}   # seeds 0-4: the ranges overlap
    with pytest.raises(DdynError, match="seed"):
        compare(f"{tmp_path / 'base'},{tmp_path / 'base'}", tmp_path / "cand")
    write("other_car", [(5, 1.0)], vehicle="av21_power")
    with pytest.raises(DdynError, match="vehicle"):
        compare(f"{tmp_path / 'base'},{tmp_path / 'other_car'}", tmp_path / "cand")
    with pytest.raises(SystemExit):
        main([f"{tmp_path / 'base'},{tmp_path / 'base'}", str(tmp_path / "cand")])
