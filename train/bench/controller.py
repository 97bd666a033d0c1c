"""`ddyn bench controller`: closed-loop timing of the C controller step.

`run_controller` drives c_src/tools/controller_bench.c (EKF, guard network, MPC against a simulated
plant) and reports median, p99 and max of the whole controller step over >= 10,000 steps.
"""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np

from ddyn.bench.identity import require_same_network, tool_checkpoint_hash
from ddyn.errors import DdynError
from ddyn.model import vehicle as vehicle_mod
from ddyn.paths import BUILD

DEFAULT_CONTROLLER_TOOL = BUILD / "c_src" / "ddyn_controller_bench"


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
    """(n, 5) rows x, y, speed, room left, room right: the MPC's raceline table (train/control/mpc_setup.py)."""
    from ddyn.control.mpc_setup import MpcSettings
    from ddyn.control.mpc_setup import raceline_table as mpc_table
    from ddyn.model.tracks import load_track

    t = mpc_table(load_track(track_name), vehicle, MpcSettings(speed_scale=speed_scale))
    return np.column_stack([t["x"], t["y"], t["speed"], t["room_left"], t["room_right"]])


def controller_setup(vehicle: str = "orca_1_43", track: str = "ethz", speed_scale: float = 1.0) -> str:
    """The stdin text of ddyn_controller_bench (format in the tool's header comment)."""
    from ddyn.model.single_track import COEFF_NAMES

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
                   vehicle: str = "orca_1_43", track: str = "ethz", speed_scale: float = 1.0,
                   prepare: bool = False) -> dict:
    """Run the C closed-loop controller benchmark and parse its "NAME n median p99 max" lines.
    prepare: the MPC's preparation after each command (ddyn_ctrl_prepare, timed apart), so that
    controller_step is the feedback latency."""
    tool = Path(tool)
    if not tool.is_file():
        raise DdynError(f"{tool} not found: build with scripts/build.sh (DDYN_BUILD_TOOLS=ON)")
    setup = controller_setup(vehicle, track, speed_scale)
    load_before = os.getloadavg()[0]  # the machine may be shared: a loaded one inflates p99 and max
    env = {**os.environ, "DDYN_BENCH_PREPARE": "1" if prepare else "0"}
    proc = subprocess.run([str(tool), str(steps), str(seed)], input=setup, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise DdynError(f"{tool} failed: {proc.stderr.strip()}")
    results = {"loadavg_1min": [load_before, os.getloadavg()[0]], "cpus": os.cpu_count(),
               "checkpoint_sha256": tool_checkpoint_hash(tool)}
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
    mpc = f"; the MPC solve alone {m['median_us']:.2f} / {m['p99_us']:.2f} / {m['max_us']:.1f}" if m else ""
    p = r.get("controller_prepare")
    if p:
        mpc = (f" = feedback latency (MPC prepared after the previous command: {p['median_us']:.2f} / "
               f"{p['p99_us']:.2f} / {p['max_us']:.1f} off the critical path)") + mpc
    return (f"| controller_step (closed loop) | {s['median_us']:.2f} / {s['p99_us']:.2f} / {s['max_us']:.1f} "
            f"(n={s['n']}){mpc} | laps {r.get('laps', 0.0):.2f}, max raceline offset {r.get('max_raceline_offset_m', 0.0):.3f} m"
            f" | network {r.get('checkpoint_sha256', '?')[:12]}; periods with status bits: {bits or 'none'}; load average {r['loadavg_1min'][0]:.1f} -> "
            f"{r['loadavg_1min'][1]:.1f} on {r['cpus']} CPUs |")


def _run(args) -> int:
    if args.model:
        require_same_network(args.tool, args.model)
    r = run_controller(args.tool, args.steps, seed=args.seed, track=args.track, prepare=args.prepare)
    print(format_controller(r))
    if args.out:
        Path(args.out).write_text(json.dumps(r, indent=2) + "\n")
    return 0


def register(subparsers) -> None:
    c = subparsers.add_parser("controller", help="closed-loop timing of the C controller step (median, p99, max)")
    c.add_argument("--tool", default=str(DEFAULT_CONTROLLER_TOOL))
    c.add_argument("--steps", type=int, default=20000)
    c.add_argument("--seed", type=int, default=1, help="sensor noise seed (default %(default)s)")
    c.add_argument("--track", default="ethz", help="track (default %(default)s)")
    c.add_argument("--prepare", action="store_true",
                   help="prepare the MPC after each command (ddyn_ctrl_prepare): the step is then the feedback latency")
    c.add_argument("--model", help="checkpoint the tool must have been built for (refused otherwise)")
    c.add_argument("--out", help="write the results as JSON here")
    c.set_defaults(func=_run)
