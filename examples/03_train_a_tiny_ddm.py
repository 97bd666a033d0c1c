"""03: train a tiny Deep Dynamics model (DDM) for a few epochs and evaluate it on another track.

Shows: ddyn.simulate for a training log (ETHZ) and a test log (ETHZMobil), ddyn.train (a small network, few
epochs: the project's defaults train far longer), ddyn.load_checkpoint, ddyn.evaluate (one-step RMSE, ADE,
the coefficients the Physics Guard estimates against the vehicle file's truth), and the same errors for a
"nothing changes" predictor as a yardstick.
Run:   .venv/bin/python examples/03_train_a_tiny_ddm.py [--epochs 10] [--out out/examples/03]
Takes about half a minute; writes OUT/train.csv, OUT/test.csv, OUT/ddm.ckpt.
"""
import argparse
from pathlib import Path

import numpy as np

import ddyn

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--epochs", type=int, default=10)
parser.add_argument("--lbfgs", type=int, default=50, help="L-BFGS iterations after Adam (project default 4000)")
parser.add_argument("--out", default="out/examples/03")
args = parser.parse_args()
out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)

train_log = ddyn.save_log(ddyn.simulate("orca_1_43", track="ethz", laps=2, seed=1), out / "train.csv")
test = ddyn.simulate("orca_1_43", track="ethzMobil", laps=1, seed=2)
ddyn.save_log(test, out / "test.csv")

ckpt = ddyn.train(train_log, out / "ddm.ckpt", epochs=args.epochs, hidden=16, lbfgs_iterations=args.lbfgs, seed=0)
print(f"trained a {ckpt.kind.upper()} (history {ckpt.tau} row, {sum(p.numel() for p in ckpt.model.parameters())} "
      f"parameters) in {ckpt.data['training']['seconds']:.1f} s, best validation loss "
      f"{ckpt.data['training']['best_val_loss']:.3e}")

m = ddyn.evaluate(ddyn.load_checkpoint(out / "ddm.ckpt"), test)
# yardstick: predict that vx, vy, omega do not change over one step
nxt = test.transition_index()
still = {ch: float(np.sqrt(np.mean((test.column(ch)[nxt + 1] - test.column(ch)[nxt]) ** 2)))
         for ch in ("vx", "vy", "omega")}
for ch in ("vx", "vy", "omega"):
    print(f"test one-step RMSE {ch:5s} DDM {m['rmse'][ch]:.3e}   nothing-changes {still[ch]:.3e}")
print(f"test ADE {m['ade']:.3e} m, FDE {m['fde']:.3e} m over {m['horizon_s'] * 1000:.0f} ms")
for name in ("Df", "Dr", "Cm1", "Iz"):
    c = m["coefficients"][name]
    print(f"coefficient {name:3s} mean {c['mean']:.4g} (true {c['true']:.4g}, error {100 * c['rel_error']:+.1f} %)")
