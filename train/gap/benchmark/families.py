"""The plant families the diagnosis is calibrated and scored on, none of them this project's model.

A family is one plant's code: every log of it comes from that code, whatever car, track, rate or noise it is
given. Leaving a family out (ddyn.gap.benchmark.lofo) is what a new plant is to the diagnosis; a new seed of the
same family is not.

  commonroad-std   CommonRoad's single-track drift model (vehicle_dynamics_std: combined-slip Pacejka MF tyres,
                   wheel spin), CommonRoad's parameter sets
  commonroad-st    CommonRoad's single-track model with linear tyres (vehicle_dynamics_st): no Pacejka curve
  commonroad-mb    CommonRoad's multi-body model (29 states: suspension, roll, load transfer, tyre relaxation)
  mujoco           a rigid-body physics-engine car (MuJoCo): tyre forces from contact, suspension; no Pacejka
                   curve and no single-track equivalent, so its nominal is a model identified with this project
                   on effect-free logs of it

Each family says which effects it can make (its plant's physical forms), which car parameter sets it varies and
which nominal a user would have for a log of it: the plant's own parameters mapped onto the single-track model
where it has an equivalent, else the identified one.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ddyn.errors import DdynError


@dataclass(frozen=True)
class Family:
    name: str
    about: str
    nominal_kind: str              # "mapped" (the plant's parameters) or "identified" (fitted on its logs)


FAMILIES = {f.name: f for f in (
    Family("commonroad-std", "CommonRoad single-track drift model (Pacejka MF tyres)", "mapped"),
    Family("commonroad-st", "CommonRoad single-track model, linear tyres", "mapped"),
    Family("commonroad-mb", "CommonRoad multi-body model (29 states)", "mapped"),
    Family("mujoco", "MuJoCo rigid-body car, contact tyres, suspension", "identified"),
)}


def _cr():
    from ddyn.plants import commonroad_st as CP

    return CP


def params_sets(family: str) -> tuple[str, ...]:
    """The car parameter sets a family's logs are drawn from."""
    if family == "mujoco":
        return ("default",)
    CP = _cr()
    sets = getattr(CP, "PARAMETER_SETS", ("vehicle2",))
    if family == "commonroad-mb":   # the multi-body model needs CommonRoad's full parameter sets
        return tuple(s for s in sets if s.startswith("vehicle")) or ("vehicle2",)
    return tuple(sets)


def supported_effects(family: str) -> tuple[str, ...]:
    if family == "mujoco":
        from ddyn.plants import mujoco_car

        return tuple(mujoco_car.SUPPORTED_EFFECTS)
    CP = _cr()
    eff = tuple(CP.PLANT_EFFECTS)
    if family == "commonroad-st":
        eff = tuple(getattr(CP, "ST_EFFECTS", tuple(e for e in eff if e != "tire_relaxation")))
    return eff


def make_log(family: str, track, effects, seed: int, settings, params: str):
    """One log of the family (a ddyn Dataset)."""
    if family not in FAMILIES:
        raise DdynError(f"unknown plant family {family!r}; expected one of {', '.join(FAMILIES)}")
    if family == "mujoco":
        from ddyn.plants import mujoco_car

        return mujoco_car.make_log(track, effects, seed, settings)
    CP = _cr()
    kw = {} if params == "vehicle2" else {"params": params}
    if family == "commonroad-mb":
        from ddyn.plants import commonroad_mb

        return commonroad_mb.make_log(track, effects, seed, settings, nominal_vehicle(family, params), **kw)
    model = CP.StdModel() if family == "commonroad-std" else CP.StModel()
    return CP.make_log(track, effects, seed, settings, nominal_vehicle(family, params), model=model, **kw)


def nominal_vehicle(family: str, params: str) -> Path:
    """The vehicle file a user would diagnose a log of this family and car with."""
    if family == "mujoco":
        from ddyn.plants import mujoco_car

        return Path(mujoco_car.NOMINAL_VEHICLE)
    CP = _cr()
    model = {"commonroad-std": "std", "commonroad-st": "st", "commonroad-mb": "mb"}[family]
    if hasattr(CP, "nominal_vehicle"):
        return Path(CP.nominal_vehicle(model, params))
    if model == "mb":
        from ddyn.plants import commonroad_mb

        return Path(commonroad_mb.NOMINAL_VEHICLE)
    return Path(CP.NOMINAL_VEHICLE)


def available(family: str) -> tuple[bool, str]:
    """(the family's plant can run here, why not)."""
    try:
        if family == "mujoco":
            from ddyn.plants import mujoco_car  # noqa: F401
        elif family == "commonroad-st":
            if not hasattr(_cr(), "StModel"):
                return False, "ddyn.plants.commonroad_st has no StModel"
        _cr().require_commonroad()
    except (ImportError, DdynError) as e:
        return False, str(e).splitlines()[0]
    return True, ""
