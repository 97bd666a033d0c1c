"""Fail when a test runner skipped a test that is not on tests/skip_allowlist.txt.

Used by scripts/test.sh for ctest (its JUnit report: `ctest --output-junit FILE`) and by
tests/python/conftest.py for pytest. A skip usually means a dependency or data set was missing:
on CI that is a failure, not a pass (allow-list entries say why a skip is legitimate).
"""
from __future__ import annotations

import fnmatch
import os
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ALLOWLIST = Path(__file__).resolve().parents[1] / "tests" / "skip_allowlist.txt"


def allowlist(runner: str, path: Path = ALLOWLIST) -> list[str]:
    """The test-name globs allowed to skip for this runner."""
    globs = []
    for line in path.read_text().splitlines():
        entry = line.split("#", 1)[0].split()
        if not entry:
            continue
        if len(entry) != 2:
            raise SystemExit(f"{path}: malformed entry {line!r} (want: <runner> <glob>  # why)")
        if entry[0] == runner:
            globs.append(entry[1])
    return globs


def unexpected(runner: str, skipped: list[str], path: Path = ALLOWLIST) -> list[str]:
    globs = allowlist(runner, path)
    return [name for name in skipped if not any(fnmatch.fnmatchcase(name, g) for g in globs)]


def ctest_skipped(junit: Path) -> list[str]:
    """Names of the skipped tests in a ctest JUnit report."""
    root = ET.parse(junit).getroot()
    return [case.get("name", "?") for case in root.iter("testcase")
            if case.find("skipped") is not None or case.get("status") in ("notrun", "disabled")]


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] != "ctest":
        print("usage: check_skips.py ctest JUNIT.xml", file=sys.stderr)
        return 2
    skipped = ctest_skipped(Path(argv[1]))
    bad = unexpected("ctest", skipped)
    for name in skipped:
        print(f"check_skips: ctest skipped {name}{'' if name in bad else ' (allow-listed)'}")
    if bad and os.environ.get("DDYN_ALLOW_SKIPS") != "1":
        print(f"check_skips: FAILED: {len(bad)} skipped test(s) not on {ALLOWLIST}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
