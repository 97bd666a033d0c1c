#!/usr/bin/env bash
# Fetch DAQP's pinned source distribution (daqp==0.11.0, whose csrc/ the runtime's QP solver compiles)
# with pip from the configured package index into DIR (default build/third_party) and check its SHA-256.
# Idempotent: an archive with the right hash is kept. Called by cmake/daqp.cmake when the archive is
# missing, and by scripts/setup.sh. usage: scripts/fetch_daqp.sh [DIR]
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
dir="${1:-$ROOT/build/third_party}"
version=0.11.0
sha=2f27baf18d2acca14186498e651b34e0bed455627e777d3fd8ba655e7e40f920
archive="$dir/daqp-$version.tar.gz"
mkdir -p "$dir"
if [ -f "$archive" ] && echo "$sha  $archive" | sha256sum -c --status; then
  exit 0
fi
rm -f "$archive"
py="${DDYN_PYTHON:-}"
if [ -z "$py" ]; then
  if [ -x "$ROOT/.venv/bin/python" ]; then py="$ROOT/.venv/bin/python"; else py=python3; fi
fi
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$py" -m pip download "daqp==$version" --no-binary :all: --no-deps -d "$tmp" >/dev/null
echo "$sha  $tmp/daqp-$version.tar.gz" | sha256sum -c --status || {
  echo "fetch_daqp.sh: daqp-$version.tar.gz does not have SHA-256 $sha" >&2; exit 1; }
mv "$tmp/daqp-$version.tar.gz" "$archive"
