"""Seeded random 1:43 tracks: `--track random:SEED` anywhere a track is taken.

Why: the MPC's weights, reference speed and racing line were chosen on ETHZMobil alone. Random
tracks give tuning tracks and held-out tracks that no choice has seen.

A track: a star-shaped loop of POINTS control points (angles jittered around the circle; half of
them pulled deep inside, so the others stand out as lobes whose tips are hairpins and whose
flanks bend concave), interpolated by a periodic cubic spline, scaled to a length drawn from
LENGTH, smoothed (neighbour averages) until its tightest radius is MIN_RADIUS, with a constant width
drawn from WIDTH. A draw is kept only if it is drivable
like the ETH tracks: every radius of curvature >= MIN_RADIUS, the track never comes closer to
itself than its width plus CLEARANCE (so the bounds never touch), and it has at least one concave
bend and one hairpin (HAIRPIN of heading change within HAIRPIN_SPAN of arc length). Draws are
made from one numpy Generator seeded with SEED, so a seed always gives the same track.
"""
from __future__ import annotations

import numpy as np

from ddyn.errors import DdynError
from ddyn.model.tracks import Track, bounds_from_widths, resample_closed

LENGTH = (8.0, 18.0)        # m, centre line
WIDTH = (0.37, 0.46)        # m, the ETH tracks' widths
MIN_RADIUS = 0.3            # m
CLEARANCE = 0.03            # m between two parts of the track's bounds (ETHZ: 0.04)
HAIRPIN = np.radians(150.0)
HAIRPIN_SPAN = 1.5          # m
POINTS = (10, 20)           # control points of the star
DEEP_SHARE = 0.5            # share of them pulled in deep (the concave bends and the hairpins' lobes)
DEEP = (0.1, 0.4)           # their radius as a fraction of the star's
OUTER = (0.75, 1.0)
SPACING = 0.03              # m between centre points (the ETH data: 2.7 - 3.4 cm)
ATTEMPTS = 500


def _candidate(rng: np.random.Generator):
    """A star-shaped loop through K random points, smoothed until its tightest radius is MIN_RADIUS."""
    from scipy.interpolate import splev, splprep

    k = int(rng.integers(*POINTS))
    ang = (np.arange(k) + rng.uniform(-0.3, 0.3, k)) * (2 * np.pi / k)
    deep = rng.uniform(0.0, 1.0, k) < DEEP_SHARE
    rad = np.where(deep, rng.uniform(*DEEP, k), rng.uniform(*OUTER, k))
    pts = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
    pts = np.vstack([pts, pts[:1]])
    tck, _ = splprep([pts[:, 0], pts[:, 1]], s=0.0, per=1, k=3, quiet=2)
    dense = np.column_stack(splev(np.linspace(0, 1, 2000, endpoint=False), tck))
    length = float(rng.uniform(*LENGTH))
    width = float(rng.uniform(*WIDTH))
    n = int(round(length / SPACING))
    centre = _scaled(dense, length, n)
    # a spline through random points has kinks where they crowd: average neighbouring points
    # (curve-shortening; it keeps the big concave bends) and restore the length, until the
    # tightest radius is the minimum
    for _ in range(300):
        if properties(centre, closest=False)["min_radius"] >= MIN_RADIUS:
            break
        centre = _scaled(_smooth(centre, 1), length, n)
    return centre, width


def _smooth(points: np.ndarray, half: int) -> np.ndarray:
    k = 2 * half + 1
    ext = np.concatenate([points[-half:], points, points[:half]])
    return np.column_stack([np.convolve(ext[:, i], np.ones(k) / k, mode="valid") for i in range(2)])


def _scaled(points: np.ndarray, length: float, n: int) -> np.ndarray:
    seg = np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)
    c = points.mean(axis=0)
    return resample_closed(c + (points - c) * (length / seg.sum()), n)


def properties(centre: np.ndarray, closest: bool = True) -> dict:
    """Minimum radius (m), concave bends, hairpins and the closest approach of non-neighbouring parts."""
    n = len(centre)
    d = np.roll(centre, -1, axis=0) - centre
    seg_heading = np.arctan2(d[:, 1], d[:, 0])
    turn = (seg_heading - np.roll(seg_heading, 1) + np.pi) % (2 * np.pi) - np.pi
    ds = np.hypot(d[:, 0], d[:, 1])
    spacing = float(np.mean(ds))
    # curvature over 3-point windows (the points are the spline's, smooth)
    kappa = turn / spacing
    kappa_s = np.convolve(np.concatenate([kappa[-2:], kappa, kappa[:2]]), np.ones(5) / 5, mode="valid")
    winding = np.sign(turn.sum())
    # a concave bend: 45 degrees or more turned against the loop's winding in one run
    runs, cur = [], 0.0
    for t in turn * winding:
        if t < 0:
            cur += -t
        else:
            if cur > 0:
                runs.append(cur)
            cur = 0.0
    runs.append(cur)
    concave = int(sum(r >= np.radians(45) for r in runs))
    # a hairpin: HAIRPIN of heading change (either way) within HAIRPIN_SPAN of arc length
    w = max(1, int(round(HAIRPIN_SPAN / spacing)))
    cum = np.concatenate([np.cumsum(np.concatenate([turn, turn])), [0.0]])
    window = np.abs(cum[w:w + n] - cum[:n])
    hairpins = int(np.sum((window >= HAIRPIN) & (np.roll(window, 1) < HAIRPIN)))
    # closest approach of parts more than 2 m apart along the track
    if not closest:
        return {"min_radius": float(1.0 / max(np.abs(kappa_s).max(), 1e-9))}
    far = max(2, int(round(2.0 / spacing)))
    diff = centre[:, None, :] - centre[None, :, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])
    idx = np.arange(n)
    gap = np.abs(idx[:, None] - idx[None, :])
    gap = np.minimum(gap, n - gap)
    closest = float(dist[gap > far].min()) if np.any(gap > far) else np.inf
    return {"min_radius": float(1.0 / max(np.abs(kappa_s).max(), 1e-9)), "concave_bends": concave,
            "hairpins": hairpins, "closest_approach": closest, "length": float(ds.sum())}


def random_track(seed: int) -> Track:
    """The random track of this seed (the same every time)."""
    rng = np.random.default_rng([18, int(seed)])
    for attempt in range(ATTEMPTS):
        centre, width = _candidate(rng)
        p = properties(centre)
        if (p["min_radius"] >= MIN_RADIUS and p["closest_approach"] >= width + CLEARANCE
                and p["concave_bends"] >= 1 and p["hairpins"] >= 1 and LENGTH[0] <= p["length"] <= LENGTH[1]):
            half = np.full(len(centre), 0.5 * width)
            left, right = bounds_from_widths(centre, half, half)
            track = Track(f"random{seed}", centre, left, right, None,
                          source=f"ddyn.model.track_random seed {seed} (draw {attempt + 1})")
            track.properties = dict(p, width=width, draws=attempt + 1)
            return track
    raise DdynError(f"random track {seed}: no drivable draw in {ATTEMPTS} attempts")


# a full-size road course from a random track (`ddyn study transfer`'s other track, `ddyn gap lofo --tracks road`):
# x200 makes MIN_RADIUS 60 m and the tracks 1.6-3.6 km; x100 and x150 put bends at 30 and 45 m where the multi-body
# AV-21 spun within the first seconds or the first lap on random:301 at 22-24 m/s
ROAD_SCALE = 200.0
ROAD_WIDTH = 9.0            # m, Putnam's median width


def road_course(seed: int, scale: float = ROAD_SCALE, width: float = ROAD_WIDTH) -> Track:
    """The random 1:43 track random:SEED scaled to a full-size road course of constant width."""
    r = random_track(seed)
    c = np.asarray(r.center, float) * scale
    half = np.full(len(c), 0.5 * width)
    left, right = bounds_from_widths(c, half, half)
    return Track(f"random{seed}x{scale:g}", c, left, right, None,
                 source=f"ddyn.model.track_random seed {seed} scaled x{scale:g}, {width:g} m wide")
