"""Which vehicle file a dataset belongs to, when that file may live anywhere.

A dataset names its vehicle (`vehicle` metadata). A name alone only finds files in
train/vehicles, so a log made with `--vehicle /somewhere/car.json` could not be loaded
again by name (issue 14). Datasets written by the simulators therefore also record the
vehicle file itself: `vehicle_json_b64` (its exact bytes, base64: metadata values have
their whitespace collapsed, which would change the bytes and the digest), `vehicle_digest`
(sha256 of those bytes) and `vehicle_file` (where it was read from, for people).

resolve() picks, in this order: the vehicle the caller gives (a Vehicle, a name or a path),
the file embedded in the dataset, the recorded path when its digest still matches, the name.
"""
from __future__ import annotations

import base64
import binascii
import hashlib
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.vehicle import Vehicle


def as_vehicle(vehicle: Vehicle | str | Path) -> Vehicle:
    """A Vehicle from a Vehicle, a name in train/vehicles or a path to a JSON file."""
    return vehicle if isinstance(vehicle, Vehicle) else vehicle_mod.load(vehicle)


def metadata_for(vehicle: Vehicle) -> dict[str, str]:
    """The metadata keys that let a dataset find its vehicle file again (written by the simulators)."""
    out = {"vehicle_digest": vehicle.digest, "vehicle_file": str(vehicle.source_path)}
    if vehicle.raw_json:
        out["vehicle_json_b64"] = base64.b64encode(vehicle.raw_json.encode()).decode()
    return out


def embedded(metadata: dict[str, str]) -> Vehicle | None:
    """The vehicle file embedded in a dataset's metadata, or None when there is none."""
    text = metadata.get("vehicle_json_b64")
    if not text:
        return None
    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as e:
        raise DdynError(f"vehicle_json_b64 in the dataset's metadata is not base64: {e}") from None
    digest = metadata.get("vehicle_digest")
    if digest and hashlib.sha256(raw).hexdigest() != digest:
        raise DdynError("the vehicle file embedded in the dataset does not match its vehicle_digest")
    return vehicle_mod.parse(raw, f"vehicle embedded in the dataset ({metadata.get('vehicle_file', '?')})")


def resolve(metadata: dict[str, str], name: str | None, given: Vehicle | str | Path | None = None) -> Vehicle:
    """The dataset's vehicle: `given` if any, else the embedded file, the recorded path, the name."""
    if given is not None:
        return as_vehicle(given)
    v = embedded(metadata)
    if v is not None:
        return v
    recorded = metadata.get("vehicle_file")
    if recorded and Path(recorded).is_file():
        v = vehicle_mod.load(recorded)
        if not metadata.get("vehicle_digest") or v.digest == metadata["vehicle_digest"]:
            return v
    if not name:
        raise DdynError("the dataset names no vehicle; pass --vehicle")
    return vehicle_mod.load(name)


def of_dataset(ds, given: Vehicle | str | Path | None = None) -> Vehicle:
    """resolve() for a Dataset."""
    return resolve(ds.metadata, ds.vehicle, given)
