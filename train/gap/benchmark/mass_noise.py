"""`python -m ddyn.gap.benchmark.mass_noise`: why the mass offset pays on effect-free logs (docs/gap.md, issue 33).

One noise-free log of the CommonRoad single-track plant (the lofo case plan's first effect-free commonroad-st case,
120 s, 10 ms DBW, no roll channel, seed 777001), diagnosed with the study's configuration (lofo.base_config):

  channels   the car's own sensor noise (its vehicle file's sensor_noise_std) added to one channel at a time;
             the mass offset's fit and its held-out dBIC on each (what makes it pay on an effect-free log)
  inertia    logs of that case with a mass offset of 0, +15 % and -15 % (the car's own noise on every channel),
             diagnosed with the mass offset holding Iz (the default) and scaling it (mass_inertia = true)

A measurement for the docs, not a test: one case, about two minutes.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json

import numpy as np

from ddyn.gap.benchmark import families as F
from ddyn.gap.benchmark import lofo
from ddyn.gap.problem import nominal_from_vehicle
from ddyn.gap.selection import diagnose
from ddyn.model.vehicle import load as load_vehicle

FAMILY = "commonroad-st"
SEED = 777001
CASE = {"duration": 120.0, "dbw_period": 0.01, "noise_color": 0.0, "roll_channel": "none"}
CHANNELS = ("x", "y", "yaw", "vx", "vy", "omega")   # the logged state's first six columns, in order


def _case(effect: str = "none", magnitude: float = 0.0, noise_scale: float = 0.0) -> dict:
    base = next(c for c in lofo.plan(FAMILY, 60, lofo.DEFAULT_SEED) if c["effect"] == "none")
    return base | CASE | {"seed": SEED, "effect": effect, "magnitude": magnitude, "noise_scale": noise_scale}


def _mass(ds, case: dict, mass_inertia: bool = False) -> dict:
    """The mass offset candidate's fit and dBIC, and what the diagnosis claims."""
    veh = load_vehicle(F.nominal_vehicle(case["family"], case["params"]))
    cfg = dataclasses.replace(lofo.base_config(), mass_inertia=mass_inertia)
    d = diagnose(ds, nominal_from_vehicle(veh, ds), cfg)
    m = next(c for c in d["candidates"] if c["effect"] == "mass_offset")
    return {"fraction": float(m["params"]["fraction"]), "delta_bic": float(m["delta_bic"]),
            "selected": list(d["selected"])}


def channels() -> list[dict]:
    case = _case()
    clean = lofo.make_case_log(case)
    std = load_vehicle(F.nominal_vehicle(case["family"], case["params"])).sensor_noise_std
    rng = np.random.default_rng(5)
    rows = [{"noise": "none"} | _mass(clean, case)]
    for i, name in enumerate(CHANNELS):
        ds = copy.deepcopy(clean)
        ds.states[:, i] += float(std[name]) * rng.standard_normal(len(ds))
        rows.append({"noise": name} | _mass(ds, case))
    return rows


def inertia() -> list[dict]:
    rows = []
    for magnitude in (0.0, 0.15, -0.15):
        case = _case("none" if magnitude == 0.0 else "mass_offset", magnitude, noise_scale=1.0)
        ds = lofo.make_case_log(case)
        for mi in (False, True):
            rows.append({"mass_offset": magnitude, "mass_inertia": mi} | _mass(ds, case, mi))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ddyn.gap.benchmark.mass_noise", description=__doc__.split("\n")[0])
    ap.add_argument("--out", help="also write the rows as JSON to this file")
    args = ap.parse_args(argv)
    doc = {"channels": channels(), "inertia": inertia()}
    for part, rows in doc.items():
        print(f"== {part}")
        for r in rows:
            print("  " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(doc, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
