"""Smoke runs of commands that had no test: `ddyn study ddm --quick`, `ddyn codegen check` with its
default tool, `ddyn bench runtime` (MPC rows). They use the tools of the test build (scripts/test.sh
builds build/ before pytest) and fail, not skip, when a tool is missing."""
from __future__ import annotations

import json

import pytest

from ddyn.analysis.crosscheck import DEFAULT_BINARY
from ddyn.cli import build_parser, commands_named
from ddyn.control.mpc_lap import DEFAULT_TOOL as MPC_LAP_TOOL
from ddyn.data import simulate
from ddyn.data.dataset import write_canonical
from ddyn.model import tracks, vehicle


def _run(argv: list[str], *commands: str) -> int:
    args = build_parser(commands_named(*commands)).parse_args(argv)
    return int(args.func(args) or 0)


def test_study_ddm_quick_writes_its_table(tmp_path, shared_data):
    out = tmp_path / "study"
    assert _run(["study", "ddm", "sim", "--quick", "--out", str(out)], "study") == 0
    res = json.loads((out / "results.json").read_text())
    assert res["quick"] is True and res["sim"] and res["real"] is None
    md = (out / "results.md").read_text()
    assert "DDM" in md and "|" in md


def test_study_ddm_real_only_one_run_with_its_seed(tmp_path, shared_data):
    """`--only` trains the named real run alone and `--seed` and `--guard-prior` reach its training (recorded in
    the checkpoint); without `--guard-prior` each run trains with its own fields (the last row's REAL_GUARD_PRIOR
    and REAL_TAU); an unknown run name is an error, not an empty table."""
    from ddyn.errors import DdynError
    from ddyn.learn import checkpoint
    from ddyn.studies.ddm import REAL_GUARD_PRIOR, REAL_TAU

    out = tmp_path / "study"
    assert _run(["study", "ddm", "real", "--quick", "--only", "ddm_putnam_powertrain", "--seed", "3",
                 "--guard-prior", "0.02", "--out", str(out)], "study") == 0
    real = json.loads((out / "results.json").read_text())["real"]
    assert [r["name"] for r in real] == ["ddm_putnam_powertrain"] and real[0]["seed"] == 3
    assert isinstance(real[0]["restarts"], list) and real[0]["restarts_requested"] == 1   # the records, not the count
    assert real[0]["guard_prior"] == 0.02 and "(guard prior 0.02)" in real[0]["label"]
    _, ckpt = checkpoint.load(out / "real" / "ddm_putnam_powertrain" / "model.ckpt")
    assert ckpt["config"]["seed"] == 3 and ckpt["config"]["guard_prior"] == 0.02
    with pytest.raises(DdynError, match="unknown real run"):
        _run(["study", "ddm", "real", "--quick", "--only", "ddm_nope", "--out", str(out)], "study")
    assert _run(["study", "ddm", "real", "--quick", "--only", "ddm_putnam_powertrain_prior_tau", "--out", str(out)],
                "study") == 0
    real = json.loads((out / "results.json").read_text())["real"]
    assert real[0]["guard_prior"] == REAL_GUARD_PRIOR and "(guard prior" not in real[0]["label"]
    _, ckpt = checkpoint.load(out / "real" / "ddm_putnam_powertrain_prior_tau" / "model.ckpt")
    assert ckpt["config"]["guard_prior"] == REAL_GUARD_PRIOR and ckpt["config"]["tau"] == REAL_TAU
    # --tau and --method reach every run's training and its label
    assert _run(["study", "ddm", "real", "--quick", "--only", "ddm_putnam_powertrain_prior", "--tau", "2",
                 "--method", "rk4", "--out", str(out)], "study") == 0
    real = json.loads((out / "results.json").read_text())["real"]
    assert real[0]["tau"] == 2 and "(history 2)" in real[0]["label"] and "(rk4 step)" in real[0]["label"]
    _, ckpt = checkpoint.load(out / "real" / "ddm_putnam_powertrain_prior" / "model.ckpt")
    assert ckpt["config"]["tau"] == 2 and ckpt["config"]["method"] == "rk4"


def test_codegen_check_passes_with_the_default_tool(tmp_path, shared_data, capsys):
    assert DEFAULT_BINARY.is_file(), f"{DEFAULT_BINARY} missing: scripts/test.sh builds it before pytest"
    v = vehicle.load("orca_1_43")
    ds = simulate.simulate(v, tracks.load_track("ethzMobil"), laps=1, seed=11, progress=False)
    data = write_canonical(ds, tmp_path / "lap.csv")
    assert _run(["codegen", "check", "--data", str(data), "--method", "rk4"], "codegen") == 0
    assert "PASS" in capsys.readouterr().out


def test_bench_runtime_mpc_rows(tmp_path, shared_data):
    assert MPC_LAP_TOOL.is_file(), f"{MPC_LAP_TOOL} missing: scripts/test.sh builds it before pytest"
    out = tmp_path / "bench.json"
    assert _run(["bench", "runtime", "--mpc-ipopt-steps", "3", "--mpc-sqp-steps", "0", "--out", str(out)],
                "bench") == 0
    r = json.loads(out.read_text())["mpc_step"]
    assert r["c"]["median_us"] > 0 and r["c"]["p99_us"] >= r["c"]["median_us"]
    assert r["c_closed_loop"]["violation_steps"] == 0
    ipopt = r["alternatives"]["ipopt"]
    assert ipopt["c_faster_median"] == pytest.approx(ipopt["stats"]["median_us"] / r["c"]["median_us"])
