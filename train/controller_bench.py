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
import os
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


# Simulated sensors of the closed-loop run: (period in control periods, noise std, std the filter
# assumes). Noise of position, heading, yaw rate, wheel speed from the vehicle's sensor_noise_std
# (x, yaw, omega, vx); the accelerometer's and steering sensor's are chosen here. GNSS and heading
# at a fifth of the rate. The filter assumes twice the noise (model error), and 1 m/s^2 for the
# accelerometer: its model goes through the estimated tyre and drivetrain coefficients, whose
# errors dominate its 0.1 m/s^2 noise on the 41 g car (a 10 % error in Cm1 alone is ~0.2 m/s^2).
SENSOR_SETUP = {"gnss_position": (5, "x", None), "heading": (5, "yaw", None), "yaw_rate": (1, "omega", None),
                "acceleration": (1, 0.1, 1.0), "wheel_speed": (1, "vx", None), "steering": (1, 0.005, None)}
# Process noise per period of the filter (x, y, yaw, vx, vy, omega, throttle, steering): the
# velocities' stands for the error of a step with estimated coefficients.
PROCESS_NOISE = (1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-2, 1e-10, 1e-10)


def raceline_table(track_name: str, speed_scale: float, vehicle: str = "orca_1_43") -> np.ndarray:
    """(n, 5) rows x, y, speed, room left, room right: the MPC's raceline table (train/mpc_setup.py)."""
    from .mpc_setup import MpcSettings, raceline_table as mpc_table
    from .tracks import load_track

    t = mpc_table(load_track(track_name), vehicle, MpcSettings(speed_scale=speed_scale))
    return np.column_stack([t["x"], t["y"], t["speed"], t["room_left"], t["room_right"]])


def controller_setup(vehicle: str = "orca_1_43", track: str = "ethz", speed_scale: float = 1.0) -> str:
    """The stdin text of ddyn_controller_bench (format in the tool's header comment)."""
    from .model import COEFF_NAMES

    v = vehicle_mod.load(vehicle)
    if v.true_coefficients is None:
        raise DdynError(f"vehicle {vehicle} has no true coefficients for the plant")
    c = [v.true_coefficients[k] for k in COEFF_NAMES]
    table = raceline_table(track, speed_scale, vehicle)
    x0, y0, sp0 = table[0, :3]
    heading = float(np.arctan2(table[1, 1] - y0, table[1, 0] - x0))
    vx = max(float(sp0), 1.0)
    coeff = dict(zip(COEFF_NAMES, c))
    # throttle that holds vx: (Cm1 - Cm2 vx) T = Cr0 + Cd vx^2
    throttle = (coeff["Cr0"] + coeff["Cd"] * vx ** 2) / (coeff["Cm1"] - coeff["Cm2"] * vx)
    sensors = []
    for name in ("gnss_position", "heading", "yaw_rate", "acceleration", "wheel_speed", "steering"):
        period, noise, assumed = SENSOR_SETUP[name]
        sd = v.sensor_noise_std[noise] if isinstance(noise, str) else noise
        sensors.append(f"{period} {sd!r} {assumed if assumed is not None else 2.0 * sd!r}")
    lines = [v.name, " ".join(repr(float(a)) for a in c), " ".join(repr(float(a)) for a in c),
             " ".join(repr(float(a)) for a in (x0, y0, heading, vx, 0.0, 0.0, throttle, 0.0)),
             " ".join(repr(a) for a in PROCESS_NOISE), " ".join(sensors), str(len(table))]
    lines += [" ".join(repr(float(a)) for a in row) for row in table]
    return "\n".join(lines) + "\n"


def run_controller(tool: str | Path = DEFAULT_CONTROLLER_TOOL, steps: int = 20000, seed: int = 1,
                   vehicle: str = "orca_1_43", track: str = "ethz", speed_scale: float = 1.0) -> dict:
    """Run the C closed-loop controller benchmark and parse its "NAME n median p99 max" lines."""
    tool = Path(tool)
    if not tool.is_file():
        raise DdynError(f"{tool} not found: build with scripts/build.sh (DDYN_BUILD_TOOLS=ON)")
    setup = controller_setup(vehicle, track, speed_scale)
    load_before = os.getloadavg()[0]  # the machine may be shared: a loaded one inflates p99 and max
    proc = subprocess.run([str(tool), str(steps), str(seed)], input=setup, capture_output=True, text=True)
    if proc.returncode != 0:
        raise DdynError(f"{tool} failed: {proc.stderr.strip()}")
    results = {"loadavg_1min": [load_before, os.getloadavg()[0]], "cpus": os.cpu_count()}
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) == 5 and parts[1].isdigit():
            name, count, med, p99, mx = parts
            results[name] = {"n": int(count), "median_us": float(med), "p99_us": float(p99), "max_us": float(mx)}
        elif line.startswith("# ") and len(parts) == 3:
            results[parts[1]] = float(parts[2])
    return results


def format_controller(r: dict) -> str:
    """One table row of the closed-loop run, and what the controller did in it."""
    s = r["controller_step"]
    bits = {k.removeprefix("steps_DDYN_CTRL_").lower(): int(v) for k, v in r.items()
            if k.startswith("steps_DDYN_CTRL_") and v > 0}
    m = r.get("mpc_solve")
    mpc = f"; of it the MPC solve {m['median_us']:.2f} / {m['p99_us']:.2f} / {m['max_us']:.1f}" if m else ""
    return (f"| controller_step (closed loop) | {s['median_us']:.2f} / {s['p99_us']:.2f} / {s['max_us']:.1f} "
            f"(n={s['n']}){mpc} | laps {r.get('laps', 0.0):.2f}, max raceline offset {r.get('max_raceline_offset_m', 0.0):.3f} m"
            f" | periods with status bits: {bits or 'none'}; load average {r['loadavg_1min'][0]:.1f} -> "
            f"{r['loadavg_1min'][1]:.1f} on {r['cpus']} CPUs |")


def build_for(ckpt: str | Path, directory: str | Path) -> Path:
    """`ddyn export` the checkpoint into directory/export and build the C side against it in
    directory/build (one build per network: the shapes are compile-time constants)."""
    from .export import export

    directory = Path(directory).resolve()
    export(ckpt, directory / "export", torch_export=False)
    build = directory / "build"
    for cmd in (["cmake", "-S", str(REPO), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release", "-DDDYN_BUILD_TESTS=OFF",
                 f"-DDDYN_NET_EXPORT_DIR={directory / 'export'}"],
                ["cmake", "--build", str(build), "-j2", "--target", "ddyn_bench", "ddyn_controller_bench"]):
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise DdynError(f"{' '.join(cmd[:2])} failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    return build / "c_src"


def large_net_bench(directory: str | Path, data: str | Path | None, tau: int, hidden: int, layers: int,
                    gru_layers: int, n: int, n_python: int, steps: int) -> dict:
    """A random DDM of the given shape: C inference against PyTorch (`ddyn bench`), and the whole
    controller step in closed loop with that network."""
    from . import bench
    from .dataset import write_canonical
    from .simulate import simulate

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if data is None:  # the histories and the normalisation come from a simulated run on ETHZ
        data = write_canonical(simulate("orca_1_43", "ethz", laps=2, seed=1, noise_scale=1.0, progress=False), directory / "data.csv")
    ckpt, count = make_net(directory / "net.ckpt", data, tau, hidden, layers, gru_layers)
    tools = build_for(ckpt, directory)
    torch.set_num_threads(1)
    r = bench.run(str(ckpt), str(data), n, n_python, tools / "ddyn_bench")
    r["controller"] = run_controller(tools / "ddyn_controller_bench", steps)
    r["shape"] = {"tau": tau, "hidden": hidden, "layers": layers, "gru_layers": gru_layers, "parameters": count}
    return r


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
    b = sub.add_parser("large-net", help="make, export, build and time a ~100k-parameter guard network")
    b.add_argument("--dir", default=str(REPO / "build-net100k"), help="working folder (default %(default)s)")
    b.add_argument("--data", help="dataset for histories and normalisation (default: a simulated ETHZ run)")
    b.add_argument("--tau", type=int, default=5)
    b.add_argument("--hidden", type=int, default=210)
    b.add_argument("--layers", type=int, default=3)
    b.add_argument("--gru-layers", type=int, default=0)
    b.add_argument("-n", type=int, default=10000, help="C inference calls")
    b.add_argument("--n-python", type=int, default=2000, help="PyTorch inference calls")
    b.add_argument("--steps", type=int, default=10000, help="closed-loop controller periods")
    b.add_argument("--out", help="write the results as JSON here")
    c = sub.add_parser("controller", help="closed-loop timing of the C controller step")
    c.add_argument("--tool", default=str(DEFAULT_CONTROLLER_TOOL))
    c.add_argument("--steps", type=int, default=20000)
    c.add_argument("--out", help="write the results as JSON here")
    args = p.parse_args(argv)
    if args.cmd == "make-net":
        path, n = make_net(args.out, args.data, args.tau, args.hidden, args.layers, args.gru_layers, args.seed)
        print(f"wrote {path}: {n} parameters")
        return 0
    if args.cmd == "large-net":
        from .bench import format_table

        r = large_net_bench(args.dir, args.data, args.tau, args.hidden, args.layers, args.gru_layers, args.n,
                            args.n_python, args.steps)
        print(f"network: {r['shape']}")
        print(format_table(r))
        print(format_controller(r["controller"]))
        if args.out:
            Path(args.out).write_text(json.dumps(r, indent=2) + "\n")
        return 0
    r = run_controller(args.tool, args.steps)
    print(format_controller(r))
    if args.out:
        Path(args.out).write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
