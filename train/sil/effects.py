"""From a diagnosis to the controller's configuration (issue 34, item 2): `ddyn sil run --effects-from D`.

`ddyn gap diagnose ... --out D` writes D/diagnosis.json; its `selected` effects (`model.effects`: each with its
`params`) are what the diagnosis claims. The controller's runtime carries actuation delays and a steering lag
(controller.json `control.delay`, `control.lag`; ddyn/controller.h), so:

    steer_delay     -> control.delay.steering: its `delay` fitted alone (the diagnosis's candidate of that name),
                       to the nearest whole control period when the period is known
    steer_lag       -> control.lag.steering: its `tau` fitted alone (likewise; a time constant, not rounded),
                       unless steer_delay is selected too: then not applied (the two split one response and
                       the delay fitted alone carries it: the laps of docs/sil.md's closed loop)
    throttle_delay  -> control.delay.throttle: its `delay` fitted alone, to the nearest whole control period, as
                       steer_delay (the compensation helps since the channels' delays were aligned, dfcabe6; the
                       loop with a throttle delay in the plant: docs/sil.md)
    anything else   -> not applied, named: "bank_angle: not in the runtime (issue 34)"

The configuration records where its delays and lag came from (`effects`: the diagnosis's path, the sha256 of its
diagnosis.json, the delays and the lag it gave); the controller refuses a file whose control.delay differs from
the recorded `effects.delay`, or control.lag from `effects.lag` (firmware_sim/controller/controller_config.c), as
it refuses a network built for another checkpoint. `ddyn sil run --effects-from D [--config-only]` writes (and drives) the SIL's controller.json with it;
`apply_to_config` puts the same two sections into another configuration (a car's).

Which of the diagnosis's numbers: the selected effects' joint fit (`model.effects`) shares the response among
them, e.g. a 60 ms steering delay as steer_delay 29 ms + steer_lag; the runtime carries only the delay, so the
value applied is the delay fitted alone (`candidates`, each effect alone against the refitted nominal: the model
the runtime can carry), and the joint value when no candidate holds it. The runtime counts a delay in whole
periods, to the nearest (`floor(delay / period + 1/2)`, ddyn/controller.h; until issue 34 it rounded down, and an
estimate 5 % short of three periods acted as two); with the period known the value written is that nearest whole
number of periods, so the file says what acts. Both the estimate and the value written are recorded. Bad input (no such folder or file, not a diagnosis, a selected effect the diagnosis does not know) is
one DdynError line naming the file and the key.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from ddyn.errors import DdynError
# every name a diagnosis may select: the effects and the profile and channel candidates (bank_profile,
# bank_from_roll, ...), each with its main parameter
from ddyn.gap.candidates import ALL as EFFECT_NAMES
from ddyn.gap.candidates import MAIN_PARAM

DIAGNOSIS_FILE = "diagnosis.json"
# what the runtime applies: effect -> (ControllerEffects field: delays or lag, its key of ddyn.sil.run, the config
# key it becomes)
APPLIED = {"steer_delay": ("delays", "steer", "control.delay.steering"),
           "throttle_delay": ("delays", "throttle", "control.delay.throttle"),
           "steer_lag": ("lag", "steer", "control.lag.steering")}
# an applied effect left out when another is selected beside it (the joint fit splits one response between them)
NOT_WITH = {"steer_lag": "steer_delay"}
DELAY_MAX_S = 1.0   # the configuration's range of control.delay and control.lag (controller_config.c)


@dataclass
class ControllerEffects:
    """What a diagnosis gives the controller: the delays (ddyn.sil.run's controller_delays: steer, throttle),
    the steering lag (controller_lag: steer), the effects applied, one line per effect not applied, and where it
    came from."""
    delays: dict[str, float] = field(default_factory=dict)
    lag: dict[str, float] = field(default_factory=dict)
    applied: list[str] = field(default_factory=list)
    not_applied: list[str] = field(default_factory=list)
    diagnosis: str = ""
    sha256: str = ""
    selected: list[str] = field(default_factory=list)
    estimates: dict[str, float] = field(default_factory=dict)   # each selected effect's main parameter (joint fit)
    applied_estimates: dict[str, dict] = field(default_factory=dict)  # per applied effect: alone, joint, written

    def record(self) -> dict:
        """controller.json's `effects` section (the controller checks control.delay against `delay`, control.lag
        against `lag`)."""
        return {"diagnosis": self.diagnosis, "diagnosis_sha256": self.sha256,
                "delay": {"steering": float(self.delays.get("steer", 0.0)),
                          "throttle": float(self.delays.get("throttle", 0.0))},
                "lag": {"steering": float(self.lag.get("steer", 0.0))}}

    def summary(self) -> dict:
        """For sil_metrics.json and the study."""
        return {"diagnosis": self.diagnosis, "diagnosis_sha256": self.sha256, "selected": self.selected,
                "estimates": self.estimates, "applied_estimates": self.applied_estimates, "applied": self.applied, "not_applied": self.not_applied,
                "controller_delays": dict(self.delays), "controller_lag": dict(self.lag)}

    def lines(self) -> list[str]:
        def how(e):
            a = self.applied_estimates.get(e, {})
            src = (f"fitted alone {a['alone']:.4g} s" if a.get("alone") is not None else "joint fit") + \
                (f", joint {a['joint']:.4g} s" if a.get("alone") is not None else "")
            per = f", to whole periods of {a['period']:g} s" if a.get("period") and APPLIED[e][0] == "delays" else ""
            return f" ({src}{per})"
        out = [f"{e}: applied as {APPLIED[e][2]} = {getattr(self, APPLIED[e][0])[APPLIED[e][1]]:.4g} s{how(e)}"
               for e in self.applied]
        return out + self.not_applied


def diagnosis_path(where: str | Path) -> Path:
    """D/diagnosis.json for a folder D, or the file itself."""
    p = Path(where)
    if p.is_dir():
        p = p / DIAGNOSIS_FILE
    if not p.is_file():
        raise DdynError(f"{p}: no such file (expected the folder of `ddyn gap diagnose --out D` or its "
                        f"{DIAGNOSIS_FILE})")
    return p


def read_diagnosis(path: Path) -> dict:
    try:
        raw = path.read_bytes()
        d = json.loads(raw)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DdynError(f"{path}: not a diagnosis: not JSON ({e})") from None
    if not isinstance(d, dict):
        raise DdynError(f"{path}: not a diagnosis: a JSON {type(d).__name__}, not an object")
    for key in ("selected", "model"):
        if key not in d:
            raise DdynError(f"{path}: not a diagnosis: no key {key!r} (written by `ddyn gap diagnose --out D`)")
    if not isinstance(d["selected"], list) or not all(isinstance(e, str) for e in d["selected"]):
        raise DdynError(f"{path}: selected: expected a list of effect names, got {d['selected']!r}")
    if not isinstance(d["model"], dict) or not isinstance(d["model"].get("effects"), list):
        raise DdynError(f"{path}: model.effects: expected the list of the selected effects' estimates")
    return d


def _estimate(path: Path, d: dict, effect: str) -> float:
    """The selected effect's main parameter from model.effects (the joint fit of the selected ones)."""
    param = MAIN_PARAM[effect]
    for i, e in enumerate(d["model"]["effects"]):
        if isinstance(e, dict) and e.get("effect") == effect:
            v = (e.get("params") or {}).get(param)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise DdynError(f"{path}: model.effects[{i}].params.{param}: expected a finite number for "
                                f"{effect}, got {v!r}")
            return float(v)
    raise DdynError(f"{path}: model.effects: no estimate of the selected effect {effect!r}")


def _alone(path: Path, d: dict, effect: str) -> float | None:
    """The effect's main parameter fitted alone (its entry in `candidates`), None if the diagnosis has none."""
    cands = d.get("candidates")
    if not isinstance(cands, list):
        return None
    for i, c in enumerate(cands):
        if isinstance(c, dict) and c.get("effect") == effect:
            v = (c.get("params") or {}).get(MAIN_PARAM[effect])
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise DdynError(f"{path}: candidates[{i}].params.{MAIN_PARAM[effect]}: expected a finite number "
                                f"for {effect}, got {v!r}")
            return float(v)
    return None


def controller_effects(where: str | Path, period: float | None = None) -> ControllerEffects:
    """The controller's effects from a diagnosis (a folder D or D/diagnosis.json); period: the control period
    (s), to write each delay as the nearest whole number of periods (None: as estimated)."""
    if period is not None and not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
        raise DdynError(f"control.period: expected a number of seconds > 0, got {period!r}")
    path = diagnosis_path(where)
    d = read_diagnosis(path)
    fx = ControllerEffects(diagnosis=str(path.resolve()), sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
                           selected=list(d["selected"]))
    for i, name in enumerate(d["selected"]):
        if name not in EFFECT_NAMES:
            raise DdynError(f"{path}: selected[{i}]: unknown effect {name!r}; expected one of "
                            f"{', '.join(EFFECT_NAMES)}")
        value = _estimate(path, d, name)
        fx.estimates[name] = value
        if name in APPLIED and NOT_WITH.get(name) in d["selected"]:
            fx.not_applied.append(f"{name}: found {value:.4g}, not applied: selected with {NOT_WITH[name]}, whose "
                                  f"fit alone carries the response the two split")
        elif name in APPLIED:
            what, key, config_key = APPLIED[name]
            alone = _alone(path, d, name)
            est = alone if alone is not None else value
            # a delay acts in whole periods (the nearest); a lag's time constant is used as it is
            value = est if period is None or what != "delays" else round(est / period) * period
            fx.applied_estimates[name] = {"alone": alone, "joint": fx.estimates[name], "written": value,
                                          "period": period}
            if not 0.0 <= value <= DELAY_MAX_S:
                raise DdynError(f"{path}: model.effects: {name} {MAIN_PARAM[name]} = {value:g} s is outside "
                                f"{config_key.rsplit('.', 1)[0]}'s 0..{DELAY_MAX_S:g} s")
            getattr(fx, what)[key] = value
            fx.applied.append(name)
        else:
            fx.not_applied.append(f"{name}: not in the runtime (issue 34)")
    return fx


def apply_to_config(cfg: dict, fx: ControllerEffects) -> dict:
    """A controller configuration (docs/deploy.md) with fx's delays in control.delay, its lag in control.lag and
    the record in `effects`; every other key as it was."""
    out = json.loads(json.dumps(cfg))
    control = out.setdefault("control", {})
    if not isinstance(control, dict):
        raise DdynError("control: expected an object")
    rec = fx.record()
    control["delay"] = dict(rec["delay"])
    control["lag"] = dict(rec["lag"])
    out["effects"] = rec
    return out
