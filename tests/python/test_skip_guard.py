"""The skip policy (tests/skip_allowlist.txt): a skipped test fails pytest and ctest runs unless listed."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import check_skips

REPO = Path(__file__).resolve().parents[2]


def _run_pytest(tmp_path: Path, env_extra: dict[str, str]) -> subprocess.CompletedProcess:
    (tmp_path / "test_some.py").write_text("import pytest\n\ndef test_skips():\n    pytest.skip('no data')\n\n"
                                           "def test_passes():\n    pass\n")
    env = {k: v for k, v in os.environ.items() if k != "DDYN_ALLOW_SKIPS"}
    env.update(PYTHONPATH=f"{REPO / 'tests' / 'python'}{os.pathsep}{REPO / 'scripts'}", **env_extra)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "skip_guard", "-p", "no:cacheprovider",
                           str(tmp_path / "test_some.py")], cwd=tmp_path, env=env, capture_output=True, text=True)


def test_a_skipped_pytest_test_fails_the_run(tmp_path):
    r = _run_pytest(tmp_path, {})
    assert r.returncode == 1, r.stdout
    assert "SKIPPED TESTS FAIL THE RUN" in r.stdout and "test_skips" in r.stdout


def test_allow_skips_for_local_runs(tmp_path):
    assert _run_pytest(tmp_path, {"DDYN_ALLOW_SKIPS": "1"}).returncode == 0


def test_allowlist_entries_match_by_glob(tmp_path):
    allow = tmp_path / "allow.txt"
    allow.write_text("# comment\npytest tests/python/test_sil.py::test_host_*  # no multicast route\n"
                     "ctest fsim.Track.*  # why\n")
    assert check_skips.unexpected("pytest", ["tests/python/test_sil.py::test_host_logger", "x::y"], allow) == ["x::y"]
    assert check_skips.unexpected("ctest", ["fsim.Track.Loads", "fsim.Plant.Step"], allow) == ["fsim.Plant.Step"]
    allow.write_text("pytest\n")
    try:
        check_skips.allowlist("pytest", allow)
    except SystemExit as e:
        assert "malformed" in str(e)
    else:
        raise AssertionError("a malformed entry must be an error")


def test_ctest_junit_skips_are_found(tmp_path):
    junit = tmp_path / "j.xml"
    junit.write_text('<?xml version="1.0"?><testsuite><testcase name="fsim.A.ok" status="run"/>'
                     '<testcase name="fsim.A.gone" status="run"><skipped message="SKIP_REGULAR_EXPRESSION matched"/>'
                     '</testcase><testcase name="vcan_guest" status="notrun"/></testsuite>')
    assert check_skips.ctest_skipped(junit) == ["fsim.A.gone", "vcan_guest"]
    assert check_skips.main(["ctest", str(junit)]) == 1


def test_the_committed_allowlist_parses():
    check_skips.allowlist("pytest")
    check_skips.allowlist("ctest")
