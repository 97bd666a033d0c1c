"""Importers: every dataset file the project reads becomes a canonical Dataset.

Four formats are accepted (docs/dataset_format.md gives the exact mappings):

- "canonical": the project's own CSV format, written by ddyn.data.dataset.write_canonical;
- "ddm_npz": the Deep Dynamics simulated sets (.npz with time, states, dstates, inputs);
- "racecar_csv": the RACECAR logs of the Indy Autonomous Challenge (a CSV whose
  header line starts with '#');
- "lcm_log": an LCM log of the controller's telemetry (train/data/lcm_import.py, docs/lcm.md).

`load_any` detects the format from the file's first bytes and is what every other
command uses. Bad input raises DataError naming the file and, where known, the
row (1-based line number of a text file, 1-based sample index of an .npz) and the
column; nothing else escapes for a bad file.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from ddyn.data import lcm_import, roll_check, vehicle_ref
from ddyn.data.dataset import COLUMNS, FORMAT_MAGIC, SAMPLE_TIME_RTOL, Dataset, write_canonical
from ddyn.errors import DataError, DdynError
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import INPUT_NAMES, STATE_NAMES

FORMATS = ("canonical", "ddm_npz", "racecar_csv", "lcm_log")
FORMAT_HELP = ("a canonical dataset (first line '# ddyn-dataset 1'), a Deep Dynamics .npz archive "
               "(arrays time, states, dstates, inputs), a RACECAR CSV (first line '# time(s),x(m),...') "
               "or an LCM log of the controller's telemetry")

DEFAULT_MIN_VX = 5.0                  # m/s; the papers drop slower rows of the real log
DEFAULT_BRAKE_FULL_SCALE_KPA = 2757.9  # brake pressure that maps to throttle -1 (400 psi)
DDM_STATE_KEYS = ("dstates", "states")

_CANONICAL_PREFIX = FORMAT_MAGIC.rsplit(" ", 1)[0]   # "# ddyn-dataset", followed by the version
_RESERVED_METADATA = ("sample_time", "vehicle", "source", "units")  # units is derived from COLUMNS
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")           # a zip with members / an empty zip


# ---------------------------------------------------------------------------------------------
# shared checks (text and binary formats)

def _read_bytes(path: Path, limit: int = -1) -> bytes:
    """The file's bytes (the first `limit` of them if limit >= 0); a missing file is a DataError."""
    try:
        with path.open("rb") as f:
            return f.read(limit)
    except FileNotFoundError:
        raise DataError(path, "no such file") from None
    except IsADirectoryError:
        raise DataError(path, "is a directory, not a dataset file") from None
    except OSError as e:
        raise DataError(path, f"cannot read: {e.strerror or e}") from None


def _read_lines(path: Path) -> list[str]:
    """The file's lines, numbered like an editor shows them (lines[i] is line i + 1)."""
    raw = _read_bytes(path)
    try:
        text = raw.decode("utf-8-sig")   # tolerate the byte-order mark spreadsheet programs add
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise DataError(path, f"not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start})", row=line) from None
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    while lines and not lines[-1].strip():   # trailing blank lines carry no rows
        lines.pop()
    if not lines:
        raise DataError(path, "empty file")
    return lines


def _parse_table(path: Path, lines: list[str], first_line: int, names: list[str]) -> np.ndarray:
    """Rows of comma-separated finite numbers, one per name; lines[0] is file line `first_line`.

    numpy converts the whole table at once (each cell as Python float() would); only
    when that fails do we walk the cells to name the first bad one.
    """
    rows = [line.split(",") for line in lines]
    for i, cells in enumerate(rows):
        if len(cells) != len(names):
            raise _ragged_row_error(path, lines[i], len(cells), len(names), first_line + i)
    try:
        table = np.array(rows, dtype=np.float64).reshape(len(rows), len(names))
    except ValueError:
        raise _bad_cell_error(path, rows, first_line, names) from None
    bad = np.argwhere(~np.isfinite(table))
    if len(bad):
        i, j = bad[0]
        raise DataError(path, f"found {rows[i][j].strip()!r} ({table[i, j]}); expected a finite number, "
                        "not NaN or infinity", row=first_line + int(i), column=names[j])
    return table


def _ragged_row_error(path: Path, line: str, found: int, expected: int, row: int) -> DataError:
    if not line.strip():
        return DataError(path, f"empty line among the rows; expected {expected} cells", row=row)
    return DataError(path, f"row has {found} cells, expected {expected} (one per header column)", row=row)


def _bad_cell_error(path: Path, rows: list[list[str]], first_line: int, names: list[str]) -> DataError:
    for i, cells in enumerate(rows):
        for j, cell in enumerate(cells):
            try:
                float(cell)
            except ValueError:
                found = repr(cell.strip()) if cell.strip() else "an empty cell"
                return DataError(path, f"found {found}; expected a number", row=first_line + i, column=names[j])
    return DataError(path, "rows could not be read as numbers")   # numpy and float() disagreed


def _step(values: np.ndarray) -> np.ndarray:
    """v[k+1] - v[k]; a difference too large for float64 is inf, which every caller then rejects."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.diff(values)


def _check_time_increasing(path: Path, time: np.ndarray, first_row: int) -> None:
    bad = np.flatnonzero(~(_step(time) > 0))
    if len(bad):
        i = bad[0]
        raise DataError(path, f"time {float(time[i + 1])!r} s does not increase after {float(time[i])!r} s "
                        "on the previous row; time must be strictly increasing", row=first_row + int(i) + 1,
                        column="time")


def _check_steps(path: Path, time: np.ndarray, segment: np.ndarray, ts: float, rows: np.ndarray,
                 what: str) -> None:
    """Every step between consecutive rows of one segment equals ts within SAMPLE_TIME_RTOL.

    rows[k] is the number DataError reports for sample k; `what` says where ts came from.
    """
    step = _step(time)
    off = (segment[1:] == segment[:-1]) & ~(np.abs(step - ts) <= SAMPLE_TIME_RTOL * ts)
    bad = np.flatnonzero(off)
    if len(bad):
        i = bad[0]
        raise DataError(path, f"time step from the previous row: found {float(step[i])!r} s, expected {ts!r} s "
                        f"({what}, relative tolerance {SAMPLE_TIME_RTOL:g})", row=int(rows[i + 1]), column="time")


def _sample_time_of(path: Path, estimate: float, what: str) -> float:
    if not (np.isfinite(estimate) and estimate > 0):
        raise DataError(path, f"cannot determine the sample time: {what} is {estimate!r} s")
    return float(estimate)


def _check_vehicle(path: Path, sample_time: float, vehicle: "str | Path | vehicle_mod.Vehicle") -> str:
    """The vehicle (a Vehicle, a name or a JSON path) exists and runs at the data's sample time; returns its name."""
    v = vehicle_ref.as_vehicle(vehicle)
    if not abs(sample_time - v.sample_time) <= SAMPLE_TIME_RTOL * v.sample_time:
        raise DataError(path, f"sample time {sample_time!r} s does not match vehicle {v.name!r} "
                        f"({v.sample_time!r} s); choose the vehicle this data belongs to")
    return v.name


def _require_finite_result(path: Path, ds: Dataset, rows: np.ndarray) -> Dataset:
    """Derived columns (rates, scaled pedals) of finite inputs can still overflow."""
    for name in STATE_NAMES + INPUT_NAMES:
        values = ds.column(name)
        bad = np.flatnonzero(~np.isfinite(values))
        if len(bad):
            raise DataError(path, f"derived value is {values[bad[0]]}; the source numbers are too large",
                            row=int(rows[bad[0]]), column=name)
    return ds


def _forward_rate(values: np.ndarray, ts: float) -> np.ndarray:
    """(v[k+1] - v[k]) / ts for every k but the last, whose value the caller decides."""
    rate = np.zeros_like(values)
    with np.errstate(over="ignore"):   # overflow is reported by _require_finite_result
        rate[:-1] = _step(values) / ts
    return rate


# ---------------------------------------------------------------------------------------------
# canonical

def read_canonical(path: str | Path) -> Dataset:
    """Read a file written by ddyn.data.dataset.write_canonical (format: docs/dataset_format.md)."""
    path = Path(path)
    lines = _read_lines(path)
    _check_magic(path, lines[0])
    meta, header_at = _read_metadata(path, lines)
    names = _read_header(path, lines, header_at)
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise DataError(path, f"missing required column(s) {', '.join(missing)}; "
                        f"required: {', '.join(COLUMNS)}", row=header_at + 1)
    first_line = header_at + 2
    table = _parse_table(path, lines[header_at + 1:], first_line, names)
    if not len(table):
        raise DataError(path, "no data rows after the header", row=header_at + 1)
    col = dict(zip(names, table.T))
    ts = _metadata_sample_time(path, meta)
    value = {k: v for k, (v, _) in meta.items()}
    segment = _segment_column(path, col["segment"], first_line)
    rows = np.arange(len(table)) + first_line
    _check_time_increasing(path, col["time"], first_line)
    _check_steps(path, col["time"], segment, ts, rows, "sample_time")
    return Dataset(
        time=col["time"], segment=segment,
        states=np.column_stack([col[c] for c in STATE_NAMES]),
        inputs=np.column_stack([col[c] for c in INPUT_NAMES]),
        sample_time=ts,
        vehicle=value.get("vehicle") or None,
        source=value.get("source", ""),
        extras={c: col[c] for c in names if c not in COLUMNS},
        metadata={k: v for k, v in value.items() if k not in _RESERVED_METADATA},
    )


def _check_magic(path: Path, first: str) -> None:
    if first.strip() == FORMAT_MAGIC:
        return
    if first.startswith(_CANONICAL_PREFIX):
        version = first[len(_CANONICAL_PREFIX):].strip()
        raise DataError(path, f"unknown canonical format version {version!r}; this reader understands "
                        f"version 1 ({FORMAT_MAGIC!r})", row=1)
    raise DataError(path, f"not a canonical dataset: the first line must be {FORMAT_MAGIC!r}, "
                    f"found {first[:60]!r}", row=1)


def _read_metadata(path: Path, lines: list[str]) -> tuple[dict[str, tuple[str, int]], int]:
    """`# key: value` lines after the magic: {key: (value, line number)}, and the header's index."""
    meta: dict[str, tuple[str, int]] = {}
    i = 1
    while i < len(lines) and lines[i].startswith("#"):
        key, sep, value = lines[i][1:].partition(":")
        key = key.strip()
        if not sep or not key:
            raise DataError(path, f"malformed metadata line {lines[i][:60]!r}; expected '# key: value'", row=i + 1)
        if key in meta:
            raise DataError(path, f"metadata key {key!r} repeated (first on line {meta[key][1]})", row=i + 1)
        meta[key] = (value.strip(), i + 1)
        i += 1
    if i == len(lines):
        raise DataError(path, "no header line after the metadata; expected the column names "
                        f"({','.join(COLUMNS)},...)", row=i)
    return meta, i


def _read_header(path: Path, lines: list[str], at: int) -> list[str]:
    names = [c.strip() for c in lines[at].split(",")]
    for j, name in enumerate(names):
        if not name:
            raise DataError(path, f"header column {j + 1} has no name", row=at + 1)
        if name in names[:j]:
            raise DataError(path, "column name repeated in the header", row=at + 1, column=name)
    return names


def _metadata_sample_time(path: Path, meta: dict[str, tuple[str, int]]) -> float:
    if "sample_time" not in meta:
        raise DataError(path, "metadata lacks sample_time; expected a line '# sample_time: <seconds>'")
    text, line = meta["sample_time"]
    try:
        ts = float(text)
    except ValueError:
        raise DataError(path, f"sample_time {text!r} is not a number; expected seconds, e.g. 0.02", row=line) from None
    if not (np.isfinite(ts) and ts > 0):
        raise DataError(path, f"sample_time {text!r} must be a positive finite number of seconds", row=line)
    return ts


def _segment_column(path: Path, seg: np.ndarray, first_line: int) -> np.ndarray:
    # beyond 2**53 a float no longer holds every integer, and int64 conversion would wrap
    not_int = np.flatnonzero((seg != np.floor(seg)) | (np.abs(seg) >= 2.0 ** 53))
    if len(not_int):
        i = not_int[0]
        raise DataError(path, f"found {float(seg[i])!r}; expected an integer segment number",
                        row=first_line + int(i), column="segment")
    down = np.flatnonzero(np.diff(seg) < 0)
    if len(down):
        i = down[0] + 1
        raise DataError(path, f"segment decreases from {int(seg[i - 1])} to {int(seg[i])}; "
                        "segment numbers must be non-decreasing", row=first_line + int(i), column="segment")
    return seg.astype(np.int64)


# ---------------------------------------------------------------------------------------------
# Deep Dynamics .npz

def read_ddm_npz(path: str | Path, vehicle: str = "orca_1_43", state_key: str | None = None) -> Dataset:
    """Read a Deep Dynamics simulated set, in either of its two layouts (shared/data/README.md):

    * absolute inputs (DYN-PP-ETHZ): time (N,), states (6,N) = pose and velocities from a high-order
      integrator, dstates (8,N) = their explicit-Euler chain with the commands, inputs (2,N-1) = the
      commands (throttle, steering) applied during each step. Row k: pose and velocities from
      `state_key` (default dstates, the chain the model reproduces: docs/data.md), throttle and
      steering inputs[:, k] (the last row holds the last command), their rates by forward differences.
    * input rates (DYN-PP-ETHZMobil): states (8,N) = pose, velocities, throttle and steering, inputs
      (2,N-1) = the rates (states[6:, k+1] = states[6:, k] + Ts inputs[:, k]), dstates (8,N). Row k:
      pose and velocities from `state_key` (default states: this file's dstates carries the rates'
      cumulative sum without Ts in rows 6-7 and departs from states by up to 41 rad/s),
      throttle and steering states[6:, k], their rates inputs[:, k] (0 on the last row).
    """
    if state_key is not None and state_key not in DDM_STATE_KEYS:
        raise DdynError(f"state_key must be one of {', '.join(DDM_STATE_KEYS)}, not {state_key!r}")
    path = Path(path)
    a = _load_npz(path, ("time", "states", "inputs", "dstates"))
    n, layout = _check_ddm_shapes(path, a)
    state_key = state_key or ("dstates" if layout == "absolute_inputs" else "states")
    time = a["time"]
    rows = np.arange(n) + 1
    _check_time_increasing(path, time, 1)
    # the median step points the error at the odd step rather than spreading it over all of them
    median = _sample_time_of(path, float(np.median(_step(time))), "the median time step")
    _check_steps(path, time, np.zeros(n), median, rows, "the median time step")
    # the grid is uniform: its span over the count is its step without the rounding noise
    # of single differences (the median of DYN-PP-ETHZ's is 0.019999999999999574)
    ts = _sample_time_of(path, (float(time[-1]) - float(time[0])) / (n - 1), "the time grid's step")
    pose = a[state_key][:6].T.copy()
    metadata = {"import_format": "ddm_npz", "state_key": state_key, "layout": layout}
    if state_key == "dstates" and not pose[0, :3].any():
        # the Deep Dynamics files store the Euler chain's first pose as zeros
        pose[0, :3] = a["states"][:3, 0]
        metadata["initial_pose"] = "row 0 x, y, yaw taken from states[:, 0] (stored as zeros in dstates)"
    if layout == "absolute_inputs":
        cmd = np.concatenate([a["inputs"], a["inputs"][:, -1:]], axis=1).T   # last command held on the last row
        rates = np.column_stack([_forward_rate(cmd[:, 0], ts), _forward_rate(cmd[:, 1], ts)])
    else:
        cmd = a["states"][6:8].T.copy()
        rates = np.concatenate([a["inputs"], np.zeros((2, 1))], axis=1).T     # no rate after the last row
        drift = float(np.max(np.abs(cmd[1:] - cmd[:-1] - ts * rates[:-1])))
        if drift > 1e-9 * max(1.0, float(np.max(np.abs(cmd)))):
            raise DataError(path, f"states rows 6-7 are not the running integral of the input rates "
                            f"(largest departure {drift:.3g}): not the input-rates layout", column="inputs")
        metadata["inputs"] = "rates: states[6:, k+1] = states[6:, k] + Ts inputs[:, k]"
    ds = Dataset(
        time=time, segment=np.zeros(n, dtype=np.int64),
        states=np.column_stack([pose, cmd]), inputs=rates,
        sample_time=ts, vehicle=_check_vehicle(path, ts, vehicle), source=path.name, metadata=metadata,
    )
    return _require_finite_result(path, ds, rows)


def _load_npz(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    # np.load would try a non-zip file as a pickle or a single .npy array: say plainly what is wrong
    if not _read_bytes(path, 4).startswith(_ZIP_MAGIC):
        raise DataError(path, "not an .npz archive (a zip file); expected a Deep Dynamics .npz with arrays "
                        "time, states, dstates, inputs")
    try:
        # our own handle: np.load leaves a file it opened unclosed when the archive is broken
        with path.open("rb") as f, np.load(f, allow_pickle=False) as npz:
            missing = [k for k in keys if k not in npz.files]
            if missing:
                raise DataError(path, f"missing array(s) {', '.join(missing)}; "
                                f"found {', '.join(npz.files) or 'none'}")
            arrays = {k: npz[k] for k in keys}
    except DataError:
        raise
    except Exception as e:  # noqa: BLE001 - zipfile, zlib and numpy's format reader raise many types
        raise DataError(path, f"not a readable .npz archive ({type(e).__name__}: {e})") from None
    for name, arr in arrays.items():
        if not isinstance(arr, np.ndarray):   # NpzFile hands back a member without the .npy header as bytes
            raise DataError(path, f"not a readable .npz archive: member {name} is not a .npy array", column=name)
        if arr.dtype.kind not in "iuf":
            raise DataError(path, f"array {name} has dtype {arr.dtype}; expected real numbers", column=name)
        arrays[name] = arr.astype(np.float64)
    return arrays


def _check_ddm_shapes(path: Path, a: dict[str, np.ndarray]) -> tuple[int, str]:
    """The arrays agree on the number of samples N >= 2 and are finite; returns N and the layout:
    "absolute_inputs" (states (6, N)) or "input_rates" (states (8, N))."""
    n = a["time"].shape[0] if a["time"].ndim == 1 else 0
    if n < 2:
        raise DataError(path, f"array time has shape {a['time'].shape}; expected (N,) with N >= 2", column="time")
    rows = a["states"].shape[0] if a["states"].ndim == 2 else 0
    layout = "input_rates" if rows == 8 else "absolute_inputs"
    expected = {"time": (n,), "states": (8 if rows == 8 else 6, n), "dstates": (8, n), "inputs": (2, n - 1)}
    for name, arr in a.items():
        if arr.shape != expected[name]:
            raise DataError(path, f"array {name} has shape {arr.shape}; expected {expected[name]} "
                            f"(N = {n} from time; states is (6, N) with absolute inputs or (8, N) with "
                            f"input rates)", column=name)
        bad = np.argwhere(~np.isfinite(arr))
        if len(bad):
            at = tuple(int(i) for i in bad[0])
            raise DataError(path, f"{name}[{', '.join(map(str, at))}] is {arr[at]}; expected a finite number",
                            row=at[-1] + 1, column=name)
    return n, layout


# ---------------------------------------------------------------------------------------------
# RACECAR CSV

# unit each known column's header must name (when it names one)
_RACECAR_UNITS = {
    "time": "s", "x": "m", "y": "m", "vx": "m/s", "vy": "m/s", "phi": "rad", "delta": "rad", "omega": "rad/s",
    "ax": "m/s^2", "deltadelta": "rad/s", "wheel_fl": "kmph", "wheel_fr": "kmph", "wheel_rl": "kmph",
    "wheel_rr": "kmph", "roll": "rad", "pitch": "rad", "throttle_ped_cmd": "%", "brake_ped_cmd": "kPa",
}
_RACECAR_REQUIRED = ("time", "x", "y", "vx", "vy", "phi", "delta", "omega", "throttle_ped_cmd", "brake_ped_cmd")
# columns kept as extras: source column -> (extra's name, factor to the extra's unit, that unit)
_RACECAR_EXTRAS = {
    "ax": ("ax", 1.0, "m/s^2"),
    "deltadelta": ("deltadelta", 1.0, "rad/s"),
    "wheel_fl": ("wheel_fl_mps", 1 / 3.6, "m/s"),
    "wheel_fr": ("wheel_fr_mps", 1 / 3.6, "m/s"),
    "wheel_rl": ("wheel_rl_mps", 1 / 3.6, "m/s"),
    "wheel_rr": ("wheel_rr_mps", 1 / 3.6, "m/s"),
    "throttle_ped_cmd": ("throttle_ped_cmd_pct", 1.0, "%"),
    "brake_ped_cmd": ("brake_ped_cmd_kpa", 1.0, "kPa"),
    # kept, but checked before anything reads the bank from it (ddyn.data.roll_check; the Putnam log's fails)
    "roll": ("roll", 1.0, "rad"),
    "pitch": ("pitch", 1.0, "rad"),     # the same for the grade (none in the Putnam log)
}
_HEADER_FIELD = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*(?:\((.*)\))?$")


def read_racecar_csv(path: str | Path, vehicle: str = "av21", min_vx: float = DEFAULT_MIN_VX,
                     brake_full_scale_kpa: float = DEFAULT_BRAKE_FULL_SCALE_KPA) -> Dataset:
    """Read a RACECAR log; rows with vx < min_vx are dropped and each remaining run is a segment.

    throttle = throttle_ped_cmd / 100, or -brake_ped_cmd / brake_full_scale_kpa on
    rows where brake_ped_cmd > 0 (braking wins over a simultaneous throttle command).
    """
    if not np.isfinite(min_vx):
        raise DdynError(f"min_vx must be a finite speed in m/s, not {min_vx!r}")
    if not (np.isfinite(brake_full_scale_kpa) and brake_full_scale_kpa > 0):
        raise DdynError(f"brake_full_scale_kpa must be a positive pressure in kPa, not {brake_full_scale_kpa!r}")
    path = Path(path)
    lines = _read_lines(path)
    names, ignored = _racecar_header(path, lines[0])
    table = _parse_table(path, lines[1:], 2, names)
    if len(table) < 2:
        raise DataError(path, f"{len(table)} data row(s); need at least 2 to determine the sample time")
    col = dict(zip(names, table.T))
    time = col["time"]
    _check_time_increasing(path, time, 2)
    what = "the median time step"
    ts = _sample_time_of(path, float(np.median(_step(time))), what)
    line_of = np.arange(len(table)) + 2
    _check_steps(path, time, np.zeros(len(table)), ts, line_of, what)
    vehicle_name = _check_vehicle(path, ts, vehicle)
    keep, segment = _speed_segments(path, col["vx"], min_vx)
    ds = _racecar_dataset(col, keep, segment, ts, brake_full_scale_kpa)
    ds.vehicle, ds.source = vehicle_name, path.name
    ds.metadata = _racecar_metadata(names, ignored, len(table), len(keep), segment, min_vx, brake_full_scale_kpa)
    for channel in ("roll", "pitch"):
        verdict = roll_check.check_dataset(ds, channel)
        if verdict is not None:
            ds.metadata[f"{channel}_check"] = json.dumps(verdict)
    return _require_finite_result(path, ds, line_of[keep])


def _racecar_header(path: Path, first: str) -> tuple[list[str], list[str]]:
    """Column names (units stripped) of the '#' header line, and the unknown columns ignored."""
    if not first.startswith("#"):
        raise DataError(path, f"not a RACECAR CSV: the first line must be the '#' header "
                        f"('# time(s),x(m),...'), found {first[:60]!r}", row=1)
    names, ignored = [], []
    for field_text in (f.strip() for f in first[1:].split(",")):
        m = _HEADER_FIELD.match(field_text)
        if not m:
            raise DataError(path, f"header field {field_text!r} is not 'name(unit)'", row=1)
        name, unit = m.group(1), m.group(2)
        if name in names:
            raise DataError(path, "column name repeated in the header", row=1, column=name)
        expected = _RACECAR_UNITS.get(name)
        if expected is not None and unit is not None and unit.strip() != expected:
            raise DataError(path, f"unit {unit!r}; expected {expected!r}", row=1, column=name)
        if expected is None:
            ignored.append(name)
        names.append(name)
    missing = [c for c in _RACECAR_REQUIRED if c not in names]
    if missing:
        raise DataError(path, f"missing required column(s) {', '.join(missing)}; "
                        f"required: {', '.join(_RACECAR_REQUIRED)}", row=1)
    return names, ignored


def _speed_segments(path: Path, vx: np.ndarray, min_vx: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the rows kept (vx >= min_vx, in runs of >= 2 rows) and each one's segment number."""
    idx = np.flatnonzero(vx >= min_vx)
    runs = [r for r in np.split(idx, np.flatnonzero(np.diff(idx) != 1) + 1) if len(r) >= 2]
    if not runs:
        raise DataError(path, f"no run of 2 or more consecutive rows with vx >= {min_vx!r} m/s "
                        f"(vx reaches {float(vx.max())!r} m/s); lower min_vx to keep slower rows", column="vx")
    keep = np.concatenate(runs)
    segment = np.repeat(np.arange(len(runs)), [len(r) for r in runs])
    return keep, segment


def _racecar_dataset(col: dict[str, np.ndarray], keep: np.ndarray, segment: np.ndarray, ts: float,
                     brake_full_scale_kpa: float) -> Dataset:
    c = {k: v[keep] for k, v in col.items()}
    brake = c["brake_ped_cmd"]
    # Braking wins: in the Putnam log both pedals are commanded on 178 rows (28 short episodes),
    # with a residual throttle under 10 % against brake pressures up to 1370 kPa, and the measured
    # ax is negative on 78 % of them (mean -0.77 m/s^2): the car is braking.
    with np.errstate(over="ignore"):   # overflow is reported by _require_finite_result
        throttle = np.where(brake > 0, -brake / brake_full_scale_kpa, c["throttle_ped_cmd"] / 100.0)
    steering = c["delta"]
    states = np.column_stack([c["x"], c["y"], c["phi"], c["vx"], c["vy"], c["omega"], throttle, steering])
    inputs = np.column_stack([_segment_rate(throttle, segment, ts), _segment_rate(steering, segment, ts)])
    extras = {new: c[src] * factor for src, (new, factor, _) in _RACECAR_EXTRAS.items() if src in c}
    return Dataset(time=c["time"], segment=segment, states=states, inputs=inputs, sample_time=ts, extras=extras)


def _segment_rate(values: np.ndarray, segment: np.ndarray, ts: float) -> np.ndarray:
    """Forward differences within each segment; a segment's last row repeats its previous rate."""
    rate = _forward_rate(values, ts)
    last = np.flatnonzero(np.append(segment[1:] != segment[:-1], True))
    rate[last] = rate[last - 1]   # segments have >= 2 rows, so last - 1 is in the same segment
    return rate


def _racecar_metadata(names: list[str], ignored: list[str], n_file: int, n_kept: int, segment: np.ndarray,
                      min_vx: float, brake_full_scale_kpa: float) -> dict[str, str]:
    meta = {
        "import_format": "racecar_csv",
        "min_vx": repr(float(min_vx)),
        "rows": f"{n_kept} of {n_file} kept (vx >= min_vx, runs of 2 or more rows) in {segment[-1] + 1} segment(s)",
        "throttle_mapping": f"throttle_ped_cmd/100, or -brake_ped_cmd/{brake_full_scale_kpa!r} kPa where "
                            "brake_ped_cmd > 0 (braking wins when both pedals are commanded)",
        "extra_units": " ".join(f"{new}={unit}" for src, (new, _, unit) in _RACECAR_EXTRAS.items()
                                if src in names),
    }
    if ignored:
        meta["ignored_columns"] = ", ".join(ignored)
    return meta


# ---------------------------------------------------------------------------------------------
# any format

def detect_format(path: str | Path) -> str:
    """"canonical", "ddm_npz", "racecar_csv" or "lcm_log", from the file's first bytes (not its extension)."""
    path = Path(path)
    head = _read_bytes(path, 4096)
    if head.startswith(_ZIP_MAGIC):
        return "ddm_npz"
    if lcm_import.is_lcm_log(head):
        return "lcm_log"
    first = head.split(b"\n", 1)[0].removeprefix(b"\xef\xbb\xbf").decode("utf-8", "replace").strip()
    if first.startswith(_CANONICAL_PREFIX):
        return "canonical"
    if first.startswith("#") and "," in first:
        return "racecar_csv"
    what = "empty file" if not head.strip() else "unrecognised format"
    raise DataError(path, f"{what}; expected {FORMAT_HELP}")


_READERS = {"canonical": read_canonical, "ddm_npz": read_ddm_npz, "racecar_csv": read_racecar_csv,
            "lcm_log": lcm_import.read_lcm_log}
_READER_OPTIONS = {"canonical": (), "ddm_npz": ("state_key",), "racecar_csv": ("min_vx", "brake_full_scale_kpa"),
                   "lcm_log": ("min_vx", "channel_prefix")}


def load_any(path: str | Path, vehicle: "str | Path | vehicle_mod.Vehicle | None" = None, fmt: str = "auto", **options) -> Dataset:
    """Read any accepted dataset file as a canonical Dataset.

    fmt: "auto" (detect from the first bytes) or one of FORMATS. options: state_key
    (ddm_npz), min_vx and brake_full_scale_kpa (racecar_csv), min_vx and channel_prefix
    (lcm_log); options of the other formats and None values are ignored, so one call
    serves any file. vehicle: for the imported formats, the vehicle the data belongs
    to (a Vehicle, a name in train/vehicles or a JSON path; default: the reader's); for a canonical file it must agree with the vehicle
    the file names, if any.
    """
    unknown = sorted(set(options) - {o for opts in _READER_OPTIONS.values() for o in opts})
    if unknown:
        raise DdynError(f"unknown dataset option(s) {', '.join(unknown)}")
    if fmt == "auto":
        fmt = detect_format(path)
    elif fmt not in _READERS:
        raise DdynError(f"unknown dataset format {fmt!r}; expected auto, {', '.join(FORMATS)}")
    if fmt == "canonical":
        return _with_vehicle(Path(path), read_canonical(path), vehicle)
    kwargs = {k: v for k, v in options.items() if k in _READER_OPTIONS[fmt] and v is not None}
    if vehicle is not None:
        kwargs["vehicle"] = vehicle
    return _READERS[fmt](path, **kwargs)


def load_with_vehicle(path: str | Path, vehicle: "str | Path | None" = None) -> "tuple[Dataset, vehicle_mod.Vehicle]":
    """A dataset and the vehicle it belongs to: the given one (a name or a JSON path), else the one the
    log records (ddyn.data.vehicle_ref); an error names the file."""
    given = vehicle_mod.load(vehicle) if vehicle else None
    ds = load_any(path, vehicle=given)
    try:
        return ds, vehicle_ref.of_dataset(ds, given)
    except DdynError as e:
        raise DdynError(f"{path}: {e}") from None


def _with_vehicle(path: Path, ds: Dataset, vehicle: "str | Path | vehicle_mod.Vehicle | None") -> Dataset:
    if vehicle is None:
        return ds
    # compare with the file's name field, not with the argument: `--vehicle /x/car.json` names "car"
    v = vehicle_ref.as_vehicle(vehicle)
    if ds.vehicle and ds.vehicle != v.name:
        raise DataError(path, f"the dataset is for vehicle {ds.vehicle!r}, not {v.name!r}")
    ds.vehicle = _check_vehicle(path, ds.sample_time, v)
    return ds


# ---------------------------------------------------------------------------------------------
# `ddyn import`

def register(subparsers) -> None:
    p = subparsers.add_parser("import", help="convert a dataset (Deep Dynamics .npz, RACECAR .csv, LCM log, "
                              "canonical) to the canonical format")
    p.add_argument("src", help="dataset file to read")
    p.add_argument("-o", "--out", required=True, help="canonical dataset to write")
    p.add_argument("--vehicle", help="vehicle the data belongs to (default: orca_1_43 for .npz, av21 for "
                   "RACECAR CSV, the one whose sample time an LCM log shows, the file's own for canonical)")
    p.add_argument("--format", choices=("auto",) + FORMATS, default="auto",
                   help="input format (default: detect from the file's first bytes)")
    p.add_argument("--min-vx", type=float,
                   help=f"RACECAR, LCM log: drop rows slower than this, m/s (default {DEFAULT_MIN_VX:g} for "
                   "RACECAR, none for an LCM log)")
    p.add_argument("--brake-full-scale-kpa", type=float,
                   help=f"RACECAR: brake pressure mapped to throttle -1 (default {DEFAULT_BRAKE_FULL_SCALE_KPA:g})")
    p.add_argument("--channel-prefix",
                   help="LCM log: prefix of the telemetry channels (default DDYN_: DDYN_STATE, DDYN_COEFFS, ...)")
    p.add_argument("--state-key", choices=DDM_STATE_KEYS,
                   help="Deep Dynamics .npz: Euler chain (dstates, default) or high-order integrator (states)")
    p.set_defaults(func=_run_import)


def _run_import(args) -> int:
    ds = load_any(args.src, vehicle=args.vehicle, fmt=args.format, min_vx=args.min_vx,
                  brake_full_scale_kpa=args.brake_full_scale_kpa, state_key=args.state_key,
                  channel_prefix=args.channel_prefix)
    try:
        write_canonical(ds, args.out)
    except OSError as e:
        raise DdynError(f"cannot write {args.out}: {e.strerror or e}") from None
    n_segments = len(np.unique(ds.segment))
    duration = len(ds.transition_index()) * ds.sample_time
    print(f"{args.src} -> {args.out}: {len(ds)} rows, {n_segments} segment(s), {duration:.2f} s of data, "
          f"sample time {ds.sample_time:g} s, vehicle {ds.vehicle or '(none)'}")
    return 0
