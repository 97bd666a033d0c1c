"""The controller benchmark's Python side (train/bench/controller.py) and a short closed-loop run
of the C tool: the parameter count of the large-network recipe, the raceline table the MPC gets,
and that the tool's report parses with every status bit accounted for."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ddyn.bench.controller import DEFAULT_CONTROLLER_TOOL, raceline_table, run_controller
from ddyn.bench.large_net import make_net, parameter_count
from ddyn.data.dataset import write_canonical
from ddyn.data.simulate import simulate
from ddyn.learn import checkpoint


@pytest.mark.parametrize("tau,hidden,layers,gru", [(5, 137, 2, 1), (5, 210, 3, 0), (3, 12, 2, 1), (1, 8, 1, 2)])
def test_parameter_count_matches_the_network(tmp_path, tau, hidden, layers, gru):
    ds = simulate("orca_1_43", "ethz", duration=2.0, seed=0)
    path = write_canonical(ds, tmp_path / "data.csv")
    ckpt, n = make_net(tmp_path / "net.ckpt", path, tau, hidden, layers, gru)
    model, _ = checkpoint.load(ckpt)
    assert n == parameter_count(tau, hidden, layers, gru) == sum(p.numel() for p in model.parameters())
    # normalisation from the data, so the export's out-of-range test judges against real statistics
    assert np.allclose(model.encoder.mean.numpy(), np.column_stack([ds.states[:, 3:8], ds.inputs]).mean(0), atol=1e-5)
    with torch.no_grad():
        c = model.coefficients(torch.zeros(1, tau, 7))
    assert torch.all((c >= model.lo) & (c <= model.hi))


def test_default_large_network_is_about_100k_parameters():
    assert 95_000 <= parameter_count(5, 137, 2, 1) <= 105_000
    assert 95_000 <= parameter_count(5, 210, 3, 0) <= 105_000


def test_raceline_table_is_the_mpcs():
    t = raceline_table("ethz", speed_scale=0.8)
    assert t.shape[1] == 5 and 100 < len(t) <= 1024  # DDYN_MPC_MAX_TRACK_POINTS
    assert np.all(t[:, 2] >= 0.5)  # floored reference speed
    assert np.median(t[:, 3]) > 0.0 and np.median(t[:, 4]) > 0.0


def test_closed_loop_tool_reports_timing_and_every_status_bit():
    if not DEFAULT_CONTROLLER_TOOL.is_file():
        pytest.fail(f"{DEFAULT_CONTROLLER_TOOL} missing: build the C side first (scripts/test.sh does)")
    r = run_controller(DEFAULT_CONTROLLER_TOOL, steps=300)
    s = r["controller_step"]
    assert s["n"] == 300 and 0 < s["median_us"] <= s["p99_us"] <= s["max_us"]
    bits = [k for k in r if k.startswith("steps_DDYN_CTRL_")]
    assert len(bits) == 18  # DDYN_CTRL_STATUS_BITS (ddyn/controller.h)
    assert r["steps_DDYN_CTRL_ERR_ARGUMENT"] == 0
    # the first tau periods fill the history (the fixture network reads 3 rows)
    assert r["steps_DDYN_CTRL_HISTORY_FILLING"] == 3
