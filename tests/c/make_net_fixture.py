"""Regenerate tests/c/generated/net_fixture: a small random-initialised DDM (GRU + dense, seed 0),
exported with `ddyn export`, and reference outputs from PyTorch for the cmocka test.

    .venv/bin/python tests/c/make_net_fixture.py

The fixture only has to exercise every code path of c_src/src/guard_net.c (feature range, GRU,
Mish, guard) under the sanitizers; its numbers mean nothing physically. Its feature range is the
mean +- 1.5 std, so about one in seven of the reference histories' features is held at an edge.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch

from ddyn.learn import checkpoint
from ddyn.learn.export import export
from ddyn.learn.networks import set_feature_range
from ddyn.learn.training import TrainConfig, TrainResult, build_model
from ddyn.model import vehicle

OUT = Path(__file__).resolve().parent / "generated" / "net_fixture"
TAU, CASES = 3, 16


def main() -> None:
    torch.manual_seed(0)
    v = vehicle.load("orca_1_43")
    cfg = TrainConfig(tau=TAU, hidden=12, layers=2, gru_layers=1)
    mean = np.array([1.5, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    std = np.array([0.7, 0.1, 2.0, 0.3, 0.15, 2.0, 1.0])
    model = build_model(cfg, v, mean, std)
    set_feature_range(model, np.stack([mean - 1.5 * std, mean + 1.5 * std])[None])
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = checkpoint.save(checkpoint.make(TrainResult(model, cfg, np.ones(3), [], 0.0, 0.0), v, "fixture",
                                               "tests/c/make_net_fixture.py", 0), Path(tmp) / "fixture.ckpt")
        export(ckpt, OUT, torch_export=False)
    rng = np.random.default_rng(0)
    hist = mean + std * rng.standard_normal((CASES, TAU, 7))
    with torch.no_grad():
        ref = model.coefficients(torch.as_tensor(hist)).numpy()
    fmt = lambda a: ",\n    ".join(", ".join(repr(float(x)) for x in row) for row in a.reshape(len(a), -1))  # noqa: E731
    (OUT / "ddyn_net_fixture_vectors.h").write_text(
        "/* GENERATED FILE - DO NOT EDIT. tests/c/make_net_fixture.py: PyTorch outputs of the fixture network. */\n"
        f"#define NET_FIXTURE_CASES {CASES}\n"
        f"/* flat: case k, row t, feature f at [(k * {TAU} + t) * 7 + f]; outputs at [k * {ref.shape[1]} + i] */\n"
        f"static const double net_fixture_history[{CASES * TAU * 7}] = {{\n    {fmt(hist)}\n}};\n"
        f"static const double net_fixture_coeffs[{ref.size}] = {{\n    {fmt(ref)}\n}};\n")


if __name__ == "__main__":
    main()
