#!/usr/bin/env bash
# Idempotent set-up: system packages with apt (only those missing), then the pinned
# Python environment in .venv (reinstalled only when requirements.lock or pyproject.toml change).
# Sourced by scripts/main.sh and scripts/test.sh; safe to run on its own.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v cc >/dev/null || missing+=(gcc)
command -v c++ >/dev/null || missing+=(g++)
command -v make >/dev/null || missing+=(make)
command -v pkg-config >/dev/null || missing+=(pkg-config)
dpkg -s libcmocka-dev >/dev/null 2>&1 || missing+=(libcmocka-dev)
dpkg -s libeigen3-dev >/dev/null 2>&1 || missing+=(libeigen3-dev)
# the SIL simulator (firmware_sim/): C++ tests and its JSON metrics/config
dpkg -s libgtest-dev >/dev/null 2>&1 || missing+=(libgtest-dev)
dpkg -s nlohmann-json3-dev >/dev/null 2>&1 || missing+=(nlohmann-json3-dev)
# ddyn_controller's JSON configuration (firmware_sim/controller/controller_config.c; not the runtime core)
dpkg -s libcjson-dev >/dev/null 2>&1 || missing+=(libcjson-dev)
# GLib: liblcm (from the pinned `lcm` wheel) links against it
dpkg -s libglib2.0-0 >/dev/null 2>&1 || missing+=(libglib2.0-0)
# the Cortex-M7 cross-build of the runtime (scripts/test.sh)
command -v arm-none-eabi-gcc >/dev/null || missing+=(gcc-arm-none-eabi)
dpkg -s libnewlib-arm-none-eabi >/dev/null 2>&1 || missing+=(libnewlib-arm-none-eabi)
# the controller firmware on an emulated Cortex-M7 (qemu mps2-an500, tests/m7/, docs/m7.md)
command -v qemu-system-arm >/dev/null || missing+=(qemu-system-arm)
# the virtual-CAN tests: a qemu guest (software emulation) with busybox (scripts/vcan_guest/);
# apt-get download and dpkg-deb fetch its kernel
command -v qemu-system-x86_64 >/dev/null || missing+=(qemu-system-x86)
dpkg -s busybox-static >/dev/null 2>&1 || missing+=(busybox-static)
# the CAN decoder's fuzz target: clang with libFuzzer (scripts/fuzz_can.sh)
command -v clang >/dev/null || missing+=(clang)
ls /usr/lib/llvm-*/lib/clang/*/lib/linux/libclang_rt.fuzzer-x86_64.a >/dev/null 2>&1 || missing+=(libclang-rt-dev)
python3 -c 'import venv, ensurepip' >/dev/null 2>&1 || missing+=(python3-venv)
# PostgreSQL server binaries (/usr/lib/postgresql/<ver>/bin): the shared-study test of ddyn tune starts a throwaway one
dpkg -s postgresql >/dev/null 2>&1 || missing+=(postgresql)
if ((${#missing[@]})); then
  echo "setup: installing system packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PY="${DDYN_PYTHON:-python3}"
if ! "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  echo "setup: warning: $("$PY" --version) found; the pinned torch 2.13.0 CPU build on these machines is for Python 3.11" >&2
fi
if [ ! -x "$ROOT/.venv/bin/python" ]; then
  echo "setup: creating $ROOT/.venv"
  "$PY" -m venv "$ROOT/.venv"
fi
stamp="$(cat "$ROOT/requirements.lock" "$ROOT/pyproject.toml" | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$ROOT/.venv/.ddyn-installed" 2>/dev/null)" != "$stamp" ]; then
  echo "setup: installing pinned Python packages (requirements.lock)"
  # the full resolved set with the sha256 of every file (scripts/lock.sh writes it from requirements.in)
  "$ROOT/.venv/bin/pip" install -q --disable-pip-version-check --require-hashes -r "$ROOT/requirements.lock" 2> >(grep -v "is ignored: it is neither" >&2)
  "$ROOT/.venv/bin/pip" install -q --disable-pip-version-check --no-deps -e "$ROOT" 2> >(grep -v "is ignored: it is neither" >&2)
  echo "$stamp" > "$ROOT/.venv/.ddyn-installed"
fi
export PATH="$ROOT/.venv/bin:$PATH"
