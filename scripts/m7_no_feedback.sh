#!/usr/bin/env bash
# Why the M7 firmware test feeds the host's applied command and MPC plan back each period (docs/m7.md):
# builds the firmware without that feedback (-DM7_NO_FEEDBACK, per-period prints -DM7_DEBUG), replays the
# recorded segment open loop under qemu and summarises |u_m7 - u_host| per period. Not a test.
# usage: scripts/m7_no_feedback.sh [BUILD_DIR]   (default build-m7-nofb)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$ROOT/build-m7-nofb}"
cmake -S "$ROOT" -B "$dir" -DCMAKE_TOOLCHAIN_FILE="$ROOT/cmake/arm-none-eabi-cortex-m7.cmake" -DCMAKE_BUILD_TYPE=Release \
  "-DCMAKE_C_FLAGS=-mcpu=cortex-m7 -mthumb -mfpu=fpv5-d16 -mfloat-abi=hard -ffunction-sections -fdata-sections -DM7_NO_FEEDBACK -DM7_DEBUG=5000 -DM7_CAP_STEPS=1" >/dev/null
cmake --build "$dir" --target ddyn_m7_controller -j "$(nproc)" >/dev/null
qemu-system-arm -M mps2-an500 -cpu cortex-m7 -icount shift=0 -nographic -monitor none -serial none \
  -semihosting-config enable=on,target=native -kernel "$dir/tests/m7/ddyn_m7_controller.elf" > "$dir/m7_no_feedback.txt" 2>&1 || true
# lines "dbg PERIOD st M7 HOST it M7 HOST du DTHROTTLE DSTEERING"
awk '$1 == "dbg" { d = ($10 > $11 ? $10 : $11) + 0; n++;
       if (d > 1e-6 && first == "") first = $2;
       big6 += d > 1e-6; big2 += d > 1e-2; if (d > 1e-2) last2 = $2; if (d > maxd) maxd = d }
     END { printf "periods %d; first period with |du| > 1e-6: %s; periods > 1e-6: %d, > 1e-2: %d (last %s); max |du| %.3g\n",
           n, first, big6, big2, last2, maxd }' "$dir/m7_no_feedback.txt"
awk '$1 == "dbg" && $2 >= 26 && $2 <= 40 { print "  period", $2, "|du|", $10, $11 }' "$dir/m7_no_feedback.txt"
