"""01: simulate a log of the 1:43 car and look at it.

Shows: ddyn.simulate (a closed-loop drive around a track), ddyn.save_log and ddyn.load_log (the canonical CSV
round-trips every float exactly), the Dataset's columns, and a plot of the path and the speed.
Run:   .venv/bin/python examples/01_simulate_a_log.py [--laps 1] [--out out/examples/01]
Takes a few seconds; writes OUT/sim.csv and OUT/sim.png.
"""
import argparse
from pathlib import Path

import numpy as np

import ddyn

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--laps", type=float, default=1.0)
parser.add_argument("--out", default="out/examples/01")
args = parser.parse_args()
out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)

log = ddyn.simulate("orca_1_43", track="ethzMobil", laps=args.laps, seed=1)
path = ddyn.save_log(log, out / "sim.csv")
back = ddyn.load_log(path)                   # the format is detected from the file's first line
same = np.array_equal(back.states, log.states) and np.array_equal(back.inputs, log.inputs)

speed = np.hypot(log.column("vx"), log.column("vy"))
print(f"rows {len(log)}, sample time {log.sample_time:g} s, duration {log.time[-1] - log.time[0]:.2f} s, "
      f"vehicle {log.vehicle}")
print(f"speed min {speed.min():.3f} max {speed.max():.3f} m/s; max |omega| {np.abs(log.column('omega')).max():.3f} "
      f"rad/s; steering within [{log.column('steering').min():+.3f}, {log.column('steering').max():+.3f}] rad")
print(f"reloaded {path}: {len(back)} rows, identical: {same}")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
sc = ax1.scatter(log.column("x"), log.column("y"), c=speed, s=2, cmap="viridis")
ax1.set_aspect("equal")
ax1.set_title("path, coloured by speed")
fig.colorbar(sc, ax=ax1, label="m/s")
ax2.plot(log.time, log.column("vx"), label="vx (m/s)")
ax2.plot(log.time, log.column("omega"), label="omega (rad/s)")
ax2.set_xlabel("time (s)")
ax2.legend()
fig.tight_layout()
fig.savefig(out / "sim.png", dpi=100)
print(f"wrote {out / 'sim.png'}")
