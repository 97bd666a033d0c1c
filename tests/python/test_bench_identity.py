"""A C tool knows which checkpoint's network it was built for, and `ddyn bench` refuses another's.

The test build (scripts/test.sh: build-test/) is built for the fixture network of tests/c/generated."""
from __future__ import annotations

import json

import pytest

from ddyn.bench.controller import DEFAULT_CONTROLLER_TOOL
from ddyn.bench.identity import require_same_network, tool_checkpoint_hash
from ddyn.bench.large_net import make_net
from ddyn.bench.runtime import DEFAULT_TOOL
from ddyn.data import simulate
from ddyn.data.dataset import write_canonical
from ddyn.errors import DdynError
from ddyn.model import tracks, vehicle
from ddyn.paths import REPO

FIXTURE = REPO / "tests" / "c" / "generated" / "net_fixture" / "export.json"


def test_tools_report_the_fixture_network():
    expected = json.loads(FIXTURE.read_text())["checkpoint_sha256"]
    assert tool_checkpoint_hash(DEFAULT_TOOL) == expected
    assert tool_checkpoint_hash(DEFAULT_CONTROLLER_TOOL) == expected


def test_bench_refuses_another_checkpoint(tmp_path, shared_data):
    v = vehicle.load("orca_1_43")
    data = write_canonical(simulate.simulate(v, tracks.load_track("ethzMobil"), laps=1, seed=2, progress=False),
                           tmp_path / "lap.csv")
    other, _ = make_net(tmp_path / "other.ckpt", data, tau=1, hidden=8, layers=1, gru_layers=0)
    with pytest.raises(DdynError, match="was built for checkpoint"):
        require_same_network(DEFAULT_TOOL, other)
    from ddyn.bench.runtime import run
    with pytest.raises(DdynError, match="ddyn export"):
        run(str(other), str(data), n=10, n_python=10)


def test_a_tool_without_a_network_is_named(tmp_path):
    with pytest.raises(DdynError, match="not found"):
        tool_checkpoint_hash(tmp_path / "ddyn_bench")
