"""A vehicle's training profile: the settings `ddyn train` uses for that vehicle when no flag gives them.

A profile is train/vehicles/training/<vehicle>.json (keyed by the vehicle file's `name`):

    {"vehicle": "av21",
     "why": "what the settings rest on (a study, a results file)",
     "settings": {"tau": 1, "guard_prior": 0.0, ...},       # TrainConfig fields (ddyn.learn.training)
     "sources": {"tau": "why this one", ...}}                # optional, a note per setting

Precedence, setting by setting: an explicit `ddyn train` flag, then the profile, then TrainConfig's built-in
default. A vehicle without a profile trains with the built-in defaults. The studies and ddyn.api.train build their
TrainConfig themselves and do not read profiles.

Why a file of its own and not a key of the vehicle file: the vehicle file's sha256 is written into the generated C
model's headers (codegen/generate.py), so a training setting there would change generated code that does not
depend on it; nor is it train/vehicles/mpc/, whose files hold the racing-line, MPC and SIL settings.
"""
from __future__ import annotations

import difflib
import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.learn.training import TrainConfig
from ddyn.model.vehicle import VEHICLE_DIR

PROFILE_DIR = VEHICLE_DIR / "training"
TOP_KEYS = ("vehicle", "why", "settings", "sources")
SETTING_NAMES = tuple(f.name for f in fields(TrainConfig))
DEFAULT = "default"
PROFILE = "profile"


@dataclass(frozen=True)
class TrainingProfile:
    vehicle: str
    path: str                                   # the file, as read (errors and the start line name it)
    why: str
    settings: dict = field(default_factory=dict)    # {TrainConfig field: value}, each checked
    sources: dict = field(default_factory=dict)     # {TrainConfig field: note}


@dataclass(frozen=True)
class ResolvedSettings:
    """What `ddyn train` trains with: the config, and for each of its fields where the value came from
    ("default", "profile", or the flag, e.g. "--epochs")."""
    vehicle: str
    config: TrainConfig
    origin: dict
    profile: TrainingProfile | None = None


def profile_path(vehicle_name: str) -> Path:
    return PROFILE_DIR / f"{vehicle_name}.json"


def _short(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _unknown(path: str, where: str, key: str, known: tuple[str, ...]) -> DdynError:
    close = difflib.get_close_matches(key.replace("-", "_"), known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return DdynError(f"{path}: unknown key {where}{key!r}{hint}; expected one of {', '.join(known)}")


def check_setting(path: str, key: str, value):
    """One setting's value, checked alone against its TrainConfig field: the type of the built-in default, then
    TrainConfig's own range checks; a DdynError names the file (or the option) and the key."""
    if key not in SETTING_NAMES:
        raise _unknown(path, "settings." if path.endswith(".json") else "", key, SETTING_NAMES)
    default = getattr(TrainConfig(), key)
    where = f"{path}: settings.{key}" if path.endswith(".json") else f"{path} {key}"
    if isinstance(default, str):
        if not isinstance(value, str):
            raise DdynError(f"{where} must be a string, got {_short(value)}")
    elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DdynError(f"{where} must be a finite number, got {_short(value)}")
    elif isinstance(default, int) and value != int(value):
        raise DdynError(f"{where} must be a whole number, got {_short(value)}")
    if isinstance(default, float):
        value = float(value)
    try:
        return getattr(TrainConfig(**{key: value}), key)
    except DdynError as e:
        raise DdynError(f"{where}: {e}") from None


def parse(text: str, path: str, vehicle_name: str) -> TrainingProfile:
    """A profile from a file's text (path names it in errors); every key and value checked."""
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as e:
        raise DdynError(f"{path}: not valid JSON: {e}") from None
    if not isinstance(raw, dict):
        raise DdynError(f"{path}: a training profile is a JSON object {{\"vehicle\": ..., \"why\": ..., "
                        f"\"settings\": {{...}}}}, got {type(raw).__name__}")
    for key in raw:
        if key not in TOP_KEYS:
            raise _unknown(path, "", key, TOP_KEYS)
    for key in ("vehicle", "why", "settings"):
        if key not in raw:
            raise DdynError(f"{path}: missing key {key!r}")
    if raw["vehicle"] != vehicle_name:
        raise DdynError(f"{path}: vehicle is {_short(raw['vehicle'])}, not {vehicle_name!r} (the file's name)")
    if not isinstance(raw["why"], str) or not raw["why"].strip():
        raise DdynError(f"{path}: why must say what the settings rest on (a non-empty string), "
                        f"got {_short(raw['why'])}")
    settings, sources = raw["settings"], raw.get("sources", {})
    for key, table in (("settings", settings), ("sources", sources)):
        if not isinstance(table, dict):
            raise DdynError(f"{path}: {key} must be a JSON object {{...}}, got {_short(table)}")
        for name in table:
            if name not in SETTING_NAMES:
                raise _unknown(path, f"{key}.", name, SETTING_NAMES)
    checked = {k: check_setting(path, k, v) for k, v in settings.items()}
    for name, note in sources.items():
        if name not in settings:
            raise DdynError(f"{path}: sources.{name} notes a setting the profile does not set")
        if not isinstance(note, str):
            raise DdynError(f"{path}: sources.{name} must be a string, got {_short(note)}")
    try:   # the settings together (e.g. a guard prior with kind dpm)
        TrainConfig(**checked)
    except DdynError as e:
        raise DdynError(f"{path}: settings: {e}") from None
    return TrainingProfile(vehicle=vehicle_name, path=path, why=raw["why"], settings=checked, sources=dict(sources))


def load(vehicle_name: str) -> TrainingProfile | None:
    """The vehicle's profile, or None when it has none."""
    path = profile_path(vehicle_name)
    if not path.is_file():
        return None
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DdynError(f"{path}: cannot be read: {e}") from None
    return parse(text, _shown(path), vehicle_name)


def _shown(path: Path) -> str:
    """The path relative to the repository where it lies inside it (as the docs name it)."""
    try:
        return str(path.resolve().relative_to(VEHICLE_DIR.parents[1]))
    except ValueError:
        return str(path)


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def resolve(vehicle_name: str, flags: dict, profile: TrainingProfile | None = None,
            use_profile: bool = True) -> ResolvedSettings:
    """The config `ddyn train` trains with: flags ({TrainConfig field: value} of the flags given), over the
    vehicle's profile (loaded when not passed; none when use_profile is False), over the built-in defaults."""
    unknown = sorted(set(flags) - set(SETTING_NAMES))
    if unknown:
        raise DdynError(f"unknown training setting(s) {', '.join(unknown)}")
    if use_profile and profile is None:
        profile = load(vehicle_name)
    if not use_profile:
        profile = None
    from_profile = profile.settings if profile else {}
    origin = {name: flag(name) if name in flags else PROFILE if name in from_profile else DEFAULT
              for name in SETTING_NAMES}
    try:
        config = TrainConfig(**{**from_profile, **flags})
    except DdynError as e:
        if not from_profile:
            raise
        raise DdynError(f"{e} (with the training profile {profile.path}: "
                        f"{', '.join(flag(k)[2:] for k in from_profile if k not in flags)}; "
                        f"--no-profile leaves it out)") from None
    return ResolvedSettings(vehicle=vehicle_name, config=config, origin=origin, profile=profile)


def _value(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def describe(resolved: ResolvedSettings, no_profile: bool = False) -> str:
    """The one line `ddyn train` prints at start: the profile applied and where each setting came from."""
    if resolved.profile is not None:
        head = f"training profile {resolved.vehicle} ({resolved.profile.path})"
    elif no_profile:
        head = f"training profile: none for {resolved.vehicle} (--no-profile), built-in defaults"
    else:
        head = (f"training profile: none for {resolved.vehicle} (no {_shown(profile_path(resolved.vehicle))}), "
                f"built-in defaults")
    body = ", ".join(f"{flag(name)[2:]} {_value(getattr(resolved.config, name))} [{resolved.origin[name]}]"
                     for name in SETTING_NAMES)
    return f"{head}: {body}"
