"""A smooth curvilinear frame of a track, sampled once at equal arc lengths.

Why: an optimisation over a track needs the centre line's position, heading and curvature as
functions of progress. As linear interpolants of the data's per-point values they have a kink at
every point (666 on ETHZ): IPOPT's dual infeasibility oscillated there, and the interpolant
expanded into every shooting interval took gigabytes. Here the frame is sampled once at m points
s_k = k L / m and the optimiser sees constants:

  - position: the centre polygon resampled at s_k (the data's points lie on the arcs; a chord of
    3 cm on a 0.3 m radius sags 0.4 mm);
  - heading theta_k: the polygon's point headings (bisectors of adjacent segments) interpolated
    at s_k, then a periodic moving average over ~SMOOTH_WINDOW of arc length (the polygon's turn
    is concentrated at its points);
  - curvature of interval k: exactly (theta_{k+1} - theta_k) / ds, so integrating it turns the
    frame by its own headings (no drift between curvature and frame).

A cubic smoothing spline through the points was tried first: at the arcs' ends (curvature steps
from 3.3 to 0 1/m on ETHZMobil) it overshot to 4.8 1/m, and its lap was 0.8 % slower for it.

The widths are measured from the frame's points to the track's bounds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ddyn.model.tracks import Track, distance_to_polyline, resample_closed

# Arc length over which the heading is averaged (m): about three of the 1:43 tracks' point spacings.
SMOOTH_WINDOW = 0.10


@dataclass(frozen=True)
class Frame:
    """The frame at m equally spaced arc lengths s_k = k * length / m (k = 0 .. m-1)."""

    s: np.ndarray          # arc length along the centre (m)
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray    # rad, direction of travel
    kappa: np.ndarray      # 1/m of interval k (from point k to k+1, the last one closes the loop)
    wl: np.ndarray         # distance to the left bound (m)
    wr: np.ndarray         # distance to the right bound (m)
    length: float          # m

    def to_xy(self, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions at lateral offset n (left +) at the frame's points."""
        return self.x - n * np.sin(self.heading), self.y + n * np.cos(self.heading)


def _smooth_periodic(values: np.ndarray, half: int) -> np.ndarray:
    if half <= 0:
        return values
    k = 2 * half + 1
    ext = np.concatenate([values[-half:], values, values[:half]])
    return np.convolve(ext, np.ones(k) / k, mode="valid")


def frame(track: Track, m: int, window: float = SMOOTH_WINDOW) -> Frame:
    """The frame of `track` at m points equally spaced in arc length."""
    length = track.length
    ds = length / m
    s = np.arange(m) * ds
    xy = resample_closed(track.center, m)
    # unwrapped point headings; the loop turns by 2 pi * winding in one lap
    h = np.unwrap(track.heading)
    turn = np.round((np.unwrap(np.append(track.heading, track.heading[0]))[-1] - h[0]) / (2 * np.pi)) * 2 * np.pi
    sp = np.append(track.s, length)
    theta = np.interp(s, sp, np.append(h, h[0] + turn))
    # smooth the periodic part (theta minus its mean winding)
    trend = turn * s / length
    theta = _smooth_periodic(theta - trend, int(round(0.5 * window / ds))) + trend
    kappa = np.diff(np.append(theta, theta[0] + turn)) / ds
    d_left = distance_to_polyline(xy, track.left_bound)
    d_right = distance_to_polyline(xy, track.right_bound)
    return Frame(s, xy[:, 0].copy(), xy[:, 1].copy(), theta, kappa, d_left, d_right, length)
