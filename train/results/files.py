"""A result file: one headline figure (or a few from one run) as a small JSON summary with the commands that
made it. Loaded and validated here; every error is one line naming the file and the key (a DdynError).

The format (results/README.md has it with an example):

    name        the file's stem
    title       what was measured, short (the README table's first column)
    summary     the README's "measured" text: a format string over the figures, e.g. "omega {raw:.3f} rad/s"
    figures     {key: figure}; a figure is {value, unit, tolerance, source} plus optional kind, about, claimed
    commands    the command lines that make it, in order, run by bash in one fresh folder (prerequisites first)
    files       optional {relative path: text} written into that folder before the commands (a config file)
    fast        true when the commands re-run in under about 60 s on the 2-core machine after the test build
    holds       {"status": "holds" | "does not hold", "why": one line}
    doc         the doc that explains it: "docs/FILE.md" or "docs/FILE.md#anchor" (checked to exist)
    measured    {"date": "YYYY-MM-DD", "commit": "abc1234", "how": "re-measured" | "transcribed", "note": ...}
    readme      {"row": N, "command": "the short command shown"} to put it in the README's table; null: not there
    timeout     optional seconds the checker allows the commands (default 3600)
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.paths import REPO

RESULTS_DIR = REPO / "results"

KINDS = ("value", "count", "ratio", "label")
TOLERANCES = ("abs", "rel", "exact", "plusminus")
REDUCE = ("first", "last", "max", "min", "count")
HOLDS = ("holds", "does not hold")
HOW = ("re-measured", "transcribed")
TOP_KEYS = {"name", "title", "summary", "figures", "commands", "files", "fast", "holds", "doc", "measured",
            "readme", "timeout", "note"}
REQUIRED = ("name", "title", "summary", "figures", "commands", "fast", "holds", "doc", "measured")
FIGURE_KEYS = {"value", "unit", "tolerance", "source", "kind", "about", "claimed"}
SOURCE_KEYS = {"file", "path", "stdout", "step", "reduce", "scale"}
MAX_TITLE, MAX_MEASURED = 140, 420


@dataclass(frozen=True)
class Figure:
    key: str
    value: float | int | str
    unit: str
    tolerance: dict          # exactly one of abs, rel, exact, plusminus
    source: dict             # {"file", "path"} or {"stdout", "step", "reduce"}; optional "scale"
    kind: str = "value"      # value, count (an integer), ratio (timings are only compared as ratios), label (text)
    about: str = ""
    claimed: float | int | str | None = None   # what the README once claimed, where the figure no longer holds

    def within(self, new) -> bool:
        """Is `new` within this figure's tolerance of the committed value?"""
        tol = self.tolerance
        if self.kind == "label" or "exact" in tol:
            return new == self.value
        if not isinstance(new, (int, float)) or isinstance(new, bool) or not math.isfinite(new):
            return False
        diff = abs(new - self.value)
        if "abs" in tol:
            return diff <= tol["abs"]
        if "rel" in tol:
            return diff <= tol["rel"] * abs(self.value)
        return diff <= tol["plusminus"]

    def tolerance_text(self) -> str:
        (k, v), = self.tolerance.items()
        unit = "" if self.unit in ("", "1") else f" {self.unit}"
        return {"abs": f"+-{v:g}{unit}", "rel": f"+-{100 * v:g} %", "exact": "exact",
                "plusminus": f"+-{v}"}[k]


@dataclass(frozen=True)
class ResultFile:
    path: Path
    name: str
    title: str
    summary: str
    figures: dict[str, Figure]
    commands: tuple[str, ...]
    fast: bool
    holds: str
    holds_why: str
    doc: str
    measured: dict
    readme: dict | None = None
    files: dict[str, str] = field(default_factory=dict)
    timeout: float = 3600.0
    note: str = ""

    @property
    def holds_ok(self) -> bool:
        return self.holds == "holds"

    def measured_text(self) -> str:
        """The README's "measured" column: the summary with the figures filled in (and the verdict if broken)."""
        text = render_summary(self.summary, {k: f.value for k, f in self.figures.items()}, self.path)
        if not self.holds_ok:
            text = f"**does not hold**: {self.holds_why} ({text})"
        return text


def _err(path: Path, key: str, message: str) -> DdynError:
    return DdynError(f"{_show(path)}: {key}: {message}")


def _show(path: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(REPO))
    except ValueError:
        return str(path)


def _type(path, key, value, types, what):
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in _tuple(types)):
        raise _err(path, key, f"expected {what}, got {json.dumps(value)[:60]}")
    return value


def _tuple(types):
    return types if isinstance(types, tuple) else (types,)


def _text(path, key, value, limit: int | None = None) -> str:
    _type(path, key, value, str, "a string")
    if not value.strip():
        raise _err(path, key, "empty")
    if "\n" in value:
        raise _err(path, key, "expected one line")
    if limit and len(value) > limit:
        raise _err(path, key, f"{len(value)} characters; at most {limit}")
    return value


def _unknown(path, key, raw: dict, known: set) -> None:
    extra = sorted(set(raw) - known)
    if extra:
        raise _err(path, f"{key}{extra[0]}" if key else extra[0], f"unknown key; expected one of {', '.join(sorted(known))}")


def _number(path, key, value, minimum=None):
    _type(path, key, value, (int, float), "a number")
    if not math.isfinite(value) or (minimum is not None and value < minimum):
        raise _err(path, key, f"expected a finite number{'' if minimum is None else f' >= {minimum}'}, got {value}")
    return value


def _figure(path: Path, key: str, raw) -> Figure:
    where = f"figures.{key}"
    _type(path, where, raw, dict, "an object {value, unit, tolerance, source}")
    _unknown(path, where + ".", raw, FIGURE_KEYS)
    for k in ("value", "unit", "tolerance", "source"):
        if k not in raw:
            raise _err(path, f"{where}.{k}", "missing")
    kind = raw.get("kind", "value")
    if kind not in KINDS:
        raise _err(path, f"{where}.kind", f"expected one of {', '.join(KINDS)}, got {kind!r}")
    value = raw["value"]
    if kind == "label":
        _type(path, f"{where}.value", value, str, "a string (kind label)")
    elif kind == "count":
        _type(path, f"{where}.value", value, int, "an integer (kind count)")
    else:
        _number(path, f"{where}.value", value)
    _type(path, f"{where}.unit", raw["unit"], str, "a string (\"1\" for a pure number)")
    tol = _type(path, f"{where}.tolerance", raw["tolerance"], dict, "an object with one of abs, rel, exact, plusminus")
    if len(tol) != 1 or next(iter(tol)) not in TOLERANCES:
        raise _err(path, f"{where}.tolerance", f"expected exactly one of {', '.join(TOLERANCES)}, got {sorted(tol)}")
    (tk, tv), = tol.items()
    if tk == "exact":
        if tv is not True:
            raise _err(path, f"{where}.tolerance.exact", "expected true")
    elif tk == "plusminus":
        _type(path, f"{where}.tolerance.plusminus", tv, int, "a non-negative integer")
        if tv < 0:
            raise _err(path, f"{where}.tolerance.plusminus", "expected a non-negative integer")
    else:
        _number(path, f"{where}.tolerance.{tk}", tv, 0)
    if kind == "count" and tk not in ("exact", "plusminus"):
        raise _err(path, f"{where}.tolerance", "a count takes an exact or plusminus tolerance")
    if kind == "label" and tk != "exact":
        raise _err(path, f"{where}.tolerance", "a label takes the exact tolerance")
    if kind == "ratio" and tk == "plusminus":
        raise _err(path, f"{where}.tolerance", "a ratio takes an abs or rel tolerance")
    src = _type(path, f"{where}.source", raw["source"], dict, "an object {file, path} or {stdout}")
    _unknown(path, f"{where}.source.", src, SOURCE_KEYS)
    if ("file" in src) == ("stdout" in src):
        raise _err(path, f"{where}.source", "expected either file (with path) or stdout (a regular expression)")
    if "file" in src:
        _text(path, f"{where}.source.file", src["file"])
        if Path(src["file"]).is_absolute() or ".." in Path(src["file"]).parts:
            raise _err(path, f"{where}.source.file", "expected a path inside the command's folder")
        _text(path, f"{where}.source.path", src.get("path"))
        parse_json_path(src["path"], path, f"{where}.source.path")
    else:
        _text(path, f"{where}.source.stdout", src["stdout"])
        try:
            groups = re.compile(src["stdout"]).groups
        except re.error as e:
            raise _err(path, f"{where}.source.stdout", f"not a regular expression: {e}") from None
        if groups != 1:
            raise _err(path, f"{where}.source.stdout", f"expected one capture group, got {groups}")
    if src.get("reduce", "first") not in REDUCE:
        raise _err(path, f"{where}.source.reduce", f"expected one of {', '.join(REDUCE)}")
    if "step" in src:
        _type(path, f"{where}.source.step", src["step"], int, "an integer (index into commands)")
    if "scale" in src:
        _number(path, f"{where}.source.scale", src["scale"])
    claimed = raw.get("claimed")
    if claimed is not None and not isinstance(claimed, (int, float, str)):
        raise _err(path, f"{where}.claimed", "expected a number or a string")
    about = raw.get("about", "")
    if about:
        _text(path, f"{where}.about", about)
    return Figure(key, value, raw["unit"], dict(tol), dict(src), kind, about, claimed)


_SEG = re.compile(r"([^.\[\]]+)|\[(-?\d+)\]|\[([^=\]]+)=([^\]]*)\]")


def parse_json_path(text: str, path: Path | None = None, key: str = "path") -> list:
    """'a.b[0].c[label=raw].d' -> ['a', 'b', 0, 'c', ('label', 'raw'), 'd']."""
    out, pos = [], 0
    while pos < len(text):
        if text[pos] == "." and out:
            pos += 1
        m = _SEG.match(text, pos)
        if not m:
            raise _err(path or Path("?"), key, f"bad JSON path {text!r} at character {pos + 1}")
        name, index, fk, fv = m.groups()
        out.append(name if name is not None else int(index) if index is not None else (fk, fv))
        pos = m.end()
    if not out:
        raise _err(path or Path("?"), key, "empty JSON path")
    return out


def render_summary(summary: str, values: dict, path: Path) -> str:
    """The summary with the figures' values filled in (a format string over the figure keys)."""
    try:
        return summary.format_map(values)
    except KeyError as e:
        raise _err(path, "summary", f"names no figure {e.args[0]!r}") from None
    except (ValueError, IndexError, TypeError) as e:
        raise _err(path, "summary", f"cannot be filled in: {e}") from None


def _doc(path: Path, doc: str, check_links: bool) -> None:
    _text(path, "doc", doc)
    file, _, anchor = doc.partition("#")
    if not file.startswith("docs/") and file not in ("README.md",):
        raise _err(path, "doc", f"expected a file under docs/, got {file!r}")
    if not check_links:
        return
    target = REPO / file
    if not target.is_file():
        raise _err(path, "doc", f"{file} does not exist")
    if anchor and anchor not in heading_anchors(target.read_text()):
        raise _err(path, "doc", f"{file} has no heading with the anchor #{anchor}")


def heading_anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a markdown file's headings (lower case, punctuation dropped, spaces to hyphens)."""
    anchors, seen, fence = set(), {}, False
    for line in markdown.splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
            continue
        m = None if fence else re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower(), flags=re.UNICODE).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


def validate(raw, path: Path, check_links: bool = True) -> ResultFile:
    """A parsed result file checked key by key."""
    path = Path(path)
    _type(path, "(top level)", raw, dict, "an object")
    _unknown(path, "", raw, TOP_KEYS)
    for k in REQUIRED:
        if k not in raw:
            raise _err(path, k, "missing")
    name = _text(path, "name", raw["name"])
    if name != path.stem:
        raise _err(path, "name", f"{name!r} is not the file's stem {path.stem!r}")
    if not re.fullmatch(r"[a-z0-9][a-z0-9_]*", name):
        raise _err(path, "name", "expected lower-case letters, digits and underscores")
    title = _text(path, "title", raw["title"], MAX_TITLE)
    figs = _type(path, "figures", raw["figures"], dict, "an object {key: figure}")
    if not figs:
        raise _err(path, "figures", "empty: a result file holds at least one figure")
    figures = {}
    for key, f in figs.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
            raise _err(path, f"figures.{key}", "expected an identifier (letters, digits, underscores)")
        figures[key] = _figure(path, key, f)
    cmds = _type(path, "commands", raw["commands"], list, "a list of command lines")
    if not cmds:
        raise _err(path, "commands", "empty: name the command(s) that made the figures")
    for i, c in enumerate(cmds):
        _text(path, f"commands[{i}]", c)
    for key, f in figures.items():
        step = f.source.get("step", -1)
        if not -len(cmds) <= step < len(cmds):
            raise _err(path, f"figures.{key}.source.step", f"{step} is not a command's index (0..{len(cmds) - 1})")
    files = _type(path, "files", raw.get("files", {}), dict, "an object {relative path: text}")
    for k, v in files.items():
        _type(path, f"files.{k}", v, str, "the file's text")
        if Path(k).is_absolute() or ".." in Path(k).parts:
            raise _err(path, f"files.{k}", "expected a path inside the command's folder")
    fast = _type(path, "fast", raw["fast"], bool, "true or false")
    holds = _type(path, "holds", raw["holds"], dict, "an object {status, why}")
    _unknown(path, "holds.", holds, {"status", "why"})
    if holds.get("status") not in HOLDS:
        raise _err(path, "holds.status", f"expected one of {', '.join(map(repr, HOLDS))}, got {holds.get('status')!r}")
    why = _text(path, "holds.why", holds.get("why"), 300)
    doc = raw["doc"]
    _doc(path, doc, check_links)
    measured = _type(path, "measured", raw["measured"], dict, "an object {date, commit, how}")
    _unknown(path, "measured.", measured, {"date", "commit", "how", "note"})
    date = _text(path, "measured.date", measured.get("date"))
    if not re.fullmatch(r"\d{4}-\d{2}-\d{2}", date):
        raise _err(path, "measured.date", f"expected YYYY-MM-DD, got {date!r}")
    commit = _text(path, "measured.commit", measured.get("commit"))
    if not re.fullmatch(r"[0-9a-f]{7,40}", commit):
        raise _err(path, "measured.commit", f"expected a commit's hex id, got {commit!r}")
    if measured.get("how") not in HOW:
        raise _err(path, "measured.how", f"expected one of {', '.join(map(repr, HOW))}, got {measured.get('how')!r}")
    if "note" in measured:
        _text(path, "measured.note", measured["note"])
    readme = raw.get("readme")
    if readme is not None:
        _type(path, "readme", readme, dict, "an object {row, command} or null")
        _unknown(path, "readme.", readme, {"row", "command"})
        row = _type(path, "readme.row", readme.get("row"), int, "a positive integer")
        if row < 1:
            raise _err(path, "readme.row", "expected a positive integer")
        _text(path, "readme.command", readme.get("command"), 160)
    timeout = _number(path, "timeout", raw.get("timeout", 3600.0), 1)
    note = raw.get("note", "")
    if note:
        _type(path, "note", note, str, "a string")
    result = ResultFile(path, name, title, _text(path, "summary", raw["summary"]), figures, tuple(cmds), fast,
                        holds["status"], why, doc, dict(measured), readme, dict(files), float(timeout), note)
    measured_text = result.measured_text()
    if readme is not None and len(measured_text) > MAX_MEASURED:
        raise _err(path, "summary", f"the README's measured text is {len(measured_text)} characters; at most "
                                    f"{MAX_MEASURED}")
    return result


def load(path: str | Path, check_links: bool = True) -> ResultFile:
    """One result file, validated (a DdynError naming the file and the key otherwise)."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except OSError as e:
        raise DdynError(f"{_show(path)}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise DdynError(f"{_show(path)}: not UTF-8 text") from None
    except json.JSONDecodeError as e:
        raise DdynError(f"{_show(path)}: not valid JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    return validate(raw, path, check_links)


def load_all(folder: str | Path = RESULTS_DIR, check_links: bool = True) -> list[ResultFile]:
    """Every results/*.json, by name; README rows must be unique."""
    folder = Path(folder)
    results = [load(p, check_links) for p in sorted(folder.glob("*.json"))]
    rows: dict[int, str] = {}
    for r in results:
        if r.readme is not None:
            row = r.readme["row"]
            if row in rows:
                raise _err(r.path, "readme.row", f"{row} is also {rows[row]}'s row")
            rows[row] = r.name
    return results


def by_name(results: list[ResultFile], names: list[str]) -> list[ResultFile]:
    known = {r.name: r for r in results}
    missing = [n for n in names if n not in known]
    if missing:
        raise DdynError(f"no result file named {', '.join(missing)} in {_show(RESULTS_DIR)} "
                        f"(known: {', '.join(sorted(known))})")
    return [known[n] for n in names]
