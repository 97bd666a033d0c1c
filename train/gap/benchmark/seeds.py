"""The seed ledger (seen_seeds.json): which benchmark seeds chose settings (calibration) and which have been scored
and looked at since, so that a run on them is reported as not blind. Data, not code: a blind run adds its seed to
the file in the commit that reports it."""
from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from ddyn.errors import DdynError

LEDGER = Path(__file__).resolve().parent / "seen_seeds.json"


def _expand(entry, where: str) -> list[int]:
    if isinstance(entry, list) and all(isinstance(s, int) for s in entry):
        return list(entry)
    if isinstance(entry, str) and "-" in entry:
        lo, _, hi = entry.partition("-")
        try:
            return list(range(int(lo), int(hi) + 1))
        except ValueError:
            pass
    raise DdynError(f"{LEDGER}: {where}: expected a list of seeds or 'FIRST-LAST', got {entry!r}")


@lru_cache(maxsize=None)
def _ledger() -> tuple[tuple[int, ...], tuple[int, ...]]:
    try:
        raw = json.loads(LEDGER.read_text())
        return (tuple(_expand(raw["calibration"], "calibration")),
                tuple(s for i, e in enumerate(raw["seen"]) for s in _expand(e["seeds"], f"seen[{i}].seeds")))
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise DdynError(f"{LEDGER}: not a seed ledger: {e}") from None


def seen_seeds() -> tuple[int, ...]:
    """Seeds scored before and looked at since (not blind)."""
    return _ledger()[1]


def calibration_seeds() -> tuple[int, ...]:
    """Seeds whose sweeps choose the margins and thresholds."""
    return _ledger()[0]


CALIBRATION_SEEDS = calibration_seeds()
