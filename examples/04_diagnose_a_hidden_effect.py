"""04: diagnose a log with a hidden effect: which unmodelled effect makes the model wrong, and how large is it?

Shows: ddyn.simulate with an effect the nominal model lacks (by default a 40 ms throttle delay), and
ddyn.diagnose (the sim-to-real gap diagnosis, ddyn.gap, as `ddyn gap diagnose` runs it) against the vehicle
file's nominal model: the calibration it used, the effect it selects, its fitted size, and how much of the
held-out error above the noise floor it removes.
Run:   .venv/bin/python examples/04_diagnose_a_hidden_effect.py [--effect throttle_delay=0.04] [--laps 2]
       [--config FILE|NAME] [--out out/examples/04]
Takes under a minute; writes OUT/hidden.csv and the report OUT/diagnosis/ (diagnosis.json, diagnosis.md, plots).
"""
import argparse
from pathlib import Path

import ddyn

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--effect", default="throttle_delay=0.04", help="the hidden effect, as `ddyn simulate --effects`")
parser.add_argument("--laps", type=float, default=2.0)
parser.add_argument("--config", help="a DiagnosisConfig TOML/JSON file or a shipped config's name (default: the "
                    "defaults, or the settings of a shipped calibration that covers the log)")
parser.add_argument("--out", default="out/examples/04")
args = parser.parse_args()
out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)

log = ddyn.simulate("orca_1_43", track="ethzMobil", laps=args.laps, seed=31, noise=1.0, effects=args.effect)
ddyn.save_log(log, out / "hidden.csv")
print(f"simulated {len(log)} rows ({log.time[-1] - log.time[0]:.1f} s) with the hidden effect {args.effect}")

d = ddyn.diagnose(out / "hidden.csv", "orca_1_43", config=args.config, out_dir=out / "diagnosis")
print(f"calibration: {d['calibration'].get('name') or 'none'} ({d['calibration']['why']})")
print(f"selected: {', '.join(d['selected']) or 'none'} ({d['verdict']})")
for e in d["model"]["effects"]:
    for key, value in e["params"].items():
        print(f"  found {e['effect']}: {key} = {value:.4f} +- {e['uncertainty'][key]:.4f} {e['unit']}")
h, gap = d["model"]["heldout"], d["model"]["gap_closed_pct"]
print("held-out one-step RMSE " + ", ".join(f"{c} {h['rmse_before'][c]:.3e} -> {h['rmse_after'][c]:.3e}"
                                          for c in ("vx", "vy", "omega")))
print(f"gap closed: {'n/a' if gap is None else f'{gap:.1f} %'} of the held-out error above the noise floor")
print(f"wrote {out / 'diagnosis'}/diagnosis.json and diagnosis.md")
