"""Guard ranges from data (`ddyn train --ranges`): read, applied, recorded, reported."""
from __future__ import annotations

import json

import pytest

from ddyn.cli import main as cli_main
from ddyn.data import simulate
from ddyn.data.dataset import write_canonical
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn.guard_ranges import read_ranges, with_ranges
from ddyn.model import tracks, vehicle


@pytest.fixture(scope="module")
def orca():
    return vehicle.load("orca_1_43")


def test_denoise_file_and_plain_mapping_are_read(tmp_path):
    denoise_style = {"coefficients": {"Cm1": {"vehicle": [0.1, 0.6], "suggested": [0.2, 0.4], "pinned": None}}}
    (tmp_path / "a.json").write_text(json.dumps(denoise_style))
    (tmp_path / "b.json").write_text(json.dumps({"Iz": [1e-5, 5e-5]}))
    assert read_ranges(tmp_path / "a.json") == {"Cm1": (0.2, 0.4)}
    assert read_ranges(tmp_path / "b.json") == {"Iz": (1e-5, 5e-5)}


@pytest.mark.parametrize("content, words", [
    ({"Xf": [0, 1]}, "unknown coefficient 'Xf'"),
    ({"Cm1": [0.4, 0.2]}, "lo < hi"),
    ({"Cm1": [0.1, float("inf")]}, "finite"),
    ({"Cm1": 0.3}, "expected [lo, hi]"),
    ([], "expected"),
])
def test_bad_ranges_files_are_named(tmp_path, content, words):
    path = tmp_path / "r.json"
    path.write_text(json.dumps(content))
    with pytest.raises(DdynError, match=words.replace("[", r"\[").replace("]", r"\]")):
        read_ranges(path)


def test_train_uses_records_and_reports_the_ranges(tmp_path, orca, shared_data, capsys):
    ds = simulate.simulate(orca, tracks.load_track("ethzMobil"), laps=1, seed=7, progress=False)
    data = write_canonical(ds, tmp_path / "lap.csv")
    lo, hi = 0.25, 0.32                                  # a narrower Cm1 range around the truth (0.287)
    (tmp_path / "r.json").write_text(json.dumps({"Cm1": [lo, hi]}))
    v2, record = with_ranges(orca, tmp_path / "r.json")
    assert v2.ranges["Cm1"] == (lo, hi) and v2.ranges["Iz"] == orca.ranges["Iz"]
    assert set(record["changed"]) == {"Cm1"}
    ck = tmp_path / "m.ckpt"
    assert cli_main(["train", "--data", str(data), "-o", str(ck), "--quiet", "--epochs", "1",
                     "--lbfgs-iterations", "0", "--hidden", "8", "--ranges", str(tmp_path / "r.json")]) == 0
    assert "guard ranges: from" in capsys.readouterr().out
    model, c = checkpoint.load(ck)
    i = c["ranges"]["names"].index("Cm1")
    assert (c["ranges"]["lo"][i], c["ranges"]["hi"][i]) == (lo, hi)        # the guard the model runs
    assert float(model.lo[i]) == lo and float(model.hi[i]) == hi           # ... after loading too
    assert c["ranges"]["source"]["changed"]["Cm1"]["vehicle"] == list(orca.ranges["Cm1"])
    assert cli_main(["evaluate", "--model", str(ck), "--data", str(data), "--out", str(tmp_path / "ev")]) == 0
    assert "guard ranges: from" in capsys.readouterr().out
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert metrics["guard_ranges"]["changed"]["Cm1"]["used"] == [lo, hi]
    # without --ranges the vehicle file's ranges, and the report says so
    ck2 = tmp_path / "n.ckpt"
    assert cli_main(["train", "--data", str(data), "-o", str(ck2), "--quiet", "--epochs", "1",
                     "--lbfgs-iterations", "0", "--hidden", "8"]) == 0
    assert "the vehicle file's" in capsys.readouterr().out
    assert checkpoint.load(ck2)[1]["ranges"]["source"] is None
