"""The benchmarks' case runner: local processes and a real Dask distributed cluster give the same results,
in input order (issue 14: "given a cluster, through an existing engine")."""
from __future__ import annotations

import os

from ddyn.analysis import parallel


def _slow_square(x: int) -> tuple[int, int]:
    # later items finish first, so a runner that returned results in completion order would fail
    import time

    time.sleep(0.02 * (5 - x % 5))
    return x * x, os.getpid()


def test_local_processes_keep_the_input_order():
    out = parallel.run_cases(_slow_square, list(range(8)), jobs=2, progress=False)
    assert [r[0] for r in out] == [x * x for x in range(8)]
    assert all(pid != os.getpid() for _, pid in out)


def test_cases_run_on_a_dask_cluster_in_input_order():
    import distributed  # pinned in requirements.lock: a missing package fails here, it does not skip

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        parallel.use_scheduler(cl.scheduler_address)
        try:
            out = parallel.run_cases(_slow_square, list(range(10)) + [3], jobs=1, progress=False)
        finally:
            parallel.use_scheduler(None)
        worker_pids = {pid for _, pid in out}
    assert [r[0] for r in out] == [x * x for x in list(range(10)) + [3]]
    # the cases ran in the cluster's worker processes, not here
    assert os.getpid() not in worker_pids
    assert 1 <= len(worker_pids) <= 2


def test_the_gap_command_hands_its_cases_to_the_scheduler(monkeypatch):
    from ddyn.analysis import gap_benchmark

    seen = []

    def fake_run_here(args):
        seen.append(parallel._scheduler)
        return 0

    monkeypatch.setattr(gap_benchmark, "_run_here", fake_run_here)

    class Args:
        scheduler = "tcp://127.0.0.1:8786"

    assert gap_benchmark._run(Args()) == 0
    assert seen == ["tcp://127.0.0.1:8786"]
    assert parallel._scheduler is None  # reset afterwards, so later runs in this process are local


def test_each_case_carries_the_gate_and_margin_set_here(monkeypatch):
    """`study gap --min-evidence/--gate` set diagnose's module defaults in this process; a Dask worker is no
    fork of it, so every case must carry them to the worker's diagnose (else it diagnoses with margin 0)."""
    import pytest

    from ddyn.analysis import diagnose as D
    from ddyn.analysis import gap_independent as G

    class Captured(Exception):
        pass

    seen = {}

    def capture(fn, cases, jobs, **kw):
        seen["cases"] = cases
        raise Captured

    limits = {"steer_lag": 0.15, "downforce": None}
    monkeypatch.setattr(D, "MIN_EVIDENCE", 13.02)
    monkeypatch.setattr(D, "NO_GAP_GATE", None)
    monkeypatch.setattr(D, "DETECTION_LIMITS", limits)
    monkeypatch.setattr(G, "run_cases", capture)
    with pytest.raises(Captured):
        G.run(3, seed=99, progress=False)
    # what a worker with the module defaults (margin 0, default gate, no limits) passes to diagnose
    monkeypatch.setattr(D, "MIN_EVIDENCE", 0.0)
    monkeypatch.setattr(D, "NO_GAP_GATE", 1.5)
    monkeypatch.setattr(D, "DETECTION_LIMITS", None)
    assert [G.vetoes_of(c) for c in seen["cases"]] == [{"gate": None, "min_evidence": 13.02,
                                                         "detection_limits": limits}] * 3
    assert G.vetoes_of({}) == {"gate": "default", "min_evidence": None, "detection_limits": "default"}
