"""`ddyn lcm replay`: publish a dataset as controller telemetry through the C telemetry module.

The C host tool ddyn_telemetry_replay (c_src/tools/telemetry_replay.c) links the
telemetry module the controller uses; this command feeds it one control step per
dataset row, so the path C publisher -> LCM -> log -> `ddyn import` runs end to end
without a controller:

    STATE   the row's state; covariance diagonal from the var_<state> extras (zeros without)
    COEFFS  the c_<name> extras, else the vehicle's true coefficients; guard bounds = the
            vehicle's ranges
    PLAN    the dataset's own next `horizon` rows (within the segment) as the plan,
            status 0 "replay", no QP iterations, cost 0: a replay has no optimiser
    FAULTS  none active
    TIMING  the replay loop's own: the wall time each kind took to parse and publish (tool option -m)

step = round((time - time[0]) / Ts), so gaps between segments stay gaps; utime is the
row's time in microseconds. Rates per message kind are the tool's (-r KIND=HZ).
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np

from ddyn.data.dataset import Dataset
from ddyn.data.importers import load_any
from ddyn.errors import DdynError
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import COEFF_NAMES, STATE_NAMES
from ddyn.paths import BUILD

DEFAULT_TOOL = BUILD / "c_src" / "ddyn_telemetry_replay"
DEFAULT_HORIZON = 10
KINDS = ("state", "coeffs", "plan", "timing", "faults")


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def stream(ds: Dataset, horizon: int = DEFAULT_HORIZON, sat_margin: float = 0.02) -> list[str]:
    """The tool's input lines for a dataset (one control step per row)."""
    if ds.vehicle is None:
        raise DdynError("the dataset names no vehicle; replay needs its coefficients and bounds")
    v = vehicle_mod.load(ds.vehicle)
    ts = ds.sample_time
    lo = [v.ranges[n][0] for n in COEFF_NAMES]
    hi = [v.ranges[n][1] for n in COEFF_NAMES]
    lines = [f"B {_fmt(lo)} {_fmt(hi)} {sat_margin!r}"]
    steps = np.rint((ds.time - ds.time[0]) / ts).astype(np.int64)
    utimes = np.rint(ds.time * 1e6).astype(np.int64)
    var = np.column_stack([ds.extras.get(f"var_{n}", np.zeros(len(ds))) for n in STATE_NAMES])
    if all(f"c_{n}" in ds.extras for n in COEFF_NAMES):
        coeffs = np.column_stack([ds.extras[f"c_{n}"] for n in COEFF_NAMES])
    else:
        coeffs = np.tile(v.true_vector(), (len(ds), 1))
    seg_end = np.append(np.flatnonzero(ds.segment[1:] != ds.segment[:-1]) + 1, len(ds))
    end_of = np.repeat(seg_end, np.diff(np.append(0, seg_end)))   # one past the last row of each row's segment
    for k in range(len(ds)):
        head = f"{utimes[k]} {steps[k]}"
        lines.append(f"S {head} {_fmt(ds.states[k])} {_fmt(var[k])}")
        lines.append(f"C {head} {_fmt(coeffs[k])}")
        n = int(min(horizon, end_of[k] - 1 - k))
        lines.append(f"P {head} 0 replay 0 0.0 {n} {_fmt(ds.states[k:k + n + 1])}"
                     + (f" {_fmt(ds.inputs[k:k + n])}" if n else ""))
        lines.append(f"F {head} 0")
    return lines


def replay(ds: Dataset, url: str, tool: Path = DEFAULT_TOOL, rates: dict[str, float] | None = None,
           prefix: str | None = None, horizon: int = DEFAULT_HORIZON, speed: float = 0.0) -> str:
    """Run the tool over the dataset, publishing on `url`; returns its summary (one line per kind).

    speed > 0 paces the messages at that multiple of real time (0: as fast as possible).
    """
    tool = Path(tool)
    if not tool.is_file():
        raise DdynError(f"{tool} not found: build the C side (scripts/build.sh) with DDYN_WITH_LCM=ON")
    cmd = [str(tool), "-u", url, "-c", repr(1.0 / ds.sample_time), "-m"]
    if prefix:
        cmd += ["-p", prefix]
    if speed > 0:
        cmd += ["-s", repr(float(speed))]
    for kind, hz in (rates or {}).items():
        cmd += ["-r", f"{kind}={hz!r}"]
    text = "\n".join(stream(ds, horizon)) + "\n"
    done = subprocess.run(cmd, input=text, capture_output=True, text=True)
    if done.returncode != 0:
        raise DdynError(f"{tool.name} failed: {done.stderr.strip()}")
    return done.stdout


def register(subparsers) -> None:
    p = subparsers.add_parser("replay", help="publish a dataset as controller telemetry over LCM "
                              "(the C telemetry module; e.g. into an LCM log for `ddyn import`)")
    p.add_argument("dataset", help="any dataset `ddyn import` reads (e.g. one written by ddyn simulate)")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("-o", "--out", help="LCM log to write (LCM's file:// provider)")
    where.add_argument("--url", help="LCM URL to publish on, e.g. udpm://239.255.76.67:7667?ttl=0")
    p.add_argument("--rate", action="append", default=[], metavar="KIND=HZ",
                   help=f"publish rate of one message kind ({', '.join(KINDS)}); default: the tool's")
    p.add_argument("--prefix", help="channel prefix (default DDYN_)")
    p.add_argument("--horizon", type=int, default=DEFAULT_HORIZON, help="rows of the replayed plan")
    p.add_argument("--speed", type=float, default=0.0,
                   help="pace the messages at this multiple of real time (default 0: as fast as possible, "
                   "which can overrun a UDP receiver)")
    p.add_argument("--tool", default=str(DEFAULT_TOOL), help="the ddyn_telemetry_replay executable")
    p.set_defaults(func=_run)


def _run(args) -> int:
    rates = {}
    for item in args.rate:
        kind, sep, hz = item.partition("=")
        try:
            rates[kind] = float(hz)
        except ValueError:
            raise DdynError(f"--rate {item!r}: expected KIND=HZ") from None
        if not sep or kind not in KINDS:
            raise DdynError(f"--rate {item!r}: KIND is one of {', '.join(KINDS)}")
    if not 0 <= args.horizon <= 100:
        raise DdynError("--horizon must be within 0 .. 100 (DDYN_TM_PLAN_MAX_HORIZON)")
    ds = load_any(args.dataset)
    if args.out:
        url = f"file://{Path(args.out).resolve()}?mode=w"   # LCM's file provider truncates the file
    else:
        url = args.url
    summary = replay(ds, url, Path(args.tool), rates, args.prefix, args.horizon, args.speed)
    print(f"{args.dataset} -> {args.out or url}: {len(ds)} steps")
    print(summary, end="")
    return 0
