"""`ddyn bench`: timing of the runtime's real-time functions against the alternatives a user would pick.

In one run, each over many calls (median, p99, max in microseconds):
  guard-network inference   C (`ddyn_bench`, built against an export)  vs  PyTorch, batch of one
  EKF step (50 Hz cycle)    C                                          vs  the same filter in numpy
                                                                           calling the CasADi model from Python
The C tool must be built for the same checkpoint: `ddyn export CKPT --out DIR`, then
`scripts/build.sh build -DDDYN_NET_EXPORT_DIR=DIR`.
"""
from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

from . import checkpoint, vehicle as vehicle_mod
from .errors import DdynError
from .paths import REPO
from .sensors import MEASUREMENTS
from .windows import make_windows

DEFAULT_TOOL = REPO / "build" / "c_src" / "ddyn_bench"


def _stats(samples_us: list[float]) -> dict:
    a = np.sort(np.asarray(samples_us))
    return {"n": len(a), "median_us": float(a[len(a) // 2]), "p99_us": float(a[int(0.99 * (len(a) - 1))]),
            "max_us": float(a[-1])}


def _torch_inference(model, histories: np.ndarray, n: int) -> dict:
    torch.set_num_threads(1)  # one core, like the car's controller thread
    x = [torch.as_tensor(h[None], dtype=next(model.parameters()).dtype) for h in histories[: min(n, 2000)]]
    out = []
    with torch.inference_mode():
        for i in range(n):
            t0 = time.perf_counter()
            model.coefficients(x[i % len(x)])
            out.append((time.perf_counter() - t0) * 1e6)
    return _stats(out)


def _python_ekf(n: int) -> dict:
    """The same EKF cycle as the C benchmark, in numpy, with the model's CasADi functions called from Python."""
    from codegen.generate import model_functions

    v = vehicle_mod.load("orca_1_43")
    f = {fn.name().removeprefix(f"ddyn_{v.name}_"): fn for fn in model_functions(v)}
    c = v.true_vector()
    x0 = np.array([0.0, 0.0, 0.0, 1.5, 0.0, 0.0, 0.2, 0.0])
    p0 = np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-4, 1e-2, 1e-8, 1e-8])
    q = np.diag([1e-8, 1e-8, 1e-8, 1e-6, 1e-6, 1e-4, 1e-12, 1e-12])
    u = np.array([0.0, 0.01])
    x, P = x0.copy(), p0.copy()

    def update(name, z, r):
        nonlocal x, P
        h, H = (np.asarray(a) for a in f[f"meas_{name}"](x, c))
        h = h.ravel()
        S = H @ P @ H.T + np.diag(r)
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (z - h)
        IKH = np.eye(8) - K @ H
        P = IKH @ P @ IKH.T + K @ np.diag(r) @ K.T

    out = []
    for i in range(n):
        t0 = time.perf_counter()
        A = np.asarray(f["step_euler_jac"](x, u, c)[0])
        x = np.asarray(f["step_euler"](x, u, c)).ravel()
        P = A @ P @ A.T + q
        update("yaw_rate", np.array([0.1]), [2.5e-3])
        update("wheel_speed", np.array([x[3], x[3]]), [0.04, 0.04])
        update("acceleration", np.array([x[3], x[3]]), [0.04, 0.04])
        update("steering", np.array([x[7]]), [2.5e-3])
        if i % 5 == 0:
            update("gnss_position", x[:2].copy(), [0.04, 0.04])
        out.append((time.perf_counter() - t0) * 1e6)
        if i % 500 == 499:
            x, P = x0.copy(), p0.copy()
    assert set(MEASUREMENTS) >= {"yaw_rate", "wheel_speed", "acceleration", "steering", "gnss_position"}
    return _stats(out)


def run(ckpt_path: str, data_path: str, n: int = 10000, n_python: int = 2000, tool: Path = DEFAULT_TOOL) -> dict:
    from .importers import load_any

    if not Path(tool).is_file():
        raise DdynError(f"{tool} not found: build with scripts/build.sh build -DDDYN_NET_EXPORT_DIR=<export dir>")
    model, ckpt = checkpoint.load(ckpt_path)
    hist = make_windows(load_any(data_path), ckpt["config"]["tau"]).history
    text = "\n".join(" ".join(repr(float(v)) for v in h.ravel()) for h in hist[:20000]) + "\n"
    proc = subprocess.run([str(tool), str(n)], input=text, capture_output=True, text=True)
    if proc.returncode != 0:
        raise DdynError(f"{tool}: {proc.stderr.strip()} (was it built for this checkpoint's export?)")
    c_results = {}
    for line in proc.stdout.splitlines():
        name, count, med, p99, mx = line.split()
        c_results[name] = {"n": int(count), "median_us": float(med), "p99_us": float(p99), "max_us": float(mx)}
    results = {
        "guard_net_infer": {"c": c_results["guard_net_infer"], "alternative": "PyTorch, batch 1, 1 thread",
                            "alt": _torch_inference(model, hist, n_python)},
        "ekf_step": {"c": c_results["ekf_step"], "alternative": "numpy + CasADi functions from Python",
                     "alt": _python_ekf(n_python)},
        "parameters": int(sum(p.numel() for p in model.parameters())),
    }
    for key in ("guard_net_infer", "ekf_step"):
        r = results[key]
        r["speedup_median"] = r["alt"]["median_us"] / r["c"]["median_us"]
    return results


def format_table(r: dict) -> str:
    lines = ["| function | C median / p99 / max (µs) | alternative | its median / p99 / max (µs) | C faster (median) |",
             "|---|---|---|---|---|"]
    for key in ("guard_net_infer", "ekf_step"):
        e = r[key]
        c, a = e["c"], e["alt"]
        lines.append(f"| {key} | {c['median_us']:.2f} / {c['p99_us']:.2f} / {c['max_us']:.1f} (n={c['n']}) | "
                     f"{e['alternative']} | {a['median_us']:.1f} / {a['p99_us']:.1f} / {a['max_us']:.1f} (n={a['n']}) | "
                     f"{e['speedup_median']:.0f}x |")
    return "\n".join(lines)


def _run(args) -> int:
    r = run(args.model, args.data, args.n, args.n_python, Path(args.tool))
    print(f"network: {r['parameters']} parameters")
    print(format_table(r))
    if args.controller:  # the whole controller step in closed loop (train/controller_bench.py)
        from .controller_bench import format_controller, run_controller

        r["controller_step"] = run_controller(Path(args.tool).parent / "ddyn_controller_bench", args.controller_steps)
        print(format_controller(r["controller_step"]))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(r, indent=2))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="time guard-net inference and the EKF step in C against Python")
    p.add_argument("--model", required=True, help="checkpoint whose export the C tool was built for")
    p.add_argument("--data", required=True, help="dataset the inference histories come from")
    p.add_argument("-n", type=int, default=10000, help="calls of each C function (default %(default)s)")
    p.add_argument("--n-python", type=int, default=2000, help="calls of each Python alternative")
    p.add_argument("--tool", default=str(DEFAULT_TOOL), help="ddyn_bench binary (default: %(default)s)")
    p.add_argument("--out", help="write the results as JSON here")
    p.add_argument("--controller", action="store_true",
                   help="also time the whole controller step in closed loop (ddyn_controller_bench beside --tool)")
    p.add_argument("--controller-steps", type=int, default=20000, help="closed-loop periods (default %(default)s)")
    p.set_defaults(func=_run)
