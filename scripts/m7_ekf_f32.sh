#!/usr/bin/env bash
# The EKF in float32 on the emulated Cortex-M7 (docs/m7.md, "float32 instead of double"); not a test.
#  1. ddyn_m7_ekf_f32 (tests/m7/CMakeLists.txt): every EKF call of pass 1 also runs in float32
#     (c_src/src/ekf.c with DDYN_EKF_FLOAT32) from a copy of the double filter's state: the EKF's
#     instructions per controller step in double and float32, and the float32 answer's largest
#     difference per call (state, relative variance, NIS).
#  2. The whole firmware with -DDDYN_EKF_FLOAT32=ON: pass 1's instructions and its commands against the
#     host's double recording (the firmware reports FAIL if they differ beyond its tight tolerance).
# usage: scripts/m7_ekf_f32.sh [BUILD_DIR]   (default build-m7-ekf32; the shadow build uses build-m7)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$ROOT/build-m7-ekf32}"
QEMU=(qemu-system-arm -M mps2-an500 -cpu cortex-m7 -icount shift=0 -nographic -monitor none -serial none
      -semihosting-config enable=on,target=native -kernel)
cmake -S "$ROOT" -B "$ROOT/build-m7" -DCMAKE_TOOLCHAIN_FILE="$ROOT/cmake/arm-none-eabi-cortex-m7.cmake" \
  -DCMAKE_BUILD_TYPE=Release >/dev/null
cmake --build "$ROOT/build-m7" --target ddyn_m7_ekf_f32 -j 2 >/dev/null
"${QEMU[@]}" "$ROOT/build-m7/tests/m7/ddyn_m7_ekf_f32.elf" 2>&1 | grep -E 'ekf_' || true
cmake -S "$ROOT" -B "$dir" -DCMAKE_TOOLCHAIN_FILE="$ROOT/cmake/arm-none-eabi-cortex-m7.cmake" -DCMAKE_BUILD_TYPE=Release \
  -DDDYN_EKF_FLOAT32=ON >/dev/null
cmake --build "$dir" --target ddyn_m7_controller -j 2 >/dev/null
"${QEMU[@]}" "$dir/tests/m7/ddyn_m7_controller.elf" 2>&1 \
  | grep -E 'insn_per_step_m|max_abs_du|outside|status_differs|iterations_differ|PASS|FAIL' || true
