"""History windows: what the networks read and what they must predict.

A sample ending at row k holds the tau rows k-tau+1 .. k of the features
[vx, vy, omega, throttle, steering, dthrottle, dsteering], the full state and
input at row k (where the physics step starts), and the velocities of row k+1
(the target). All tau+1 rows lie in one segment, so no window spans a gap.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ddyn.data.dataset import Dataset
from ddyn.errors import DdynError

FEATURE_NAMES = ("vx", "vy", "omega", "throttle", "steering", "dthrottle", "dsteering")
TARGET_NAMES = ("vx", "vy", "omega")


@dataclass
class Windows:
    history: np.ndarray   # (n, tau, 7) raw (un-normalised) features
    state: np.ndarray     # (n, 8) state at the window's last row
    inputs: np.ndarray    # (n, 2) input applied at that row
    target: np.ndarray    # (n, 3) vx, vy, omega of the next row
    end_row: np.ndarray   # (n,) index of the window's last row in the dataset

    def __len__(self) -> int:
        return len(self.end_row)

    def subset(self, idx) -> "Windows":
        return Windows(self.history[idx], self.state[idx], self.inputs[idx], self.target[idx], self.end_row[idx])


def features(ds: Dataset) -> np.ndarray:
    return np.column_stack([ds.states[:, 3:8], ds.inputs])


def valid_end_rows(ds: Dataset, tau: int, horizon: int = 1) -> np.ndarray:
    """Rows k such that rows k-tau+1 .. k+horizon all lie in k's segment."""
    n = len(ds)
    k = np.arange(tau - 1, n - horizon)
    if len(k) == 0:
        return k
    ok = (ds.segment[k - tau + 1] == ds.segment[k]) & (ds.segment[k + horizon] == ds.segment[k])
    return k[ok]


def rollout_starts(ds: Dataset, tau: int, steps: int, max_starts: int = 20000) -> np.ndarray:
    """The rows a multi-step score (ADE, FDE) starts from: every row with tau rows of history and `steps`
    successors in its segment, thinned evenly to at most max_starts."""
    k = valid_end_rows(ds, tau, horizon=steps)
    if len(k) > max_starts:
        k = k[np.linspace(0, len(k) - 1, max_starts).astype(int)]
    return k


def make_windows(ds: Dataset, tau: int, end_rows: np.ndarray | None = None) -> Windows:
    if tau < 1:
        raise DdynError(f"history length tau must be at least 1, got {tau}")
    k = valid_end_rows(ds, tau) if end_rows is None else np.asarray(end_rows)
    if len(k) == 0:
        raise DdynError(f"dataset ({len(ds)} rows) has no window of {tau} rows plus a successor in one segment")
    f = features(ds)
    offsets = np.arange(-tau + 1, 1)
    return Windows(f[k[:, None] + offsets], ds.states[k], ds.inputs[k], ds.states[k + 1, 3:6], k)


def split_train_validation(ds: Dataset, tau: int, val_fraction: float) -> tuple[Windows, Windows]:
    """Disjoint split by time: the last val_fraction of rows validate, the rest train.

    The cut is at a row boundary and no window of one side reads a row of the
    other (windows that would straddle the cut are dropped), so no sample, and
    no row of any sample, is in both sets.
    """
    if not 0 < val_fraction < 1:
        raise DdynError(f"validation fraction must lie in (0, 1), got {val_fraction}")
    cut = int(round(len(ds) * (1 - val_fraction)))
    k = valid_end_rows(ds, tau)
    train_k = k[k + 1 < cut]
    val_k = k[k - tau + 1 >= cut]
    if len(train_k) == 0 or len(val_k) == 0:
        raise DdynError(f"dataset too short for a {val_fraction:.0%} validation split with tau = {tau}")
    return make_windows(ds, tau, train_k), make_windows(ds, tau, val_k)
