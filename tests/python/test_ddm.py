"""DDM / DPM: windows and splits, the guard, training, checkpoints, evaluation (tiny models, short logs)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ddyn.cli import main as cli_main
from ddyn.data import simulate
from ddyn.data.dataset import Dataset, write_canonical
from ddyn.data.windows import make_windows, split_train_validation
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn.evaluate import evaluate
from ddyn.learn.training import TrainConfig, build_model, train
from ddyn.model import tracks, vehicle

TINY = dict(epochs=3, lbfgs_iterations=20, hidden=16, batch_size=128)


@pytest.fixture(scope="module")
def orca():
    return vehicle.load("orca_1_43")


@pytest.fixture(scope="module")
def lap(orca, shared_data):
    return simulate.simulate(orca, tracks.load_track("ethz"), laps=1, seed=3, progress=False)


def _result(ds, v, **over):
    return train(ds, v, TrainConfig(**{**TINY, **over}), progress=False)


def test_windows_never_cross_segments():
    n = 20
    seg = np.array([0] * 8 + [1] * 12)
    ds = Dataset(np.arange(n) * 0.02 + seg * 10, seg, np.random.rand(n, 8), np.random.rand(n, 2), 0.02)
    w = make_windows(ds, tau=3)
    for k in w.end_row:
        assert ds.segment[k - 2] == ds.segment[k] == ds.segment[k + 1]
    assert np.array_equal(w.target, ds.states[w.end_row + 1, 3:6])
    assert np.array_equal(w.history[:, -1, :3], ds.states[w.end_row, 3:6])


def test_split_is_disjoint_by_rows(lap):
    tau = 4
    tr, va = split_train_validation(lap, tau, 0.2)
    rows_tr = set((tr.end_row[:, None] + np.arange(-tau + 1, 2)).ravel())
    rows_va = set((va.end_row[:, None] + np.arange(-tau + 1, 2)).ravel())
    assert not rows_tr & rows_va, "a row is read by both training and validation windows"
    assert tr.end_row.max() < va.end_row.min()


def test_guard_keeps_every_coefficient_in_range(orca, lap):
    w = make_windows(lap, 3)
    model = build_model(TrainConfig(tau=3, hidden=16), orca, np.zeros(7), np.ones(7))
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 50.0)  # absurd weights: logits far beyond the sigmoid's range
        c = model.coefficients(torch.as_tensor(w.history)).numpy()
    lo, hi = orca.range_arrays()
    assert np.all((c >= lo) & (c <= hi))


def _truth_model(v, tau=3):
    """A DDM whose head outputs exactly the vehicle's true coefficients (zero weights, inverse-sigmoid bias)."""
    model = build_model(TrainConfig(tau=tau, hidden=16), v, np.zeros(7), np.ones(7))
    lo, hi = v.range_arrays()
    frac = (v.true_vector() - lo) / (hi - lo)
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.copy_(torch.as_tensor(np.log(frac / (1 - frac))))
    return model.eval()


def _minimal_ckpt(v, tau=3):
    lo, hi = v.range_arrays()
    return {"config": {"tau": tau}, "architecture": {"outputs": list(checkpoint.COEFF_NAMES)},
            "ranges": {"lo": list(lo), "hi": list(hi)}, "vehicle": {"name": v.name, "json": v.raw_json}}


def test_true_coefficients_give_zero_error_on_euler_data(orca, lap):
    """The whole evaluation path (windows, physics step, rollout) against exact data."""
    m = evaluate(_truth_model(orca), _minimal_ckpt(orca), lap)
    assert max(m["rmse"].values()) < 1e-12
    assert m["ade"] < 1e-10 and m["fde"] < 1e-10
    assert m["truth_source"].startswith("plant coefficients")
    # "nothing changes" on the same windows and starts: worse than the exact model on a lap that turns and
    # changes speed
    ref = m["reference"]
    assert ref["samples"] == m["samples"] and ref["starts"] == m["starts"]
    assert min(ref["rmse"].values()) > 1e-6 and ref["ade"] > 1e-4
    lo, hi = orca.range_arrays()
    for i, (name, c) in enumerate(m["coefficients"].items()):
        assert abs(c["rel_error"] or 0) < 1e-9, name
        # flagged exactly when the truth itself lies within 1 % of the range of a bound (Er = -0.019 of [-2, 0])
        near = min(c["true"] - lo[i], hi[i] - c["true"]) <= 0.01 * (hi[i] - lo[i])
        assert (c["at_lower_bound"] + c["at_upper_bound"] == 1.0) == near, name


def test_saturated_guard_is_reported(orca, lap):
    model = _truth_model(orca)
    with torch.no_grad():
        model.head.bias[16] = 40.0  # Iz pinned at its upper bound
    m = evaluate(model, _minimal_ckpt(orca), lap)
    assert m["coefficients"]["Iz"]["at_upper_bound"] == 1.0
    assert m["coefficients"]["Bf"]["at_upper_bound"] == 0.0


def test_training_learns_and_is_deterministic(orca, lap):
    a = _result(lap, orca, seed=5)
    b = _result(lap, orca, seed=5)
    c = _result(lap, orca, seed=6)
    curve = [h["val_loss"] for h in a.history]
    assert a.best_val_loss < 0.5 * curve[0], "validation loss did not fall"
    assert a.best_val_loss == b.best_val_loss
    for k, v in a.model.state_dict().items():
        assert torch.equal(v, b.model.state_dict()[k]), k
    assert c.best_val_loss != a.best_val_loss


def test_restarts_keep_the_lowest_validation_loss(orca, lap):
    """restarts=3 trains seeds 5, 6, 7 and keeps the one that validates best: the same model as that seed's own
    training; every restart recorded in the checkpoint with its loss and its guard saturation on the validation
    part."""
    alone = {s: _result(lap, orca, seed=s) for s in (5, 6, 7)}
    r = _result(lap, orca, seed=5, restarts=3)
    assert [x["seed"] for x in r.restarts] == [5, 6, 7]
    assert [x["best_val_loss"] for x in r.restarts] == [alone[s].best_val_loss for s in (5, 6, 7)]
    assert [x["validation_saturation"] for x in r.restarts] == [alone[s].validation_saturation for s in (5, 6, 7)]
    assert all(0.0 <= x["validation_saturation"]["share"] <= 1.0 for x in r.restarts)
    kept = min(alone, key=lambda s: alone[s].best_val_loss)
    assert len({alone[s].best_val_loss for s in alone}) == 3     # a real choice
    assert r.seed == kept and r.best_val_loss == alone[kept].best_val_loss
    for k, v in r.model.state_dict().items():
        assert torch.equal(v, alone[kept].model.state_dict()[k]), k
    ck = checkpoint.make(r, orca, lap.content_hash(), "lap", len(lap))
    assert ck["training"]["seed"] == kept and len(ck["training"]["restarts"]) == 3
    assert ck["config"]["seed"] == 5 and ck["config"]["restarts"] == 3
    with pytest.raises(DdynError, match="restarts"):
        TrainConfig(restarts=0)


def test_dpm_uses_given_inertia_and_trains(orca, lap):
    r = _result(lap, orca, kind="dpm", dpm_iz_scale=1.2)
    assert r.model.iz == pytest.approx(1.2 * orca.true_coefficients["Iz"])
    assert np.isfinite(r.best_val_loss)


def test_checkpoint_round_trip_and_refusals(orca, lap, tmp_path):
    r = _result(lap, orca)
    path = checkpoint.save(checkpoint.make(r, orca, lap.content_hash(), "lap", len(lap)), tmp_path / "m.ckpt")
    model, ckpt = checkpoint.load(path)
    assert ckpt["data"]["train_sha256"] == lap.content_hash()
    assert ckpt["vehicle"]["sha256"] == orca.digest
    w = make_windows(lap, r.config.tau)
    args = [torch.as_tensor(a) for a in (w.history, w.state, w.inputs)]
    with torch.no_grad():
        assert torch.equal(model(*args)[0], r.model(*args)[0])
    (tmp_path / "bad.ckpt").write_bytes(path.read_bytes()[:100])
    with pytest.raises(DdynError, match="not a readable checkpoint"):
        checkpoint.read(tmp_path / "bad.ckpt")
    ckpt["version"] = 99
    torch.save(ckpt, tmp_path / "v99.ckpt")
    with pytest.raises(DdynError, match="version 99"):
        checkpoint.read(tmp_path / "v99.ckpt")


def test_cli_train_and_evaluate(lap, tmp_path, capsys):
    data = write_canonical(lap, tmp_path / "lap.csv")
    ck = tmp_path / "m.ckpt"
    assert cli_main(["train", "--data", str(data), "-o", str(ck), "--quiet", "--epochs", "2",
                     "--lbfgs-iterations", "0", "--hidden", "8", "--restarts", "2"]) == 0
    assert "restarts: kept seed" in capsys.readouterr().out
    assert cli_main(["evaluate", "--model", str(ck), "--data", str(data), "--out", str(tmp_path / "ev")]) == 0
    out = capsys.readouterr().out
    assert "one-step RMSE" in out and "ADE" in out and "reference, nothing changes" in out
    for f in ("metrics.json", "tyre_curves.png", "predictions.png"):
        assert (tmp_path / "ev" / f).stat().st_size > 0


def test_evaluate_refuses_other_vehicle(lap, tmp_path, shared_data):
    data = write_canonical(lap, tmp_path / "lap.csv")
    ck = tmp_path / "m.ckpt"
    cli_main(["train", "--data", str(data), "-o", str(ck), "--quiet", "--epochs", "1", "--lbfgs-iterations", "0"])
    putnam = shared_data / "real" / "Putnam_park2023_run4_2.csv"
    assert cli_main(["evaluate", "--model", str(ck), "--data", str(putnam)]) == 2


def test_evaluate_reads_the_racecar_format_directly(tmp_path, shared_data):
    """A tiny full-scale DDM trained on a piece of the real log evaluates on the raw RACECAR CSV."""
    from ddyn.data.importers import load_any

    putnam = shared_data / "real" / "Putnam_park2023_run4_2.csv"
    piece = write_canonical(load_any(putnam).subset(slice(0, 600)), tmp_path / "piece.csv")
    ck = tmp_path / "av.ckpt"
    assert cli_main(["train", "--data", str(piece), "-o", str(ck), "--quiet", "--epochs", "1",
                     "--lbfgs-iterations", "0", "--hidden", "8"]) == 0
    assert cli_main(["evaluate", "--model", str(ck), "--data", str(putnam)]) == 0


def test_training_recovers_the_identifiable_coefficients_on_clean_data(orca):
    """Coefficient recovery, not just a falling loss: a short training on two clean laps of ETHZ gets
    the coefficients this driving excites (front tyre B, C, D; yaw inertia; rolling resistance) within
    3 % of the vehicle file's truth, judged on another track. The bounds come from training seeds 0-2
    (0.2-2.1 % seen); this test's training seed (5) was not among them. The rear tyre and E, G, K
    need the full training of the main job (docs/learning.md), and an untrained guard misses them all."""
    from ddyn.model.single_track import COEFF_NAMES

    train_ds = simulate.simulate(orca, tracks.load_track("ethz"), laps=2, seed=3, progress=False)
    test_ds = simulate.simulate(orca, tracks.load_track("ethzMobil"), laps=1, seed=4, progress=False)
    torch.manual_seed(0)
    cfg = TrainConfig(epochs=20, lbfgs_iterations=1500, hidden=16, batch_size=128, seed=5)
    r = train(train_ds, orca, cfg, progress=False)
    ckpt = checkpoint.make(r, orca, train_ds.content_hash(), "two clean laps of ETHZ", len(train_ds))
    identifiable = ("Bf", "Cf", "Df", "Iz", "Cr0")
    errors = {k: abs(evaluate(r.model, ckpt, test_ds)["coefficients"][k]["rel_error"]) for k in identifiable}
    assert max(errors.values()) < 0.03, errors
    # the bound can fail: the same network before training (its guard near the range midpoints) misses it
    untrained = build_model(cfg, orca, r.model.encoder.mean.numpy(), r.model.encoder.std.numpy())
    e0 = {k: abs(evaluate(untrained, ckpt, test_ds)["coefficients"][k]["rel_error"]) for k in identifiable}
    assert max(e0.values()) > 0.03, e0
    assert set(identifiable) <= set(COEFF_NAMES)


def test_guard_prior_pulls_logits_toward_the_middle_of_the_ranges(orca, lap):
    """TrainConfig.guard_prior adds its weight times the mean squared guard logit to the training loss: the same
    seed and data end with logits nearer 0 (coefficients nearer the middle of their ranges) and fewer samples at
    a bound; the validation loss that picks the weights stays the data's alone. DDM only, never negative."""
    def logits_and_share(r):
        w = make_windows(lap, 1)
        with torch.no_grad():
            z = r.model.logits(torch.as_tensor(w.history, dtype=r.model.lo.dtype))
        return float((z ** 2).mean()), float((z.abs() >= 4.6).double().mean())

    free = _result(lap, orca, seed=2, epochs=10, lbfgs_iterations=100)
    held = _result(lap, orca, seed=2, epochs=10, lbfgs_iterations=100, guard_prior=1.0)
    (z_free, at_free), (z_held, at_held) = logits_and_share(free), logits_and_share(held)
    assert z_held < 0.8 * z_free, (z_held, z_free)      # the data keep the logits that fit them
    assert at_held <= at_free
    assert np.isfinite(held.best_val_loss)
    with pytest.raises(DdynError, match="guard_prior"):
        TrainConfig(guard_prior=-1.0)
    with pytest.raises(DdynError, match="DDM only"):
        TrainConfig(kind="dpm", guard_prior=0.1)
