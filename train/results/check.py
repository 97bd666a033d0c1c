"""Re-run a result file's commands in a fresh temporary folder, read its figures back and compare each with the
committed value within the file's tolerance: one line per figure, PASS or MOVED (old -> new), or FAILED when a
command fails or a figure cannot be read.

The commands run with bash, one after the other, in that folder (a failing command stops the run). `ddyn` and
`python` are this interpreter's (its bin folder goes first on PATH); DDYN_REPO names the repository and
DDYN_SHARED_DATA the shared data, so a command can name their files.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from ddyn.paths import REPO, shared_data_dir
from ddyn.results.files import Figure, ResultFile, parse_json_path


@dataclass(frozen=True)
class Outcome:
    """One figure's verdict: status PASS, MOVED or FAILED; new is None when it could not be read."""
    result: str
    figure: str
    status: str
    old: object
    new: object
    detail: str = ""

    def line(self) -> str:
        where = f"{self.result}.{self.figure}" if self.figure else self.result
        if self.status == "FAILED":
            return f"FAILED {where}: {self.detail}"
        return f"{self.status:6s} {where}: {_fmt(self.old)} -> {_fmt(self.new)}" + (f" ({self.detail})" if self.detail else "")


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


class FigureError(Exception):
    """A figure could not be read from the commands' output."""


def _follow(doc, path: str):
    cur = doc
    for seg in parse_json_path(path):
        if isinstance(seg, tuple):
            key, want = seg
            if not isinstance(cur, list):
                raise FigureError(f"[{key}={want}]: not a list")
            match = [x for x in cur if isinstance(x, dict) and str(x.get(key)) == want]
            if not match:
                raise FigureError(f"no element with {key} = {want!r}")
            cur = match[0]
        elif isinstance(seg, int):
            if not isinstance(cur, list) or not -len(cur) <= seg < len(cur):
                raise FigureError(f"[{seg}]: no such element")
            cur = cur[seg]
        else:
            if not isinstance(cur, dict) or seg not in cur:
                raise FigureError(f"no key {seg!r}")
            cur = cur[seg]
    return cur


def _coerce(f: Figure, raw):
    if f.kind == "label":
        return raw if isinstance(raw, str) else json.dumps(raw)
    if isinstance(raw, bool):
        raw = int(raw)
    if isinstance(raw, str):
        try:
            raw = float(raw.replace(",", ""))
        except ValueError:
            raise FigureError(f"{raw!r} is not a number") from None
    if not isinstance(raw, (int, float)):
        raise FigureError(f"{json.dumps(raw)[:60]} is not a number")
    raw = raw * f.source.get("scale", 1)
    if f.kind == "count":
        if float(raw) != int(raw):
            raise FigureError(f"{raw} is not a whole count")
        return int(raw)
    return float(raw)


def read_figure(f: Figure, folder: Path, stdouts: list[str]):
    """The figure's new value from a command's output (a JSON file in the folder, or a command's stdout)."""
    src = f.source
    if "file" in src:
        p = folder / src["file"]
        try:
            doc = json.loads(p.read_text())
        except OSError:
            raise FigureError(f"{src['file']} was not written") from None
        except json.JSONDecodeError as e:
            raise FigureError(f"{src['file']}: not valid JSON ({e.msg})") from None
        try:
            return _coerce(f, _follow(doc, src["path"]))
        except FigureError as e:
            raise FigureError(f"{src['file']} {src['path']}: {e}") from None
    text = stdouts[src.get("step", -1)]
    found = re.findall(src["stdout"], text, flags=re.MULTILINE)
    how = src.get("reduce", "first")
    if how == "count":
        return len(found)
    if not found:
        raise FigureError(f"stdout of command {src.get('step', -1)} has no match of {src['stdout']!r}")
    values = [_coerce(f, v) for v in found]
    if how == "first":
        return values[0]
    if how == "last":
        return values[-1]
    return max(values) if how == "max" else min(values)


def environment() -> dict:
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["DDYN_REPO"] = str(REPO)
    env.setdefault("DDYN_SHARED_DATA", str(shared_data_dir()))
    env.setdefault("MPLBACKEND", "Agg")
    return env


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1][:200] if lines else "(no output)"


def run_commands(r: ResultFile, folder: Path, log=None) -> tuple[list[str], str | None]:
    """Write the file's files, run its commands in `folder`: (stdout of each command run, failure or None)."""
    for rel, text in r.files.items():
        p = folder / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    env, stdouts = environment(), []
    deadline = time.monotonic() + r.timeout
    for i, cmd in enumerate(r.commands):
        if log:
            log(f"  [{r.name} {i + 1}/{len(r.commands)}] {cmd}")
        try:
            proc = subprocess.run(["bash", "-c", cmd], cwd=folder, env=env, capture_output=True, text=True,
                                  timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            return stdouts, f"command {i} timed out after the file's {r.timeout:g} s: {cmd}"
        stdouts.append(proc.stdout)
        (folder / f".command{i}.log").write_text(proc.stdout + proc.stderr)
        if proc.returncode != 0:
            return stdouts, (f"command {i} exited {proc.returncode}: {cmd}: "
                             f"{_last_line(proc.stderr) if proc.stderr.strip() else _last_line(proc.stdout)}")
    return stdouts, None


def check_result(r: ResultFile, keep: bool = False, log=None) -> list[Outcome]:
    """Re-run one result file and compare its figures; the temporary folder is removed unless `keep`."""
    tmp = tempfile.mkdtemp(prefix=f"ddyn-results-{r.name}-")
    folder = Path(tmp)
    try:
        stdouts, failure = run_commands(r, folder, log)
        if failure:
            return [Outcome(r.name, "", "FAILED", None, None, failure + (f" (folder {folder})" if keep else ""))]
        out = []
        for key, f in r.figures.items():
            try:
                new = read_figure(f, folder, stdouts)
            except FigureError as e:
                out.append(Outcome(r.name, key, "FAILED", f.value, None, str(e)))
                continue
            status = "PASS" if f.within(new) else "MOVED"
            out.append(Outcome(r.name, key, status, f.value, new,
                               f"{f.tolerance_text()}" + ("" if r.holds_ok else "; the file says it does not hold")))
        return out
    finally:
        if not keep:
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
        elif log:
            log(f"  [{r.name}] kept {folder}")
