#!/usr/bin/env bash
# Fails if any of the given static libraries references a heap allocator or exits the process:
# the runtime owns no memory of its own (caller-owned contexts, fixed-size arrays).
set -euo pipefail
forbidden='^(malloc|calloc|realloc|free|aligned_alloc|posix_memalign|memalign|valloc|exit|abort)$'
status=0
for lib in "$@"; do
  hits=$(nm -u "$lib" | awk '{print $NF}' | sed 's/@.*//' | grep -E "$forbidden" || true)
  if [ -n "$hits" ]; then
    echo "FAIL: $(basename "$lib") references: $(echo $hits)"
    status=1
  else
    echo "ok: $(basename "$lib") references no allocator ($(nm -u "$lib" | wc -l) undefined symbols checked)"
  fi
done
exit $status
