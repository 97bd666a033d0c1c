"""07: load the real AV-21 log from Putnam Park and look at its roll column.

Shows: ddyn.load_log on the RACECAR CSV of the shared data (the importer keeps the rows above 5 m/s, splits
them into segments where it dropped rows, and keeps the extra columns such as `roll`), and why the diagnosis
does not read the road's bank from that roll channel: ddyn.data.roll_check's physical plausibility checks.
The shared data folder is ../shared/data (override: DDYN_SHARED_DATA).
Run:   .venv/bin/python examples/07_putnam_roll.py [--out out/examples/07]
Takes a few seconds; writes OUT/roll.png.
"""
import argparse
from pathlib import Path

import numpy as np

import ddyn
from ddyn.data.roll_check import check_dataset
from ddyn.paths import shared_data_dir

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", default="out/examples/07")
args = parser.parse_args()

path = shared_data_dir() / "real" / "Putnam_park2023_run4_2.csv"
if not path.is_file():
    raise SystemExit(f"{path} is missing: set DDYN_SHARED_DATA to the shared data folder")
log = ddyn.load_log(path)      # a RACECAR CSV: vehicle av21 unless another is given
roll = log.column("roll")
speed = log.column("vx")
print(f"{path.name}: {len(log)} rows kept at {1 / log.sample_time:g} Hz, {len(np.unique(log.segment))} segment(s), "
      f"vehicle {log.vehicle}; extra columns: {', '.join(sorted(log.extras))}")
print(f"vx {speed.min():.1f} to {speed.max():.1f} m/s; roll {roll.min():+.3f} to {roll.max():+.3f} rad "
      f"({np.degrees(roll.min()):+.0f} to {np.degrees(roll.max()):+.0f} deg)")
v = check_dataset(log, "roll")
print(f"roll |p99.9| {v['abs_p999_rad']:.3f} rad (limit {v['thresholds']['max_abs_rad']}), rate p99 "
      f"{v['rate_p99_rad_s']:.3f} rad/s (limit {v['thresholds']['max_rate_rad_s']}), drift {v['drift_rad']:+.3f} rad "
      f"(limit {v['thresholds']['max_drift_rad']})")
print(f"roll plausible as bank + body roll: {v['plausible']} (failed: {', '.join(v['failed']) or 'none'}); "
      f"{v['reason']}")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)
fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
t = log.time - log.time[0]
ax1.plot(t, roll, lw=0.8)
ax1.axhspan(-v["thresholds"]["max_abs_rad"], v["thresholds"]["max_abs_rad"], color="g", alpha=0.1,
            label="plausible range")
ax1.set_ylabel("roll (rad)")
ax1.legend(loc="upper right")
ax2.plot(t, speed * log.column("omega") / 9.81, lw=0.8)
ax2.set_ylabel("vx omega (g)")
ax2.set_xlabel("time (s)")
fig.tight_layout()
fig.savefig(out / "roll.png", dpi=100)
print(f"wrote {out / 'roll.png'}")
