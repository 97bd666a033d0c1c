#!/usr/bin/env bash
# Regenerate tests/m7/generated/controller_segment.c: the closed-loop segment the Cortex-M7 firmware
# replays (docs/m7.md). A host build with the firmware's network (tests/m7/generated/net_m7) runs the
# controller bench (c_src/tools/controller_bench.c) on its stdin set-up (ddyn.bench.controller:
# orca_1_43 on ETHZ, seed 1) and records its first 1,200 periods (24 s, 2.2 laps).
# usage: scripts/m7_record.sh [BUILD_DIR]   (default build-m7-host)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$ROOT/build-m7-host}"
PY="$ROOT/.venv/bin/python"
cmake -S "$ROOT" -B "$dir" -DCMAKE_BUILD_TYPE=Release -DDDYN_BUILD_TESTS=OFF -DDDYN_WITH_LCM=OFF \
  -DDDYN_NET_EXPORT_DIR="$ROOT/tests/m7/generated/net_m7" >/dev/null
cmake --build "$dir" --target ddyn_controller_bench -j "$(nproc)" >/dev/null
"$PY" -c 'from ddyn.bench.controller import controller_setup; print(controller_setup(), end="")' \
  | "$dir/c_src/ddyn_controller_bench" 1200 1 "$ROOT/tests/m7/generated/controller_segment.c" 1200 \
  | grep -E '^# (laps|max_raceline_offset_m|steps_DDYN_CTRL_(SAFE_COMMAND|OUT_OF_RANGE|MPC_NOT_CONVERGED)) '
echo "wrote $ROOT/tests/m7/generated/controller_segment.c"
