"""candump-format CAN logs of the drive-by-wire protocol: write, import, replay, record.

  ddyn can export DATASET -o LOG.log   the frames the car's DBW unit and sensors would send
                                       for a canonical dataset (e.g. from `ddyn simulate`):
                                       steering, pedals, wheel speeds, IMU, GNSS, with rolling
                                       counters and checksums (train/model/sensors.py measurement models)
  ddyn can import LOG.log -o DIR       decode a candump log with the DBC into one CSV table per
                                       message (time, counter, physical signals) and issues.json:
                                       frames rejected by the C's checks and counter jumps/repeats,
                                       counted by the C's failure names
  ddyn can replay LOG.log --channel vcan0      send a log onto a bus at its recorded pace (python-can)
  ddyn can record --channel vcan0 -o LOG.log   record a bus into a candump log (python-can)

Logs are read and written with python-can's candump ("canutils") reader and writer, the format
of can-utils' `candump -l` and `canplayer`.
"""
from __future__ import annotations

import csv
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import can
from ddyn.data import can_protocol as proto
from ddyn.errors import DataError, DdynError

# in DBC order of the frames each dataset row produces
EXPORTED_MESSAGES = ("DBW_Steering", "DBW_Status", "DBW_WheelSpeeds", "IMU", "GNSS_Position", "GNSS_Heading")
FRAME_SPACING_S = 1e-4  # the frames of one row go out 0.1 ms apart, in this order


@dataclass
class CanTable:
    """Decoded frames per message: columns of equal length (time, counter, then the signals)."""

    columns: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    issues: dict[str, int] = field(default_factory=dict)
    frames: int = 0
    foreign: int = 0

    def message(self, name: str) -> dict[str, np.ndarray]:
        if name not in self.columns:
            raise DdynError(f"no {name} frames in the log (messages present: {', '.join(sorted(self.columns)) or 'none'})")
        return self.columns[name]


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def dataset_frames(ds, vehicle_name: str | None = None) -> list[can.Message]:
    """The protocol frames of every row of a canonical dataset, timestamped with its time."""
    from ddyn.data import vehicle_ref
    from ddyn.model import mathns, sensors

    # a name or JSON path, else the vehicle file the dataset records (its coefficients give the accelerations)
    v = vehicle_ref.of_dataset(ds, vehicle_name)
    coeffs = v.coefficient_vector("true")
    st = np.asarray(ds.states, dtype=float).T  # (8, N): the measurement models take arrays
    ns = mathns.NUMPY
    wheel_front, wheel_rear = sensors.measure(ns, "wheel_speed", st, coeffs, v.known)
    ax, ay = sensors.measure(ns, "acceleration", st, coeffs, v.known)
    throttle, steering = st[6], st[7]
    dsteer = np.asarray(ds.inputs, dtype=float)[:, 1]
    per_row = {
        "DBW_Steering": lambda k: {"SteeringAngle": steering[k], "SteeringRate": dsteer[k]},
        "DBW_Status": lambda k: {"ThrottlePedal": min(max(throttle[k], 0.0), 1.0),
                                 "BrakePedal": min(max(-throttle[k], 0.0), 1.0),
                                 "Mode": 1, "Enabled": 1, "DriverOverride": 0, "Faults": 0},
        "DBW_WheelSpeeds": lambda k: {"WheelSpeedFront": wheel_front[k], "WheelSpeedRear": wheel_rear[k]},
        "IMU": lambda k: {"YawRate": st[5, k], "AccelX": ax[k], "AccelY": ay[k]},
        "GNSS_Position": lambda k: {"PositionX": st[0, k], "PositionY": st[1, k]},
        "GNSS_Heading": lambda k: {"Heading": float(_wrap(np.array(st[2, k]))), "FixType": 4},
    }
    db = proto.database()
    out = []
    for k in range(len(ds)):
        for j, name_ in enumerate(EXPORTED_MESSAGES):
            # quantise onto the DBC's steps first: cantools' strict range check is on the physical value
            values = {s: float(x) for s, x in per_row[name_](k).items()}
            try:
                fid, data = proto.encode(name_, values, counter=k, db=db)
            except DdynError as e:
                raise DataError(ds.source or "dataset", f"{e} (outside the DBC's range)", row=k + 1) from None
            out.append(can.Message(timestamp=float(ds.time[k]) + j * FRAME_SPACING_S, arbitration_id=fid,
                                   is_extended_id=False, data=data, channel="vcan0"))
    return out


def write_candump(messages, path: str | Path, channel: str = "vcan0") -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with can.CanutilsLogWriter(str(path), channel=channel) as w:
        for m in messages:
            w.on_message_received(m)
    return path


def read_candump(path: str | Path) -> list[can.Message]:
    path = Path(path)
    if not path.is_file():
        raise DdynError(f"{path}: no such candump log")
    try:
        return list(can.CanutilsLogReader(str(path)))
    except (ValueError, IndexError) as e:
        raise DataError(path, f"not a candump log: {e}") from None


def decode_messages(messages) -> CanTable:
    """Decode with the DBC and the C's checks; count every defect by the C's failure names."""
    db = proto.database()
    rows: dict[str, list[tuple]] = {}
    sig_names: dict[str, list[str]] = {}
    last_counter: dict[int, int] = {}
    table = CanTable(issues={k: 0 for k in ("unknown_frame", "bad_length", "checksum", "range",
                                            "counter_jump", "counter_repeat", "error_frame")})
    for m in messages:
        table.frames += 1
        if m.is_error_frame:
            table.issues["error_frame"] += 1
            continue
        if m.is_extended_id or m.is_remote_frame:
            table.foreign += 1
            continue
        try:
            d = proto.decode(m.arbitration_id, bytes(m.data), db=db)
        except proto.FrameError as e:
            table.issues[e.kind] += 1
            last_counter.pop(m.arbitration_id, None)  # a rejected frame's counter is not trusted
            continue
        if d is None:
            table.foreign += 1
            continue
        prev = last_counter.get(d.frame_id)
        if prev is not None and d.counter != (prev + 1) % proto.COUNTER_MODULO:
            table.issues["counter_repeat" if d.counter == prev else "counter_jump"] += 1
        last_counter[d.frame_id] = d.counter
        names = sig_names.setdefault(d.name, list(d.signals))
        rows.setdefault(d.name, []).append((float(m.timestamp), d.counter, *(d.signals[n] for n in names)))
    for name, rs in rows.items():
        arr = np.array(rs, dtype=float)
        cols = {"time": arr[:, 0], "counter": arr[:, 1].astype(np.int64)}
        cols.update({n: arr[:, 2 + i] for i, n in enumerate(sig_names[name])})
        table.columns[name] = cols
    return table


def write_table(table: CanTable, out: str | Path) -> list[Path]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in sorted(table.columns):
        cols = table.columns[name]
        f = out / f"{name}.csv"
        with open(f, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(list(cols))
            for row in zip(*cols.values()):
                w.writerow([repr(float(x)) if isinstance(x, (float, np.floating)) else int(x) for x in row])
        written.append(f)
    f = out / "issues.json"
    f.write_text(json.dumps({"frames": table.frames, "foreign": table.foreign, "issues": table.issues,
                             "messages": {n: len(c["time"]) for n, c in sorted(table.columns.items())}},
                            indent=1) + "\n")
    written.append(f)
    return written


def replay(path: str | Path, bus: can.BusABC, realtime: bool = True) -> int:
    """Send a log's frames onto `bus`, at the recorded pace when `realtime`. Returns the count."""
    msgs = read_candump(path)
    source = can.MessageSync(msgs, timestamps=True, skip=3600.0) if realtime else msgs
    n = 0
    for m in source:
        bus.send(can.Message(arbitration_id=m.arbitration_id, is_extended_id=m.is_extended_id, data=m.data,
                             is_fd=m.is_fd, is_remote_frame=m.is_remote_frame))
        n += 1
    return n


def record(bus: can.BusABC, path: str | Path, duration: float, channel: str = "vcan0", max_frames: int = 10**7) -> int:
    """Record frames from `bus` into a candump log for `duration` seconds. Returns the count."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    end = time.monotonic() + duration
    with can.CanutilsLogWriter(str(path), channel=channel) as w:
        while n < max_frames:
            left = end - time.monotonic()
            if left <= 0:
                break
            m = bus.recv(timeout=min(left, 0.1))
            if m is not None:
                w.on_message_received(m)
                n += 1
    return n


# ---- CLI ----

def _export(args) -> int:
    from ddyn.data.importers import load_any

    ds = load_any(args.dataset, vehicle=args.vehicle)
    msgs = dataset_frames(ds, args.vehicle)
    write_candump(msgs, args.out, channel=args.channel)
    print(f"wrote {len(msgs)} frames ({len(ds)} rows x {len(EXPORTED_MESSAGES)} messages) to {args.out}")
    return 0


def _import(args) -> int:
    table = decode_messages(read_candump(args.log))
    for f in write_table(table, args.out):
        print(f"wrote {f}")
    bad = {k: v for k, v in table.issues.items() if v}
    print(f"{table.frames} frames, {table.foreign} not of the protocol; issues: {bad or 'none'}")
    return 0


def _bus(args) -> can.BusABC:
    try:
        return can.Bus(interface=args.interface, channel=args.channel)
    except (can.CanError, OSError, ValueError, ImportError) as e:
        raise DdynError(f"cannot open CAN bus {args.interface}:{args.channel}: {e}") from e


def _replay(args) -> int:
    with _bus(args) as bus:
        n = replay(args.log, bus, realtime=not args.fast)
    print(f"sent {n} frames to {args.interface}:{args.channel}")
    return 0


def _record(args) -> int:
    with _bus(args) as bus:
        n = record(bus, args.out, args.duration, channel=args.channel)
    print(f"recorded {n} frames from {args.interface}:{args.channel} into {args.out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("export", help="write the DBW/sensor CAN frames of a dataset as a candump log")
    p.add_argument("dataset", help="canonical dataset (or any format `ddyn import` reads)")
    p.add_argument("-o", "--out", required=True, help="candump log to write (.log)")
    p.add_argument("--vehicle", help="vehicle name (default: the dataset's)")
    p.add_argument("--channel", default="vcan0", help="interface name written into the log (default: %(default)s)")
    p.set_defaults(func=_export)
    p = subparsers.add_parser("import", help="decode a candump log with the DBC into per-message CSV tables")
    p.add_argument("log", help="candump log (candump -l / python-can format)")
    p.add_argument("-o", "--out", required=True, help="output directory")
    p.set_defaults(func=_import)
    for name, fn, helptext in (("replay", _replay, "send a candump log onto a CAN bus (python-can)"),
                               ("record", _record, "record a CAN bus into a candump log (python-can)")):
        p = subparsers.add_parser(name, help=helptext)
        if name == "replay":
            p.add_argument("log", help="candump log")
            p.add_argument("--fast", action="store_true", help="send as fast as possible instead of at the recorded pace")
        else:
            p.add_argument("-o", "--out", required=True, help="candump log to write")
            p.add_argument("--duration", type=float, default=10.0, help="seconds to record (default: %(default)s)")
        p.add_argument("--interface", default="socketcan", help="python-can interface (default: %(default)s)")
        p.add_argument("--channel", default="vcan0", help="channel / interface name (default: %(default)s)")
        p.set_defaults(func=fn)
