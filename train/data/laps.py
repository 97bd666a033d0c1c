"""Laps from a log's own path (x, y): is it a closed circuit, and where along the lap is each row?

Why: without a track file the only position a log has is the distance it travelled, and that cannot line up
lap after lap: the distance per lap depends on the line driven (inside or outside of a turn, a few metres per
turn), so after a few laps the same spot of the track sits tens of metres apart. A profile along the track
(a bank, a grade) and a channel's repeat check (ddyn.data.roll_check) need the same spot to get the same
position on every lap. The log's first lap is a map of the track good enough for that:

  circuit     the start line is the line through the log's first point across its direction of travel; the
              log drives a closed circuit when it crosses that line again, heading the same way (within 60
              degrees of the start's heading), within GATE of the first point, after at least the path's
              extent of distance (a closed lap is at least twice as long as it is wide, so jitter near the
              start never counts);
              GATE = min(MAX_GATE, GATE_SHARE x the extent): a racing line moves across a track's width, a
              road passing near the start elsewhere is farther away than that;
  reference   the first complete lap's path (smoothed over SMOOTH m), closed by the short gap from its last row
              back to its first point, resampled evenly (at most STEP m apart); its length is the lap length.
              The first lap, not a median of laps: it needs no alignment of its own, and a lap driven on
              another line maps onto it as well (the projection is across the track);
  position    each row's point projected onto the reference, searched within WINDOW of where the distance
              travelled since the last crossing of the start line puts it (that distance scaled to the lap
              length: the line driven changes a lap's distance by a few per cent, spread along the lap), so
              parts of a track that pass near each other (the two straights of an oval, a crossing) are never
              confused; a row the window misses by more than FALLBACK (a detour, a pit lane) takes the nearest
              reference point anywhere. Positions are in [0, lap length), the lap number counts crossings.

When the path never returns across its start line (a log shorter than a lap, a drive from A to B) the
positions are the distance travelled (continuing across segments, as before) and `reason` says why.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

MAX_GATE = 25.0      # m: the start line's half-width (a racing line's spread across a wide track)
GATE_SHARE = 0.1     # of the path's extent: a small (model car's) track gets a narrower start line
SMOOTH = 5.0         # m: the reference path's moving average (position noise, not the track's shape)
MAX_REF_POINTS = 200_000   # reference lap points: 200 km at STEP, far beyond any circuit
MAX_COORDINATE = 1e7       # m: positions beyond this (10,000 km) are no circuit's
STEP = 1.0           # m between reference points (at most: a lap of under 500 m gets 500 points)
WINDOW = 40.0        # m either side of the predicted position searched for the nearest reference point
FALLBACK = 5.0       # m: a window's best this much farther than the nearest point anywhere is a miss


@dataclass
class Laps:
    """Each row's position along the log's lap (or the distance travelled when the log is no circuit)."""

    circuit: bool
    position: np.ndarray            # (N,) m: in [0, length) on a circuit, else the distance travelled
    length: float | None            # m: the lap length (None: no circuit)
    lap: np.ndarray                 # (N,) int: lap number (0: the first, the reference lap); all 0 without a circuit
    laps: float                     # laps driven (the distance travelled / length; 0 without a circuit)
    reason: str                     # how the positions were found (or why not from laps)
    reference: np.ndarray | None = None   # (M, 2) the reference lap's path (None: no circuit)

    @property
    def source(self) -> str:
        return (f"laps from x, y ({self.laps:.1f} laps of {self.length:.0f} m)" if self.circuit
                else f"distance travelled ({self.reason})")


def distance(xy: np.ndarray, segment: np.ndarray | None = None) -> np.ndarray:
    """Distance travelled along the path, continuing across segments (no step across a segment boundary)."""
    xy = np.asarray(xy, float)
    with np.errstate(over="ignore", invalid="ignore"):   # a corrupt log's 1e308 m positions: inf, not a warning
        step = np.r_[0.0, np.hypot(*np.diff(xy, axis=0).T)] if len(xy) else np.zeros(0)
    # a step longer than MAX_COORDINATE is no vehicle's (a corrupt row): capped, so the sum stays finite
    step = np.clip(np.where(np.isfinite(step), step, 0.0), 0.0, MAX_COORDINATE)
    if segment is not None and len(xy):
        seg = np.asarray(segment)
        step[np.r_[False, seg[1:] != seg[:-1]]] = 0.0
    return np.cumsum(step)


def from_dataset(ds) -> Laps:
    return from_xy(ds.states[:, 0], ds.states[:, 1], ds.segment)


def _not_circuit(xy, segment, reason: str) -> Laps:
    n = len(xy)
    return Laps(False, distance(xy, segment), None, np.zeros(n, int), 0.0, reason)


def from_xy(x, y, segment=None) -> Laps:
    """The laps of a path (see the module docstring)."""
    xy = np.column_stack([np.asarray(x, float), np.asarray(y, float)])
    n = len(xy)
    if n < 10 or not np.all(np.isfinite(xy)):
        return _not_circuit(np.nan_to_num(xy), segment, "fewer than 10 rows or positions not finite: no laps looked for")
    if np.max(np.abs(xy)) > MAX_COORDINATE:
        return _not_circuit(xy, segment, f"positions beyond {MAX_COORDINATE:.0e} m: not a vehicle log's; no laps looked for")
    step = np.r_[0.0, np.hypot(*np.diff(xy, axis=0).T)]      # across segment gaps too: the car got there
    d = np.cumsum(step)
    extent = float(np.hypot(*np.ptp(xy, axis=0)))
    if extent < 1.0:
        return _not_circuit(xy, segment, "the path stays within 1 m: no laps")
    gate = min(MAX_GATE, GATE_SHARE * extent)
    # the start: the first row, heading along the path's first few metres
    ahead = int(np.searchsorted(d, min(max(2 * STEP, 0.02 * extent), 0.5 * d[-1])))
    h = xy[min(ahead, n - 1)] - xy[0]
    if np.hypot(*h) <= 0:
        return _not_circuit(xy, segment, "the path does not leave its first point")
    h = h / np.hypot(*h)
    rel = xy - xy[0]
    along = rel @ h
    lateral = np.abs(rel[:, 0] * h[1] - rel[:, 1] * h[0])
    forwards = np.diff(along) > 0.5 * step[1:]                 # moving within 60 degrees of the start's heading
    cross = np.flatnonzero((along[:-1] < 0) & (along[1:] >= 0) & (lateral[1:] < gate) & forwards) + 1
    crossings = []
    for c in cross:                                              # a lap is at least the extent long
        if d[c] - (d[crossings[-1]] if crossings else d[0]) >= extent:
            crossings.append(int(c))
    if not crossings:
        return _not_circuit(xy, segment, f"the path does not come back across its start line (within {gate:.0f} m "
                                         f"of its first point, heading the same way): no complete lap")
    c1 = crossings[0]
    # the reference lap: rows 0 .. c1 - 1 (the last one just short of the start line), smoothed and resampled
    lap_xy, lap_d = xy[:c1], d[:c1]
    lap_len = float(lap_d[-1] - lap_d[0] + np.hypot(*(xy[c1 - 1] - xy[0])))   # plus the gap back to the start
    mean_step = max(float(lap_d[-1] - lap_d[0]) / max(c1 - 1, 1), 1e-9)
    w = int(max(1, round(SMOOTH / mean_step)))
    if w > 1 and c1 > 2 * w:
        kern = np.ones(w) / w
        pad = np.r_[lap_xy[-w:], lap_xy, lap_xy[:w]]                # a loop: the ends smooth into each other
        lap_xy = np.column_stack([np.convolve(pad[:, i], kern, mode="same")[w:-w] for i in range(2)])
    # the closed loop (the last row back to the start point), resampled evenly: M points, step_ref apart
    # at most MAX_REF_POINTS (a lap of any size, e.g. a corrupt log's 1e12 m coordinates, stays bounded in memory)
    m = int(min(MAX_REF_POINTS, max(500, math.ceil(lap_len / STEP))))
    step_ref = lap_len / m
    loop_s = np.r_[lap_d - lap_d[0], lap_len]
    loop_xy = np.r_[lap_xy, lap_xy[:1]]
    s_ref = np.arange(m) * step_ref
    ref = np.column_stack([np.interp(s_ref, loop_s, loop_xy[:, i]) for i in range(2)])
    # the predicted position: the distance since the last crossing, scaled to the lap length on complete laps
    starts = np.r_[0, crossings]
    lap_no = np.searchsorted(np.asarray(crossings), np.arange(n), side="right")
    s0 = np.r_[0.0, along[crossings]]                             # the position at each lap's first row
    ends = np.r_[crossings, n]
    lap_dist = np.array([d[e] - d[a] + s0[j] - along[e] if e < n else np.nan
                         for j, (a, e) in enumerate(zip(starts, ends))])
    scale = lap_len / lap_dist
    done = np.isfinite(scale)
    scale[~done] = np.median(scale[done]) if done.any() else 1.0
    pred = (s0[lap_no] + d - d[starts[lap_no]]) * scale[lap_no]
    # the nearest reference point within the window around the prediction
    window = min(WINDOW, 0.5 * lap_len)       # a lap shorter than the window: half a lap either side is all of it
    offsets = np.arange(-window, window + step_ref / 2, step_ref)
    idx = np.empty(n, int)
    best = np.empty(n)
    for a in range(0, n, 20000):
        b = min(n, a + 20000)
        cand = np.mod(np.round((pred[a:b, None] + offsets[None, :]) / step_ref).astype(int), m)
        dist = np.hypot(ref[cand, 0] - xy[a:b, 0, None], ref[cand, 1] - xy[a:b, 1, None])
        j = np.argmin(dist, axis=1)
        idx[a:b], best[a:b] = cand[np.arange(b - a), j], dist[np.arange(b - a), j]
    g_dist, g_idx = cKDTree(ref).query(xy)
    miss = best > g_dist + FALLBACK
    idx[miss] = g_idx[miss]
    # refine onto the segment before or after the nearest point (the loop is closed: index m is index 0)
    pos = s_ref[idx].copy()
    bestd = np.hypot(*(xy - ref[idx]).T)
    for lo in (idx - 1, idx):
        lo = np.mod(lo, m)
        seg = ref[np.mod(lo + 1, m)] - ref[lo]
        seg2 = np.maximum(np.sum(seg * seg, axis=1), 1e-12)
        t = np.clip(np.sum((xy - ref[lo]) * seg, axis=1) / seg2, 0.0, 1.0)
        foot = ref[lo] + t[:, None] * seg
        dd = np.hypot(*(xy - foot).T)
        better = dd < bestd
        pos[better], bestd[better] = s_ref[lo][better] + t[better] * step_ref, dd[better]
    pos = np.mod(pos, lap_len)
    # the lap number that keeps the unwrapped position next to the prediction (a row just short of the start
    # line on the next lap's count belongs to the lap before)
    unwrapped_pred = lap_no * lap_len + pred
    lap = np.round((unwrapped_pred - pos) / lap_len).astype(int)
    n_laps = float(d[-1] / lap_len)
    reason = (f"a closed circuit: {len(crossings)} crossing(s) of the start line (within {gate:.0f} m of the first "
              f"point); the lap ({lap_len:.0f} m) mapped from the first lap's path; {int(miss.sum())} row(s) "
              f"located away from their predicted position")
    return Laps(True, pos, lap_len, lap, n_laps, reason, ref)
