"""Results as data: every result file validates, the README's table is the one the files give, a bad file is one
line naming the file and key, the checker names a moved figure, and the fast figures re-run and hold."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pytest

from ddyn.errors import DdynError
from ddyn.results import cli as results_cli
from ddyn.results.check import check_result
from ddyn.results.files import RESULTS_DIR, load, load_all
from ddyn.results.table import MAX_ROWS, README, readme_with_table, rows_of

FAST = ("fidelity", "codegen_check", "gap_main_job")


def _good(tmp_path: Path, name: str = "tiny", value=1.0, command: str | None = None) -> dict:
    return {
        "name": name, "title": "a tiny figure", "summary": "a = {a:.2f}",
        "figures": {"a": {"value": value, "unit": "m", "tolerance": {"abs": 0.01},
                          "source": {"file": "o.json", "path": "x.a"}}},
        "commands": [command or f"{sys.executable} -c \"import json; json.dump({{'x': {{'a': 1.0}}}}, open('o.json', 'w'))\""],
        "fast": True, "holds": {"status": "holds", "why": "a test"}, "doc": "docs/model.md#measured-figures",
        "measured": {"date": "2026-11-28", "commit": "3a50f07", "how": "re-measured"}, "readme": None,
    }


def _write(tmp_path: Path, raw: dict) -> Path:
    p = tmp_path / f"{raw['name']}.json"
    p.write_text(json.dumps(raw))
    return p


def test_every_result_file_validates():
    results = load_all()
    assert len(results) >= 15
    assert {r.name for r in results} >= set(FAST)
    assert sorted(r.name for r in results if r.fast) == sorted(FAST)
    rows = rows_of(results)
    assert 0 < len(rows) <= MAX_ROWS
    # a file that does not hold says why, and the README row shows it
    for r in results:
        if not r.holds_ok:
            assert r.holds_why and "does not hold" in r.measured_text(), r.name


def test_readme_table_is_current_and_readme_small():
    text = README.read_text()
    assert readme_with_table(text, load_all()) == text, "README.md's results table is stale: ddyn results table --write"
    assert len(text.encode()) <= 20_000


def test_denoising_row_shows_raw_savgol_and_ekf():
    r = load(RESULTS_DIR / "denoise_sim.json")
    text = r.measured_text()
    assert "raw" in text and "Savitzky-Golay" in text and "EKF-FTHD" in text


@pytest.mark.parametrize("change, key", [
    (lambda d: d.pop("commands"), "commands"),
    (lambda d: d["figures"]["a"].pop("tolerance"), "figures.a.tolerance"),
    (lambda d: d["figures"]["a"].update(tolerance={"abs": 1, "rel": 1}), "figures.a.tolerance"),
    (lambda d: d["figures"]["a"].update(kind="count"), "figures.a.value"),
    (lambda d: d["holds"].update(status="maybe"), "holds.status"),
    (lambda d: d.update(fast="yes"), "fast"),
    (lambda d: d.update(doc="docs/model.md#no-such-heading"), "doc"),
    (lambda d: d["measured"].update(commit="HEAD"), "measured.commit"),
    (lambda d: d.update(summary="a = {b}"), "summary"),
    (lambda d: d.update(colour="red"), "colour"),
])
def test_bad_file_is_one_line_naming_file_and_key(tmp_path, change, key):
    raw = _good(tmp_path)
    change(raw)
    p = _write(tmp_path, raw)
    with pytest.raises(DdynError) as e:
        load(p)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(f"{p}: {key}"), msg


def test_not_json_is_one_line(tmp_path):
    p = tmp_path / "broken.json"
    p.write_text('{"name": ')
    with pytest.raises(DdynError, match=r"broken\.json: not valid JSON"):
        load(p)


def test_checker_passes_a_held_figure_and_names_a_moved_one(tmp_path):
    ok = check_result(load(_write(tmp_path, _good(tmp_path, "held", 1.0))))
    assert [(o.figure, o.status) for o in ok] == [("a", "PASS")]
    moved = check_result(load(_write(tmp_path, _good(tmp_path, "moved", 1.5))))
    assert [(o.figure, o.status, o.old, o.new) for o in moved] == [("a", "MOVED", 1.5, 1.0)]
    assert moved[0].line().startswith("MOVED  moved.a: 1.5 -> 1")
    failed = check_result(load(_write(tmp_path, _good(tmp_path, "failing", 1.0, "exit 3"))))
    assert failed[0].status == "FAILED" and "exited 3" in failed[0].line()


def test_check_command_exit_code(tmp_path, capsys):
    _write(tmp_path, _good(tmp_path, "held", 1.0))
    _write(tmp_path, _good(tmp_path, "moved", 1.5))
    parser = argparse.ArgumentParser()
    results_cli.register(parser.add_subparsers())
    args = parser.parse_args(["check", "--quiet", "--dir", str(tmp_path), "held"])
    assert args.func(args) == 0
    args = parser.parse_args(["check", "--quiet", "--dir", str(tmp_path)])
    assert args.func(args) == 1
    out = capsys.readouterr().out
    assert "PASS   held.a: 1 -> 1" in out and "MOVED  moved.a: 1.5 -> 1" in out


@pytest.mark.parametrize("name", FAST)
def test_fast_figure_reruns_and_holds(name):
    outcomes = check_result(load(RESULTS_DIR / f"{name}.json"))
    assert outcomes and all(o.status == "PASS" for o in outcomes), "\n".join(o.line() for o in outcomes)
