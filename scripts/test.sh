#!/usr/bin/env bash
# Every test (the README's second command): Python tests with pytest, then the C tests
# with ctest in a normal build and in an AddressSanitizer + UBSan build.
# Runs all three even when one fails; exits non-zero if any failed. Idempotent.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/setup.sh" || exit 1
cd "$ROOT"
status=0

echo "== Python tests (pytest)"
python -m pytest -q || status=1

echo "== C tests (ctest, release build)"
{ bash scripts/build.sh "$ROOT/build" -DDDYN_NET_EXPORT_DIR="$ROOT/tests/c/generated/net_fixture" && ctest --test-dir "$ROOT/build" --output-on-failure; } || status=1

echo "== C tests (ctest, AddressSanitizer + UndefinedBehaviorSanitizer build)"
{ bash scripts/build.sh "$ROOT/build-asan" -DDDYN_SANITIZE=ON -DCMAKE_BUILD_TYPE=Debug \
    && ctest --test-dir "$ROOT/build-asan" --output-on-failure; } || status=1

if [ "$status" -eq 0 ]; then echo "== all tests passed"; else echo "== SOME TESTS FAILED"; fi
exit "$status"
