"""Run benchmark cases in worker processes, or on a Dask cluster, with a progress bar, results in input order.

Why processes: a case is a pure-Python plant integration plus a scipy fit, both holding the GIL.
Each worker pins torch and BLAS to one thread so `--jobs N` uses N cores, not N x cores.

Why Dask for a cluster: a benchmark of hundreds of cases is embarrassingly parallel; Dask distributed already
schedules, retries and reports on many machines, so `use_scheduler(ADDRESS)` (`ddyn study gap --scheduler
tcp://HOST:8786`) hands the cases to an existing scheduler instead of a home-made one. The workers must have
this package installed (the same version: cases and results are pickled).
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Callable, Sequence


def _init_worker() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a declared dependency
        pass


_scheduler: str | None = None


def use_scheduler(address: str | None) -> None:
    """Send every later run_cases to the Dask scheduler at `address` (None: back to local processes)."""
    global _scheduler
    _scheduler = address


def _run_on_dask(fn: Callable, items: Sequence, out: list, bar) -> None:
    try:
        from distributed import Client, as_completed as dask_completed
    except ImportError as e:  # pragma: no cover - distributed is a declared dependency
        raise RuntimeError("a Dask scheduler was given but the 'distributed' package is missing") from e
    with Client(_scheduler) as client:
        # pure=False: two equal cases (the same seed twice) are still two runs, not one cached result
        futures = client.map(fn, list(items), pure=False)
        index = {fut.key: i for i, fut in enumerate(futures)}
        for fut in dask_completed(futures):
            out[index[fut.key]] = fut.result()
            if bar is not None:
                bar.update(1)


def run_cases(fn: Callable, items: Sequence, jobs: int = 1, desc: str = "cases", progress: bool = True) -> list:
    """[fn(item) for item in items]: on the Dask scheduler set by use_scheduler, else in `jobs` processes
    (1: in this process); fn must be picklable."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc=desc)
    out: list = [None] * len(items)
    try:
        if _scheduler is not None:
            _run_on_dask(fn, items, out, bar)
            return out
        if jobs <= 1:
            for i, item in enumerate(items):
                out[i] = fn(item)
                if bar is not None:
                    bar.update(1)
            return out
        with ProcessPoolExecutor(max_workers=jobs, initializer=_init_worker) as pool:
            futures = {pool.submit(fn, item): i for i, item in enumerate(items)}
            for fut in as_completed(futures):
                out[futures[fut]] = fut.result()
                if bar is not None:
                    bar.update(1)
        return out
    finally:
        if bar is not None:
            bar.close()
