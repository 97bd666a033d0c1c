"""Race tracks: a closed centre line with its two bounds, and optionally a racing line.

A Track is a closed polyline (the centre line, no repeated end point; the closing
segment from the last point back to the first belongs to the loop) plus the two
track bounds as read from the data files. Positions along the track are given by
arc length s in [0, length); the lateral offset is signed, positive to the left of
the direction of travel (the order of the centre-line points).

Track files live in the shared data folder (env DDYN_SHARED_DATA, else
<repo root>/../shared/data), sub-folder tracks/:

    ethz, ethzMobil  <name>_center.txt, _inner.txt, _outer.txt: two comma-separated
                     rows, x then y (metres); racing line <name>_raceline*.npz
    putnam           putnam_inner_bound.csv, putnam_outer_bound.csv: rows x,y,z of the
                     two bounds only; the centre line is built here (see
                     centre_from_bounds)

The "inner"/"outer" names are those of the files; they are the left and right
bounds in some order (which one is left is worked out, see Track.left_bound).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.paths import shared_data_dir

DATA_ENV = "DDYN_SHARED_DATA"
TRACK_NAMES = ("ethz", "ethzMobil", "putnam")
_RACELINE_FILES = {"ethz": "ethz_raceline.npz", "ethzMobil": "ethzMobil_raceline_long.npz"}
# number of (query, segment) pairs evaluated at once by the nearest-point search
_CHUNK = 1 << 21


def data_dir() -> Path:
    """The shared data folder: $DDYN_SHARED_DATA, else <repo root>/../shared/data."""
    return shared_data_dir()


def _require(path: Path) -> Path:
    if not path.is_file():
        raise DdynError(f"track file not found: {path} (set {DATA_ENV} to the shared data folder)")
    return path


# ----------------------------------------------------------------------------------------------
# polyline helpers (closed loops given as (N, 2) arrays without a repeated end point)

def _close_open(points: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Drop a last point that repeats the first (a loop stored explicitly closed)."""
    points = np.asarray(points, dtype=float)
    scale = max(float(np.ptp(points, axis=0).max()), 1.0)
    while len(points) > 3 and np.hypot(*(points[-1] - points[0])) <= rtol * scale:
        points = points[:-1]
    return points


def _drop_repeats(points: np.ndarray) -> np.ndarray:
    """Remove consecutive duplicate points (zero-length segments)."""
    step = np.hypot(*(np.roll(points, -1, axis=0) - points).T)
    keep = step > 1e-12 * max(float(np.ptp(points, axis=0).max()), 1.0)
    return points[keep]


def _segments(points: np.ndarray):
    """Start points, vectors, lengths and cumulative start arc length of the loop's segments."""
    d = np.roll(points, -1, axis=0) - points
    ln = np.hypot(d[:, 0], d[:, 1])
    s = np.concatenate(([0.0], np.cumsum(ln)[:-1]))
    return points, d, ln, s


def signed_area(points: np.ndarray) -> float:
    """Shoelace area of a closed loop: positive when counter-clockwise."""
    x, y = points[:, 0], points[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def resample_closed(points: np.ndarray, n: int) -> np.ndarray:
    """n points equally spaced in arc length around a closed loop, starting at points[0]."""
    p0, d, ln, s = _segments(points)
    total = s[-1] + ln[-1]
    u = np.arange(n) * (total / n)
    i = np.clip(np.searchsorted(s, u, side="right") - 1, 0, len(s) - 1)
    t = (u - s[i]) / np.where(ln[i] > 0, ln[i], 1.0)
    return p0[i] + t[:, None] * d[i]


def _nearest_on_segments(q: np.ndarray, p0: np.ndarray, d: np.ndarray, ln: np.ndarray,
                         seg_index: np.ndarray | None = None):
    """For each query point (Q, 2): index of the nearest segment, parameter t in [0, 1], squared distance.

    seg_index optionally restricts the search to a (Q, W) set of segment indices per query.
    Chunked so memory stays bounded for many queries against many segments.
    """
    q = np.asarray(q, dtype=float).reshape(-1, 2)
    nq = len(q)
    inv = 1.0 / np.where(ln > 0, ln * ln, 1.0)
    best_i = np.empty(nq, dtype=np.int64)
    best_t = np.empty(nq)
    best_d2 = np.empty(nq)
    width = len(p0) if seg_index is None else seg_index.shape[1]
    rows = max(1, _CHUNK // max(width, 1))
    for a in range(0, nq, rows):
        b = min(nq, a + rows)
        if seg_index is None:
            P, D, I = p0[None], d[None], inv[None]
        else:
            idx = seg_index[a:b]
            P, D, I = p0[idx], d[idx], inv[idx]
        rx = q[a:b, 0:1] - P[..., 0]
        ry = q[a:b, 1:2] - P[..., 1]
        t = np.clip((rx * D[..., 0] + ry * D[..., 1]) * I, 0.0, 1.0)
        ex = rx - t * D[..., 0]
        ey = ry - t * D[..., 1]
        d2 = ex * ex + ey * ey
        j = np.argmin(d2, axis=1)
        r = np.arange(b - a)
        best_t[a:b] = t[r, j]
        best_d2[a:b] = d2[r, j]
        best_i[a:b] = j if seg_index is None else seg_index[a:b][r, j]
    return best_i, best_t, best_d2


def distance_to_polyline(q: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance from each query point (Q, 2) to a closed polyline."""
    p0, d, ln, _ = _segments(points)
    _, _, d2 = _nearest_on_segments(q, p0, d, ln)
    return np.sqrt(d2)


def _periodic_smooth(values: np.ndarray, half: int) -> np.ndarray:
    """Centred moving average over 2*half+1 samples of a periodic sequence (vectorised)."""
    if half <= 0:
        return values.copy()
    n = len(values)
    k = 2 * half + 1
    ext = np.concatenate([values[n - half:], values, values[:half]], axis=0)
    c = np.cumsum(np.concatenate([np.zeros((1,) + values.shape[1:]), ext], axis=0), axis=0)
    return (c[k:] - c[:-k]) / k


def centre_from_bounds(bound_a: np.ndarray, bound_b: np.ndarray, spacing: float | None = None,
                       iterations: int = 3) -> np.ndarray:
    """A centre line between two closed bounds of different point counts.

    The bounds are brought to a common direction (by the sign of their area), the
    second is rotated so that it starts at its point closest to the first bound's
    start, both are resampled by arc length to a common count and averaged. That
    first guess pairs points by fraction of length, which drifts where the bounds'
    lengths differ (inside versus outside of corners), so it is refined: each centre
    point moves to the midpoint of its nearest points on the two bounds, and the
    line is lightly smoothed and resampled at uniform spacing again.
    """
    a = _drop_repeats(_close_open(bound_a))
    b = _drop_repeats(_close_open(bound_b))
    if np.sign(signed_area(a)) != np.sign(signed_area(b)):
        b = b[::-1]
    start = int(np.argmin(np.hypot(b[:, 0] - a[0, 0], b[:, 1] - a[0, 1])))
    b = np.roll(b, -start, axis=0)
    n = max(len(a), len(b))
    centre = 0.5 * (resample_closed(a, n) + resample_closed(b, n))
    pa, da, la, _ = _segments(a)
    pb, db, lb, _ = _segments(b)
    if spacing is None:
        _, _, ln, _ = _segments(centre)
        spacing = float(np.median(ln))
    for _ in range(iterations):
        ia, ta, _ = _nearest_on_segments(centre, pa, da, la)
        ib, tb, _ = _nearest_on_segments(centre, pb, db, lb)
        mid = 0.5 * ((pa[ia] + ta[:, None] * da[ia]) + (pb[ib] + tb[:, None] * db[ib]))
        mid = _periodic_smooth(mid, 2)
        _, _, ln, _ = _segments(mid)
        total = float(ln.sum())
        centre = resample_closed(mid, max(8, int(round(total / spacing))))
    return centre


def bounds_from_widths(centre: np.ndarray, w_left: np.ndarray, w_right: np.ndarray):
    """Left and right bounds: the centre points moved along their normals (bisector of adjacent segments)."""
    d = np.roll(centre, -1, axis=0) - centre
    t_seg = d / np.hypot(d[:, 0], d[:, 1])[:, None]
    t = t_seg + np.roll(t_seg, 1, axis=0)
    t /= np.hypot(t[:, 0], t[:, 1])[:, None]
    normal = np.column_stack([-t[:, 1], t[:, 0]])  # left of the direction of travel
    return centre + w_left[:, None] * normal, centre - w_right[:, None] * normal


# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Raceline:
    """A time-optimal racing line from the data files: positions, time and speed at n points."""

    x: np.ndarray
    y: np.ndarray
    time: np.ndarray
    speed: np.ndarray
    inputs: np.ndarray | None
    path: str = ""


class Track:
    """A closed track: centre line, bounds, widths, arc length, projection and inside tests."""

    def __init__(self, name: str, center: np.ndarray, inner: np.ndarray, outer: np.ndarray,
                 raceline: Raceline | None = None, source: str = ""):
        center = _drop_repeats(_close_open(np.asarray(center, dtype=float).reshape(-1, 2)))
        if len(center) < 4:
            raise DdynError(f"track {name!r}: centre line needs at least 4 distinct points")
        if not np.all(np.isfinite(center)):
            raise DdynError(f"track {name!r}: centre line has non-finite points")
        self.name = name
        self.source = source
        self.files: dict[str, str] = {}  # the user's files it was read from (ddyn.model.track_files)
        self.raceline = raceline
        self.inner = _close_open(np.asarray(inner, dtype=float).reshape(-1, 2))
        self.outer = _close_open(np.asarray(outer, dtype=float).reshape(-1, 2))
        self.center = center
        self._p0, self._d, self._len, self.s = _segments(center)
        self.length = float(self.s[-1] + self._len[-1])
        self.x, self.y = center[:, 0].copy(), center[:, 1].copy()
        self.n = len(center)

        # tangent heading of each segment, and at each point (bisector of the adjacent segments)
        seg_heading = np.arctan2(self._d[:, 1], self._d[:, 0])
        turn = _wrap(seg_heading - np.roll(seg_heading, 1))
        self.heading = _wrap(np.roll(seg_heading, 1) + 0.5 * turn)
        ds_pt = 0.5 * (self._len + np.roll(self._len, 1))
        self.curvature_raw = turn / ds_pt
        # lightly smoothed (5-point periodic average): the data's arcs are polygons
        self.curvature = _periodic_smooth(self.curvature_raw, 2)

        # which bound is on the left (positive lateral offset)
        _, lat_inner = self.project(self.inner[:, 0], self.inner[:, 1])
        inner_left = float(np.median(lat_inner)) > 0.0
        self.left_bound, self.right_bound = (self.inner, self.outer) if inner_left else (self.outer, self.inner)
        self.left_name = "inner" if inner_left else "outer"
        # half widths at the centre points: distance to each bound
        self.half_width_left = distance_to_polyline(center, self.left_bound)
        self.half_width_right = distance_to_polyline(center, self.right_bound)
        self.width = float(np.median(self.half_width_left + self.half_width_right))

    def __repr__(self) -> str:
        return (f"Track({self.name!r}, {self.n} points, length {self.length:.3f} m, "
                f"width {self.width:.3f} m{', raceline' if self.raceline is not None else ''})")

    # ---- interpolation along the centre line (periodic in s)
    def _locate(self, s):
        s = np.mod(np.asarray(s, dtype=float), self.length)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, self.n - 1)
        t = (s - self.s[i]) / self._len[i]
        return i, t

    def interpolate(self, values: np.ndarray, s):
        """Linear interpolation along the loop of per-centre-point values (length n) at arc length s."""
        i, t = self._locate(s)
        return values[i] * (1.0 - t) + values[(i + 1) % self.n] * t

    def road_profile_at(self, name: str, s) -> np.ndarray:
        """The track's own per-centre-point road profile `name` ("bank", "grade"; rad) at arc lengths s; zero when
        the track has none (a level, unbanked track)."""
        values = getattr(self, name, None)
        if values is None:
            return np.zeros(np.shape(s))
        return self.interpolate(np.asarray(values, float), s)

    def position(self, s):
        """Centre-line point (x, y) at arc length s (wraps around)."""
        i, t = self._locate(s)
        p = self._p0[i] + np.asarray(t)[..., None] * self._d[i]
        return p[..., 0], p[..., 1]

    def heading_at(self, s):
        """Heading of the centre line's segment containing s (rad)."""
        i, _ = self._locate(s)
        return np.arctan2(self._d[i, 1], self._d[i, 0])

    def curvature_at(self, s):
        """Smoothed signed curvature (1/m, positive turning left) at s."""
        return self.interpolate(self.curvature, s)

    def half_widths(self, s):
        """(left, right) distances from the centre line to the bounds at s."""
        return self.interpolate(self.half_width_left, s), self.interpolate(self.half_width_right, s)

    # ---- projection
    def project(self, x, y, s_hint=None, window: float | None = None):
        """Nearest point on the centre line: (s, lateral offset), vectorised over x, y.

        lateral offset is signed, positive to the left of the direction of travel. With
        s_hint (same shape as x, or scalar) and window (metres), only segments within
        +-window of s_hint are searched (fast, and immune to jumps onto a neighbouring
        section of the track).
        """
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        shape = np.broadcast_shapes(x.shape, y.shape)
        q = np.stack(np.broadcast_arrays(x, y), axis=-1).reshape(-1, 2)
        seg_index = None
        if s_hint is not None:
            if window is None:
                window = 0.1 * self.length
            i0, _ = self._locate(np.broadcast_to(np.asarray(s_hint, dtype=float), shape).reshape(-1))
            mean_len = self.length / self.n
            w = int(min(self.n // 2, np.ceil(window / mean_len) + 1))
            seg_index = (i0[:, None] + np.arange(-w, w + 1)[None, :]) % self.n
        i, t, d2 = _nearest_on_segments(q, self._p0, self._d, self._len, seg_index)
        s = self.s[i] + t * self._len[i]
        s = np.where(s >= self.length, s - self.length, s)
        rx = q[:, 0] - self._p0[i, 0]
        ry = q[:, 1] - self._p0[i, 1]
        cross = self._d[i, 0] * ry - self._d[i, 1] * rx
        lat = np.where(cross >= 0.0, 1.0, -1.0) * np.sqrt(d2)
        return s.reshape(shape), lat.reshape(shape)

    def boundary_distance(self, x, y, s_hint=None, window: float | None = None):
        """Signed distance to the nearer bound, measured laterally: positive inside, negative outside."""
        s, lat = self.project(x, y, s_hint, window)
        wl, wr = self.half_widths(s)
        return np.minimum(wl - lat, wr + lat)

    def inside(self, x, y, margin: float = 0.0, s_hint=None, window: float | None = None):
        """True where (x, y) lies between the bounds (with `margin` metres of slack outwards)."""
        return self.boundary_distance(x, y, s_hint, window) >= -margin


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def _read_rows_xy(path: Path) -> np.ndarray:
    try:
        a = np.loadtxt(_require(path), delimiter=",", ndmin=2)
    except ValueError as e:
        raise DdynError(f"{path}: cannot read two comma-separated rows x, y: {e}") from None
    if a.shape[0] != 2 or a.shape[1] < 4:
        raise DdynError(f"{path}: expected two rows (x then y), got shape {a.shape}")
    return a.T.copy()


def _read_csv_xyz(path: Path) -> np.ndarray:
    try:
        a = np.loadtxt(_require(path), delimiter=",", ndmin=2, comments="#")
    except ValueError as e:
        raise DdynError(f"{path}: cannot read rows x,y,z: {e}") from None
    if a.shape[1] < 2 or a.shape[0] < 4:
        raise DdynError(f"{path}: expected rows x,y[,z], got shape {a.shape}")
    return a[:, :2].copy()


def load_raceline(path: Path) -> Raceline:
    with np.load(_require(path)) as z:
        try:
            return Raceline(np.asarray(z["x"], float), np.asarray(z["y"], float), np.asarray(z["time"], float),
                            np.asarray(z["speed"], float),
                            np.asarray(z["inputs"], float) if "inputs" in z else None, str(path))
        except KeyError as e:
            raise DdynError(f"{path}: raceline lacks array {e.args[0]!r}") from None


_CACHE: dict[tuple[str, str], Track] = {}


def load_track(name: str, directory: str | Path | None = None) -> Track:
    """Load a track by name: ethz, ethzMobil or putnam (cached per data folder)."""
    if name not in TRACK_NAMES:
        raise DdynError(f"unknown track {name!r}; expected one of {', '.join(TRACK_NAMES)}")
    base = Path(directory) if directory is not None else data_dir()
    key = (name, str(base))
    if key in _CACHE:
        return _CACHE[key]
    folder = base / "tracks"
    if name == "putnam":
        inner = _read_csv_xyz(folder / "putnam_inner_bound.csv")
        outer = _read_csv_xyz(folder / "putnam_outer_bound.csv")
        center = centre_from_bounds(inner, outer)
        track = Track(name, center, inner, outer, None,
                      source=f"{folder / 'putnam_inner_bound.csv'} + putnam_outer_bound.csv (centre built)")
    else:
        center = _read_rows_xy(folder / f"{name}_center.txt")
        inner = _read_rows_xy(folder / f"{name}_inner.txt")
        outer = _read_rows_xy(folder / f"{name}_outer.txt")
        rl_path = folder / _RACELINE_FILES[name]
        raceline = load_raceline(rl_path) if rl_path.is_file() else None
        track = Track(name, center, inner, outer, raceline, source=str(folder / f"{name}_center.txt"))
    _CACHE[key] = track
    return track
