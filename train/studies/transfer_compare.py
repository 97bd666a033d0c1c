"""`python -m ddyn.studies.transfer_compare OLD NEW`: two runs of `ddyn study transfer` compared figure by figure.

OLD and NEW are folders holding one output folder per study run (transfer, transfer_swap, transfer_clean, ...: the
--out names of results/ddm_transfer.json's commands), each with its results.json. For every study present in both,
every figure of the model trained on the first track scored on the other (A other) and of FTHD and the model from
scratch at each fraction, on vx, vy, omega, ADE, FDE: NEW's seed mean against OLD's seed range. A figure is better
(worse) beyond the seed spread when NEW's mean lies below (above) OLD's whole range and OLD's mean outside NEW's.

How docs/learning.md's "Inputs held to the trained range" tally was made: OLD from the six commands run at cf44030
(before the inputs were held), NEW from the same commands at 2714169 or later. A measurement for the docs, not a test.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

CHANNELS = ("vx", "vy", "omega", "ade", "fde")
STUDIES = ("transfer", "transfer_swap", "transfer_clean", "transfer_clean_swap", "transfer_mujoco_clean",
           "transfer_mujoco_clean_swap")


def verdict(old: dict, new: dict) -> str:
    """better / worse beyond the seed spread, or within it (old, new: {mean, min, max})."""
    if new["mean"] < old["min"] and old["mean"] > new["max"]:
        return "better"
    if new["mean"] > old["max"] and old["mean"] < new["min"]:
        return "worse"
    return "within"


def compare(old_dir: Path, new_dir: Path, studies=STUDIES) -> tuple[list[str], dict]:
    lines, tally = [], {"better": 0, "within": 0, "worse": 0}
    for study in studies:
        po, pn = old_dir / study / "results.json", new_dir / study / "results.json"
        if not (po.is_file() and pn.is_file()):
            continue
        so, sn = json.loads(po.read_text())["summary"], json.loads(pn.read_text())["summary"]
        items = [("A other", so["other"], sn["other"])]
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
    args = ap.parse_args(argv)
    lines, tally = compare(args.old, args.new)
    print("\n".join(lines))
    print(f"{sum(tally.values())} figures: {tally['better']} better beyond the seed spread, {tally['within']} within it, "
          f"{tally['worse']} worse")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
