#!/usr/bin/env bash
# The main job, end to end, on embedded defaults (the README's first command):
# set up, simulate and import datasets, train a Deep Dynamics model and evaluate it
# on another track, generate the model's C code, build it, and check the C model
# against the Python model on every simulated and real row.
# Outputs go to out/ (override with DDYN_OUT). Idempotent.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/setup.sh"
cd "$ROOT"
OUT="${DDYN_OUT:-$ROOT/out}"
SHARED="${DDYN_SHARED_DATA:-$ROOT/../shared/data}"
mkdir -p "$OUT"

step() { printf '\n== %s\n' "$*"; }

step "simulate: 1:43 ORCA car, 3 laps of ETHZ and 2 of ETHZMobil (Euler), 2 of ETHZMobil (RK4, sensor noise)"
ddyn simulate --vehicle orca_1_43 --track ethz --laps 3 --seed 1 -o "$OUT/orca_ethz_euler.csv"
ddyn simulate --vehicle orca_1_43 --track ethzMobil --laps 2 --seed 2 -o "$OUT/orca_ethzMobil_euler.csv"
ddyn simulate --vehicle orca_1_43 --track ethzMobil --laps 2 --method rk4 --noise 1 --seed 2 -o "$OUT/orca_ethzMobil_rk4_noisy.csv"

step "train: Deep Dynamics model on ETHZ; evaluate on ETHZMobil (plots in $OUT/evaluate)"
ddyn train --data "$OUT/orca_ethz_euler.csv" -o "$OUT/ddm_orca.ckpt" --quiet
ddyn evaluate --model "$OUT/ddm_orca.ckpt" --data "$OUT/orca_ethzMobil_euler.csv" --out "$OUT/evaluate"

step "import: the papers' simulated set and the real Indy car log"
ddyn import "$SHARED/reference/DYN-PP-ETHZ.npz" -o "$OUT/dyn_pp_ethz.csv"
ddyn import "$SHARED/real/Putnam_park2023_run4_2.csv" -o "$OUT/putnam.csv"

step "codegen: C code of the model step and Jacobians (CasADi)"
ddyn codegen model
git -C "$ROOT" diff --quiet -- c_src/generated tests/c/generated 2>/dev/null \
  || echo "note: generated code differs from the committed copy (model or vehicle files changed): commit it"

step "export: the trained guard network as fixed-size C weight tables (+ torch.export program)"
ddyn export "$OUT/ddm_orca.ckpt" --out "$OUT/export"

step "build: C runtime with CMake, guard network built for the exported tables"
bash "$ROOT/scripts/build.sh" "$ROOT/build" -DDDYN_NET_EXPORT_DIR="$OUT/export"

step "bench: C guard-net inference and EKF step against PyTorch / numpy+CasADi (median, p99, max)"
ddyn bench runtime --model "$OUT/ddm_orca.ckpt" --data "$OUT/orca_ethzMobil_euler.csv" --out "$OUT/bench/bench.json"

step "crosscheck: generated C model against the Python model"
ddyn codegen check --data "$OUT/orca_ethz_euler.csv" --method euler
ddyn codegen check --data "$OUT/orca_ethzMobil_rk4_noisy.csv" --method rk4
ddyn codegen check --data "$OUT/dyn_pp_ethz.csv" --coeffs reference_dataset
ddyn codegen check --data "$OUT/putnam.csv" --method rk4

step "sil: one lap of ETHZMobil, the plant and the controller (the DDM above) as two processes over vcan"
ddyn sil run --track ethzMobil --vehicle orca_1_43 --model "$OUT/ddm_orca.ckpt" --laps 1 --out "$OUT/sil"

step "diagnose: a noisy log with one unmodelled effect, diagnosed blind (where, which effect, how far)"
# the simulator records its effects in the log's metadata; the diagnosis does not read them (it only echoes
# them under data.effects_in_metadata), so the verdict below is found, not told
ddyn simulate --vehicle orca_1_43 --track ethzMobil --laps 3 --noise 1 --seed 31 --quiet \
  --effects "throttle_delay=0.04" -o "$OUT/orca_hidden_effect.csv"
OMP_NUM_THREADS=1 ddyn gap diagnose --vehicle orca_1_43 --data "$OUT/orca_hidden_effect.csv" --out "$OUT/diagnosis"
echo "the log's hidden effect was: throttle_delay = 0.04 s; report: $OUT/diagnosis/diagnosis.md"

printf '\nmain job done; outputs in %s\n' "$OUT"
