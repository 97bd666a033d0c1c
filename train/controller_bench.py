"""Benchmarks of the C controller (c_src/src/controller.c) and of a large guard network.

Two jobs:

* `make_net`: a random-initialised DDM of a chosen size (about 100k parameters by default),
  saved as a normal checkpoint whose input normalisation comes from a dataset, so that
  `ddyn export` turns it into C tables and `ddyn bench` times it against PyTorch. The
  weights are random: the point is the cost of inference at that size, not its accuracy.
* `run_controller`: the closed-loop controller timing of c_src/tools/controller_bench.c
  (median, p99, max of the whole controller step over >= 10,000 steps).
"""
from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np
import torch

from . import checkpoint, vehicle as vehicle_mod
from .errors import DdynError
from .importers import load_any
from .paths import REPO
from .training import TrainConfig, TrainResult, build_model
from .windows import features

DEFAULT_CONTROLLER_TOOL = REPO / "build" / "c_src" / "ddyn_controller_bench"


def parameter_count(tau: int, hidden: int, layers: int, gru_layers: int, n_out: int = 17, n_feat: int = 7) -> int:
    """Trainable parameters of a DDM of this shape (what export.json reports)."""
    n, width = 0, tau * n_feat
    for layer in range(gru_layers):
        inp = n_feat if layer == 0 else hidden
        n += 3 * hidden * (inp + hidden) + 6 * hidden
        width = hidden
    for _ in range(layers):
        n += hidden * width + hidden
        width = hidden
    return n + n_out * width + n_out


def make_net(out: str | Path, data: str | Path, tau: int, hidden: int, layers: int, gru_layers: int,
             seed: int = 0, vehicle: str = "orca_1_43") -> tuple[Path, int]:
    """Write a random-initialised DDM checkpoint; returns its path and parameter count."""
    torch.manual_seed(seed)
    v = vehicle_mod.load(vehicle)
    ds = load_any(data, vehicle=vehicle)
    f = features(ds)
    mean, std = f.mean(axis=0), np.maximum(f.std(axis=0), 1e-6)
    cfg = TrainConfig(tau=tau, hidden=hidden, layers=layers, gru_layers=gru_layers, seed=seed, dtype="float32")
    model = build_model(cfg, v, mean, std)
    n = int(sum(p.numel() for p in model.parameters()))
    ckpt = checkpoint.make(TrainResult(model, cfg, np.ones(3), [], 0.0, 0.0), v, "random-init",
                           f"train/controller_bench.py make-net (random weights, seed {seed}; normalisation of {data})",
                           len(ds))
    return checkpoint.save(ckpt, out), n


# Simulated sensors of the closed-loop run: (period in control periods, noise std). Position,
# heading, yaw rate, wheel speed from the vehicle's sensor_noise_std (x, yaw, omega, vx); the
# accelerometer's and steering sensor's are chosen here. GNSS and heading at a fifth of the rate.
SENSOR_SETUP = {"gnss_position": (5, "x"), "heading": (5, "yaw"), "yaw_rate": (1, "omega"),
                "acceleration": (1, 0.1), "wheel_speed": (1, "vx"), "steering": (1, 0.005)}


def raceline_table(track_name: str, speed_scale: float, margin: float, min_speed: float = 0.5) -> np.ndarray:
    """(n, 5) rows x, y, speed, room left, room right of the track's racing line for the MPC.

    The room to each bound is the centre line's half width at the raceline point's projection,
    shifted by its lateral offset, less `margin` (the car's half width and a safety distance).
    """
    from .tracks import load_track

    t = load_track(track_name)
    if t.raceline is None:
        raise DdynError(f"track {track_name} has no racing line")
    r = t.raceline
    x, y, speed = r.x.copy(), r.y.copy(), r.speed.copy()
    if np.hypot(x[-1] - x[0], y[-1] - y[0]) < 1e-9:  # closed by a repeated point
        x, y, speed = x[:-1], y[:-1], speed[:-1]
    s, lat = t.project(x, y)
    wl, wr = t.half_widths(s)
    return np.column_stack([x, y, np.maximum(speed * speed_scale, min_speed), wl - lat - margin, wr + lat - margin])


def controller_setup(vehicle: str = "orca_1_43", track: str = "ethz", speed_scale: float = 0.8,
                     margin: float = 0.03) -> str:
    """The stdin text of ddyn_controller_bench (format in the tool's header comment)."""
    from .model import COEFF_NAMES

    v = vehicle_mod.load(vehicle)
    if v.true_coefficients is None:
        raise DdynError(f"vehicle {vehicle} has no true coefficients for the plant")
    c = [v.true_coefficients[k] for k in COEFF_NAMES]
    table = raceline_table(track, speed_scale, margin)
    x0, y0, sp0 = table[0, :3]
    heading = float(np.arctan2(table[1, 1] - y0, table[1, 0] - x0))
    vx = max(float(sp0), 1.0)
    coeff = dict(zip(COEFF_NAMES, c))
    # throttle that holds vx: (Cm1 - Cm2 vx) T = Cr0 + Cd vx^2
    throttle = (coeff["Cr0"] + coeff["Cd"] * vx ** 2) / (coeff["Cm1"] - coeff["Cm2"] * vx)
    sensors = []
    for name in ("gnss_position", "heading", "yaw_rate", "acceleration", "wheel_speed", "steering"):
        period, noise = SENSOR_SETUP[name]
        sd = v.sensor_noise_std[noise] if isinstance(noise, str) else noise
        sensors.append(f"{period} {sd!r}")
    lines = [v.name, " ".join(repr(float(a)) for a in c), " ".join(repr(float(a)) for a in c),
             " ".join(repr(float(a)) for a in (x0, y0, heading, vx, 0.0, 0.0, throttle, 0.0)),
             " ".join(sensors), str(len(table))]
    lines += [" ".join(repr(float(a)) for a in row) for row in table]
    return "\n".join(lines) + "\n"


def run_controller(tool: str | Path = DEFAULT_CONTROLLER_TOOL, steps: int = 20000, seed: int = 1,
                   vehicle: str = "orca_1_43", track: str = "ethz", speed_scale: float = 0.8) -> dict:
    """Run the C closed-loop controller benchmark and parse its "NAME n median p99 max" lines."""
    tool = Path(tool)
    if not tool.is_file():
        raise DdynError(f"{tool} not found: build with scripts/build.sh (DDYN_BUILD_TOOLS=ON)")
    setup = controller_setup(vehicle, track, speed_scale)
    proc = subprocess.run([str(tool), str(steps), str(seed)], input=setup, capture_output=True, text=True)
    if proc.returncode != 0:
        raise DdynError(f"{tool} failed: {proc.stderr.strip()}")
    results = {}
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) == 5 and parts[1].isdigit():
            name, count, med, p99, mx = parts
            results[name] = {"n": int(count), "median_us": float(med), "p99_us": float(p99), "max_us": float(mx)}
        elif line.startswith("# ") and len(parts) == 3:
            results[parts[1]] = float(parts[2])
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m train.controller_bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make-net", help="random-initialised DDM checkpoint of a chosen size")
    m.add_argument("--data", required=True, help="dataset whose feature mean/std become the normalisation")
    m.add_argument("-o", "--out", required=True)
    m.add_argument("--tau", type=int, default=5)
    m.add_argument("--hidden", type=int, default=137)
    m.add_argument("--layers", type=int, default=2)
    m.add_argument("--gru-layers", type=int, default=1)
    m.add_argument("--seed", type=int, default=0)
    c = sub.add_parser("controller", help="closed-loop timing of the C controller step")
    c.add_argument("--tool", default=str(DEFAULT_CONTROLLER_TOOL))
    c.add_argument("--steps", type=int, default=20000)
    c.add_argument("--out", help="write the results as JSON here")
    args = p.parse_args(argv)
    if args.cmd == "make-net":
        path, n = make_net(args.out, args.data, args.tau, args.hidden, args.layers, args.gru_layers, args.seed)
        print(f"wrote {path}: {n} parameters")
        return 0
    r = run_controller(args.tool, args.steps)
    print(json.dumps(r, indent=2))
    if args.out:
        Path(args.out).write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
