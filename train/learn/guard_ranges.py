"""Guard ranges from data: the ranges file `ddyn train --ranges` takes.

The FTHD paper's EKF-FTHD suggests coefficient ranges from a DDM's estimates on denoised data
(`ddyn denoise --model CKPT` writes OUT.ranges.json, rule in ddyn.learn.denoise.suggest_ranges).
This closes the loop: such a file, or a plain {"Cm1": [lo, hi], ...} mapping, replaces the vehicle
file's Physics Guard ranges for the coefficients it names; the others keep the vehicle's. What was
used is recorded in the checkpoint (ranges.source) and printed by `ddyn train` and `ddyn evaluate`.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.model.single_track import COEFF_NAMES
from ddyn.model.vehicle import Vehicle


def read_ranges(path: str | Path) -> dict[str, tuple[float, float]]:
    """{coefficient: (lo, hi)} from a `ddyn denoise` ranges file ("coefficients" -> "suggested") or a
    plain mapping; every named coefficient known, both bounds finite and lo < hi."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DdynError(f"ranges file {path}: {e}") from None
    table = raw.get("coefficients", raw) if isinstance(raw, dict) else None
    if not isinstance(table, dict) or not table:
        raise DdynError(f"ranges file {path}: expected {{\"coefficient\": [lo, hi], ...}} or a `ddyn denoise` "
                        f"ranges file with \"coefficients\"")
    out = {}
    for name, value in table.items():
        if name not in COEFF_NAMES:
            raise DdynError(f"ranges file {path}: unknown coefficient {name!r} (known: {', '.join(COEFF_NAMES)})")
        pair = value.get("suggested") if isinstance(value, dict) else value
        if not (isinstance(pair, (list, tuple)) and len(pair) == 2):
            raise DdynError(f"ranges file {path}: {name}: expected [lo, hi], got {pair!r}")
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in pair):
            raise DdynError(f"ranges file {path}: {name}: bounds must be numbers, got {pair!r}")
        lo, hi = (float(x) for x in pair)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise DdynError(f"ranges file {path}: {name}: need finite lo < hi, got [{lo!r}, {hi!r}]")
        out[name] = (lo, hi)
    return out


def with_ranges(vehicle: Vehicle, path: str | Path) -> tuple[Vehicle, dict]:
    """The vehicle with the file's ranges in place of its own, and the record for the checkpoint."""
    new = read_ranges(path)
    ranges = {**vehicle.ranges, **new}
    changed = {k: {"vehicle": list(vehicle.ranges[k]), "used": list(v)} for k, v in new.items()
               if tuple(vehicle.ranges[k]) != tuple(v)}
    record = {"file": str(path), "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
              "changed": changed}
    return dataclasses.replace(vehicle, ranges=ranges), record


def describe(record: dict | None) -> str:
    if not record:
        return "guard ranges: the vehicle file's"
    parts = ", ".join(f"{k} [{v['used'][0]:.4g}, {v['used'][1]:.4g}] (vehicle [{v['vehicle'][0]:.4g}, "
                      f"{v['vehicle'][1]:.4g}])" for k, v in record["changed"].items())
    return f"guard ranges: from {record['file']}: {parts or 'no change'}"
