"""Tracks from a name or from a user's files, checked before anything drives on them.

`--track` everywhere goes through open_track(spec):

    ethz | ethzMobil | putnam        the shared data's tracks (ddyn.model.tracks.load_track)
    random:SEED                      a seeded random 1:43 track (ddyn.model.track_random)
    oval                             the banked oval of ddyn.model.track_oval (full scale, banking in Track.bank)
    path/prefix                      prefix_center.txt, prefix_inner.txt, prefix_outer.txt in the shared
                                     data's format (two comma-separated rows, x then y, metres)
    path/dir/                        a directory holding exactly one such triple
    path/track.csv                   one CSV: columns x, y, w_left, w_right (the centre line and the
                                     distances to the left and right bound; a header line is optional)

A user's track is checked (check_track) and any problem is a DdynError naming the file: an open
loop, a bound or centre line that crosses itself, bounds that cross each other or the centre line,
and a track narrower than the car's footprint (FOOTPRINT in ddyn.model.vehicle). The shared data's
tracks are trusted as they are (they are what the tests were written against).
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.model.tracks import TRACK_NAMES, Track, bounds_from_widths, load_track
from ddyn.model.vehicle import FOOTPRINT

PARTS = ("center", "inner", "outer")
# A loop is closed when its end points are at most this many median point spacings apart.
CLOSE_GAP = 3.0


def is_named(spec: str) -> bool:
    return spec in TRACK_NAMES


def open_track(spec: str, vehicle_name: str | None = None) -> Track:
    """The track named or stored at `spec` (see the module's doc); checked against the vehicle's footprint."""
    spec = str(spec)
    if is_named(spec):
        return load_track(spec)
    if spec == "oval":   # the banked oval of ddyn.model.track_oval (its banking comes with it)
        from ddyn.model.track_oval import oval_track

        return oval_track()
    if spec.startswith("random:"):
        from ddyn.model.track_random import random_track

        try:
            seed = int(spec.split(":", 1)[1])
        except ValueError:
            raise DdynError(f"track {spec!r}: expected random:SEED with an integer seed") from None
        track = random_track(seed)
    else:
        track = read_track(Path(spec))
    check_track(track, vehicle_name)
    return track


# ---------------------------------------------------------------------------------------------- reading

def _rows_xy(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DdynError(f"track file not found: {path}")
    try:
        a = np.loadtxt(path, delimiter=",", ndmin=2)
    except ValueError as e:
        raise DdynError(f"{path}: cannot read two comma-separated rows x, y: {e}") from None
    if a.shape[0] != 2 or a.shape[1] < 4:
        raise DdynError(f"{path}: expected two rows (x then y) of at least 4 points, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DdynError(f"{path}: non-finite coordinates")
    return a.T.copy()


def _prefix_of(path: Path) -> Path:
    """The common prefix of a <prefix>_center.txt triple given as a prefix, a directory or one of the files."""
    if path.is_dir():
        found = sorted(path.glob("*_center.txt"))
        if len(found) != 1:
            raise DdynError(f"{path}: expected exactly one *_center.txt in the directory, found {len(found)}")
        return found[0].with_name(found[0].name[: -len("_center.txt")])
    for part in PARTS:
        if path.name.endswith(f"_{part}.txt"):
            return path.with_name(path.name[: -len(f"_{part}.txt")])
    return path


def read_track(path: Path) -> Track:
    """A track from a user's files (not checked: see check_track)."""
    if path.suffix.lower() == ".csv":
        return read_csv(path)
    prefix = _prefix_of(path)
    files = {p: prefix.with_name(f"{prefix.name}_{p}.txt") for p in PARTS}
    missing = [str(f) for f in files.values() if not f.is_file()]
    if missing:
        raise DdynError(f"track {str(path)!r} is not a track name ({', '.join(TRACK_NAMES)}, random:SEED) "
                        f"and its files are missing: {', '.join(missing)}")
    pts = {p: _rows_xy(f) for p, f in files.items()}
    for p, f in files.items():
        _check_closed(pts[p], f)
    track = Track(prefix.name, pts["center"], pts["inner"], pts["outer"], None, source=str(files["center"]))
    track.files = {p: str(f) for p, f in files.items()}
    return track


def read_csv(path: Path) -> Track:
    """A track from one CSV of the centre line and its widths: x, y, w_left, w_right."""
    if not path.is_file():
        raise DdynError(f"track file not found: {path}")
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if lines and not _is_number(lines[0].split(",")[0]):
        lines = lines[1:]  # a header
    try:
        a = np.array([[float(v) for v in ln.split(",")] for ln in lines], dtype=float)
    except ValueError as e:
        raise DdynError(f"{path}: cannot read rows x, y, w_left, w_right: {e}") from None
    if a.ndim != 2 or a.shape[1] != 4 or len(a) < 4:
        raise DdynError(f"{path}: expected at least 4 rows of 4 columns x, y, w_left, w_right, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DdynError(f"{path}: non-finite values")
    if np.any(a[:, 2:] <= 0):
        raise DdynError(f"{path}: widths must be positive (row {int(np.argmin(a[:, 2:].min(axis=1))) + 1})")
    _check_closed(a[:, :2], path)
    centre = _dedupe_closing(a)
    left, right = bounds_from_widths(centre[:, :2], centre[:, 2], centre[:, 3])
    track = Track(path.stem, centre[:, :2], left, right, None, source=str(path))
    track.files = {"csv": str(path)}
    return track


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _dedupe_closing(a: np.ndarray) -> np.ndarray:
    """Drop a last row that repeats the first (a loop stored explicitly closed)."""
    if len(a) > 4 and np.hypot(*(a[-1, :2] - a[0, :2])) < 1e-9:
        return a[:-1]
    return a


def _check_closed(points: np.ndarray, path: Path) -> None:
    gaps = np.hypot(*np.diff(points, axis=0).T)
    spacing = float(np.median(gaps[gaps > 0])) if np.any(gaps > 0) else 0.0
    end_gap = float(np.hypot(*(points[-1] - points[0])))
    if spacing == 0.0 or end_gap > CLOSE_GAP * spacing:
        raise DdynError(f"{path}: the loop is open: its last point is {end_gap:.3f} m from its first "
                        f"(points are {spacing:.3f} m apart; a track must be a closed loop)")


# ---------------------------------------------------------------------------------------------- writing

def write_track(track: Track, prefix: Path) -> dict[str, Path]:
    """Write the track's centre line and bounds as prefix_center.txt, _inner.txt, _outer.txt
    (the shared data's format, full precision: reading them back gives the same arrays)."""
    prefix = Path(prefix)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    out = {}
    for part, pts in zip(PARTS, (track.center, track.inner, track.outer)):
        path = prefix.with_name(f"{prefix.name}_{part}.txt")
        np.savetxt(path, pts.T, delimiter=",", fmt="%.17g")
        out[part] = path
    return out


def track_digest(track: Track) -> str:
    """A short digest of the geometry (to tell a computed line's track from another of the same name)."""
    h = hashlib.sha256()
    for a in (track.center, track.inner, track.outer):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


# ---------------------------------------------------------------------------------------------- checks

def _segments_cross(a: np.ndarray, b: np.ndarray, same: bool) -> tuple[int, int] | None:
    """The first pair (i, j) of crossing segments of closed polylines a and b (proper crossings only);
    with same, a is b and neighbouring segments (which share a point) are skipped."""
    pa, qa = a, np.roll(a, -1, axis=0)
    pb, qb = b, np.roll(b, -1, axis=0)
    rows = max(1, (1 << 21) // max(len(b), 1))
    for s in range(0, len(a), rows):
        P, Q = pa[s:s + rows, None], qa[s:s + rows, None]

        def orient(u, v, w):
            return np.sign((v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1])
                           - (v[..., 1] - u[..., 1]) * (w[..., 0] - u[..., 0]))

        c1 = orient(P, Q, pb[None]) * orient(P, Q, qb[None])
        c2 = orient(pb[None], qb[None], P) * orient(pb[None], qb[None], Q)
        hit = (c1 < 0) & (c2 < 0)
        if same:
            i = np.arange(s, min(s + rows, len(a)))[:, None]
            j = np.arange(len(b))[None, :]
            gap = np.abs(i - j)
            hit &= (gap > 1) & (gap < len(a) - 1)
        if hit.any():
            i, j = np.argwhere(hit)[0]
            return int(s + i), int(j)
    return None


def check_track(track: Track, vehicle_name: str | None = None) -> None:
    """Raise DdynError naming the file and the problem if the track cannot be driven on."""
    files = getattr(track, "files", {}) or {}
    where = files.get("csv") or track.source or track.name
    lines = {"centre line": (track.center, files.get("center", where)),
             "inner bound": (track.inner, files.get("inner", where)),
             "outer bound": (track.outer, files.get("outer", where))}
    if "csv" in files:
        lines = {"centre line": (track.center, where), "left bound (x, y + w_left)": (track.inner, where),
                 "right bound (x, y - w_right)": (track.outer, where)}
    for what, (pts, path) in lines.items():
        hit = _segments_cross(pts, pts, same=True)
        if hit is not None:
            x, y = pts[hit[0]]
            raise DdynError(f"{path}: the {what} crosses itself (segment {hit[0]} near ({x:.3f}, {y:.3f}) "
                            f"and segment {hit[1]})")
    names = list(lines)
    for a in range(3):
        for b in range(a + 1, 3):
            hit = _segments_cross(lines[names[a]][0], lines[names[b]][0], same=False)
            if hit is not None:
                x, y = lines[names[a]][0][hit[0]]
                raise DdynError(f"{where}: the {names[a]} and the {names[b]} cross near ({x:.3f}, {y:.3f})")
    if np.median(track.half_width_left) <= 0 or np.median(track.half_width_right) <= 0:
        raise DdynError(f"{where}: the centre line does not lie between the bounds")
    if vehicle_name is not None and vehicle_name in FOOTPRINT:
        car = FOOTPRINT[vehicle_name][1]
        full = track.half_width_left + track.half_width_right
        i = int(np.argmin(full))
        if full[i] <= car:
            raise DdynError(f"{where}: the track is {full[i]:.3f} m wide at s = {track.s[i]:.2f} m "
                            f"({track.x[i]:.3f}, {track.y[i]:.3f}), narrower than the {vehicle_name} "
                            f"({car:.3f} m wide)")
