"""The feature range a DDM holds its inputs in (ddyn.learn.networks.HistoryEncoder, issue 36): set from the
windows it is trained and selected on, the identity on them, an input beyond it gets the edge's coefficients;
kept by checkpoints, widened by fine-tuning, exported to C; a checkpoint from before it loads unheld."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ddyn.data import simulate
from ddyn.data.windows import make_windows, split_train_validation
from ddyn.learn import checkpoint
from ddyn.learn import finetune as ft
from ddyn.learn.export import export
from ddyn.learn.training import TrainConfig, train
from ddyn.model import tracks

TINY = TrainConfig(hidden=8, layers=2, epochs=2, lbfgs_iterations=2, batch_size=128)
TINY_FIT = ft.FitConfig(adam_steps=5, lbfgs_iterations=2, lr=3e-3, batch_size=128, eval_every=5)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def lap(orca, shared_data):
    return simulate.simulate(orca, tracks.load_track("ethz"), laps=1, seed=3, progress=False)


@pytest.fixture(scope="module")
def trained(orca, lap, tmp_path_factory):
    result = train(lap, orca, TINY, progress=False)
    path = checkpoint.save(checkpoint.make(result, orca, lap.content_hash(), "test", len(lap)),
                           tmp_path_factory.mktemp("ckpt") / "m.ckpt")
    return result.model, path


def _extremes(*windows):
    flat = np.concatenate([w.history.reshape(-1, 7) for w in windows])
    return flat.min(axis=0), flat.max(axis=0)


def test_training_sets_the_range_of_its_training_and_validation_windows(orca, lap, trained):
    model, _ = trained
    lo, hi = _extremes(*split_train_validation(lap, TINY.tau, TINY.val_fraction))
    np.testing.assert_array_equal(model.encoder.feature_lo.numpy(), lo)
    np.testing.assert_array_equal(model.encoder.feature_hi.numpy(), hi)
    assert np.all(hi > lo)


def test_the_range_is_the_identity_inside_and_holds_outside(lap, trained):
    model, _ = trained
    w = make_windows(lap, TINY.tau)
    h = torch.as_tensor(w.history)
    enc = model.encoder
    with torch.no_grad():
        held = model.coefficients(h)
        lo, hi = enc.feature_lo.clone(), enc.feature_hi.clone()
        enc.feature_lo.fill_(-float("inf"))
        enc.feature_hi.fill_(float("inf"))
        unheld = model.coefficients(h)
        torch.testing.assert_close(held, unheld, rtol=0, atol=0)    # every training row lies inside
        far = h[:1].clone()
        far[..., 0] = hi[0] + 5.0                                      # faster than anything trained on
        edge = far.clone()
        edge[..., 0] = hi[0]
        beyond_unheld = model.coefficients(far)
        enc.feature_lo.copy_(lo)
        enc.feature_hi.copy_(hi)
        torch.testing.assert_close(model.coefficients(far), model.coefficients(edge), rtol=0, atol=0)
        assert not torch.equal(beyond_unheld, model.coefficients(far))


def test_checkpoints_keep_it_and_the_c_export_carries_it(trained, tmp_path):
    model, path = trained
    loaded, ckpt = checkpoint.load(path)
    torch.testing.assert_close(loaded.encoder.feature_lo, model.encoder.feature_lo, rtol=0, atol=0)
    export(path, tmp_path / "c", torch_export=False)
    text = (tmp_path / "c" / "ddyn_net_weights.c").read_text()
    assert "ddyn_net_feature_lo[7]" in text and "ddyn_net_feature_lo, ddyn_net_feature_hi\n};" in text


def test_a_checkpoint_from_before_the_range_loads_unheld_and_exports_none(trained, tmp_path):
    _, path = trained
    ckpt = checkpoint.read(path)
    for key in ("encoder.feature_lo", "encoder.feature_hi"):
        del ckpt["state_dict"][key]
    old = checkpoint.save(ckpt, tmp_path / "old.ckpt")
    model, _ = checkpoint.load(old)
    assert torch.isinf(model.encoder.feature_lo).all() and torch.isinf(model.encoder.feature_hi).all()
    export(old, tmp_path / "c", torch_export=False)
    text = (tmp_path / "c" / "ddyn_net_weights.c").read_text()
    assert "feature_lo[7]" not in text and text.rstrip().endswith("NULL, NULL\n};")


def test_finetuning_widens_the_base_range_to_its_own_rows(orca, lap, tmp_path):
    # the base sees the lap's first half, the fine-tuning the second: the result holds both
    first, second = lap.subset(slice(0, len(lap) // 2)), lap.subset(slice(len(lap) // 2, len(lap)))
    pool, val = ft.split_by_time(first, 0.3)
    base_model, base_ckpt, _ = ft.train_scratch(orca, pool, val, TrainConfig(hidden=8, layers=3), TINY_FIT)
    base_path = checkpoint.save(base_ckpt, tmp_path / "base.ckpt")
    np.testing.assert_array_equal(base_model.encoder.feature_lo.numpy(),
                                  _extremes(ft.windows_of(pool, 1), ft.windows_of(val, 1))[0])
    ft_pool, ft_val = ft.split_by_time(second, 0.3)
    model, _ = ft.finetune(base_path, ft_pool, ft_val, ft.FinetuneConfig(fit=TINY_FIT))
    lo, hi = _extremes(ft.windows_of(ft_pool, 1), ft.windows_of(ft_val, 1))
    np.testing.assert_array_equal(model.encoder.feature_lo.numpy(),
                                  np.minimum(base_model.encoder.feature_lo.numpy(), lo))
    np.testing.assert_array_equal(model.encoder.feature_hi.numpy(),
                                  np.maximum(base_model.encoder.feature_hi.numpy(), hi))
    assert not np.array_equal(model.encoder.feature_hi.numpy(), base_model.encoder.feature_hi.numpy())


def test_evaluate_reports_the_rows_outside_the_range(lap, trained, capsys):
    from ddyn.learn.evaluate import evaluate, format_summary

    model, path = trained
    _, ckpt = checkpoint.load(path)
    assert evaluate(model, ckpt, lap)["outside_range"]["any"] == 0.0      # its own rows: inside
    faster = lap.subset(slice(None))
    faster.states[:, 3] *= 1.5                                            # every row faster than trained on
    m = evaluate(model, ckpt, faster)
    assert m["outside_range"]["features"]["vx"] > 0.3 and m["outside_range"]["features"]["steering"] == 0.0
    assert "inputs outside the trained range in" in format_summary(m) and "vx " in format_summary(m)
