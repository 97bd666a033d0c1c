"""Run benchmark cases in worker processes with a progress bar, results in input order.

Why processes: a case is a pure-Python plant integration plus a scipy fit, both holding the GIL.
Each worker pins torch and BLAS to one thread so `--jobs N` uses N cores, not N x cores.
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


def run_cases(fn: Callable, items: Sequence, jobs: int = 1, desc: str = "cases", progress: bool = True) -> list:
    """[fn(item) for item in items], in `jobs` processes (1: in this process); fn must be picklable."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc=desc)
    out: list = [None] * len(items)
    try:
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
