#!/usr/bin/env bash
# Every test (the README's second command): Python tests with pytest, the C tests with
# ctest in a normal build (including the virtual-CAN tests in a qemu guest) and in an
# AddressSanitizer + UBSan build, a bounded libFuzzer run of the CAN input path, the
# cross-build of the runtime for a Cortex-M7 and the controller firmware run on an emulated one
# (tests/m7/). Runs all even when one fails; exits non-zero if any failed.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/setup.sh" || exit 1
cd "$ROOT"
status=0

# The tests build into build-test/ (for the fixture network) and the Python tests drive the tools
# there (DDYN_BUILD_DIR): the main job's build/, built for its trained network, is never replaced.
export DDYN_BUILD_DIR="$ROOT/build-test"
echo "== build (release): the C tests and the host tools some Python tests drive ($DDYN_BUILD_DIR)"
bash scripts/build.sh "$DDYN_BUILD_DIR" -DDDYN_NET_EXPORT_DIR="$ROOT/tests/c/generated/net_fixture" || status=1

# LCM's multicast group needs a route for the tests that log over UDP multicast (test_lcm.py,
# test_sil.py's host logger): set one up on loopback when the host has none; failing that, those tests
# fail naming the command (tests/python/conftest.py multicast_route), they never skip
LCM_GROUP=239.255.76.67
if ! ip route get "$LCM_GROUP" >/dev/null 2>&1; then
  ip route add "$LCM_GROUP/32" dev lo 2>/dev/null \
    && echo "== multicast: route for $LCM_GROUP added on lo" \
    || echo "== multicast: no route for $LCM_GROUP and none could be added (ip route add $LCM_GROUP/32 dev lo, as root)"
fi

echo "== Python tests (pytest)"
python -m pytest -q || status=1

echo "== C tests (ctest, release build)"
{ ctest --test-dir "$DDYN_BUILD_DIR" --output-on-failure --output-junit "$DDYN_BUILD_DIR/ctest-junit.xml" \
    && python scripts/check_skips.py ctest "$DDYN_BUILD_DIR/ctest-junit.xml"; } || status=1

echo "== C tests (ctest, AddressSanitizer + UndefinedBehaviorSanitizer build)"
{ bash scripts/build.sh "$ROOT/build-asan" -DDDYN_SANITIZE=ON -DCMAKE_BUILD_TYPE=Debug \
    && ctest --test-dir "$ROOT/build-asan" --output-on-failure --output-junit "$ROOT/build-asan/ctest-junit.xml" \
    && python scripts/check_skips.py ctest "$ROOT/build-asan/ctest-junit.xml"; } || status=1

echo "== fuzz: CAN frame decoder and the controller's CAN input path (libFuzzer + ASan/UBSan, ${DDYN_FUZZ_SECONDS:-30} s)"
bash scripts/fuzz_can.sh || status=1

echo "== C runtime cross-build for a Cortex-M7 (arm-none-eabi-gcc, -Werror)"
{ rm -rf "$ROOT/build-m7" \
    && cmake -S "$ROOT" -B "$ROOT/build-m7" -DCMAKE_TOOLCHAIN_FILE="$ROOT/cmake/arm-none-eabi-cortex-m7.cmake" \
         -DCMAKE_BUILD_TYPE=Release >/dev/null \
    && cmake --build "$ROOT/build-m7" -j "$(nproc)" >/dev/null \
    && for lib in "$ROOT"/build-m7/c_src/libddyn_*.a; do \
         printf '%-28s text data bss: %s\n' "$(basename "$lib")" "$(arm-none-eabi-size -t "$lib" | tail -1 | awk '{print $1, $2, $3}')"; done \
    && echo "Cortex-M7 build: ok" \
    && bash tests/install/check_install.sh "$ROOT/build-m7" "$ROOT/build-m7/install-check" \
         "$ROOT/cmake/arm-none-eabi-cortex-m7.cmake"; } || { echo "Cortex-M7 build: FAILED"; status=1; }

echo "== the controller step on an emulated Cortex-M7 (qemu mps2-an500, -icount shift=0; docs/m7.md)"
{ ctest --test-dir "$ROOT/build-m7" --output-on-failure --output-junit "$ROOT/build-m7/ctest-junit.xml" \
    && python scripts/check_skips.py ctest "$ROOT/build-m7/ctest-junit.xml"; } || status=1

if [ "$status" -eq 0 ]; then echo "== all tests passed"; else echo "== SOME TESTS FAILED"; fi
exit "$status"
