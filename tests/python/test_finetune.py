"""FTHD fine-tuning: freezing, the hybrid loss's weights, the derivative term, checkpoints, the study's smoke run."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import torch

from ddyn.data import simulate
from ddyn.data.dataset import write_canonical
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn import finetune as ft
from ddyn.learn.evaluate import evaluate
from ddyn.learn.training import TrainConfig, build_model
from ddyn.model import backends, tracks, vehicle
from ddyn.model.single_track import COEFF_NAMES
from ddyn.studies import fthd as fthd_study

TINY_FIT = ft.FitConfig(adam_steps=15, lbfgs_iterations=3, lr=3e-3, batch_size=128, eval_every=5)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def orca():
    return vehicle.load("orca_1_43")


@pytest.fixture(scope="module")
def lap(orca, shared_data):
    """One noise-free explicit-Euler lap of ETHZ."""
    return simulate.simulate(orca, tracks.load_track("ethz"), laps=1, seed=3, progress=False)


@pytest.fixture(scope="module")
def data(lap):
    pool, val = ft.split_by_time(lap, 0.3)
    return pool, val


@pytest.fixture(scope="module")
def base_path(orca, data, tmp_path_factory):
    """A tiny pre-trained DDM (3 dense layers of 8) saved as a normal checkpoint."""
    pool, val = data
    _, ckpt, _ = ft.train_scratch(orca, pool, val, TrainConfig(hidden=8, layers=3), TINY_FIT)
    return checkpoint.save(ckpt, tmp_path_factory.mktemp("base") / "base.ckpt")


@pytest.fixture(scope="module")
def lap_csv(lap, tmp_path_factory):
    return write_canonical(lap, tmp_path_factory.mktemp("lap") / "lap.csv")


def _constant_model(orca, coeffs: np.ndarray):
    """A DDM whose head ignores the history and outputs `coeffs` through the guard."""
    model = build_model(TrainConfig(hidden=8), orca, np.zeros(7), np.ones(7))
    lo, hi = orca.range_arrays()
    x = (coeffs - lo) / (hi - lo)
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.copy_(torch.as_tensor(np.log(x / (1 - x))))
    return model


def _cli(monkeypatch, argv):
    import ddyn.cli as cli

    monkeypatch.setattr(cli, "COMMANDS", cli.commands_named("evaluate", "finetune", "study"))
    return cli.main(argv)


# ---------------------------------------------------------------------------------------------
# lambdas and freezing

def test_lambdas_must_be_non_negative_and_sum_to_one():
    assert ft.check_lambdas(0.7, 0.3) == (0.7, 0.3)
    assert ft.check_lambdas(1.0, 0.0) == (1.0, 0.0)
    for bad in ((0.7, 0.7), (0.5, 0.4), (1.2, -0.2), (float("nan"), 1.0), (float("inf"), 0.0)):
        with pytest.raises(DdynError, match="lambda"):
            ft.check_lambdas(*bad)
    with pytest.raises(DdynError, match="lambda1 \\+ lambda2"):
        ft.FinetuneConfig(lambda1=0.3, lambda2=0.3)


def test_layer_list_and_freeze_counts(orca):
    model = build_model(TrainConfig(hidden=8, layers=2, gru_layers=1), orca, np.zeros(7), np.ones(7))
    names = [n for n, _ in ft.trainable_layers(model)]
    assert names == ["encoder.gru.l0", "encoder.dense.0", "encoder.dense.2", "head"]
    assert {id(p) for _, ps in ft.trainable_layers(model) for p in ps} == {id(p) for p in model.parameters()}
    assert ft.freeze_count(4, 0.0) == 0
    assert ft.freeze_count(4, 0.5) == 2
    for fraction in (0.75, 1.0):  # would leave no hidden layer (or nothing at all) trainable
        with pytest.raises(DdynError, match="at least one hidden layer"):
            ft.freeze_count(4, fraction)
    with pytest.raises(DdynError, match="at least one hidden layer"):
        ft.freeze_count(2, 0.5)  # one dense layer + head: the only hidden layer may not be frozen
    with pytest.raises(DdynError, match="fraction"):
        ft.freeze_count(4, 1.5)
    frozen, trainable = ft.freeze(model, 0.5)
    assert frozen == ["encoder.gru.l0", "encoder.dense.0"] and trainable == ["encoder.dense.2", "head"]
    assert not any(p.requires_grad for p in model.encoder.gru.parameters())
    assert all(p.requires_grad for p in model.head.parameters())


def test_finetune_changes_exactly_the_unfrozen_layers(base_path, data):
    pool, val = data
    base = checkpoint.read(base_path)["state_dict"]
    model, ckpt = ft.finetune(base_path, pool, val, ft.FinetuneConfig(freeze_fraction=0.5, fit=TINY_FIT))
    assert ckpt["finetune"]["frozen_layers"] == ["encoder.dense.0", "encoder.dense.2"]
    after = model.state_dict()
    for key in base:
        same = torch.equal(base[key], after[key])
        frozen = key.startswith(("encoder.dense.0.", "encoder.dense.2."))
        # the feature range is widened to the fine-tuning rows: here the base's own rows, so it stays
        if frozen or key in ("encoder.mean", "encoder.std", "encoder.feature_lo", "encoder.feature_hi", "lo", "hi"):
            assert same, f"{key} changed although frozen"
        else:
            assert not same, f"{key} did not change although trainable"
    assert ckpt["finetune"]["optimizer_steps"] == {"adam": TINY_FIT.adam_steps, "lbfgs": TINY_FIT.lbfgs_iterations}


def test_finetune_refuses_freezing_everything(base_path, data):
    pool, val = data
    with pytest.raises(DdynError, match="at least one hidden layer"):
        ft.finetune(base_path, pool, val, ft.FinetuneConfig(freeze_fraction=1.0, fit=TINY_FIT))


# ---------------------------------------------------------------------------------------------
# the derivative term

def test_derivative_term_vanishes_for_true_coefficients_on_euler_data(orca, lap):
    w = ft.windows_of(lap, 1)
    b = ft.batch_of(lap, w)
    scale = torch.as_tensor(ft.one_step_scale(w))
    true = orca.true_vector()
    with torch.no_grad():
        assert float(ft.derivative_loss(_constant_model(orca, true), b, scale)) < 1e-24
        for name, factor in (("Bf", 1.2), ("Cm1", 0.9), ("Iz", 1.1)):
            wrong = true.copy()
            wrong[COEFF_NAMES.index(name)] *= factor
            assert float(ft.derivative_loss(_constant_model(orca, wrong), b, scale)) > 1e-3, name


def test_derivative_term_matches_a_hand_computation(orca, lap):
    torch.manual_seed(1)
    model = build_model(TrainConfig(hidden=8), orca, np.zeros(7), np.ones(7) * 3.0)  # random weights
    rows = np.array([0, 5, 6, 100])  # row 0 has no previous row: it gets no derivative term
    w = ft.windows_of(lap, 1).subset(rows)  # tau 1: window i ends at row i
    b = ft.batch_of(lap, w)
    assert b.has_prev.tolist() == [False, True, True, True]
    scale_np = np.array([0.01, 0.002, 0.05])
    with torch.no_grad():
        c = model.coefficients(b.history)
        r = ft.derivative_residual(model, c, b).numpy()
        loss = float(ft.derivative_loss(model, b, torch.as_tensor(scale_np)))
    c = c.numpy()
    Ts, p = orca.sample_time, orca.known
    x, u = lap.states[rows], lap.inputs[rows]
    xp, up = lap.states[rows - 1], lap.inputs[rows - 1]
    pred = backends.step_numpy(x, u, c, p, Ts)
    f_prev = backends.derivatives_numpy(xp, up, c, p)[:, 3:6]
    f_now = backends.derivatives_numpy(x, u, c, p)[:, 3:6]
    hand = (pred[:, 3:6] - xp[:, 3:6]) / (2 * Ts) - 0.5 * (f_prev + f_now)
    np.testing.assert_allclose(r[1:], hand[1:], rtol=1e-10, atol=1e-12)
    # Euler: the term is half the mismatch between the last measured transition and c_k's acceleration there
    euler = 0.5 * ((x[:, 3:6] - xp[:, 3:6]) / Ts - f_prev)
    np.testing.assert_allclose(r[1:], euler[1:], rtol=1e-8, atol=1e-10)
    expected = np.mean((2 * Ts * hand[1:] / scale_np) ** 2)
    assert loss == pytest.approx(expected, rel=1e-10)


def test_hybrid_loss_weights_the_two_terms(orca, lap):
    torch.manual_seed(2)
    model = build_model(TrainConfig(hidden=8), orca, np.zeros(7), np.ones(7))
    w = ft.windows_of(lap, 1).subset(slice(10, 60))
    b = ft.batch_of(lap, w)
    scale = torch.as_tensor(ft.one_step_scale(w))
    with torch.no_grad():
        total, sup, der = ft.hybrid_loss(model, b, scale, 0.3, 0.7)
    assert float(total) == pytest.approx(0.3 * float(sup) + 0.7 * float(der), rel=1e-12)
    assert float(der) > 0 and float(sup) > 0


# ---------------------------------------------------------------------------------------------
# checkpoints and the command line

def test_finetuned_checkpoint_loads_and_evaluates(base_path, data, tmp_path):
    pool, val = data
    model, ckpt = ft.finetune(base_path, pool, val,
                              ft.FinetuneConfig(freeze_fraction=0.3, lambda1=0.6, lambda2=0.4, data_fraction=0.5,
                                                fit=TINY_FIT))
    path = checkpoint.save(ckpt, tmp_path / "fthd.ckpt")
    loaded, ck = checkpoint.load(path)
    assert ck["kind"] == "ddm"
    f = ck["finetune"]
    assert f["base_sha256"] == checkpoint.file_sha256(base_path)
    assert f["lambdas"] == {"lambda1": 0.6, "lambda2": 0.4}
    assert f["data_fraction"] == 0.5 and f["frozen_layers"] == ["encoder.dense.0"]
    assert f["train_rows"] == round(len(pool) * 0.5)
    m = evaluate(loaded, ck, val)
    assert m["samples"] > 0 and all(np.isfinite(v) for v in m["rmse"].values())
    assert m["coefficients"]["Bf"]["true"] == pytest.approx(5.579)


def test_scratch_and_finetune_take_the_same_counted_steps(orca, base_path, data):
    pool, val = data
    _, ddm, _ = ft.train_scratch(orca, pool, val, TrainConfig(hidden=8, layers=3), TINY_FIT)
    _, fthd = ft.finetune(base_path, pool, val, ft.FinetuneConfig(fit=TINY_FIT))
    assert ddm["training"]["optimizer_steps"] == fthd["training"]["optimizer_steps"] == {"adam": 15, "lbfgs": 3}


def test_cli_finetune_then_evaluate(monkeypatch, base_path, lap_csv, tmp_path, capsys):
    out = tmp_path / "ft.ckpt"
    assert _cli(monkeypatch, ["finetune", "--base", str(base_path), "--data", str(lap_csv), "-o", str(out),
                              "--fraction", "0.5", "--adam-steps", "10", "--lbfgs-iterations", "2", "--quiet",
                              "--metrics-json", str(tmp_path / "m.json")]) == 0
    assert "frozen: encoder.dense.0" in capsys.readouterr().out
    assert json.loads((tmp_path / "m.json").read_text())["validation"]["samples"] > 0
    assert _cli(monkeypatch, ["evaluate", "--model", str(out), "--data", str(lap_csv)]) == 0
    assert "one-step RMSE" in capsys.readouterr().out


@pytest.mark.parametrize("extra, message", [(["--lambda1", "0.7", "--lambda2", "0.7"], "must equal 1"),
                                            (["--freeze-fraction", "1"], "at least one hidden layer")])
def test_cli_refuses_bad_settings(monkeypatch, base_path, lap_csv, tmp_path, capsys, extra, message):
    argv = ["finetune", "--base", str(base_path), "--data", str(lap_csv), "-o", str(tmp_path / "x.ckpt"),
            "--adam-steps", "2", "--lbfgs-iterations", "0", "--quiet"] + extra
    assert _cli(monkeypatch, argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.ckpt").exists()


def test_register_adds_both_subcommands():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    ft.register(sub)
    fthd_study.register(sub)
    args = parser.parse_args(["fthd", "sim", "--quick"])
    assert args.which == "sim" and args.quick
    args = parser.parse_args(["finetune", "--base", "b", "--data", "d", "-o", "o"])
    assert (args.lambda1, args.lambda2, args.freeze_fraction, args.fraction) == (0.5, 0.5, 0.5, 1.0)


# ---------------------------------------------------------------------------------------------
# the study

def test_fthd_beats_scratch_at_small_fractions_over_seeds(monkeypatch, shared_data, tmp_path):
    """The paper's claim at small data fractions, in quick mode: fine-tuning the pre-trained DDM beats
    training from scratch with the same counted steps. One training seed is a thin sample (seed 0: FTHD/DDM
    validation loss 0.55, 0.97, 0.11 at 30, 20, 15 %; seed 5 lost at 20 %, 1.004), so the measured quantity
    is the median of the ratio over five training seeds (both arms seeded alike), per fraction; the bound
    stays 1 (FTHD better). Measured over seeds 0-4: medians 0.38, 0.59, 0.32 (over seeds 0-9: 0.48, 0.57,
    0.17); the full study: 38-115x."""
    import dataclasses
    data = fthd_study.sim_data(tmp_path / "data", True)
    settings = fthd_study.settings
    ratios: dict[float, list[float]] = {}
    for seed in range(5):
        def seeded(quick, seed=seed):
            st = settings(quick)
            return dataclasses.replace(st, ddm=dataclasses.replace(st.ddm, seed=seed),
                                       fthd=dataclasses.replace(st.fthd, seed=seed))
        monkeypatch.setattr(fthd_study, "settings", seeded)
        res = fthd_study.run_setting("sim", data, tmp_path / f"seed{seed}", (0.3, 0.2, 0.15), True, progress=False)
        for r in res["fractions"]:
            assert r["ddm"]["steps"] == r["fthd"]["steps"]
            ratios.setdefault(r["fraction"], []).append(r["fthd"]["min_val_loss"] / r["ddm"]["min_val_loss"])
    medians = {f: float(np.median(v)) for f, v in ratios.items()}
    assert all(m < 1.0 for m in medians.values()), (medians, ratios)


def test_study_quick_runs_end_to_end(monkeypatch, shared_data, tmp_path):
    out = tmp_path / "study"
    assert _cli(monkeypatch, ["study", "fthd", "all", "--quick", "--quiet", "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert [r["fraction"] for r in res["sim"]["fractions"]] == list(fthd_study.SIM_FRACTIONS)
    for source in ("sim", "log"):
        assert [r["fraction"] for r in res["real"][source]["fractions"]] == list(fthd_study.REAL_FRACTIONS)
    for r in res["sim"]["fractions"]:
        assert r["ddm"]["steps"] == r["fthd"]["steps"]
        assert set(r["fthd"]["coefficients"]) == set(r["ddm"]["coefficients"])
        assert np.isfinite(r["fthd"]["coefficients"]["Bf"]["abs_error"])
        # the paper's claim at small fractions: test_fthd_beats_scratch_at_small_fractions_over_seeds (one
        # seed's 0.41 against 0.43 at 20 % was too thin a margin to assert, issue 35)
    assert [r["fraction"] for r in res["sim"]["budget_check"]["fractions"]] == [0.8, 0.15]
    assert {"sim_val_loss", "sim_coefficients", "real_sim_val_loss", "real_log_val_loss"} <= set(res["targets"])
    md = (out / "results.md").read_text()
    assert "Quick mode" in md and "| fraction |" in md and "## Targets" in md
    assert (out / "sim" / "f15" / "tyre_curves.png").stat().st_size > 1000
    # every checkpoint the study writes is a normal one
    model, ck = checkpoint.load(out / "sim" / "f15" / "fthd.ckpt")
    assert ck["finetune"]["data_fraction"] == 0.15
