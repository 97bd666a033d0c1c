"""The benchmarks' case runner: local processes and a real Dask distributed cluster give the same results,
in input order (issue 14: "given a cluster, through an existing engine")."""
from __future__ import annotations

import os

from ddyn.gap.benchmark import parallel


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


def test_the_gap_commands_hand_their_cases_to_the_scheduler():
    """--scheduler: the run inside sees the scheduler in force; afterwards (also after a failure) runs are local."""
    import pytest

    from ddyn.gap import cli

    seen = []

    class Args:
        scheduler = "tcp://127.0.0.1:8786"

    assert cli._with_scheduler(Args(), lambda: seen.append(parallel._scheduler) or 0) == 0
    assert seen == ["tcp://127.0.0.1:8786"]
    assert parallel._scheduler is None  # reset afterwards, so later runs in this process are local

    def fail():
        raise RuntimeError("a case failed")
    with pytest.raises(RuntimeError):
        cli._with_scheduler(Args(), fail)
    assert parallel._scheduler is None


def test_each_case_carries_the_runs_config(monkeypatch):
    """Every case carries the run's DiagnosisConfig (a Dask worker is no fork of this process), and running a
    benchmark changes nothing in the diagnosis's module state: a later diagnose() sees the defaults."""
    import pytest

    from ddyn.gap import config as CFG
    from ddyn.gap.benchmark import commonroad as G

    class Captured(Exception):
        pass

    seen = {}

    def capture(fn, cases, jobs, **kw):
        seen["cases"] = cases
        raise Captured

    cfg = CFG.DiagnosisConfig(min_evidence=13.02, detection_limits={"steer_lag": 0.15, "downforce": None}, hold=True)
    monkeypatch.setattr(G, "run_cases", capture)
    with pytest.raises(Captured):
        G.run(3, seed=99, config=cfg, progress=False)
    assert [CFG.DiagnosisConfig.from_dict(c["config"]) for c in seen["cases"]] == [cfg] * 3
    assert CFG.DiagnosisConfig() == CFG.DiagnosisConfig(min_evidence=0.0, detection_limits=None, hold=False)
