"""`ddyn export`: the C guard-network inference matches PyTorch on 10,000 real and simulated histories.

Each case exports a network (randomly initialised: parity does not need training),
compiles the C runtime's guard_net.c against the exported tables with -Werror, runs
it on histories from logs, and compares with the PyTorch model in float64.
"""
from __future__ import annotations

import filecmp
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from ddyn.data import simulate
from ddyn.data.importers import load_any
from ddyn.data.windows import make_windows
from ddyn.learn import checkpoint
from ddyn.learn.export import export
from ddyn.learn.training import TrainConfig, TrainResult, build_model
from ddyn.model import tracks, vehicle

REPO = Path(__file__).resolve().parents[2]
N_HISTORIES = 10_000
FLOAT_RTOL, DOUBLE_RTOL = 1e-5, 1e-12


def _random_checkpoint(tmp: Path, vehicle_name: str, histories: np.ndarray, seed: int, **cfg) -> Path:
    """A randomly initialised network, normalised on the histories it will see, saved as a checkpoint."""
    torch.manual_seed(seed)
    v = vehicle.load(vehicle_name)
    c = TrainConfig(**cfg)
    flat = histories.reshape(-1, 7)
    model = build_model(c, v, flat.mean(axis=0), np.maximum(flat.std(axis=0), 1e-12))
    with torch.no_grad():  # larger weights than the default init, so activations leave the linear zone
        for name, p in model.named_parameters():
            if "weight" in name:
                p.mul_(2.0)
    result = TrainResult(model, c, np.ones(3), [], 0.0, 0.0)
    return checkpoint.save(checkpoint.make(result, v, "random", "random init", 0), tmp / f"net_{seed}.ckpt")


def _build(export_dir: Path, tmp: Path) -> Path:
    exe = tmp / f"infer_{export_dir.name}"
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc, "no C compiler: scripts/setup.sh installs gcc"
    subprocess.run([cc, "-std=c99", "-O2", "-Wall", "-Wextra", "-Wpedantic", "-Werror",
                    "-I", str(REPO / "c_src/include"), "-I", str(export_dir),
                    str(REPO / "c_src/src/guard_net.c"), str(REPO / "c_src/src/status.c"),
                    str(export_dir / "ddyn_net_weights.c"),
                    str(REPO / "c_src/tools/net_infer.c"), "-lm", "-o", str(exe)], check=True)
    return exe


def _run_c(exe: Path, histories: np.ndarray) -> np.ndarray:
    text = "\n".join(" ".join(repr(float(x)) for x in h.ravel()) for h in histories) + "\n"
    proc = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True)
    return np.loadtxt(proc.stdout.splitlines(), ndmin=2)


@pytest.fixture(scope="module")
def logs(shared_data):
    """Histories source: a simulated 1:43 log of >= 10,000 rows and the real Putnam log."""
    sim = simulate.simulate(vehicle.load("orca_1_43"), tracks.load_track("ethz"), duration=205.0, seed=4,
                            progress=False)
    real = load_any(shared_data / "real" / "Putnam_park2023_run4_2.csv")
    return {"orca_1_43": sim, "av21": real}


CASES = [
    ("ddm_dense", "orca_1_43", dict(kind="ddm", tau=3, hidden=32, layers=2, gru_layers=0)),
    ("ddm_gru", "av21", dict(kind="ddm", tau=5, hidden=128, layers=2, gru_layers=1)),   # ~90k parameters
    ("dpm_dense", "orca_1_43", dict(kind="dpm", tau=1, hidden=64, layers=3, gru_layers=0)),
]


@pytest.mark.parametrize("name,vehicle_name,cfg", CASES, ids=[c[0] for c in CASES])
def test_c_inference_matches_pytorch(tmp_path, logs, name, vehicle_name, cfg):
    w = make_windows(logs[vehicle_name], cfg["tau"])
    assert len(w) >= N_HISTORIES
    hist = w.history[np.linspace(0, len(w) - 1, N_HISTORIES).astype(int)]
    ckpt = _random_checkpoint(tmp_path, vehicle_name, hist, seed=len(name), **cfg)
    model, ck = checkpoint.load(ckpt)
    with torch.no_grad():
        ref = model.coefficients(torch.as_tensor(hist)).numpy()
    # judge each output on its natural scale: the guard's range width, or the output's spread
    if ck["ranges"] is not None:
        scale = np.array(ck["ranges"]["hi"]) - np.array(ck["ranges"]["lo"])
    else:
        scale = np.abs(ref).max(axis=0)
    for double, rtol in ((False, FLOAT_RTOL), (True, DOUBLE_RTOL)):
        out = tmp_path / f"{name}_{'double' if double else 'float'}"
        export(ckpt, out, double=double, torch_export=False)
        got = _run_c(_build(out, tmp_path), hist)
        err = np.abs(got - ref) / np.maximum(np.abs(ref), scale)
        print(f"parity {name} {'double' if double else 'float'}: worst relative error {err.max():.2e}")
        assert err.max() <= rtol, f"{'double' if double else 'float'}: worst relative error {err.max():.2e}"


def test_runtime_refuses_other_shape_or_checkpoint(tmp_path, logs):
    hist = make_windows(logs["orca_1_43"], 2).history[:100]
    ckpt = _random_checkpoint(tmp_path, "orca_1_43", hist, seed=1, tau=2, hidden=8)
    export(ckpt, tmp_path / "e", torch_export=False)
    out = subprocess.run([str(_build(tmp_path / "e", tmp_path)), "--check"], capture_output=True, text=True,
                         check=True).stdout.split("\n")
    assert out[:3] == ["exported DDYN_OK", "other_shape DDYN_ERR_NET_SHAPE", "other_hash DDYN_ERR_NET_HASH"]


def test_export_is_reproducible_and_has_a_torch_program(tmp_path, logs):
    hist = make_windows(logs["orca_1_43"], 1).history[:100]
    ckpt = _random_checkpoint(tmp_path, "orca_1_43", hist, seed=2, tau=1, hidden=8)
    a = export(ckpt, tmp_path / "a")
    export(ckpt, tmp_path / "b")
    for f in a:
        if f.suffix != ".pt2":  # torch.export archives embed non-deterministic metadata
            assert filecmp.cmp(f, tmp_path / "b" / f.name, shallow=False), f.name
    program = torch.export.load(tmp_path / "a" / "model.pt2")
    model, _ = checkpoint.load(ckpt)
    x = torch.as_tensor(hist[:7])
    assert torch.allclose(program.module()(x), model.coefficients(x), rtol=0, atol=1e-12)
