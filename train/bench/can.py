"""`ddyn can bench`: the cost of receiving one drive-by-wire frame, C beside Python, in one run.

C: `ddyn_dbw_bench` (built by CMake) times ddyn_dbw_on_frame (decode, checksum, range and
counter checks, monitor update) and ddyn_dbw_command_frame per call. Python: the same decode
with the DBC through cantools (train/can_protocol.decode: checksum, range checks) per call.
Reports median, p99 and max per call and the Python/C ratio of the medians.
"""
from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np

from ddyn.data import can_protocol as proto
from ddyn.errors import DdynError
from ddyn.paths import BUILD

REPO = Path(__file__).resolve().parents[2]
DEFAULT_TOOL = BUILD / "c_src" / "ddyn_dbw_bench"


def python_decode_ns(calls: int) -> np.ndarray:
    db = proto.database()
    frames = [proto.encode("IMU", {"YawRate": 0.3, "AccelX": 1.5, "AccelY": -4.0}, counter=k, db=db)
              for k in range(16)]
    out = np.empty(calls, dtype=np.int64)
    clock = time.perf_counter_ns
    for i in range(calls):
        fid, data = frames[i % 16]
        t0 = clock()
        proto.decode(fid, data, db=db)
        out[i] = clock() - t0
    return out


def run(tool: Path, calls: int, py_calls: int) -> list[dict]:
    if not tool.is_file():
        raise DdynError(f"{tool} missing: build the C side first (scripts/build.sh)")
    res = subprocess.run([str(tool), str(calls)], capture_output=True, text=True)
    if res.returncode != 0:
        raise DdynError(f"{tool} failed: {res.stderr.strip()}")
    rows = []
    for line in res.stdout.splitlines():
        name, n, med, p99, mx = line.split()
        rows.append({"name": f"C {name}", "calls": int(n), "median_ns": int(med), "p99_ns": int(p99), "max_ns": int(mx)})
    py = python_decode_ns(py_calls)
    rows.append({"name": "Python cantools decode", "calls": py_calls, "median_ns": int(np.median(py)),
                 "p99_ns": int(np.percentile(py, 99)), "max_ns": int(py.max())})
    return rows


def _run(args) -> int:
    rows = run(Path(args.tool), args.calls, args.python_calls)
    c_rx = rows[0]["median_ns"]
    print(f"{'per call':32s} {'calls':>8s} {'median':>10s} {'p99':>10s} {'max':>10s}")
    for r in rows:
        print(f"{r['name']:32s} {r['calls']:8d} {r['median_ns']:8d}ns {r['p99_ns']:8d}ns {r['max_ns']:8d}ns")
    print(f"Python decode / C receive (medians): {rows[-1]['median_ns'] / max(c_rx, 1):.0f}x")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="time the drive-by-wire frame path: C vs the Python decoder")
    p.add_argument("--tool", default=str(DEFAULT_TOOL), help="ddyn_dbw_bench binary (default: %(default)s)")
    p.add_argument("--calls", type=int, default=100000, help="C calls per function (default: %(default)s)")
    p.add_argument("--python-calls", type=int, default=20000, help="Python calls (default: %(default)s)")
    p.set_defaults(func=_run)
