#!/usr/bin/env bash
# Fetch DAQP's pinned source distribution (daqp==0.11.0, whose csrc/ the runtime's QP solver compiles)
# from the package index into DIR (default build/third_party), hash-pinned: cmake/fetch_sdist.py reads
# the index's simple page, downloads the exact file and checks its SHA-256 before it is moved into DIR.
# Nothing of the archive runs (no pip, no build backend). Idempotent: an archive with the right hash is
# kept. Called by cmake/daqp.cmake (cmake/third_party.cmake) when the archive is missing.
# usage: scripts/fetch_daqp.sh [DIR]
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
dir="${1:-$ROOT/build/third_party}"
version=0.11.0
sha=2f27baf18d2acca14186498e651b34e0bed455627e777d3fd8ba655e7e40f920
py="${DDYN_PYTHON:-}"
if [ -z "$py" ]; then
  if [ -x "$ROOT/.venv/bin/python" ]; then py="$ROOT/.venv/bin/python"; else py=python3; fi
fi
"$py" "$ROOT/cmake/fetch_sdist.py" daqp "$version" "$sha" "$dir"
# checked once more here, independently of the fetcher
echo "$sha  $dir/daqp-$version.tar.gz" | sha256sum -c --status || {
  echo "fetch_daqp.sh: daqp-$version.tar.gz does not have SHA-256 $sha" >&2; exit 1; }
