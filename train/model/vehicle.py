"""Vehicle definitions: data files in train/vehicles/*.json, loaded into a Vehicle.

A vehicle file holds the known quantities (mass, lf, lr, v_min), the sample time,
the nominal coefficient ranges used by the Physics Guard, the coefficients used as
ground truth in simulation, input limits, default sensor noise, and where each
number comes from ("sources").
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.model.effects import MAIN_PARAM
from ddyn.model.single_track import BRAKE_GAIN_FORMS, COEFF_NAMES, DRIVETRAINS, KnownParams

VEHICLE_DIR = Path(__file__).resolve().parents[1] / "vehicles"  # train/vehicles

# Each car's body, length by width in m, for track-bound checks (MPC, racing line, SIL). The 1:43 car's body (not in the vehicle file, which holds only what the model needs): about
# 10 cm by 5 cm, centred on the centre of gravity. Chosen here from the ORCA car's size class.
FOOTPRINT = {"orca_1_43": (0.10, 0.05), "av21": (4.9, 1.9)}
FOOTPRINT["av21_powertrain"] = FOOTPRINT["av21"]   # the same car with the real log's drivetrain and ranges
FOOTPRINT["av21_power"] = FOOTPRINT["av21"]        # the same car with the power-limited drivetrain


def footprint(vehicle_name: str) -> tuple[float, float]:
    """The car's body (length, width) in m; a car without one is one line naming it, not a KeyError deep in the MPC
    setup (a vehicle file of the user's own car: its body is what the track-bound checks need)."""
    if vehicle_name not in FOOTPRINT:
        raise DdynError(f"vehicle {vehicle_name!r}: no body size known (FOOTPRINT in ddyn.model.vehicle holds "
                        f"{', '.join(sorted(FOOTPRINT))}); the MPC, racing line and SIL check the car's body "
                        "against the track")
    return FOOTPRINT[vehicle_name]


@dataclass(frozen=True)
class Vehicle:
    name: str
    sample_time: float
    rk4_substeps: int
    max_speed: float
    evaluation_horizon: float      # s: horizon of the ADE/FDE multi-step metrics
    known: KnownParams
    ranges: dict[str, tuple[float, float]]
    true_coefficients: dict[str, float] | None
    # the coefficients that generated a published reference dataset, where they differ from the truth
    reference_dataset_coefficients: dict[str, float] | None
    input_limits: dict[str, tuple[float, float]]
    sensor_noise_std: dict[str, float]
    description: str = ""
    # another vehicle file's name when this one is the same car with other model settings (drivetrain,
    # ranges): never inferred from a log's clock in place of that car
    variant_of: str = ""
    sources: dict[str, str] = field(default_factory=dict)
    # effects the car's nominal itself carries ({effect: main parameter}, ddyn.model.effects.MAIN_PARAM), e.g. a
    # downforce identified on effect-free logs: what a gap diagnosis reports is what comes on top of them
    effects: dict[str, float] = field(default_factory=dict)
    source_path: str = ""
    raw_json: str = ""
    digest: str = ""

    def true_vector(self) -> np.ndarray:
        """Ground-truth coefficients in COEFF_NAMES order (simulation's truth)."""
        return self.coefficient_vector("true")

    def coefficient_vector(self, which: str = "true") -> np.ndarray:
        """A named coefficient set ("true" or "reference_dataset") in COEFF_NAMES order."""
        table = {"true": self.true_coefficients, "reference_dataset": self.reference_dataset_coefficients}
        if which not in table:
            raise DdynError(f"unknown coefficient set {which!r}; expected true or reference_dataset")
        if table[which] is None:
            raise DdynError(f"vehicle {self.name!r} has no {which} coefficients")
        return np.array([table[which][k] for k in COEFF_NAMES], dtype=float)

    def range_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.array([self.ranges[k][0] for k in COEFF_NAMES], dtype=float)
        hi = np.array([self.ranges[k][1] for k in COEFF_NAMES], dtype=float)
        return lo, hi


def available() -> list[str]:
    return sorted(p.stem for p in VEHICLE_DIR.glob("*.json"))


def load(name_or_path: str | Path) -> Vehicle:
    """Load a vehicle by name (a file in train/vehicles) or by path to a JSON file."""
    path = Path(name_or_path)
    if not path.suffix:
        path = VEHICLE_DIR / f"{name_or_path}.json"
    if not path.is_file():
        raise DdynError(f"vehicle {str(name_or_path)!r} not found (known: {', '.join(available())})")
    return parse(path.read_bytes(), str(path))


def _mapping(raw: dict, key: str, path: str, required: bool = True) -> dict:
    """raw[key] as a JSON object ({} when optional and absent); a list or number there is refused by name."""
    if key not in raw:
        if required:
            raise DdynError(f"{path}: missing field {key!r}")
        return {}
    value = raw[key]
    if not isinstance(value, dict):
        raise DdynError(f"{path}: {key} must be a JSON object {{...}}, got {type(value).__name__}: {_short(value)}")
    return value


def _short(value) -> str:
    text = repr(value) if isinstance(value, (str, float)) else json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _number(value, where: str, path: str, positive: bool = False, nonnegative: bool = False) -> float:
    """A finite JSON number (not a bool, not a string); positive/nonnegative as asked. where names the key."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DdynError(f"{path}: {where} must be a number, got {type(value).__name__}: {_short(value)}")
    x = float(value)
    if not math.isfinite(x):
        raise DdynError(f"{path}: {where} must be finite, got {x!r}")
    if positive and not x > 0:
        raise DdynError(f"{path}: {where} must be > 0, got {x!r}")
    if nonnegative and not x >= 0:
        raise DdynError(f"{path}: {where} must be >= 0, got {x!r}")
    return x


def _pair(value, where: str, path: str) -> tuple[float, float]:
    """[lo, hi] of finite numbers."""
    if not (isinstance(value, list) and len(value) == 2):
        raise DdynError(f"{path}: {where} must be [lo, hi], got {_short(value)}")
    return _number(value[0], f"{where}[0]", path), _number(value[1], f"{where}[1]", path)


def _coefficients(raw: dict, key: str, path: str) -> dict[str, float] | None:
    if raw.get(key) is None:
        return None
    table = _mapping(raw, key, path)
    missing = [k for k in COEFF_NAMES if k not in table]
    if missing:
        raise DdynError(f"{path}: {key} lacks {', '.join(missing)}")
    return {k: _number(table[k], f"{key}.{k}", path) for k in COEFF_NAMES}


def _effects(raw: dict, path: str) -> dict[str, float]:
    """The optional "effects" table: {effect name: its main parameter}, names from ddyn.model.effects.MAIN_PARAM."""
    table = _mapping(raw, "effects", path, required=False)
    unknown = [k for k in table if k not in MAIN_PARAM]
    if unknown:
        raise DdynError(f"{path}: effects.{unknown[0]} is not an effect; expected one of {', '.join(MAIN_PARAM)}")
    return {k: _number(v, f"effects.{k}", path) for k, v in table.items()}


def _known(raw: dict, path: str) -> KnownParams:
    """mass, lf, lr, v_min from "known"; the drivetrain form from "drivetrain" (default the papers'), and
    for "powertrain" and "power_limited" the brake gain from known.brake_gain (required there, refused elsewhere)."""
    form = raw.get("drivetrain", "papers")
    if form not in DRIVETRAINS:
        raise DdynError(f"{path}: drivetrain {_short(form)} is not one of {', '.join(DRIVETRAINS)}")
    known = _mapping(raw, "known", path)
    gain = known.get("brake_gain")
    if gain is not None:
        gain = _number(gain, "known.brake_gain", path)
    if form in BRAKE_GAIN_FORMS and not (gain is not None and gain > 0.0):
        raise DdynError(f"{path}: the {form} drivetrain needs known.brake_gain > 0 (N per unit brake input)")
    if form not in BRAKE_GAIN_FORMS and gain is not None:
        raise DdynError(f"{path}: known.brake_gain is used only by the {' and '.join(BRAKE_GAIN_FORMS)} drivetrains")
    values = {}
    for k in ("mass", "lf", "lr", "v_min"):
        if k not in known:
            raise DdynError(f"{path}: missing field {k!r} in known")
        values[k] = _number(known[k], f"known.{k}", path, positive=k != "v_min", nonnegative=k == "v_min")
    return KnownParams(**values, drivetrain=form, brake_gain=gain if gain is not None else 0.0)


def parse(raw_bytes: bytes, origin: str) -> Vehicle:
    """A vehicle from the bytes of a vehicle file (origin names it in errors), e.g. one embedded in a checkpoint.

    Every field is checked where it enters: the top level and known, ranges, input_limits, sensor_noise_std,
    sources are JSON objects; numbers are finite (sample_time, max_speed, evaluation_horizon, mass, lf, lr > 0;
    v_min, noise >= 0; rk4_substeps a whole number >= 1); a DdynError names the file and the key."""
    path = origin
    try:
        raw_json = raw_bytes.decode()
        raw = json.loads(raw_json)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DdynError(f"{path}: not valid JSON: {e}") from None
    if not isinstance(raw, dict):
        raise DdynError(f"{path}: a vehicle file is a JSON object {{\"name\": ..., \"known\": {{...}}, ...}}, "
                        f"got {type(raw).__name__}")
    for key in ("name", "sample_time", "max_speed", "evaluation_horizon"):
        if key not in raw:
            raise DdynError(f"{path}: missing field {key!r}")
    known = _known(raw, path)
    range_table = _mapping(raw, "ranges", path)
    missing = [k for k in COEFF_NAMES if k not in range_table]
    if missing:
        raise DdynError(f"{path}: ranges lacks {', '.join(missing)}")
    ranges = {k: _pair(range_table[k], f"ranges.{k}", path) for k in COEFF_NAMES}
    true = _coefficients(raw, "true_coefficients", path)
    ref = _coefficients(raw, "reference_dataset_coefficients", path)
    substeps = raw.get("rk4_substeps", 1)
    if (isinstance(substeps, bool) or not isinstance(substeps, (int, float)) or not math.isfinite(substeps)
            or substeps != int(substeps) or substeps < 1):
        raise DdynError(f"{path}: rk4_substeps must be a whole number >= 1, got {_short(substeps)}")
    substeps = int(substeps)
    limits = _mapping(raw, "input_limits", path)
    noise = _mapping(raw, "sensor_noise_std", path, required=False)
    sources = _mapping(raw, "sources", path, required=False)
    effects = _effects(raw, path)
    for key in ("name", "description", "variant_of"):
        if key in raw and not isinstance(raw[key], str):
            raise DdynError(f"{path}: {key} must be a string, got {_short(raw[key])}")
    vehicle = Vehicle(
        name=raw["name"],
        sample_time=_number(raw["sample_time"], "sample_time", path, positive=True),
        rk4_substeps=substeps,
        max_speed=_number(raw["max_speed"], "max_speed", path, positive=True),
        evaluation_horizon=_number(raw["evaluation_horizon"], "evaluation_horizon", path, positive=True),
        raw_json=raw_json,
        known=known,
        ranges=ranges,
        true_coefficients=true,
        reference_dataset_coefficients=ref,
        input_limits={k: _pair(v, f"input_limits.{k}", path) for k, v in limits.items()},
        sensor_noise_std={k: _number(v, f"sensor_noise_std.{k}", path, nonnegative=True) for k, v in noise.items()},
        description=raw.get("description", ""),
        variant_of=raw.get("variant_of", ""),
        sources=dict(sources),
        effects=effects,
        source_path=path,
        digest=hashlib.sha256(raw_bytes).hexdigest(),
    )
    for k, (lo, hi) in vehicle.ranges.items():
        if not lo < hi:
            raise DdynError(f"{path}: range of {k} is empty: [{lo}, {hi}]")
        if vehicle.true_coefficients is not None and not lo <= vehicle.true_coefficients[k] <= hi:
            raise DdynError(f"{path}: true {k} = {vehicle.true_coefficients[k]} lies outside its range [{lo}, {hi}]")
    if known.drivetrain == "power_limited":
        # the slots' physical meanings: a traction cap and a power (both > 0), a resistance and a drag (>= 0)
        for k, what, strict in (("Cm1", "traction cap (N)", True), ("Cm2", "wheel power (W)", True),
                                ("Cr0", "resistance at zero pedal (N)", False), ("Cd", "aero drag (kg/m)", False)):
            lo = vehicle.ranges[k][0]
            if (lo <= 0) if strict else (lo < 0):
                raise DdynError(f"{path}: range of {k} (the power_limited drivetrain's {what}) must lie "
                                f"{'above' if strict else 'at or above'} 0, got [{lo}, {vehicle.ranges[k][1]}]")
    for k in ("throttle", "steering", "dthrottle", "dsteering"):
        if k not in vehicle.input_limits:
            raise DdynError(f"{path}: input_limits lacks {k!r}")
    for k, (lo, hi) in vehicle.input_limits.items():
        if not lo <= hi:
            raise DdynError(f"{path}: input_limits.{k} is empty: [{lo}, {hi}]")
    return vehicle
