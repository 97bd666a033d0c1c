"""`ddyn codegen check`: the generated C model against the Python model on every row of a dataset.

Each row's state and input, with the vehicle's coefficients, go through one step
of the C runtime (the ddyn_model_replay tool built by CMake) and of the numpy
model; the command reports the largest difference per state channel and fails
when any exceeds the float64 tolerance.
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.model import backends
from ddyn.model.single_track import STATE_NAMES
from ddyn.paths import BUILD

DEFAULT_BINARY = BUILD / "c_src" / "ddyn_model_replay"
# relative to each channel's magnitude over the dataset: rounding of the same
# float64 expressions in two implementations
RTOL = 1e-12


def run_c_model(binary: Path, vehicle_name: str, method: str, x: np.ndarray, u: np.ndarray, c: np.ndarray) -> np.ndarray:
    if not Path(binary).is_file():
        raise DdynError(f"C replay tool not found at {binary}: build it with cmake (see README)")
    rows = np.column_stack([x, u, np.broadcast_to(c, (len(x), c.shape[-1]))])
    text = "\n".join(" ".join(repr(float(v)) for v in r) for r in rows) + "\n"
    proc = subprocess.run([str(binary), vehicle_name, method], input=text, capture_output=True, text=True)
    if proc.returncode != 0:
        raise DdynError(f"{binary} failed: {proc.stderr.strip()}")
    return np.loadtxt(proc.stdout.splitlines(), ndmin=2)


def crosscheck(data_path: str, binary: Path, method: str = "euler", coeff_set: str = "true",
               vehicle_name: str | None = None) -> dict:
    from ddyn.data.importers import load_with_vehicle

    ds, v = load_with_vehicle(data_path, vehicle_name)
    c = v.coefficient_vector(coeff_set)
    substeps = v.rk4_substeps if method == "rk4" else 1
    py = backends.step_numpy(ds.states, ds.inputs, c, v.known, v.sample_time, method, substeps)
    cc = run_c_model(binary, v.name, method, ds.states, ds.inputs, c)
    if cc.shape != py.shape:
        raise DdynError(f"C tool returned {cc.shape[0]} rows for {py.shape[0]} inputs")
    scale = np.maximum(np.abs(py).max(axis=0), 1e-300)
    abs_err = np.abs(cc - py).max(axis=0)
    rel_err = abs_err / scale
    return {"rows": len(ds), "vehicle": v.name, "method": method,
            "max_abs_error": dict(zip(STATE_NAMES, abs_err.tolist())),
            "max_rel_error": dict(zip(STATE_NAMES, rel_err.tolist())),
            "passed": bool(np.all(rel_err <= RTOL))}


def _run(args) -> int:
    report = crosscheck(args.data, Path(args.binary), args.method, args.coeffs, args.vehicle)
    print(f"C model vs Python model, {report['vehicle']} {report['method']}, {report['rows']} rows:")
    for ch in STATE_NAMES:
        print(f"  {ch:9s} max |C - Python| = {report['max_abs_error'][ch]:.3e}"
              f"  (relative {report['max_rel_error'][ch]:.1e})")
    print("PASS" if report["passed"] else f"FAIL: relative difference above {RTOL:g}")
    return 0 if report["passed"] else 1


def register(subparsers) -> None:
    p = subparsers.add_parser("check", help="compare the generated C model with the Python model on a dataset")
    p.add_argument("--data", required=True, help="dataset (canonical, DDM .npz or RACECAR .csv)")
    p.add_argument("--binary", default=str(DEFAULT_BINARY), help="ddyn_model_replay tool (default: %(default)s)")
    p.add_argument("--method", choices=("euler", "rk4"), default="euler")
    p.add_argument("--coeffs", choices=("true", "reference_dataset"), default="true",
                   help="coefficient set of the vehicle file to use")
    p.add_argument("--vehicle", help="vehicle name or JSON file (default: the one the dataset records)")
    p.set_defaults(func=_run)
