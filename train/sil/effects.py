"""From a diagnosis to the controller's configuration (issue 34, item 2): `ddyn sil run --effects-from D`.

`ddyn gap diagnose ... --out D` writes D/diagnosis.json; its `selected` effects (`model.effects`: each with its
`params`) are what the diagnosis claims. The controller's runtime carries actuation delays and a steering lag
(controller.json `control.delay`, `control.lag`), a mass offset (`control.mass_offset`), a downforce
(`control.downforce`) and the road's bank and grade (`control.bank`, `control.grade`; ddyn/controller.h), so:

    steer_delay     -> control.delay.steering: its `delay` fitted alone (the diagnosis's candidate of that name),
                       to the nearest whole control period when the period is known
    steer_lag       -> control.lag.steering: its `tau` fitted alone (likewise; a time constant, not rounded),
                       unless steer_delay is selected too: then not applied (the two split one response and
                       the delay fitted alone carries it: the laps of docs/sil.md's closed loop)
    throttle_delay  -> control.delay.throttle: its `delay` fitted alone, to the nearest whole control period, as
                       steer_delay (the compensation helps since the channels' delays were aligned, dfcabe6; the
                       loop with a throttle delay in the plant: docs/sil.md)
    bank_angle      -> control.bank true and raceline.csv's 6th column (the road's bank, rad) the constant angle
    bank_profile    -> control.bank true and the 6th column the profile at each raceline row's track position
                       (the row projected on the centre line, as the diagnosis placed its log's rows; the
                       diagnosis's own ddyn.gap.candidates.profile_at: its knots, linear, periodic along the lap),
                       when the diagnosis placed its rows on a track, and that track is the one driven (else one
                       line: not applied, or a DdynError naming the key when it is another track)
    bank_from_roll  -> not applied, named: diagnosis.json carries the gain and the roll channel's check, not the
                       log's roll along the track, which a column along the raceline would need
    mass_offset     -> control.mass_offset, when named first: its `fraction` of the joint fit (as the bank's:
                       fitted alone, the refitted nominal takes up part of it); the controller scales its
                       coefficients for that mass and the line's speeds (ddyn/controller.h); named after another
                       effect, or outside the controller's [-0.5, 1], it is named and not applied
    downforce       -> control.downforce, when named first: its `k` of the joint fit (s^2/m^2), as the mass
                       offset's (both are families a systematic mismatch of the whole nominal pays as, so a
                       second or third one is not trusted); outside the controller's [0, 0.5] named, not applied
    grade, grade_profile, grade_from_pitch
                    -> as the bank's: control.grade true and the raceline's grade column (the constant, or the profile
                       at each row's track position); the pitch channel's gain named, not applied
    a delay beyond the runtime's 6 control periods (DDYN_CTRL_MAX_DELAY_STEPS, with the period known) -> named, not
                       applied (the controller would refuse the whole configuration)
    anything else   -> not applied, named: "tire_wear: not in the runtime"

The configuration records where its delays, lag, mass offset, downforce and bank came from (`effects`: the diagnosis's
path, the sha256 of its diagnosis.json, the delays, the lag, the mass offset and the downforce it gave, and with a bank `bank` true, `bank_peak` the column's largest
|bank| and `bank_from` a line saying which effect); the controller refuses a file whose control.delay differs from
the recorded `effects.delay`, control.lag from `effects.lag`, control.mass_offset from `effects.mass_offset`,
control.downforce from `effects.downforce`, control.bank from `effects.bank`, control.grade from `effects.grade`,
or whose raceline's bank (grade) column does not peak at `effects.bank_peak` (`effects.grade_peak`) (firmware_sim/controller/controller_config.c), as it refuses a
network built for another checkpoint. `ddyn sil run --effects-from D [--config-only]` writes (and drives) the SIL's controller.json with it;
`apply_to_config` puts the same sections into another configuration (a car's; a diagnosed bank's column, made by
`bank_column`, into its raceline by the caller).

Which of the diagnosis's numbers: the selected effects' joint fit (`model.effects`) shares the response among
them, e.g. a 60 ms steering delay as steer_delay 29 ms + steer_lag; the runtime carries only the delay, so the
value applied is the delay fitted alone (`candidates`, each effect alone against the refitted nominal: the model
the runtime can carry), and the joint value when no candidate holds it. The runtime counts a delay in whole
periods, to the nearest (`floor(delay / period + 1/2)`, ddyn/controller.h; until issue 34 it rounded down, and an
estimate 5 % short of three periods acted as two); with the period known the value written is that nearest whole
number of periods, so the file says what acts. Both the estimate and the value written are recorded. Bad input (no such folder or file, not a diagnosis, a selected effect the diagnosis does not know) is
one DdynError line naming the file and the key.

The bank applied is the selected model's (`model.effects`, the joint fit): unlike a delay and a lag, no other
applied effect shares its response.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
# every name a diagnosis may select: the effects and the profile and channel candidates (bank_profile,
# bank_from_roll, ...), each with its main parameter
from ddyn.gap.candidates import ALL as EFFECT_NAMES
from ddyn.gap.candidates import MAIN_PARAM, profile_at

DIAGNOSIS_FILE = "diagnosis.json"
# what the runtime applies: effect -> (ControllerEffects field: delays or lag, its key of ddyn.sil.run, the config
# key it becomes)
APPLIED = {"steer_delay": ("delays", "steer", "control.delay.steering"),
           "throttle_delay": ("delays", "throttle", "control.delay.throttle"),
           "steer_lag": ("lag", "steer", "control.lag.steering")}
# an applied effect left out when another is selected beside it (the joint fit splits one response between them)
NOT_WITH = {"steer_lag": "steer_delay"}
DELAY_MAX_S = 1.0   # the configuration's range of control.delay and control.lag (controller_config.c)
# the runtime's compiled maximum delay in control periods (DDYN_CTRL_MAX_DELAY_STEPS, ddyn/controller.h): a longer
# one is named and not applied (the controller would refuse the whole configuration)
MAX_DELAY_PERIODS = 6
BANK = ("bank_angle", "bank_profile", "bank_from_roll")   # the bank family (one at most is selected)
BANK_MAX_RAD = math.radians(45.0)   # the controller refuses a bank column reaching 45 degrees (DDYN_MPC_MAX_BANK)
GRADE = ("grade", "grade_profile", "grade_from_pitch")    # the grade family, mapped as the bank's
GRADE_MAX_RAD = math.radians(20.0)  # the controller refuses a grade column reaching 20 degrees (DDYN_MPC_MAX_GRADE)
# each road family: its members, (constant, profile, channel), the controller's limit and that limit in words
ROAD = {"bank": (BANK, BANK_MAX_RAD, "45 degrees"), "grade": (GRADE, GRADE_MAX_RAD, "20 degrees")}
MASS_OFFSET_RANGE = (-0.5, 1.0)     # control.mass_offset's range (DDYN_CTRL_MASS_OFFSET_MIN/MAX)
DOWNFORCE_RANGE = (0.0, 0.5)        # control.downforce's range, s^2/m^2 (0..DDYN_MODEL_DOWNFORCE_MAX)
# nominal-wide families: applied only when named first (see mass_offset in controller_effects)
FIRST_ONLY = {"mass_offset": ("mass_offset", MASS_OFFSET_RANGE), "downforce": ("downforce", DOWNFORCE_RANGE)}


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
    bank: dict | None = None   # the diagnosed bank (_road): effect, kind constant/profile, angle or profile, track
    grade: dict | None = None  # the diagnosed grade (_road), as the bank
    mass_offset: float = 0.0   # the mass offset (control.mass_offset; 0: none)
    downforce: float = 0.0     # the downforce k, s^2/m^2 (control.downforce; 0: none)

    def record(self, bank_column=None, grade_column=None) -> dict:
        """controller.json's `effects` section (the controller checks control.delay against `delay`, control.lag
        against `lag`, control.bank against `bank` and the raceline's bank column against `bank_peak`).
        bank_column: the column made from self.bank (bank_column()); the bank keys only with a bank."""
        return record(self.summary(), bank_column, grade_column)

    def summary(self) -> dict:
        """For sil_metrics.json and the study (and SilSpec.effects_from: what the configuration is made from)."""
        return {"diagnosis": self.diagnosis, "diagnosis_sha256": self.sha256, "selected": self.selected,
                "estimates": self.estimates, "applied_estimates": self.applied_estimates, "applied": self.applied, "not_applied": self.not_applied,
                "controller_delays": dict(self.delays), "controller_lag": dict(self.lag),
                "controller_mass_offset": self.mass_offset, "controller_downforce": self.downforce,
                "bank": self.bank, "grade": self.grade}

    def lines(self) -> list[str]:
        def how(e):
            a = self.applied_estimates.get(e, {})
            src = (f"fitted alone {a['alone']:.4g} s" if a.get("alone") is not None else "joint fit") + \
                (f", joint {a['joint']:.4g} s" if a.get("alone") is not None else "")
            per = f", to whole periods of {a['period']:g} s" if a.get("period") and APPLIED[e][0] == "delays" else ""
            return f" ({src}{per})"
        out = [f"{e}: applied as {APPLIED[e][2]} = {getattr(self, APPLIED[e][0])[APPLIED[e][1]]:.4g} s{how(e)}"
               for e in self.applied if e in APPLIED]
        for name in FIRST_ONLY:
            if name in self.applied:
                alone = self.applied_estimates.get(name, {}).get("alone")
                out.append(f"{name}: applied as control.{name} = {getattr(self, name):.4g} (joint fit"
                           + (f"; fitted alone {alone:.4g}" if alone is not None else "") + ")")
        if self.bank is not None:
            out.append(f"{self.bank['effect']}: applied as control.bank = true, raceline.csv's bank column "
                       f"{bank_from(self.bank)}")
        if self.grade is not None:
            out.append(f"{self.grade['effect']}: applied as control.grade = true, raceline.csv's grade column "
                       f"{bank_from(self.grade)}")
        return out + self.not_applied


def record(summary: dict, bank_column=None, grade_column=None) -> dict:
    """controller.json's `effects` section from a ControllerEffects.summary() (what SilSpec.effects_from holds)
    and, when the summary has a bank (a grade), the bank (grade) column made from it."""
    rec = {"diagnosis": summary["diagnosis"], "diagnosis_sha256": summary["diagnosis_sha256"],
           "delay": {"steering": float(summary["controller_delays"].get("steer", 0.0)),
                     "throttle": float(summary["controller_delays"].get("throttle", 0.0))},
           "lag": {"steering": float(summary["controller_lag"].get("steer", 0.0))},
           "mass_offset": float(summary.get("controller_mass_offset", 0.0)),
           "downforce": float(summary.get("controller_downforce", 0.0))}
    bank = summary.get("bank")
    if bank is not None:
        if bank_column is None:
            raise DdynError(f"{summary['diagnosis']}: {bank['effect']}: a diagnosed bank is raceline.csv's 6th "
                            "column: make it with the raceline (ddyn.sil.effects.bank_column; `ddyn sil run "
                            "--effects-from D --config-only` writes both)")
        # the largest |bank| of the column as written: the controller compares it with the column it reads
        rec |= {"bank": True, "bank_peak": float(np.max(np.abs(np.asarray(bank_column, float)))),
                "bank_from": f"{bank['effect']}: {bank_from(bank)}"}
    grade = summary.get("grade")
    if grade is not None:
        if grade_column is None:
            raise DdynError(f"{summary['diagnosis']}: {grade['effect']}: a diagnosed grade is raceline.csv's grade "
                            "column: make it with the raceline (ddyn.sil.effects.grade_column; `ddyn sil run "
                            "--effects-from D --config-only` writes both)")
        rec |= {"grade": True, "grade_peak": float(np.max(np.abs(np.asarray(grade_column, float))))}
    return rec


def bank_from(bank: dict) -> str:
    """One line: which bank (or grade) the column is."""
    if bank["kind"] == "constant":
        return f"the constant {bank['angle']:.4g} rad ({math.degrees(bank['angle']):.3g} deg) on every row"
    p = bank["profile"]
    return (f"the profile at each row's position on track {bank['track']} ({len(p['knots_m'])} knots, linear, "
            f"peak {bank['peak']:.4g} rad = {math.degrees(bank['peak']):.3g} deg)")


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


def _effect_index(path: Path, d: dict, effect: str) -> int:
    for i, e in enumerate(d["model"]["effects"]):
        if isinstance(e, dict) and e.get("effect") == effect:
            return i
    raise DdynError(f"{path}: model.effects: no estimate of the selected effect {effect!r}")


def _numbers(path: Path, key: str, v, n: int | None = None) -> list[float]:
    """A list of finite numbers (n of them when given), else one DdynError line naming the key."""
    if (not isinstance(v, list) or not v or (n is not None and len(v) != n)
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        want = f"{n} finite numbers" if n is not None else "a list of finite numbers"
        raise DdynError(f"{path}: {key}: expected {want}, got {str(v)[:80]}")
    return [float(x) for x in v]


def _profile_track(position_from: str) -> str | None:
    """The track a profile's positions lie on ("track oval, knots tied to its curvature" -> "oval"); None when
    the diagnosis placed its rows along the log's own lap or the distance it travelled (ddyn.gap.candidates
    layout)."""
    if not position_from.startswith("track "):
        return None
    return position_from[len("track "):].split(",", 1)[0].strip() or None


def _road(path: Path, d: dict, name: str, kind: str = "bank") -> tuple[dict | None, str | None]:
    """(the diagnosed bank (kind "bank") or grade ("grade") to apply, or None with the one-line reason it is not
    applied)."""
    (constant, _, channel), limit, words = ROAD[kind]
    i = _effect_index(path, d, name)
    e = d["model"]["effects"][i]
    value = _estimate(path, d, name)
    if name == channel:
        what = "roll" if kind == "bank" else "pitch"
        return None, (f"{name}: found gain {value:.4g}, not applied: diagnosis.json carries the gain and the "
                      f"{what} channel's check, not the log's {what} along the track, which a {kind} column along "
                      "the raceline needs")
    if name == constant:
        if not abs(value) < limit:
            raise DdynError(f"{path}: model.effects[{i}].params.angle: {value:g} rad, beyond the controller's "
                            f"+-{limit:.4g} rad ({words})")
        return {"effect": name, "kind": "constant", "angle": value, "peak": value, "index": i}, None
    key = f"model.effects[{i}].profile"
    prof = e.get("profile")
    if not isinstance(prof, dict):
        raise DdynError(f"{path}: {key}: expected the fitted profile (knots_m, angle_rad, periodic_length_m, "
                        "position_from)")
    knots = _numbers(path, f"{key}.knots_m", prof.get("knots_m"))
    angle = _numbers(path, f"{key}.angle_rad", prof.get("angle_rad"), len(knots))
    if any(b <= a for a, b in zip(knots, knots[1:])):
        raise DdynError(f"{path}: {key}.knots_m: expected ascending positions")
    if max(abs(a) for a in angle) >= limit:
        raise DdynError(f"{path}: {key}.angle_rad: reaches {max(abs(a) for a in angle):g} rad, beyond the "
                        f"controller's +-{limit:.4g} rad ({words})")
    length = prof.get("periodic_length_m")
    if length is not None and not (isinstance(length, (int, float)) and not isinstance(length, bool)
                                   and math.isfinite(length) and length > knots[-1]):
        raise DdynError(f"{path}: {key}.periodic_length_m: expected null or a lap length beyond the last knot, got "
                        f"{length!r}")
    where = prof.get("position_from")
    if not isinstance(where, str):
        raise DdynError(f"{path}: {key}.position_from: expected where the positions come from, got {where!r}")
    track = _profile_track(where)
    if track is None or length is None:
        return None, (f"{name}: peak {value:.4g} rad, not applied: its positions are {where!r}, not a "
                      "track's, so the raceline's rows cannot be placed on them (diagnose with the track known: "
                      "the log's `track` metadata or --track)")
    return {"effect": name, "kind": "profile", "peak": value, "index": i, "track": track,
            "profile": {"knots_m": knots, "angle_rad": angle, "periodic_length_m": float(length),
                        "position_from": where}}, None


def bank_column(summary: dict, track, table: np.ndarray, kind: str = "bank") -> np.ndarray:
    """raceline.csv's bank column (rad per row) from the diagnosed bank of a ControllerEffects.summary() (kind
    "grade": its grade column from the diagnosed grade): the constant on every row, or the profile at each row's
    position (the row projected on the track's centre line, as the diagnosis placed its log's rows; evaluated by
    the diagnosis's own ddyn.gap.candidates.profile_at). A profile fitted on another track (or another lap length)
    is refused, naming the key."""
    bank = summary[kind]
    path = summary["diagnosis"]
    if bank["kind"] == "constant":
        return np.full(len(table), float(bank["angle"]))
    key = f"model.effects[{bank['index']}].profile"
    prof = bank["profile"]
    if bank["track"] != track.name:
        raise DdynError(f"{path}: {key}.position_from: the profile lies along track {bank['track']!r}, but the "
                        f"controller drives {track.name!r}")
    if abs(prof["periodic_length_m"] - float(track.length)) > 1e-6 * float(track.length):
        raise DdynError(f"{path}: {key}.periodic_length_m: {prof['periodic_length_m']:g} m, but track "
                        f"{track.name!r} is {float(track.length):g} m long")
    s, _ = track.project(table[:, 0], table[:, 1])
    return np.asarray(profile_at(prof, s), float)


def grade_column(summary: dict, track, table: np.ndarray) -> np.ndarray:
    """raceline.csv's grade column from the diagnosed grade (as bank_column's)."""
    return bank_column(summary, track, table, "grade")


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
        elif name in BANK or name in GRADE:
            kind = "bank" if name in BANK else "grade"
            road, why = _road(path, d, name, kind)
            setattr(fx, kind, road)
            if road is None:
                fx.not_applied.append(why)
            else:
                fx.applied.append(name)
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
            if what == "delays" and period is not None and value > MAX_DELAY_PERIODS * period * (1.0 + 1e-9):
                # seen: a false 0.18 s throttle delay on a graded random:302 log stopped the rebuilt controller
                fx.not_applied.append(f"{name}: found {est:.4g} s, not applied: beyond the runtime's "
                                      f"{MAX_DELAY_PERIODS} control periods ({MAX_DELAY_PERIODS * period:g} s; "
                                      "DDYN_CTRL_MAX_DELAY_STEPS)")
                continue
            getattr(fx, what)[key] = value
            fx.applied.append(name)
        elif name in FIRST_ONLY:
            # the joint fit's (as the bank's), not the one fitted alone: alone, against the refitted nominal, the
            # nominal's own refit takes up part of a mass offset (on ETHZMobil's logs of `ddyn study sil-loop`
            # with -10 % and +20 % in the plant: alone -0.148 and +0.115, joint -0.111 and +0.159)
            attr, (lo, hi) = FIRST_ONLY[name]
            alone = _alone(path, d, name)
            est = value
            fx.applied_estimates[name] = {"alone": alone, "joint": fx.estimates[name], "written": est}
            if i > 0:
                # named after another effect: on ETHZMobil's logs of the loop (effect-free, steering and throttle
                # delays, lags at seeds 1 and 2, mass offsets at seed 1) a mass offset named second or third was a
                # false claim in 9 of 10 cases (the tenth: the +10 % offset, after a 2.5 ms lag); a downforce, the
                # other family a mismatch of the whole nominal pays as, is held to the same rule
                fx.not_applied.append(f"{name}: found {est:.4g}, not applied: named after {d['selected'][0]} "
                                      f"(a {name.replace('_', ' ')} is applied only when named first)")
            elif lo <= est <= hi:
                setattr(fx, attr, est)
                fx.applied.append(name)
            else:
                fx.not_applied.append(f"{name}: found {est:.4g}, not applied: outside the controller's "
                                      f"control.{name} range [{lo:g}, {hi:g}]")
        else:
            fx.not_applied.append(f"{name}: not in the runtime")
    return fx


def apply_to_config(cfg: dict, fx: ControllerEffects, bank_column=None, grade_column=None) -> dict:
    """A controller configuration (docs/deploy.md) with fx's delays in control.delay, its lag in control.lag, its
    mass offset in control.mass_offset, its downforce in control.downforce, control.bank (true with a diagnosed bank, whose column, bank_column(), the caller writes into the raceline)
    and the record in `effects`; every other key as it was."""
    out = json.loads(json.dumps(cfg))
    control = out.setdefault("control", {})
    if not isinstance(control, dict):
        raise DdynError("control: expected an object")
    rec = fx.record(bank_column, grade_column)
    control["delay"] = dict(rec["delay"])
    control["lag"] = dict(rec["lag"])
    control["mass_offset"] = rec["mass_offset"]
    control["downforce"] = rec["downforce"]
    if fx.bank is not None:
        control["bank"] = True
    elif control.get("bank"):
        # the controller refuses a bank its effects do not record; dropping the car's own would change its drive
        raise DdynError("control.bank: true in the configuration, but the diagnosis gives no bank: remove the bank "
                        "(control.bank and the raceline's 6th column) first, or diagnose a log that finds it")
    if fx.grade is not None:
        control["grade"] = True
    elif control.get("grade"):
        raise DdynError("control.grade: true in the configuration, but the diagnosis gives no grade: remove the grade "
                        "(control.grade and the raceline's grade column) first, or diagnose a log that finds it")
    out["effects"] = rec
    return out
