"""`ddyn bench runtime`: timing of the runtime's real-time functions against the alternatives a user would pick.

In one run, each over many calls (median, p99, max in microseconds):
  guard-network inference   C (`ddyn_bench`, built against an export)  vs  PyTorch, batch of one
  EKF step (50 Hz cycle)    C                                          vs  the same filter in numpy
                                                                           calling the CasADi model from Python
  MPC step (H = 20, 50 Hz)   C (`ddyn_mpc_lap`: the closed loop on     vs  the same MPC with CasADi + IPOPT, and with
                            ethzMobil, >= 10,000 steps, every solve       CasADi's code-generated sqpmethod + qrqp,
                            timed; QP iterations reported too)            each over a closed-loop stretch from the start
The C tool must be built for the same checkpoint: `ddyn export CKPT --out DIR`, then
`scripts/build.sh build -DDDYN_NET_EXPORT_DIR=DIR`. Without --model the network and EKF rows are
skipped (the MPC does not depend on the network); --no-mpc skips the MPC rows.
"""
from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

from ddyn.bench.controller import format_controller, run_controller
from ddyn.bench.identity import require_same_network
from ddyn.data.windows import make_windows
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.sensors import MEASUREMENTS
from ddyn.paths import BUILD, REPO

DEFAULT_TOOL = BUILD / "c_src" / "ddyn_bench"


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
    from ddyn.codegen.generate import model_functions

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


def _stats_us(samples_us) -> dict:
    return _stats(list(np.asarray(samples_us, float)))


def mpc_bench(n: int = 10000, n_ipopt: int = 200, n_sqp: int = 50, tool: Path | None = None,
              generated_dir: Path | None = None) -> dict:
    """MPC step: C closed loop over n steps, IPOPT over n_ipopt, generated sqpmethod over n_sqp (0 = skip)."""
    from ddyn.control import mpc_lap, mpc_reference
    from ddyn.control.mpc_setup import MpcSettings
    from ddyn.model.tracks import load_track

    torch.set_num_threads(1)
    settings, track = MpcSettings(), load_track("ethzMobil")
    c_run = mpc_lap.run_c("orca_1_43", track, settings, n, tool=tool or mpc_lap.DEFAULT_TOOL)
    it = np.sort(c_run["qp_iterations"])
    out = {"c": _stats_us(c_run["solve_us"]),
           "qp_iterations": {"median": float(it[len(it) // 2]), "p99": float(it[int(0.99 * (len(it) - 1))]),
                             "max": int(it[-1])},
           "c_status_counts": {mpc_lap.STATUS_NAMES.get(int(k), str(k)): int(c)
                               for k, c in zip(*np.unique(c_run["status"], return_counts=True))},
           "c_closed_loop": mpc_lap.score(track, c_run["x"], c_run["dt"], "orca_1_43"),
           "settings": settings.as_dict()}
    alts = {}
    if n_ipopt > 0:
        r = mpc_reference.closed_loop("orca_1_43", track, settings, n_ipopt, "ipopt")
        alts["ipopt"] = {"what": "CasADi + IPOPT from Python (nlpsol built once, warm-started)",
                         "stats": _stats_us(r["solve_ms"] * 1e3),
                         "iterations_median": float(np.median(r["iterations"]))}
    if n_sqp > 0:
        gen = Path(generated_dir) if generated_dir else REPO / "out" / "mpc_sqp"
        r = mpc_reference.closed_loop("orca_1_43", track, settings, n_sqp, "sqpmethod", generated_dir=gen)
        alts["sqpmethod_generated"] = {"what": "CasADi sqpmethod + qrqp, code-generated C (-O1), via casadi.external",
                                       "stats": _stats_us(r["solve_ms"] * 1e3)}
    for a in alts.values():
        a["c_faster_median"] = a["stats"]["median_us"] / out["c"]["median_us"]
    out["alternatives"] = alts
    return out


def run(ckpt_path: str, data_path: str, n: int = 10000, n_python: int = 2000, tool: Path = DEFAULT_TOOL) -> dict:
    from ddyn.data.importers import load_any

    if not Path(tool).is_file():
        raise DdynError(f"{tool} not found: build with scripts/build.sh build -DDDYN_NET_EXPORT_DIR=<export dir>")
    network = require_same_network(tool, ckpt_path)
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
        "checkpoint_sha256": network,
    }
    for key in ("guard_net_infer", "ekf_step"):
        r = results[key]
        r["speedup_median"] = r["alt"]["median_us"] / r["c"]["median_us"]
    return results


def format_table(r: dict) -> str:
    lines = ["| function | C median / p99 / max (µs) | alternative | its median / p99 / max (µs) | C faster (median) |",
             "|---|---|---|---|---|"]
    if "mpc_step" in r:
        m = r["mpc_step"]
        c = m["c"]
        for a in m["alternatives"].values():
            s = a["stats"]
            lines.append(f"| mpc_step | {c['median_us']:.1f} / {c['p99_us']:.1f} / {c['max_us']:.1f} (n={c['n']}) | "
                         f"{a['what']} | {s['median_us']:.0f} / {s['p99_us']:.0f} / {s['max_us']:.0f} (n={s['n']}) | "
                         f"{a['c_faster_median']:.0f}x |")
    for key in ("guard_net_infer", "ekf_step"):
        if key not in r:
            continue
        e = r[key]
        c, a = e["c"], e["alt"]
        lines.append(f"| {key} | {c['median_us']:.2f} / {c['p99_us']:.2f} / {c['max_us']:.1f} (n={c['n']}) | "
                     f"{e['alternative']} | {a['median_us']:.1f} / {a['p99_us']:.1f} / {a['max_us']:.1f} (n={a['n']}) | "
                     f"{e['speedup_median']:.0f}x |")
    return "\n".join(lines)


def _run(args) -> int:
    if (args.model is None) != (args.data is None):
        raise DdynError("--model and --data go together (or leave both out for the MPC rows only)")
    if args.model is None and args.no_mpc:
        raise DdynError("nothing to time: give --model and --data, or drop --no-mpc")
    r = run(args.model, args.data, args.n, args.n_python, Path(args.tool)) if args.model else {}
    if not args.no_mpc:
        r["mpc_step"] = mpc_bench(max(args.n, 10000), args.mpc_ipopt_steps, args.mpc_sqp_steps, Path(args.mpc_tool))
    if "parameters" in r:
        print(f"network: {r['parameters']} parameters")
    print(format_table(r))
    if "mpc_step" in r:
        m = r["mpc_step"]
        print(f"MPC: QP iterations median {m['qp_iterations']['median']:.0f}, p99 {m['qp_iterations']['p99']:.0f}, "
              f"max {m['qp_iterations']['max']}; status {m['c_status_counts']}; closed loop "
              f"{m['c_closed_loop']['steps']} steps, {m['c_closed_loop']['violation_steps']} track violations")
    if args.controller:  # the whole controller step in closed loop (ddyn/bench/controller.py)
        if args.model:
            require_same_network(Path(args.tool).parent / "ddyn_controller_bench", args.model)
        r["controller_step"] = run_controller(Path(args.tool).parent / "ddyn_controller_bench", args.controller_steps)
        print(format_controller(r["controller_step"]))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(r, indent=2))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("runtime", help="time guard-net inference, the EKF step and the MPC step in C against Python")
    p.add_argument("--model", help="checkpoint whose export the C tool was built for (omit: MPC rows only)")
    p.add_argument("--data", help="dataset the inference histories come from")
    p.add_argument("--no-mpc", action="store_true", help="skip the MPC rows")
    p.add_argument("--mpc-ipopt-steps", type=int, default=200, help="closed-loop steps timed with IPOPT")
    p.add_argument("--mpc-sqp-steps", type=int, default=50,
                   help="closed-loop steps timed with the generated sqpmethod (0: skip; compiling it takes ~1 min)")
    p.add_argument("--mpc-tool", default=str(BUILD / "c_src" / "ddyn_mpc_lap"), help="ddyn_mpc_lap binary")
    p.add_argument("-n", type=int, default=10000, help="calls of each C function (default %(default)s)")
    p.add_argument("--n-python", type=int, default=2000, help="calls of each Python alternative")
    p.add_argument("--tool", default=str(DEFAULT_TOOL), help="ddyn_bench binary (default: %(default)s)")
    p.add_argument("--out", help="write the results as JSON here")
    p.add_argument("--controller", action="store_true",
                   help="also time the whole controller step in closed loop (ddyn_controller_bench beside --tool)")
    p.add_argument("--controller-steps", type=int, default=20000, help="closed-loop periods (default %(default)s)")
    p.set_defaults(func=_run)
