"""A vehicle's own racing-line, MPC and SIL settings (train/vehicles/mpc/<vehicle>.json).

Why: the defaults of RacelineSettings and MpcSettings were chosen for the 1:43 car (3 cm intervals
and margins, a 0.5 m/s speed floor, 2.5 cm table spacing). The full-scale AV-21 needs metres: its
file overrides those fields and nothing else, so the 1:43 defaults (and the M7 segment recorded with
them) stay as they are. A vehicle without a file uses the defaults. The files sit in a subfolder:
train/vehicles/*.json are vehicle files (ddyn.model.vehicle.available lists them).
"""
from __future__ import annotations

import json
from functools import lru_cache

from ddyn.errors import DdynError
from ddyn.model.vehicle import VEHICLE_DIR

SETTINGS_DIR = VEHICLE_DIR / "mpc"
SECTIONS = ("raceline", "mpc", "sil")


@lru_cache(maxsize=None)
def _read(vehicle_name: str) -> dict:
    path = SETTINGS_DIR / f"{vehicle_name}.json"
    if not path.is_file():
        return {}
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DdynError(f"{path}: not valid JSON: {e}") from None
    if raw.get("vehicle") != vehicle_name:
        raise DdynError(f"{path}: is for vehicle {raw.get('vehicle')!r}, not {vehicle_name!r}")
    return raw


def overrides(vehicle_name: str, section: str) -> dict:
    """The fields a vehicle's settings file sets in one section (empty when it has none)."""
    if section not in SECTIONS:
        raise ValueError(section)
    return dict(_read(vehicle_name).get(section, {}))
