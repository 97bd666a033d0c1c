"""EKF-FTHD denoiser: guards, filter correctness, the denoise command and the study's smoke run."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from ddyn.data.dataset import Dataset
from ddyn.data.importers import load_any
from ddyn.data.simulate import simulate
from ddyn.learn import denoise as dn
from ddyn.learn import ekf_layer as ek
from ddyn.model.vehicle import load as load_vehicle

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def orca():
    return load_vehicle("orca_1_43")


@pytest.fixture(scope="module")
def noisy(orca):
    """A short noisy simulated log (4 s at 50 Hz) with its clean truth in true_* extras."""
    return simulate(orca, "ethz", duration=4.0, seed=3, noise_scale=1.0, progress=False)


def _truth(ds):
    return np.column_stack([ds.extras[f"true_{c}"] for c in ek.CHANNELS])


def _rmse(a, b):
    return np.sqrt(np.mean((a - b) ** 2, axis=0))


def _tensors(ds, coeffs):
    z = torch.as_tensor(ds.states[None, :, 3:6])
    exo = torch.as_tensor(np.column_stack([ds.states[:, 6:8], ds.inputs])[None])
    c = torch.as_tensor(coeffs, dtype=torch.float64).expand(1, len(ds), 17)
    return z, exo, c


def _parser():
    from ddyn.cli import build_parser, commands_named

    return build_parser(commands_named("denoise", "study"))


# ----------------------------------------------------------------------------- guards

@pytest.mark.parametrize("scale", ["log", "linear"])
def test_guards_keep_q_and_r_inside_their_ranges(orca, scale):
    r = ek.default_ranges(orca)
    r = ek.NoiseRanges(r.q_lo, r.q_hi, r.r_lo, r.r_hi, scale)
    layer = ek.EKFLayer(orca.known, orca.sample_time, r)
    for logits in (torch.full((3,), -1e4), torch.full((3,), 1e4), torch.randn(3) * 30, torch.zeros(3)):
        with torch.no_grad():
            layer.q.logit.copy_(logits)
            layer.r.logit.copy_(-logits)
        q, rr = layer.q().detach().numpy(), layer.r().detach().numpy()
        assert np.all(q >= np.array(r.q_lo) * (1 - 1e-12)) and np.all(q <= np.array(r.q_hi) * (1 + 1e-12))
        assert np.all(rr >= np.array(r.r_lo) * (1 - 1e-12)) and np.all(rr <= np.array(r.r_hi) * (1 + 1e-12))
    # set() lands on the requested value; values outside the range are clipped inside it
    layer.r.set([2e-5, 1e-6, 1e-3])
    assert np.allclose(layer.r().detach().numpy(), [2e-5, 1e-6, 1e-3], rtol=1e-9)
    layer.q.set(1e9)
    assert np.all(layer.q().detach().numpy() <= np.array(r.q_hi))


def test_default_ranges_scale_with_the_sensor_noise(orca):
    r = ek.default_ranges(orca)
    sigma2 = np.array([orca.sensor_noise_std[c] for c in ek.CHANNELS]) ** 2
    assert np.allclose(r.r_lo, sigma2 / 100) and np.allclose(r.r_hi, sigma2 * 100)
    assert np.allclose(r.q_lo, sigma2 / 1e6) and np.allclose(r.q_hi, sigma2 * 100)
    with pytest.raises(Exception):
        ek.NoiseRanges.uniform((1.0, 0.5), (0.01, 1.0))


# ----------------------------------------------------------------------------- the filter

def test_jacobian_matches_torch_func_and_finite_differences(orca, noisy):
    z, exo, c = _tensors(noisy, orca.true_vector())
    s, e, cc = z[0, :50], exo[0, :50], c[0, :50]
    f, F = ek.linearise(s, e, cc, orca.known, orca.sample_time)
    J = ek.jacobian_torchfunc(s, e, cc, orca.known, orca.sample_time)
    assert torch.allclose(F, J, rtol=1e-10, atol=1e-12)
    h = 1e-6
    for j in range(3):
        d = torch.zeros(3, dtype=torch.float64)
        d[j] = h
        fd = (ek.velocity_step(s + d, e, cc, orca.known, orca.sample_time)
              - ek.velocity_step(s - d, e, cc, orca.known, orca.sample_time)) / (2 * h)
        assert torch.allclose(F[:, :, j], fd, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("linearisation", ["nominal", "filtered"])
def test_one_ekf_update_equals_a_hand_computed_kalman_update(orca, noisy, linearisation):
    from scipy.stats import multivariate_normal

    z, exo, c = _tensors(noisy.subset(slice(10, 12)), orca.true_vector())
    layer = ek.EKFLayer(orca.known, orca.sample_time, ek.default_ranges(orca),
                        q_init=[1e-6, 4e-6, 1e-4], r_init=[1e-4, 2.5e-5, 2.5e-3])
    with torch.no_grad():
        res = layer(z, exo, c, linearisation=linearisation, smooth=True)
    Q, R = np.diag([1e-6, 4e-6, 1e-4]), np.diag([1e-4, 2.5e-5, 2.5e-3])
    z0, z1 = z[0, 0].numpy(), z[0, 1].numpy()
    f, F = ek.linearise(z[0, :1], exo[0, :1], c[0, :1], orca.known, orca.sample_time)
    f, F = f[0].numpy(), F[0].numpy()
    # diffuse start: x0|0 = z0, P0|0 = R; predict; update with H = I
    P1 = F @ R @ F.T + Q
    S = P1 + R
    K = P1 @ np.linalg.inv(S)
    x1 = f + K @ (z1 - f)
    P1_post = (np.eye(3) - K) @ P1
    assert np.allclose(res.predicted[0, 1].numpy(), f, rtol=1e-12, atol=1e-14)
    assert np.allclose(res.filtered[0, 1].numpy(), x1, rtol=1e-10, atol=1e-13)
    assert np.allclose(res.P_filtered[0, 1].numpy(), P1_post, rtol=1e-8, atol=1e-16)
    nll = -multivariate_normal(f, S).logpdf(z1)
    assert float(res.nll) == pytest.approx(nll, rel=1e-10)
    # one RTS step back: G = P0 F' P1^-1, xs0 = x0 + G (x1 - f)
    G = R @ F.T @ np.linalg.inv(P1)
    assert np.allclose(res.smoothed[0, 0].numpy(), z0 + G @ (x1 - f), rtol=1e-9, atol=1e-13)


def test_ekf_reduces_the_error_of_a_noisy_log(orca, noisy):
    truth = _truth(noisy)
    raw = _rmse(noisy.states[:, 3:6], truth)
    settings = dn.EKFSettings(relinearisations=1, iterations=(4,), chunk=50)
    phys, std, report = dn.ekf_denoise(noisy, dn.source_from_vehicle(orca), settings)
    ekf = _rmse(phys, truth)
    # an identity filter would give ratio 1; the model-based smoother removes most of the white noise
    assert np.all(ekf < 0.5 * raw), (ekf, raw)
    assert np.all(std > 0) and np.all(np.isfinite(std))


def test_with_tiny_r_the_filter_follows_the_measurements(orca, noisy):
    z, exo, c = _tensors(noisy, orca.true_vector())
    ranges = ek.NoiseRanges.uniform((1e-8, 1e-2), (1e-16, 1e-2))
    layer = ek.EKFLayer(orca.known, orca.sample_time, ranges, q_init=1e-4, r_init=1e-16)
    with torch.no_grad():
        res = layer(z, exo, c, linearisation="filtered")
    assert torch.allclose(res.filtered, z, atol=1e-9)
    assert torch.allclose(res.smoothed, z, atol=1e-9)


def test_innovation_nll_decreases_with_a_few_steps(orca, noisy):
    z, exo, c = _tensors(noisy.subset(slice(0, 60)), orca.true_vector())
    ranges = ek.default_ranges(orca)
    bad_q, bad_r = np.array(ranges.q_hi) / 10, np.array(ranges.r_lo) * 3   # far from the truth, inside the ranges
    layer = ek.EKFLayer(orca.known, orca.sample_time, ranges, q_init=bad_q, r_init=bad_r)
    fit = ek.fit_noise(layer, z, exo, lambda: c, z, None, iterations=3)
    assert fit.nll_history[-1] < fit.nll_history[0] - 0.5
    # Adam path (used when a DDM head is fine-tuned) decreases too
    layer2 = ek.EKFLayer(orca.known, orca.sample_time, ranges, q_init=bad_q, r_init=bad_r)
    dummy = torch.nn.Parameter(torch.zeros(1, dtype=torch.float64))
    fit2 = ek.fit_noise(layer2, z, exo, lambda: c + 0 * dummy, z, None, iterations=5, lr=0.2,
                        extra_params=[dummy])
    assert fit2.nll_history[-1] < fit2.nll_history[0]


def test_chunks_cover_each_row_once_and_never_cross_segments():
    seg = np.array([0] * 7 + [1] * 5 + [2] * 1 + [3] * 3)
    idx, mask = ek.chunk_index(seg, 3)
    kept = idx[mask > 0]
    assert sorted(kept.tolist()) == [i for i in range(len(seg)) if seg[i] != 2]   # 1-row segment: no transition
    for row, m in zip(idx, mask):
        assert len(set(seg[row[m > 0]])) == 1


def test_coloured_noise_states_run_and_keep_covariances_symmetric(orca, noisy):
    z, exo, c = _tensors(noisy.subset(slice(0, 60)), orca.true_vector())
    layer = ek.EKFLayer(orca.known, orca.sample_time, ek.default_ranges(orca), coloured=True)
    with torch.no_grad():
        res = layer(z, exo, c)
    assert res.filtered.shape == (1, 60, 6) and res.physical.shape == (1, 60, 3)
    P = res.P_smoothed
    assert torch.allclose(P, P.transpose(-1, -2))
    assert torch.all(torch.linalg.eigvalsh(P) > -1e-15)


# ----------------------------------------------------------------------------- Savitzky-Golay

def test_savitzky_golay_works_per_segment_and_never_mixes_segments():
    rng = np.random.default_rng(0)
    n0, n1 = 40, 30
    x = np.concatenate([1.0 + 0.01 * rng.standard_normal(n0), 100.0 + 0.01 * rng.standard_normal(n1)])
    seg = np.array([0] * n0 + [1] * n1)
    segs = dn._segments(seg)
    out = dn.savgol_apply(x, segs, 11)
    sep = np.concatenate([dn.savgol_apply(x[:n0], [(0, n0)], 11), dn.savgol_apply(x[n0:], [(0, n1)], 11)])
    assert np.array_equal(out, sep)
    assert np.all(np.abs(out[:n0] - 1) < 0.05) and np.all(np.abs(out[n0:] - 100) < 0.05)
    # the window rule picks a window, and a segment shorter than it is smoothed with what fits
    w, cv = dn.savgol_window(x, segs)
    assert w in cv and w >= 5
    short = dn.savgol_apply(x[:7], [(0, 7)], 51)
    assert short.shape == (7,) and np.all(np.isfinite(short))


# ----------------------------------------------------------------------------- the command

@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory, orca):
    from ddyn.learn import checkpoint
    from ddyn.learn.training import TrainConfig, train

    ds = simulate(orca, "ethz", duration=3.0, seed=4, progress=False)
    r = train(ds, orca, TrainConfig(epochs=2, lbfgs_iterations=0), progress=False)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.ckpt"
    checkpoint.save(checkpoint.make(r, orca, ds.content_hash(), "tiny", len(ds)), path)
    return path


def _two_segment_log(noisy) -> Dataset:
    ds = noisy.subset(slice(0, 120))
    ds.segment = np.where(np.arange(120) < 70, 0, 1)
    ds.time = ds.time + np.where(np.arange(120) < 70, 0.0, 1.0)
    return ds


@pytest.mark.parametrize("method", ["ekf", "savgol"])
def test_denoise_writes_a_canonical_file_with_raw_extras(tmp_path, noisy, tiny_ckpt, method):
    from ddyn.data.dataset import write_canonical

    src = write_canonical(_two_segment_log(noisy), tmp_path / "in.csv")
    out = tmp_path / "out.csv"
    args = _parser().parse_args(["denoise", str(src), "--model", str(tiny_ckpt), "--method", method,
                                 "-o", str(out), "--relinearisations", "1"])
    assert args.func(args) == 0
    back = load_any(out)
    orig = load_any(src)
    assert len(back) == len(orig) and np.array_equal(back.segment, orig.segment)
    for c, col in zip(ek.CHANNELS, (3, 4, 5)):
        assert np.array_equal(back.extras[f"raw_{c}"], orig.states[:, col])
        assert np.allclose(back.extras[f"noise_{c}"], orig.states[:, col] - back.states[:, col])
        assert np.array_equal(back.extras[f"true_{c}"], orig.extras[f"true_{c}"])
    assert np.array_equal(back.states[:, [0, 1, 2, 6, 7]], orig.states[:, [0, 1, 2, 6, 7]])
    assert not np.array_equal(back.states[:, 3:6], orig.states[:, 3:6])
    assert back.metadata["denoise_method"] == method
    report = json.loads((tmp_path / "out.denoise.json").read_text())
    assert report["method"] == method
    ranges = json.loads((tmp_path / "out.ranges.json").read_text())
    for name, r in ranges["coefficients"].items():
        lo, hi = r["suggested"]
        assert lo < hi
        if r["pinned"] is None:   # not pinned: inside the vehicle range
            assert r["vehicle"][0] <= lo and hi <= r["vehicle"][1]


def test_denoise_with_vehicle_coefficients_and_the_errors(tmp_path, noisy):
    from ddyn.data.dataset import write_canonical
    from ddyn.errors import DdynError

    src = write_canonical(noisy.subset(slice(0, 60)), tmp_path / "in.csv")
    args = _parser().parse_args(["denoise", str(src), "--vehicle", "orca_1_43", "-o", str(tmp_path / "o.csv"),
                                 "--relinearisations", "1", "--chunk", "40",
                                 "--q-range", "1e-10", "1e-2", "--r-range", "1e-7", "1"])
    assert args.func(args) == 0
    rep = json.loads((tmp_path / "o.denoise.json").read_text())
    assert rep["ranges"]["r_hi"] == [1.0, 1.0, 1.0]
    assert all(1e-7 * (1 - 1e-9) <= r <= 1.0 for r in rep["r"])
    assert not (tmp_path / "o.ranges.json").exists()   # no DDM, no suggested ranges
    args = _parser().parse_args(["denoise", str(src), "--method", "ekf", "-o", str(tmp_path / "x.csv")])
    with pytest.raises(DdynError):
        args.func(args)


def test_suggested_ranges_rule(orca):
    lo, hi = orca.range_arrays()
    est = np.tile(0.5 * (lo + hi), (200, 1))
    est[:, 0] = np.linspace(10, 12, 200)          # Bf well inside 5..30: tightened around the estimates
    est[:, 16] = lo[16]                           # Iz pinned at its lower bound: extended to lo / 2
    est[:, 3] = hi[3]                             # Ef pinned at its upper bound 0: a sign constraint, kept
    est[:, 4] = np.linspace(lo[4], hi[4], 200)    # Gf fills its range: kept, flagged
    est[:, 5] = lo[5]                             # Kf pinned low at a negative bound: half the width further
    r = dn.suggest_ranges(est, orca)["coefficients"]
    a, b = r["Bf"]["suggested"]
    assert 5 <= a < 10.1 and 11.9 < b <= 30 and r["Bf"]["pinned"] is None
    assert r["Iz"]["pinned"] == "low" and r["Iz"]["suggested"][0] == pytest.approx(lo[16] / 2)
    assert r["Ef"]["pinned"] == "high" and r["Ef"]["suggested"][1] == 0.0
    assert r["Gf"]["pinned"] == "both" and r["Gf"]["suggested"] == [lo[4], hi[4]]
    assert r["Kf"]["suggested"][0] == pytest.approx(lo[5] - 0.5 * (hi[5] - lo[5]))


# ----------------------------------------------------------------------------- the study

def test_denoise_study_quick_sim_runs_end_to_end(tmp_path):
    args = _parser().parse_args(["study", "denoise", "sim", "--quick", "--out", str(tmp_path)])
    assert args.func(args) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    labels = [a["label"] for a in res["sim"]["conditions"]["white+coloured"]["arms"]]
    assert labels[:2] == ["raw", "Savitzky-Golay"] and any(x.startswith("EKF-FTHD") for x in labels)
    assert "DDM trained on" in (tmp_path / "results.md").read_text()


def test_denoise_study_quick_real_runs_end_to_end(tmp_path, shared_data):
    args = _parser().parse_args(["study", "denoise", "real", "--quick", "--out", str(tmp_path)])
    assert args.func(args) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert set(res["real"]["arms"][0]["tests"]) == {"raw", "Savitzky-Golay", "EKF-FTHD"}
    assert "Suggested coefficient ranges" in (tmp_path / "results.md").read_text()
