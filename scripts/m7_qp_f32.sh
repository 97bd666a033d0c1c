#!/usr/bin/env bash
# The controller firmware (tests/m7/) with the MPC's QP (DAQP and its workspace) in float32
# (-DDDYN_QP_FLOAT32=ON: DAQP_SINGLE_PRECISION), on the same double-precision FPU (fpv5-d16), under qemu
# on the recorded segment: instructions against the double build and how far its commands are from the
# host's double ones (docs/m7.md, "float32 instead of double"). Not a test: the firmware reports FAIL
# because its commands are compared with the double recording at 1e-6.
# usage: scripts/m7_qp_f32.sh [BUILD_DIR]   (default build-m7-f32)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$ROOT/build-m7-f32}"
cmake -S "$ROOT" -B "$dir" -DCMAKE_TOOLCHAIN_FILE="$ROOT/cmake/arm-none-eabi-cortex-m7.cmake" -DCMAKE_BUILD_TYPE=Release \
  -DDDYN_QP_FLOAT32=ON >/dev/null
cmake --build "$dir" --target ddyn_m7_controller -j "$(nproc)" >/dev/null
qemu-system-arm -M mps2-an500 -cpu cortex-m7 -icount shift=0 -nographic -monitor none -serial none \
  -semihosting-config enable=on,target=native -kernel "$dir/tests/m7/ddyn_m7_controller.elf" 2>&1 \
  | grep -E 'insn|periods|max_abs_du|sizeof_ddyn_ctrl' || true
