"""`python -m ddyn.studies.transfer_compare OLD NEW`: two runs of `ddyn study transfer` compared figure by figure.

OLD and NEW are folders holding one output folder per study run (transfer, transfer_swap, transfer_clean, ...: the
--out names of results/ddm_transfer.json's commands; any name), each with its results.json. For every study present
in both, every figure of the model trained on the first track scored on the other (A other) and of FTHD and the model
from scratch at each fraction, on vx, vy, omega, ADE, FDE: NEW's seed mean against OLD's seed range. A figure is
better (worse) beyond the seed spread when NEW's mean lies below (above) OLD's whole range and OLD's mean outside
NEW's. With --own the same model on its own track's last 20 % (A own) counts too: a candidate setting that carries
to the other track by fitting its own worse is not better (issue 36: neither error worse than the defaults').

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


def common_studies(old_dir: Path, new_dir: Path) -> list[str]:
    """The study folders (each with a results.json) both hold, by name."""
    names = lambda d: {p.parent.name for p in d.glob("*/results.json")}  # noqa: E731
    return sorted(names(old_dir) & names(new_dir))


def compare(old_dir: Path, new_dir: Path, studies=None, own: bool = False) -> tuple[list[str], dict]:
    lines, tally = [], {"better": 0, "within": 0, "worse": 0}
    for study in (studies if studies is not None else common_studies(old_dir, new_dir)):
        po, pn = old_dir / study / "results.json", new_dir / study / "results.json"
        if not (po.is_file() and pn.is_file()):
            continue
        so, sn = json.loads(po.read_text())["summary"], json.loads(pn.read_text())["summary"]
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
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    ap.add_argument("--own", action="store_true", help="count the own-track figures (A own) too")
    args = ap.parse_args(argv)
    if not (args.old.is_dir() and args.new.is_dir()):
        ap.error(f"{args.old if not args.old.is_dir() else args.new}: not a folder")
    lines, tally = compare(args.old, args.new, own=args.own)
    if not lines:
        ap.error(f"{args.old} and {args.new} hold no study folder (NAME/results.json) of the same name")
    print("\n".join(lines))
    print(f"{sum(tally.values())} figures: {tally['better']} better beyond the seed spread, {tally['within']} within it, "
          f"{tally['worse']} worse")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
