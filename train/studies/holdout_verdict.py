"""`python -m ddyn.studies.holdout_verdict DIR [DIR ...]`: issue 36's selection rule applied to held-out runs.

Each DIR is the output of `ddyn study ddm real --holdout laps|speed ... --seeds ...` (its results.json). The runs are
grouped by the condition they held out (the split's description: a lap, the rows above a speed); in each, every
setting (run name) is compared with the baseline's (--baseline; default ddm_putnam, what `ddyn train --vehicle
av21` trained with until a setting beats it) held-out figures, channel by channel (vx, vy, omega, ADE, FDE):
better or worse beyond the seed spread (ddyn.studies.transfer_compare.verdict: the one mean outside the other's
whole range, both ways) or within it. A setting

- is **rejected** when any held-out figure of any condition is worse beyond the spread, whatever it does in sample;
- **meets the bound target** when on every condition and seed no coefficient sits at a guard bound in more than
  5 % of the held-out samples and the mean Iz lies inside the car's physical range (the papers' Iz range of the
  vehicle file av21, 500-2,000 kg m2);
- is **adoptable** when it is not rejected, meets the bound target and was measured on every condition the
  baseline was.

Beside the baseline, every condition reports the reference "nothing changes" (constant vx, vy and yaw rate,
ddyn.learn.reference) on the same held-out rows, and on which channels each setting beats it. It is reported, not
part of the rule: on the Putnam log it beats nearly every setting on vy and omega held out, the baseline included.

So that a verdict in docs/learning.md is a command's output, not a reading of tables by hand.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.studies.transfer_compare import CHANNELS, verdict

BASELINE = "ddm_putnam"
BOUND_SHARE_MAX = 0.05          # issue 36: no coefficient at a guard bound in more than 5 % of held-out samples
IZ_VEHICLE = "av21"             # whose Iz range is the physical one (the papers' range for this car)


def _read(folder: Path) -> dict:
    path = folder / "results.json"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DdynError(f"{path}: no such file (DIR must be the --out folder of `ddyn study ddm real --holdout "
                        f"laps|speed --seeds ...`)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DdynError(f"{path}: cannot be read: {e}") from None
    if not isinstance(data, dict) or not data.get("holdout_summary") or not data.get("real"):
        raise DdynError(f"{path}: no holdout_summary (a run of `ddyn study ddm real` with --holdout laps or speed)")
    return data


def _read_fields(row: dict, runs: list[dict]) -> None:
    """Every field judge() reads, read once while collecting, so that a broken file is one line naming it."""
    for r in runs:
        for c in r["coefficients"].values():
            float(c.get("at_lower_bound", 0.0))
            float(c.get("at_upper_bound", 0.0))
        if "Iz" in r["coefficients"]:
            float(r["coefficients"]["Iz"]["mean"])
    for c in CHANNELS:
        for k in ("mean", "min", "max"):
            float(row["test"][c][k])


def collect(folders: list[Path]) -> dict:
    """{split description: {run name: {"summary": holdout_summary row, "seeds": [per-seed run records]}}}."""
    splits: dict = {}
    for folder in folders:
        data = _read(folder)
        for row in data["holdout_summary"]:
            try:
                runs = [r for r in data["real"] if r["name"] == row["name"] and "in_sample" in r]
                what = runs[0]["split"]["what"]
                _read_fields(row, runs)
            except (KeyError, IndexError, TypeError, AttributeError) as e:
                raise DdynError(f"{folder / 'results.json'}: run {row.get('name')!r} lacks {e} (not the output of "
                                f"`ddyn study ddm real --holdout ... --seeds ...`)") from None
            if row["name"] in splits.get(what, {}):
                raise DdynError(f"{folder / 'results.json'}: run {row['name']!r} on '{what}' is also in an earlier "
                                f"DIR; give each setting and condition once")
            splits.setdefault(what, {})[row["name"]] = {"summary": row, "seeds": runs, "folder": str(folder)}
    return splits


def _bounds(seeds: list[dict], iz_range: tuple[float, float]) -> dict:
    worst, worst_name, iz = 0.0, None, []
    for r in seeds:
        for name, c in r["coefficients"].items():
            share = c.get("at_lower_bound", 0.0) + c.get("at_upper_bound", 0.0)
            if share > worst:
                worst, worst_name = share, name
        if "Iz" in r["coefficients"]:
            iz.append(r["coefficients"]["Iz"]["mean"])
    iz_ok = all(iz_range[0] <= x <= iz_range[1] for x in iz)
    return {"worst_bound": worst, "worst_coefficient": worst_name, "Iz_means": iz, "Iz_inside": iz_ok,
            "meets": worst <= BOUND_SHARE_MAX and iz_ok}


def reference_of(run: dict) -> dict:
    """The reference's held-out figures on the rows a run was scored on: its split of the Putnam log remade
    (ddyn.studies.ddm.split_real, from the split the run recorded), its history length and its vehicle's horizon."""
    from ddyn.data.importers import load_any
    from ddyn.learn.reference import constant_motion_errors
    from ddyn.model import vehicle as vehicle_mod
    from ddyn.paths import putnam_log
    from ddyn.studies.ddm import HOLDOUT_LAPS, HOLDOUT_SPEED, split_real

    try:
        split, tau, v = run["split"], int(run["tau"]), vehicle_mod.load(run["vehicle"])
        holdout = split["holdout"]
    except (KeyError, TypeError, ValueError) as e:
        raise DdynError(f"run {run.get('name')!r} (seed {run.get('seed')}) lacks {e}: its held-out rows cannot be "
                        f"remade for the reference (not the output of `ddyn study ddm real --holdout ...`)") from None
    src = putnam_log()
    if not src.is_file():
        raise DdynError(f"real log not found: {src} (the reference is scored on the runs' own held-out rows)")
    _, test, _ = split_real(load_any(src, vehicle=v.name), holdout,
                            tuple(split.get("test_laps", HOLDOUT_LAPS)), float(split.get("speed", HOLDOUT_SPEED)))
    r = constant_motion_errors(test, tau, max(1, int(round(v.evaluation_horizon / v.sample_time))))
    return {**r["rmse"], "ade": r["ade"], "fde": r["fde"]}


def references_of(splits: dict, score=None) -> dict:
    """{(condition, run name): the reference on that setting's own held-out windows}: a longer history drops rows
    at each segment's start, so each setting is read against its own. score: reference_of (the default), called once
    per condition, history length and vehicle (each call reads and splits the log)."""
    score = score or reference_of
    cache, out = {}, {}
    for what, runs in splits.items():
        for name, run in runs.items():
            first = run["seeds"][0]
            key = (what, first.get("tau"), first.get("vehicle"))
            if key not in cache:
                cache[key] = score(first)
            out[(what, name)] = cache[key]
    return out


def judge(splits: dict, baseline: str = BASELINE, iz_range: tuple[float, float] = (500.0, 2000.0),
          references: dict | None = None) -> dict:
    """Per setting: per condition the channel verdicts against the baseline and the bound check; overall flags.
    references: {(condition, run name): the reference's figures on that run's held-out windows} (reference_of)."""
    settings: dict = {}
    for what, runs in splits.items():
        if baseline not in runs:
            raise DdynError(f"no baseline run {baseline!r} held out on '{what}' (in {', '.join(sorted(runs))}); "
                            f"add its DIR (`ddyn study ddm real ... --only {baseline} --seeds ...`)")
        base = runs[baseline]["summary"]["test"]
        for name, run in runs.items():
            ref = (references or {}).get((what, name))
            test = run["summary"]["test"]
            channels = {c: {"baseline": base[c], "setting": test[c], "verdict": verdict(base[c], test[c])}
                        for c in CHANNELS}
            settings.setdefault(name, {})[what] = {"seeds": run["summary"]["seeds"], "channels": channels,
                                                   "bounds": _bounds(run["seeds"], iz_range)}
            if ref is not None:
                # beats "nothing changes" on a channel: its worst seed below the reference
                settings[name][what]["reference"] = ref
                settings[name][what]["beats_reference"] = {c: test[c]["max"] < ref[c] for c in CHANNELS}
    conditions = list(splits)
    out = {}
    for name, per in settings.items():
        worse = [f"{c} ({what})" for what, v in per.items() for c, x in v["channels"].items()
                 if x["verdict"] == "worse"]
        better = [f"{c} ({what})" for what, v in per.items() for c, x in v["channels"].items()
                  if x["verdict"] == "better"]
        meets = all(v["bounds"]["meets"] for v in per.values())
        complete = all(w in per for w in conditions)
        out[name] = {"conditions": per, "worse": worse, "better": better, "rejected": bool(worse),
                     "meets_bound_target": meets, "complete": complete,
                     "adoptable": name != baseline and not worse and meets and complete}
    return out


def report(verdicts: dict, baseline: str = BASELINE) -> list[str]:
    lines = []
    for name, v in verdicts.items():
        if name == baseline:
            b = [f"{what}: worst bound {100 * c['bounds']['worst_bound']:.0f} % ({c['bounds']['worst_coefficient']})"
                 for what, c in v["conditions"].items()]
            lines.append(f"{name} (baseline): " + "; ".join(b))
            lines += [f"  reference on {what}: " + ", ".join(f"{k} {c['reference'][k]:.3g}" for k in CHANNELS)
                      + "; the baseline beats it on " + _beats(c) for what, c in v["conditions"].items()
                      if "reference" in c]
            continue
        for what, c in v["conditions"].items():
            cells = [f"{k} {x['baseline']['mean']:.3g}->{x['setting']['mean']:.3g}"
                     + ("" if x["verdict"] == "within" else f" {x['verdict'].upper()}")
                     for k, x in c["channels"].items()]
            bd = c["bounds"]
            lines.append(f"{name} on {what} (seeds {', '.join(map(str, c['seeds']))}): " + "; ".join(cells)
                         + f"; worst bound {100 * bd['worst_bound']:.1f} % ({bd['worst_coefficient']})"
                         + ("" if bd["Iz_inside"] else "; Iz outside its physical range")
                         + (f"; beats the reference on {_beats(c)}" if "reference" in c else ""))
        lines.append(f"  => {name}: {_state(v)}")
    return lines


def _beats(c: dict) -> str:
    won = [k for k, b in c["beats_reference"].items() if b]
    return ", ".join(won) if won else "no channel"


def _state(v: dict) -> str:
    if v["adoptable"]:
        return "ADOPTABLE"
    if v["rejected"]:
        return "REJECTED (worse beyond the spread: " + ", ".join(v["worse"]) + ")"
    return ("not rejected, " + ("bound target met" if v["meets_bound_target"] else "bound target missed")
            + ("" if v["complete"] else ", not measured on every condition"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ddyn.studies.holdout_verdict", description=__doc__.split("\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="--out folders of `ddyn study ddm real --holdout ...`")
    ap.add_argument("--baseline", default=BASELINE, help=f"the run every setting is compared with (default "
                    f"{BASELINE})")
    ap.add_argument("--json", type=Path, help="also write the verdicts to this file")
    args = ap.parse_args(argv)
    try:
        from ddyn.model import vehicle as vehicle_mod
        iz = tuple(vehicle_mod.load(IZ_VEHICLE).ranges["Iz"])
        splits = collect(args.dirs)
        judge(splits, args.baseline, iz)     # every DIR's baseline present before the log is read
        verdicts = judge(splits, args.baseline, iz, references_of(splits))
    except DdynError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print("\n".join(report(verdicts, args.baseline)))
    if args.json:
        args.json.write_text(json.dumps(verdicts, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
