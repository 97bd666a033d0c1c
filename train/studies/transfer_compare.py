"""`python -m ddyn.studies.transfer_compare OLD NEW`: two runs of `ddyn study transfer` compared figure by figure.

OLD and NEW are folders holding one output folder per study run (transfer, transfer_swap, transfer_clean, ...: the
--out names of results/ddm_transfer.json's commands; any name), each with its results.json. For every study present
in both, every figure of the model trained on the first track scored on the other (A other) and of FTHD and the model
from scratch at each fraction, on vx, vy, omega, ADE, FDE: NEW's seed mean against OLD's seed range. A figure is
better (worse) beyond the seed spread when NEW's mean lies below (above) OLD's whole range and OLD's mean outside
NEW's. With --own the same model on its own track's last 20 % (A own) counts too: a candidate setting that carries
to the other track by fitting its own worse is not better (issue 36: neither error worse than the defaults').
OLD or NEW may name several folders joined by commas (e.g. `defaults,more/defaults`): each study's runs are pooled
over them (the same study with other training seeds, as `--seeds 3 4` adds to `--seeds 0 1 2`) and summarised
again; the settings must agree and no seed may repeat.

How docs/learning.md's "Inputs held to the trained range" tally was made: OLD from the six commands run at cf44030
(before the inputs were held), NEW from the same commands at 2714169 or later. A measurement for the docs, not a test.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

CHANNELS = ("vx", "vy", "omega", "ade", "fde")


def verdict(old: dict, new: dict) -> str:
    """better / worse beyond the seed spread, or within it (old, new: {mean, min, max})."""
    if new["mean"] < old["min"] and old["mean"] > new["max"]:
        return "better"
    if new["mean"] > old["max"] and old["mean"] < new["min"]:
        return "worse"
    return "within"


# what must agree between runs pooled into one study (the seeds differ)
POOLED_KEYS = ("family", "vehicle", "duration", "speed", "swap", "noise_scale")


def _dirs(d) -> list[Path]:
    return [Path(x) for x in str(d).split(",")] if not isinstance(d, (list, tuple)) else [Path(x) for x in d]


def common_studies(old_dir, new_dir) -> list[str]:
    """The study folders (each with a results.json) every folder of both sides holds, by name."""
    names = lambda d: {p.parent.name for p in d.glob("*/results.json")}  # noqa: E731
    sets = [names(d) for d in _dirs(old_dir) + _dirs(new_dir)]
    return sorted(set.intersection(*sets))


def pooled_summary(dirs: list[Path], study: str) -> dict | None:
    """A study's summary, its runs pooled over the folders (one folder: its own summary)."""
    paths = [d / study / "results.json" for d in dirs]
    if not all(p.is_file() for p in paths):
        return None
    results = [json.loads(p.read_text()) for p in paths]
    if len(results) == 1:
        return results[0]["summary"]
    from ddyn.errors import DdynError
    from ddyn.studies.transfer import summarise

    first = results[0]
    for p, r in zip(paths[1:], results[1:]):
        for key in POOLED_KEYS:
            if r.get(key) != first.get(key):
                raise DdynError(f"{p}: {key} is {r.get(key)!r}, not {first.get(key)!r} as in {paths[0]}: not one study")
        for key in ("sets", "ranges", "fractions"):
            if r["settings"].get(key) != first["settings"].get(key):
                raise DdynError(f"{p}: settings.{key} differ from {paths[0]}'s: not one study")
    runs = [run for r in results for run in r["runs"]]
    seeds = [run["seed"] for run in runs]
    if len(set(seeds)) != len(seeds):
        raise DdynError(f"{study}: seed(s) repeat across {', '.join(map(str, dirs))}: {sorted(seeds)}")
    return summarise(runs, first["settings"]["fractions"])


def compare(old_dir, new_dir, studies=None, own: bool = False) -> tuple[list[str], dict]:
    lines, tally = [], {"better": 0, "within": 0, "worse": 0}
    for study in (studies if studies is not None else common_studies(old_dir, new_dir)):
        so, sn = pooled_summary(_dirs(old_dir), study), pooled_summary(_dirs(new_dir), study)
        if so is None or sn is None:
            continue
        items = ([("A own", so["own"], sn["own"])] if own else []) + [("A other", so["other"], sn["other"])]
        for fo, fn in zip(so["fractions"], sn["fractions"]):
            items += [(f"fthd {fo['fraction']:.0%}", fo["fthd"], fn["fthd"]),
                      (f"scratch {fo['fraction']:.0%}", fo["scratch"], fn["scratch"])]
        for label, o, n in items:
            cells = []
            for c in CHANNELS:
                v = verdict(o[c], n[c])
                tally[v] += 1
                cells.append(f"{c} {o[c]['mean']:.3g}->{n[c]['mean']:.3g}" + ("" if v == "within" else f" {v.upper()}"))
            lines.append(f"{study:28s} {label:12s} " + "; ".join(cells))
    return lines, tally


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ddyn.studies.transfer_compare", description=__doc__.split("\n")[0])
    ap.add_argument("old", help="folder of study runs (several joined by commas: their runs pooled)")
    ap.add_argument("new", help="the same for the candidate")
    ap.add_argument("--own", action="store_true", help="count the own-track figures (A own) too")
    args = ap.parse_args(argv)
    for d in _dirs(args.old) + _dirs(args.new):
        if not d.is_dir():
            ap.error(f"{d}: not a folder")
    from ddyn.errors import DdynError

    try:
        lines, tally = compare(args.old, args.new, own=args.own)
    except DdynError as e:
        ap.error(str(e))
    if not lines:
        ap.error(f"{args.old} and {args.new} hold no study folder (NAME/results.json) of the same name")
    print("\n".join(lines))
    print(f"{sum(tally.values())} figures: {tally['better']} better beyond the seed spread, {tally['within']} within it, "
          f"{tally['worse']} worse")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
