#!/usr/bin/env bash
# Run virtual-CAN test binaries where vcan0 exists.
#   usage: scripts/vcan_guest/run.sh TEST_BINARY [TEST_BINARY ...]
# Each binary gets the interface name as its argument and must exit 0 on success.
# DDYN_VCAN_MODE: auto (default: the host's vcan0 if it exists or can be created, else the
# guest), host, or guest. The guest: build_guest.py (kernel cached in build/vcan-guest) and
# qemu-system-x86_64 in software emulation (DDYN_VCAN_KVM=1 adds -enable-kvm; never by
# default) with a virtual clock driven by the instruction count (-icount shift=4,sleep=off: a
# loaded host slows the guest down but cannot stretch its time between two frames; idle time is
# skipped; DDYN_VCAN_QEMU_CLOCK="" uses the host clock instead). A missing qemu, kernel or
# module is a FAILURE, never a skip.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
CACHE="${DDYN_VCAN_GUEST_DIR:-$ROOT/build/vcan-guest}"
MODE="${DDYN_VCAN_MODE:-auto}"
TIMEOUT="${DDYN_VCAN_TIMEOUT:-300}"
[ $# -ge 1 ] || { echo "usage: $0 TEST_BINARY..." >&2; exit 2; }

host_has_vcan() {
  [ -e /sys/class/net/vcan0 ] && { ip link set up vcan0 2>/dev/null || true; return 0; }
  ip link add dev vcan0 type vcan 2>/dev/null && ip link set vcan0 mtu 72 && ip link set up vcan0 2>/dev/null
}

if [ "$MODE" = host ] || { [ "$MODE" = auto ] && host_has_vcan; }; then
  echo "vcan: running on the host's vcan0"
  status=0
  for t in "$@"; do "$t" vcan0 || status=1; done
  exit $status
fi

command -v qemu-system-x86_64 >/dev/null || { echo "vcan: FAIL: qemu-system-x86_64 not installed (scripts/setup.sh installs qemu-system-x86)"; exit 1; }
mkdir -p "$CACHE"
initramfs="$CACHE/initramfs-$$.cpio.gz"
trap 'rm -f "$initramfs"' EXIT
kernel="$(python3 "$ROOT/scripts/vcan_guest/build_guest.py" --cache "$CACHE" --initramfs "$initramfs" "$@")" \
  || { echo "vcan: FAIL: could not build the guest"; exit 1; }
accel=()
[ "${DDYN_VCAN_KVM:-0}" = 1 ] && accel=(-enable-kvm)
log="$CACHE/last-run.log"
echo "vcan: booting $(basename "$kernel") in qemu (software emulation) with $# test binary(ies)"
start=$(date +%s.%N)
timeout "$TIMEOUT" qemu-system-x86_64 "${accel[@]}" -m 256M -smp 1 ${DDYN_VCAN_QEMU_CLOCK:--icount shift=4,sleep=off} -nodefaults -no-reboot \
  -display none -serial stdio -monitor none \
  -kernel "$kernel" -initrd "$initramfs" \
  -append "console=ttyS0 quiet loglevel=3 panic=-1 rdinit=/init" </dev/null >"$log" 2>&1
qrc=$?
end=$(date +%s.%N)
tr -d '\r' <"$log" | grep -v '^$'
echo "vcan: guest ran $(awk "BEGIN{printf \"%.1f\", $end-$start}") s (qemu exit $qrc)"
if [ $qrc -eq 124 ]; then echo "vcan: FAIL: the guest timed out after ${TIMEOUT}s"; exit 1; fi
if grep -q "DDYN_GUEST_EXIT: 0" "$log"; then exit 0; fi
echo "vcan: FAIL: the guest did not report success (log: $log)"
exit 1
