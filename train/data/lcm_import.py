"""LCM logs of the controller's telemetry -> a canonical Dataset (`ddyn import run.lcm`).

An LCM log (the event-log format lcm-logger writes, also written by LCM's file://
provider and lcm.EventLog) holds the messages of lcmtypes/*.lcm on channels
<prefix>STATE, <prefix>COEFFS, ... (docs/lcm.md). One canonical row per state
estimate message:

    x .. steering          = the message's fields
    time                   = (step - first step) * Ts / d      (d: the usual step difference)
    dthrottle, dsteering   = forward differences of throttle, steering within a segment,
                             the last row of a segment repeating the previous rate
    segment                = runs of messages whose step differs by exactly d; a lost
                             message (or a min_vx drop) starts a new segment

Ts is the vehicle's sample time; the controller clock (utime) only has to agree with
it within CLOCK_RTOL, and is kept as the extra `clock_s` so its jitter stays visible.
Extras: var_<state> (the covariance diagonal) always; the coefficients c_<name> and
their saturation flags, the plan's status, QP iterations and cost, the loop's period,
duration and deadline miss, and the active fault bits, each when its channel carries a
message for every row kept (a canonical column needs a value on every row; a
decimated channel is listed in the metadata instead).

Every event is checked: its framing (sync word, lengths, nothing truncated, nothing
between events), and each message on a known channel must decode as its type and
re-encode to its own length. A bad log is
a DataError naming the file and the event (1-based, in file order) with its byte offset.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ddyn.data import lcm_types
from ddyn.data.dataset import Dataset
from ddyn.errors import DataError, DdynError
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import COEFF_NAMES, INPUT_NAMES, STATE_NAMES

LOG_MAGIC = b"\xed\xa1\xda\x01"     # the sync word that starts every event of an LCM log
EVENT_HEADER_BYTES = 4 + 8 + 8 + 4 + 4   # sync, event number, timestamp, channel length, data length
CLOCK_RTOL = 0.05                    # controller clock vs the vehicle's sample time
_HEADER = struct.Struct(">4sqqii")


def is_lcm_log(head: bytes) -> bool:
    return head.startswith(LOG_MAGIC)


def read_events(path: Path) -> list[tuple[int, int, str, bytes]]:
    """(1-based event index, byte offset, channel, data) of every event of an LCM log.

    The framing is read here rather than with lcm.EventLog: LCM's reader returns None
    both at the end of the file and at corruption, skips ahead to the next sync word
    on its own, and writes its complaints to stderr, so it cannot say which event is
    bad. Each event is: sync word, event number (int64), timestamp (int64), channel
    length (int32, 1..999), data length (int32), channel, data; big-endian.
    """
    events = []
    try:
        f = path.open("rb")
    except OSError as e:
        raise DataError(path, f"cannot read: {e.strerror or e}") from None
    with f:
        size = f.seek(0, 2)
        f.seek(0)
        pos, index = 0, 0
        while pos < size:
            index += 1
            where = f"event {index} (byte offset {pos})"
            header = f.read(EVENT_HEADER_BYTES)
            if len(header) < EVENT_HEADER_BYTES:
                raise DataError(path, f"{where}: truncated: {len(header)} byte(s) where an event header needs "
                                f"{EVENT_HEADER_BYTES}")
            sync, _eventnum, _timestamp, channel_len, data_len = _HEADER.unpack(header)
            if sync != LOG_MAGIC:
                raise DataError(path, f"{where}: corrupt: found 0x{sync.hex()} where the event sync word "
                                f"0x{LOG_MAGIC.hex()} must be")
            if not 0 < channel_len < 1000 or data_len < 0:
                raise DataError(path, f"{where}: corrupt: channel length {channel_len} (1..999) "
                                f"or data length {data_len} (>= 0) out of range")
            body = f.read(channel_len + data_len) if pos + EVENT_HEADER_BYTES + channel_len + data_len <= size else b""
            if len(body) != channel_len + data_len:
                raise DataError(path, f"{where}: truncated: the event needs {EVENT_HEADER_BYTES + channel_len + data_len}"
                                f" bytes, {size - pos} left in the file")
            try:
                channel = body[:channel_len].decode("utf-8")
            except UnicodeDecodeError:
                raise DataError(path, f"{where}: corrupt: the channel name is not UTF-8 text") from None
            events.append((index, pos, channel, body[channel_len:]))
            pos += EVENT_HEADER_BYTES + channel_len + data_len
    return events


def _decode(path: Path, index: int, offset: int, channel: str, data: bytes, cls: type):
    where = f"event {index} (byte offset {offset}), channel {channel}"
    try:
        msg = cls.decode(data)
    except Exception as e:  # noqa: BLE001 - generated decoders raise ValueError or struct.error
        raise DataError(path, f"{where}: does not decode as {cls.__name__} ({type(e).__name__}: {e})") from None
    if len(msg.encode()) != len(data):
        raise DataError(path, f"{where}: {len(data)} bytes, but the {cls.__name__} in them is "
                        f"{len(msg.encode())} bytes; the message is corrupt")
    return msg


def read_lcm_log(path: str | Path, vehicle: str | None = None, min_vx: float | None = None,
                 channel_prefix: str = lcm_types.DEFAULT_PREFIX) -> Dataset:
    """Read a telemetry LCM log as a canonical Dataset (see the module docstring)."""
    if min_vx is not None and not np.isfinite(min_vx):
        raise DdynError(f"min_vx must be a finite speed in m/s, not {min_vx!r}")
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "no such file" if not path.exists() else "is not a file")
    with path.open("rb") as f:
        if not is_lcm_log(f.read(4)):
            raise DataError(path, "not an LCM log: it does not start with the event sync word 0xEDA1DA01")
    types = lcm_types.channel_types(channel_prefix)
    by_channel: dict[str, list] = {c: [] for c in types}
    state_events: list[int] = []
    other: dict[str, int] = {}
    for index, offset, channel, data in read_events(path):
        if channel in types:
            by_channel[channel].append(_decode(path, index, offset, channel, data, types[channel]))
            if channel == channel_prefix + "STATE":
                state_events.append(index)
        else:
            other[channel] = other.get(channel, 0) + 1
    states = by_channel[channel_prefix + "STATE"]
    if len(states) < 2:
        found = ", ".join(f"{c} ({n})" for c, n in {**{c: len(v) for c, v in by_channel.items() if v}, **other}.items())
        raise DataError(path, f"{len(states)} state estimate(s) on channel {channel_prefix}STATE; need at least 2 "
                        f"(channels found: {found or 'none'})")
    return _dataset(path, states, state_events, by_channel, channel_prefix, other, vehicle, min_vx)


def _dataset(path, states, state_events, by_channel, prefix, other, vehicle, min_vx) -> Dataset:
    step = np.array([m.step for m in states], dtype=np.int64)
    # the clock in float: differences of int64 extremes (a corrupt log) would wrap without a word
    utime = np.array([m.utime for m in states], dtype=float)
    bad = np.flatnonzero(step[1:] <= step[:-1])
    if len(bad):
        i = bad[0] + 1
        raise DataError(path, f"event {state_events[i]}: state estimate of step {step[i]} after step {step[i - 1]}; "
                        "steps must increase (a controller restart? split the log there)")
    if np.any(np.abs(step) >= 2 ** 53):   # beyond that a double (time) no longer holds every step
        i = int(np.flatnonzero(np.abs(step) >= 2 ** 53)[0])
        raise DataError(path, f"event {state_events[i]}: step number {step[i]} is beyond 2**53")
    step_f = step.astype(float)
    d = int(np.median(np.diff(step_f)))
    clock_period = float(np.median(np.diff(utime) / np.diff(step_f))) * 1e-6
    v = _vehicle(path, d * clock_period, vehicle)
    x = np.array([[getattr(m, n) for n in STATE_NAMES] for m in states], dtype=float)
    nonfinite = np.argwhere(~np.isfinite(x))
    if len(nonfinite):
        i, j = nonfinite[0]
        raise DataError(path, f"event {state_events[i]}: state estimate {STATE_NAMES[j]} is {x[i, j]}; "
                        "expected a finite number", column=STATE_NAMES[j])
    keep, segment = _segments(path, step_f, d, x[:, STATE_NAMES.index("vx")], min_vx)
    ts = v.sample_time
    time = (step_f - step_f[0]) * (ts / d)
    extras = {"clock_s": (utime - utime[0]) * 1e-6}
    extras |= {f"var_{n}": np.array([m.cov_diag[i] for m in states]) for i, n in enumerate(STATE_NAMES)}
    notes = []
    extras |= _per_step_extras(by_channel, prefix, step, notes)
    k = keep
    xs = x[k]
    inputs = np.column_stack([_segment_rate(xs[:, STATE_NAMES.index(n)], segment, ts)
                              for n in ("throttle", "steering")])
    ds = Dataset(time=time[k], segment=segment, states=xs, inputs=inputs, sample_time=ts, vehicle=v.name,
                 source=path.name, extras={n: a[k] for n, a in extras.items()})
    nonfinite_extra = [n for n, a in ds.extras.items() if not np.all(np.isfinite(a))]
    for n in nonfinite_extra:   # e.g. NaN bounds when the controller has none: not a column
        del ds.extras[n]
        notes.append(f"{n} dropped (not finite on every row)")
    ds.metadata = {
        "import_format": "lcm_log",
        "channel_prefix": prefix,
        "rows": f"{len(k)} of {len(step)} state estimates kept in {segment[-1] + 1} segment(s)"
                + (f" (vx >= {min_vx!r} m/s)" if min_vx is not None else ""),
        "steps_per_row": str(d),
        "clock_period_s": repr(clock_period),
        "utime_start": str(states[0].utime),
        "input_mapping": "dthrottle, dsteering = forward differences of throttle, steering within a segment",
        "messages": " ".join(f"{c}={len(msgs)}" for c, msgs in by_channel.items()),
    }
    if notes:
        ds.metadata["extras_notes"] = "; ".join(notes)
    if other:
        ds.metadata["ignored_channels"] = " ".join(f"{c}={n}" for c, n in sorted(other.items()))
    for name in INPUT_NAMES:
        if not np.all(np.isfinite(ds.column(name))):
            raise DataError(path, f"derived {name} is not finite; the throttle or steering estimates are too large",
                            column=name)
    return ds


def _vehicle(path: Path, sample_time: float, name: str | None):
    """The vehicle the log belongs to: the named one, or the one whose sample time the clock shows."""
    if not (np.isfinite(sample_time) and sample_time > 0):
        raise DataError(path, f"the controller clock gives a sample time of {sample_time!r} s; "
                        "utime must increase with step")
    if name is None:
        # a variant (another model setting of the same car) is chosen by name only, never by the clock
        matches = [v for v in (vehicle_mod.load(n) for n in vehicle_mod.available()) if not v.variant_of]
        matches = [v for v in matches if abs(v.sample_time - sample_time) <= CLOCK_RTOL * v.sample_time]
        if len(matches) != 1:
            raise DataError(path, f"the log's sample time is {sample_time:.6g} s, which "
                            + ("no vehicle has" if not matches else
                               f"fits {', '.join(v.name for v in matches)}") + "; choose the vehicle with --vehicle")
        return matches[0]
    v = name if isinstance(name, vehicle_mod.Vehicle) else vehicle_mod.load(name)   # a Vehicle, name or path
    if abs(v.sample_time - sample_time) > CLOCK_RTOL * v.sample_time:
        raise DataError(path, f"the log's sample time is {sample_time:.6g} s (state estimates every "
                        f"{sample_time:.6g} s of the controller clock), not vehicle {v.name!r}'s {v.sample_time!r} s; "
                        "publish the state at the control rate, or choose the vehicle this log belongs to")
    return v


def _segments(path: Path, step: np.ndarray, d: int, vx: np.ndarray, min_vx: float | None):
    """Rows kept and their segment numbers: runs of >= 2 rows d steps apart (and vx >= min_vx)."""
    ok = np.ones(len(step), dtype=bool) if min_vx is None else vx >= min_vx
    idx = np.flatnonzero(ok)
    breaks = np.flatnonzero((np.diff(idx) != 1) | (np.diff(step[idx]) != d)) + 1
    runs = [r for r in np.split(idx, breaks) if len(r) >= 2]
    if not runs:
        raise DataError(path, "no run of 2 or more consecutive state estimates"
                        + (f" with vx >= {min_vx!r} m/s" if min_vx is not None else ""), column="vx")
    keep = np.concatenate(runs)
    return keep, np.repeat(np.arange(len(runs)), [len(r) for r in runs])


def _segment_rate(values: np.ndarray, segment: np.ndarray, ts: float) -> np.ndarray:
    rate = np.zeros_like(values)
    with np.errstate(over="ignore", invalid="ignore"):
        rate[:-1] = np.diff(values) / ts
    last = np.flatnonzero(np.append(segment[1:] != segment[:-1], True))
    rate[last] = rate[last - 1]   # segments have >= 2 rows
    return rate


def _per_step_extras(by_channel, prefix, step, notes) -> dict[str, np.ndarray]:
    """Columns from the other channels, for those with a message at every state step."""
    out: dict[str, np.ndarray] = {}
    columns = {
        "COEFFS": lambda m: {**{f"c_{n}": m.coeffs[i] for i, n in enumerate(COEFF_NAMES)},
                             "sat_lo_mask": m.saturated_lo & 0xFFFFFFFF, "sat_hi_mask": m.saturated_hi & 0xFFFFFFFF},
        "PLAN": lambda m: {"mpc_status": m.status, "mpc_qp_iterations": m.qp_iterations, "mpc_cost": m.cost},
        "TIMING": lambda m: {"loop_period_s": m.period_s, "loop_total_s": m.total_s,
                             "deadline_missed": float(bool(m.deadline_missed))},
        "FAULTS": lambda m: {"faults_active": m.active & 0xFFFFFFFF},
    }
    for suffix, fields in columns.items():
        msgs = {m.step: m for m in by_channel[prefix + suffix]}
        if not msgs:
            continue
        missing = int(np.sum([s not in msgs for s in step]))
        if missing:
            notes.append(f"{prefix}{suffix}: {len(msgs)} message(s), none at {missing} of {len(step)} state steps "
                         "(published at a lower rate?): not kept as columns")
            continue
        rows = [fields(msgs[s]) for s in step]
        out |= {n: np.array([r[n] for r in rows], dtype=float) for n in rows[0]}
    return out
