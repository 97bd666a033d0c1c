"""Errors in variables for the `smoothed` fit (`fit = "smoothed"`): regressors the next sample's noise cannot reach.

A one-step fit predicts the measured state at k+1 from the measured state at k. When the state at k is
noisy, the least-squares estimate is biased (the classic errors-in-variables attenuation: the model's
response to the noise is fitted as if it were the response to the signal), and an effect that scales the
response, a mass offset above all, is "found" on effect-free logs.

The fix used here: the state the step starts from is a local polynomial (Savitzky-Golay) estimate at k
from the samples k-h..k+h WITHOUT sample k+1, the one being predicted. Its noise is a weighted sum of
the other samples' noise, so (for white sensor noise) it is independent of the target's noise, and its
variance is sum(w^2) s2 instead of s2 (about a fifth for h = 5, order 2): the attenuation bias shrinks by
that factor. A local quadratic over +-0.2 s at 25 Hz follows the vehicle's velocities closely (its own
bias, a second-order smoothing of the signal, is measured by the tests on noise-free plant states).
Channels smoothed: vx, vy, omega (the dynamics' states); the commands (throttle, steering) are recorded
exactly and kept; positions and yaw enter only rollouts and stay as logged.
"""
from __future__ import annotations

import numpy as np

HALF_WIDTH = 5      # samples on each side (0.2 s at 25 Hz)
ORDER = 2           # local polynomial order
SMOOTHED = (3, 4, 5)   # state columns: vx, vy, omega


def loo_weights(offsets: np.ndarray, order: int = ORDER) -> np.ndarray:
    """Weights w such that sum_j w_j y(offsets_j) is the local polynomial's value at offset 0."""
    offsets = np.asarray(offsets, float)
    V = np.vander(offsets, min(order, len(offsets) - 1) + 1, increasing=True)
    return np.linalg.pinv(V)[0]


def _window(k: int, a: int, b: int, h: int, skip: int | None) -> np.ndarray:
    j = np.arange(max(a, k - h), min(b, k + h + 1)) - k
    return j[j != skip] if skip is not None else j


def smooth_states(states: np.ndarray, segment: np.ndarray, h: int = HALF_WIDTH, order: int = ORDER,
                  skip: int | None = 1) -> tuple[np.ndarray, float]:
    """The states with columns SMOOTHED replaced by the local polynomial estimate at each row from the samples
    within h rows (same segment), sample k + skip left out (None: none left out). Returns the states and the
    interior rows' noise gain sum(w^2)."""
    out = np.array(states, float, copy=True)
    seg = np.asarray(segment)
    bounds = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1], True])
    w_in = loo_weights(_window(10 * h, 0, 20 * h + 1, h, skip), order)
    j_in = _window(10 * h, 0, 20 * h + 1, h, skip)
    cols = list(SMOOTHED)
    for a, b in zip(bounds[:-1], bounds[1:]):
        y = np.asarray(states[a:b][:, cols], float)
        n = b - a
        if n < 2 * h + 2:          # too short to smooth: keep the logged states
            continue
        inner = np.arange(h, n - h)
        acc = np.zeros((len(inner), len(cols)))
        for jj, ww in zip(j_in, w_in):
            acc += ww * y[inner + jj]
        out[a + inner[0]:a + inner[-1] + 1, cols] = acc
        for k in list(range(0, h)) + list(range(n - h, n)):   # the edges: one-sided windows
            j = _window(k, 0, n, h, skip)
            out[a + k, cols] = loo_weights(j, order) @ y[k + j]
    return out, float(np.sum(w_in ** 2))


def noise_variance(states: np.ndarray, segment: np.ndarray, h: int = HALF_WIDTH, order: int = ORDER) -> np.ndarray:
    """White sensor-noise variance per smoothed channel, from the measurements alone: y_k minus the local
    polynomial from its neighbours (k left out) has variance s2 (1 + sum w^2) plus the smoothing bias."""
    sm, gain = smooth_states(states, segment, h, order, skip=0)
    r = np.asarray(states)[:, list(SMOOTHED)] - sm[:, list(SMOOTHED)]
    r = r[h:-h] if len(r) > 2 * h + 2 else r
    return np.mean(r ** 2, axis=0) / (1.0 + gain)
