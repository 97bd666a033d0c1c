#!/usr/bin/env bash
# Fuzz the CAN frame decoder and the controller's CAN input path (tests/fuzz/fuzz_dbw.c) with
# libFuzzer under AddressSanitizer + UBSan for a bounded time, and report executions and crashes.
#   usage: scripts/fuzz_can.sh [SECONDS]   (default 30; DDYN_FUZZ_SECONDS also sets it)
# The corpus persists in build/fuzz-can/corpus (outside git); crash inputs land in
# build/fuzz-can/ and fail the run. A missing clang/libFuzzer is a failure, not a skip.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
secs="${1:-${DDYN_FUZZ_SECONDS:-30}}"
out="${DDYN_BUILD_DIR:-$ROOT/build}/fuzz-can"
mkdir -p "$out/corpus"
command -v clang >/dev/null || { echo "fuzz: FAIL: clang not installed (scripts/setup.sh installs it)"; exit 1; }
clang -std=c99 -g -O1 -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all \
  -Wall -Wextra -Wpedantic -Wvla -Werror -Wno-unused-parameter \
  -I"$ROOT/c_src/include" -I"$ROOT/c_src/generated/can" \
  "$ROOT/tests/fuzz/fuzz_dbw.c" "$ROOT/c_src/src/dbw.c" "$ROOT/c_src/generated/can/ddyn_can.c" -lm \
  -o "$out/fuzz_dbw" || { echo "fuzz: FAIL: could not build the fuzz target with libFuzzer"; exit 1; }
# Seeds (regenerated each run, never edited by libFuzzer): scripts that drive the monitor to ACTIVE,
# the region random bytes rarely reach: six well-formed frames (op 6, kinds 0-5), a control period
# (op 4, READY), the enable (op 3), a control period (ACTIVE); the second adds a checksum failure
# (a raw frame, op 0, id 0x120 with a wrong checksum) and the recovery.
mkdir -p "$out/seeds"
frames=""; for k in 0 1 2 3 4 5; do frames+="\x06\x0$k\x80\x80\x80\x80\x80\x80\x80\x80\x00"; done
active="$frames\x04\x80\x10\x80\x03\x04\x80\x10\x80"
printf "$active" >"$out/seeds/active"
printf "$active\x00\x20\x01\x08\x01\x02\x03\x04\x05\x06\x07\x00\x00\x04\x80\x10\x80$frames\x04\x80\x10\x80\x03\x04\x80\x10\x80" \
  >"$out/seeds/fail_recover"
log="$out/last-run.log"
( cd "$out" && ./fuzz_dbw -max_total_time="$secs" -print_final_stats=1 -artifact_prefix="$out/" \
    -max_len=512 corpus seeds ) >"$log" 2>&1
rc=$?
runs=$(grep -oE "Done [0-9]+ runs in [0-9]+ second" "$log" | tail -1)
execs=$(grep -oE "stat::number_of_executed_units: *[0-9]+" "$log" | grep -oE "[0-9]+$")
crashes=$(ls "$out"/crash-* "$out"/leak-* "$out"/timeout-* 2>/dev/null | wc -l)
cov=$(grep -oE "cov: [0-9]+ ft: [0-9]+" "$log" | tail -1)
echo "fuzz: ${execs:-?} executions in ${secs} s (${runs:-no summary}), ${cov:-no coverage line}, corpus $(ls "$out/corpus" | wc -l) inputs, crashes found: $crashes"
if [ $rc -ne 0 ] || [ "$crashes" -ne 0 ]; then
  tail -40 "$log"
  echo "fuzz: FAIL (libFuzzer exit $rc; reproduce with $out/fuzz_dbw <crash file>)"
  exit 1
fi
