"""The gap diagnosis's shape: every benchmark module implements the one interface, no module assigns another
module's globals at run time, settings and calibrations come from files with one-line errors, and the commands
stay small."""
from __future__ import annotations

import ast
import importlib
import json
from pathlib import Path

import pytest

import ddyn
from ddyn.cli import build_parser, main
from ddyn.gap import calibration as CAL
from ddyn.gap.benchmark import base
from ddyn.gap.config import DiagnosisConfig

PACKAGE = Path(ddyn.__file__).parent


@pytest.mark.parametrize("name", sorted(base.MODULES))
def test_every_benchmark_module_implements_the_interface(name):
    mod = importlib.import_module(base.MODULES[name])
    missing = [f for f in base.INTERFACE if not callable(getattr(mod, f, None))]
    assert not missing, f"{base.MODULES[name]} lacks {missing}"


def test_no_module_assigns_another_modules_globals():
    """`X.NAME = value` on an imported module (what `study gap` once did to the diagnosis's defaults) makes a
    function behave differently after another ran in the same process; settings travel as DiagnosisConfig."""
    offenders = []
    for f in sorted(PACKAGE.rglob("*.py")):
        imported = set()
        tree = ast.parse(f.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                imported |= {(a.asname or a.name).split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                imported |= {a.asname or a.name for a in node.names}
        for node in ast.walk(tree):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] \
                if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else []
            for t in targets:
                if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id in imported \
                        and t.attr.isupper():
                    offenders.append(f"{f.relative_to(PACKAGE)}:{node.lineno} {t.value.id}.{t.attr}")
    assert not offenders, offenders


def _options(parser) -> dict:
    for action in parser._actions:
        if action.__class__.__name__ == "_SubParsersAction":
            return action.choices
    return {}


def test_the_gap_commands_are_small():
    gap = _options(build_parser())["gap"]
    for name, sub in _options(gap).items():
        flags = [a for a in sub._actions if a.option_strings and a.dest != "help"]
        assert len(flags) <= 12, f"ddyn gap {name}: {len(flags)} options"


def test_a_bad_config_is_one_line_naming_the_file_and_key(tmp_path, capsys):
    log = tmp_path / "none.csv"
    for text, msg in (('fit = "two-step"\n', "unknown fit 'two-step'"), ("warp = 1\n", "unknown key(s) warp"),
                      ("[diagnosis\n", "not valid TOML"), ("gate = -1\n", "gate: -1 is outside"),
                      ('[diagnosis]\nhold = 2\n', "hold: expected true, false")):
        cfg = tmp_path / "c.toml"
        cfg.write_text(text)
        assert main(["gap", "diagnose", "--vehicle", "orca_1_43", "--data", str(log), "--out", str(tmp_path / "o"),
                     "--config", str(cfg)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(cfg) in err and msg in err, err
    assert main(["gap", "diagnose", "--vehicle", "orca_1_43", "--data", str(log), "--out", str(tmp_path / "o"),
                 "--config", "no-such-config"]) == 2
    assert "no such file, nor a shipped config (dbw, sweep)" in capsys.readouterr().err


def test_calibrate_from_recorded_sweeps(tmp_path, capsys):
    """`ddyn gap calibrate --from-runs`: the calibration of recorded sweeps, written as one file that loads back
    with its settings, margin, thresholds, decision levels, claim record and code version."""
    def row(e, mag, top1, dbic=-40.0):
        return {"status": "ok", "effect": e, "magnitude": mag, "estimate": mag * 1.02, "top1": top1,
                "correct": top1 == e, "selected_without_gate": [] if top1 == "none" else [top1], "gate_ratio": 1.1,
                "delta_bic_top": dbic}
    runs = []
    for seed in (11, 13):
        rs = [row("throttle_delay", m, "throttle_delay" if m > 0.06 else "none") for m in (0.05, 0.08, 0.12, 0.2)]
        rs += [row("none", 0.0, "none"), row("none", 0.0, "mass_offset", -3.0 - seed)]
        doc = {"settings": {"plant": "commonroad", "case_set": "sweep", "duration": 60.0, "seed": seed,
                            "track": "putnam", "car": "commonroad_vehicle2", "nominal": "mapped", "sample_time": 0.04,
                            "pitch_channel": False, "roll_channel": False,
                            "diagnosis": DiagnosisConfig(hold=True).to_dict()}, "results": rs}
        p = tmp_path / f"sweep_{seed}.json"
        p.write_text(json.dumps(doc))
        runs.append(str(p))
    out = tmp_path / "cal.json"
    assert main(["gap", "calibrate", "--from-runs", ",".join(runs), "--out", str(out)]) == 0
    cal = CAL.load(out)
    assert cal.name == "cal" and cal.seeds == (11, 13) and cal.cases == 12 and cal.duration == 60.0
    assert cal.margin == pytest.approx(16.0)   # 4 effect-free logs: 5 % allows no alarm, so the larger (-3 - 13)
    assert cal.thresholds["throttle_delay"] == pytest.approx(0.08) and cal.decision_levels["throttle_delay"] > 0
    assert cal.stale() is None and cal.applied().hold is True
    assert "calibration cal: 12 cases of 60 s logs" in capsys.readouterr().out
    (tmp_path / "bad.json").write_text("{")
    assert main(["gap", "calibrate", "--from-runs", str(tmp_path / "bad.json"), "--out", str(out)]) == 2
    assert "--from-runs" in capsys.readouterr().err
