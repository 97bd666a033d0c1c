#!/usr/bin/env bash
# Where the controller step's instructions go on the emulated Cortex-M7 (docs/m7.md): builds the
# profiling variant of the firmware (SysTick interrupt every 250 ticks = 10,000 instructions,
# interrupted PC counted), replays the recorded segment (pass 1) under qemu and prints the share of
# samples per function (arm-none-eabi-nm symbol sizes), largest first.
# usage: scripts/m7_profile.sh [BUILD_DIR] [TOP]   (default build-m7, 25)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$ROOT/build-m7}"; top="${2:-25}"
cmake -S "$ROOT" -B "$dir" -DCMAKE_TOOLCHAIN_FILE="$ROOT/cmake/arm-none-eabi-cortex-m7.cmake" \
  -DCMAKE_BUILD_TYPE=Release >/dev/null
cmake --build "$dir" --target ddyn_m7_controller_profile -j "$(nproc)" >/dev/null
elf="$dir/tests/m7/ddyn_m7_controller_profile.elf"
qemu-system-arm -M mps2-an500 -cpu cortex-m7 -icount shift=0 -nographic -monitor none -serial none \
  -semihosting-config enable=on,target=native -kernel "$elf" > "$dir/m7_profile.txt" 2>&1
arm-none-eabi-nm -S --defined-only "$elf" > "$dir/m7_profile_syms.txt"
python3 - "$dir/m7_profile.txt" "$dir/m7_profile_syms.txt" "$top" <<'PY'
import bisect, sys
samples = [tuple(int(v) for v in line.split()[2:4]) for line in open(sys.argv[1]) if line.startswith("m7: profile ")]
syms = []
for line in open(sys.argv[2]):
    p = line.split()
    if len(p) == 4 and p[2] in "tTwW":
        syms.append((int(p[0], 16) & ~1, int(p[1], 16), p[3]))
syms.sort()
starts = [s[0] for s in syms]
total, per = 0, {}
for addr, n in samples:
    i = bisect.bisect_right(starts, addr) - 1
    name = syms[i][2] if i >= 0 and addr < syms[i][0] + max(syms[i][1], 16) else "?"
    per[name] = per.get(name, 0) + n
    total += n
print(f"{total} samples of 10,000 instructions (pass 1, {total * 1e4 / 1200 / 1e6:.2f} M instructions per period)")
for name, n in sorted(per.items(), key=lambda kv: -kv[1])[:int(sys.argv[3])]:
    print(f"{100.0 * n / total:6.2f} %  {name}")
PY
