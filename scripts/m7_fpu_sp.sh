#!/usr/bin/env bash
# The controller firmware (tests/m7/) built for a Cortex-M7 with a single-precision FPU only
# (-mfpu=fpv5-sp-d16: every double operation becomes a libgcc soft-float call), run under qemu on the
# first 100 periods of the recorded segment (and 20 with every QP at its cap): what double costs on
# such a part (docs/m7.md). Not a test: the instruction counts exceed the target by far.
# usage: scripts/m7_fpu_sp.sh [BUILD_DIR]   (default build-m7-sp)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$ROOT/build-m7-sp}"
cmake -S "$ROOT" -B "$dir" -DCMAKE_TOOLCHAIN_FILE="$ROOT/cmake/arm-none-eabi-cortex-m7.cmake" -DCMAKE_BUILD_TYPE=Release \
  "-DCMAKE_C_FLAGS=-mcpu=cortex-m7 -mthumb -mfpu=fpv5-sp-d16 -mfloat-abi=hard -ffunction-sections -fdata-sections -DM7_MAX_STEPS=100 -DM7_CAP_STEPS=20" >/dev/null
cmake --build "$dir" --target ddyn_m7_controller -j "$(nproc)" >/dev/null
qemu-system-arm -M mps2-an500 -cpu cortex-m7 -icount shift=0 -nographic -monitor none -serial none \
  -semihosting-config enable=on,target=native -kernel "$dir/tests/m7/ddyn_m7_controller.elf" 2>&1 \
  | grep -E 'insn_per_step|periods|FAIL|max_abs_du' || true
