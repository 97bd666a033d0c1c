"""Vehicle definitions: data files in train/vehicles/*.json, loaded into a Vehicle.

A vehicle file holds the known quantities (mass, lf, lr, v_min), the sample time,
the nominal coefficient ranges used by the Physics Guard, the coefficients used as
ground truth in simulation, input limits, default sensor noise, and where each
number comes from ("sources").
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.model.single_track import COEFF_NAMES, DRIVETRAINS, KnownParams

VEHICLE_DIR = Path(__file__).resolve().parents[1] / "vehicles"  # train/vehicles

# Each car's body, length by width in m, for track-bound checks (MPC, racing line, SIL). The 1:43 car's body (not in the vehicle file, which holds only what the model needs): about
# 10 cm by 5 cm, centred on the centre of gravity. Chosen here from the ORCA car's size class.
FOOTPRINT = {"orca_1_43": (0.10, 0.05), "av21": (4.9, 1.9)}
FOOTPRINT["av21_powertrain"] = FOOTPRINT["av21"]   # the same car with the real log's drivetrain and ranges


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


def _known(raw: dict, path: str) -> KnownParams:
    """mass, lf, lr, v_min from "known"; the drivetrain form from "drivetrain" (default the papers'), and
    for "powertrain" the brake gain from known.brake_gain (required there, refused elsewhere)."""
    form = str(raw.get("drivetrain", "papers"))
    if form not in DRIVETRAINS:
        raise DdynError(f"{path}: drivetrain {form!r} is not one of {', '.join(DRIVETRAINS)}")
    gain = raw["known"].get("brake_gain")
    if form == "powertrain" and not (gain is not None and float(gain) > 0.0):
        raise DdynError(f"{path}: the powertrain drivetrain needs known.brake_gain > 0 (N per unit brake input)")
    if form == "papers" and gain is not None:
        raise DdynError(f"{path}: known.brake_gain is used only by the powertrain drivetrain")
    return KnownParams(**{k: float(raw["known"][k]) for k in ("mass", "lf", "lr", "v_min")},
                       drivetrain=form, brake_gain=float(gain) if gain is not None else 0.0)


def parse(raw_bytes: bytes, origin: str) -> Vehicle:
    """A vehicle from the bytes of a vehicle file (origin names it in errors), e.g. one embedded in a checkpoint."""
    path = origin
    try:
        raw = json.loads(raw_bytes)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DdynError(f"{path}: not valid JSON: {e}") from None
    try:
        known = _known(raw, path)
        ranges = {k: (float(raw["ranges"][k][0]), float(raw["ranges"][k][1])) for k in COEFF_NAMES}
        true = raw.get("true_coefficients")
        ref = raw.get("reference_dataset_coefficients")
        ref = {k: float(ref[k]) for k in COEFF_NAMES} if ref is not None else None
        true = {k: float(true[k]) for k in COEFF_NAMES} if true is not None else None
        vehicle = Vehicle(
            name=str(raw["name"]),
            sample_time=float(raw["sample_time"]),
            rk4_substeps=int(raw.get("rk4_substeps", 1)),
            max_speed=float(raw["max_speed"]),
            evaluation_horizon=float(raw["evaluation_horizon"]),
            raw_json=raw_bytes.decode(),
            known=known,
            ranges=ranges,
            true_coefficients=true,
            reference_dataset_coefficients=ref,
            input_limits={k: (float(v[0]), float(v[1])) for k, v in raw["input_limits"].items()},
            sensor_noise_std={k: float(v) for k, v in raw.get("sensor_noise_std", {}).items()},
            description=str(raw.get("description", "")),
            variant_of=str(raw.get("variant_of", "")),
            sources=dict(raw.get("sources", {})),
            source_path=path,
            digest=hashlib.sha256(raw_bytes).hexdigest(),
        )
    except KeyError as e:
        raise DdynError(f"{path}: missing field {e.args[0]!r}") from None
    except (TypeError, ValueError, IndexError) as e:
        raise DdynError(f"{path}: malformed field: {e}") from None
    for k, (lo, hi) in vehicle.ranges.items():
        if not lo < hi:
            raise DdynError(f"{path}: range of {k} is empty: [{lo}, {hi}]")
        if vehicle.true_coefficients is not None and not lo <= vehicle.true_coefficients[k] <= hi:
            raise DdynError(f"{path}: true {k} = {vehicle.true_coefficients[k]} lies outside its range [{lo}, {hi}]")
    for k in ("throttle", "steering", "dthrottle", "dsteering"):
        if k not in vehicle.input_limits:
            raise DdynError(f"{path}: input_limits lacks {k!r}")
    return vehicle
