#!/usr/bin/env bash
# Install a configured ddyn build into a fresh prefix and build (and on the host run) a consumer
# project against the installed tree only: find_package(ddyn), ddyn:: targets, pkg-config file.
# usage: check_install.sh BUILD_DIR WORK_DIR [CMAKE_TOOLCHAIN_FILE]
set -euo pipefail
build="$1"; work="$2"; toolchain="${3:-}"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
rm -rf "$work"; mkdir -p "$work"
cmake --install "$build" --prefix "$work/prefix" >/dev/null
for f in include/ddyn/controller.h include/ddyn_models.h include/ddyn_net_config.h include/ddyn_can.h \
         lib/libddyn_runtime.a lib/libddyn_controller.a lib/libddyn_guard_net.a lib/libddyn_dbw.a \
         lib/libddyn_can_frames.a lib/cmake/ddyn/ddynConfig.cmake lib/cmake/ddyn/ddynTargets.cmake \
         lib/pkgconfig/ddyn.pc; do
  [ -f "$work/prefix/$f" ] || { echo "check_install: $f not installed" >&2; exit 1; }
done
args=(-S "$here/consumer" -B "$work/consumer" -DCMAKE_PREFIX_PATH="$work/prefix" -DCMAKE_BUILD_TYPE=Release)
[ -n "$toolchain" ] && args+=(-DCMAKE_TOOLCHAIN_FILE="$toolchain")
cmake "${args[@]}" >/dev/null
cmake --build "$work/consumer" >/dev/null
if [ -z "$toolchain" ]; then
  # the car's controller executable and its example unit and configuration (docs/deploy.md)
  for f in bin/ddyn_controller share/ddyn/ddyn-controller.service share/ddyn/controller.example.json; do
    [ -f "$work/prefix/$f" ] || { echo "check_install: $f not installed" >&2; exit 1; }
  done
  keys="$("$work/prefix/bin/ddyn_controller" --keys)" \
    || { echo "check_install: the installed ddyn_controller does not run" >&2; exit 1; }
  grep -q '^control.period ' <<<"$keys" \
    || { echo "check_install: the installed ddyn_controller does not list its configuration keys" >&2; exit 1; }
  "$work/consumer/consumer"
  # the pkg-config file alone is enough to compile and link the same consumer
  PKG_CONFIG_PATH="$work/prefix/lib/pkgconfig" cc -std=c99 "$here/consumer/consumer.c" \
    $(PKG_CONFIG_PATH="$work/prefix/lib/pkgconfig" pkg-config --cflags --libs ddyn) -o "$work/consumer-pc"
  "$work/consumer-pc" >/dev/null
  echo "check_install: host consumer built with find_package and with pkg-config, and ran"
else
  echo "check_install: consumer built against the installed tree with $(basename "$toolchain")"
fi
