"""06: a closed-loop lap of the C MPC on the host.

Shows: ddyn.run_mpc_lap: the host tool ddyn_mpc_lap (built by `bash scripts/build.sh`) runs the car's MPC
(real-time iteration, QP on DAQP) against the simulated 1:43 car (the generated RK4 step, true coefficients)
from near standstill along its racing line; the lap is scored for time and for footprint violations.
Run:   .venv/bin/python examples/06_c_mpc_lap.py [--track ethzMobil] [--seconds 7] [--out out/examples/06]
       (the tools of another build folder: DDYN_BUILD_DIR=build-test .venv/bin/python examples/06_c_mpc_lap.py)
Takes a few seconds; writes OUT/mpc_lap.json and OUT/mpc_lap.png.
"""
import argparse

import ddyn

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--track", default="ethzMobil")
parser.add_argument("--seconds", type=float, default=7.0)
parser.add_argument("--out", default="out/examples/06")
args = parser.parse_args()

r = ddyn.run_mpc_lap(vehicle="orca_1_43", track=args.track, seconds=args.seconds, out_dir=args.out)
c = r["c_mpc"]
laps = ", ".join(f"{t:.3f}" for t in c["lap_times_s"]) or "none"
print(f"{r['vehicle']} on {r['track']}, {c['steps']} steps of the C MPC (horizon {r['settings']['horizon']})")
print(f"lap times {laps} s; violation steps {c['violation_steps']}; closest footprint corner to a bound "
      f"{c['min_boundary_distance_m'] * 1000:.1f} mm")
print(f"QP iterations median {c['qp_iterations_median']:.0f}, max {c['qp_iterations_max']}; status "
      f"{c['status_counts']}; solve time median {c['solve_us']['median']:.0f} us (this machine, not real-time)")
print(f"wrote {args.out}/mpc_lap.json, {args.out}/mpc_lap.png")
