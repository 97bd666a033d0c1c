"""Unmodelled effects, composed on top of the one vehicle model (ddyn.model.single_track).

Each effect is off by default and has one main parameter (zero means off):

  steer_delay      delay      s      the tyres see the steering commanded `delay` seconds ago
  throttle_delay   delay      s      the drivetrain sees the throttle commanded `delay` seconds ago
  steer_lag        tau        s      first-order lag between commanded and actual steering
  bank_angle       angle      rad    road bank: lateral gravity g sin(angle) (positive pushes to the left, +vy)
  grade            angle      rad    road slope: longitudinal gravity -g sin(angle) (positive: uphill)
  downforce        k          s2/m2  tyre peak forces Df, Dr scaled by 1 + k vx^2
  combined_slip    coupling   -      friction ellipse: Fry scaled by sqrt(1 - (coupling Frx / Dr)^2)
  tire_relaxation  length     m      slip angles relax to their steady value with time constant length / vx
  tire_wear        rate       1/s    tyre peak forces Df, Dr scaled by exp(-rate t), t since the log's start
  yaw_rate_bias    bias       rad/s  the yaw-rate sensor reads omega + bias (the dynamics are unchanged)
  mass_offset      fraction   -      the mass is m (1 + fraction) (Iz, lf, lr unchanged)
  throttle_map     shape      -      pedal map shape: the drive force sees T + shape T (1 - T) for T in [0, 1]
                                     (shape > 0: more force at part throttle; full and zero throttle unchanged)
  brake_gain       fraction   -      the braking force (T < 0) is (1 + fraction) times the nominal's
  power_limit      power      W      the drive force is capped at power / vx (an engine's power limit; 0: off)
  gear_step        step       -      stepped gearbox: the drive force is (1 + step)^(GEAR_REF - gear(vx)) times the
                                     nominal's, gears changing at GEAR_SHIFTS (the car's table; the step is fitted)

Drivetrain effects (the last four) act on the drive term (Cm1 - Cm2 vx) T of the drivetrain force only;
rolling resistance and drag are unchanged.

bank_angle and grade may vary along the track (position s): params `profile` "constant"
(default: `angle`), "sinusoid" (angle + amplitude sin(2 pi s / wavelength + phase);
wavelength defaults to the track length), "piecewise" (`breaks` [[s0, a0], [s1, a1], ...]:
angle a_i from s_i to the next break, periodic along the lap), "linear" (the same breaks as
knots, linearly interpolated between them: periodic along the lap when the track length is
known, held beyond the first and last knot otherwise; what the diagnosis fits) or "channel"
(angle = `amplitude` x a logged channel, `channel` (e.g. "roll"), per row: bank from the log's
roll channel when that is plausible; the predictor on a log only).

A spec is {"effect": name, "params": {...}}; parse_effects reads JSON (a list of specs, one
spec, or {name: value-or-params}) or key=value strings ("steer_delay=0.04",
"bank_angle.profile=sinusoid", comma- or space-separated).

No equation of the model is re-typed: `derivatives` modifies the coefficient tuple (peak
forces, slip-angle shifts) before ddyn.model.single_track.forces, scales Fry after it, gives
ddyn.model.single_track.rigid_body a changed mass, and adds the gravity terms to its result. It is
written against a math namespace, so it serves numpy, torch and CasADi alike.

Memory. Delays, the steering lag and tyre relaxation need history; they are carried by
the caller as an augmented state (the simulator, `Plant`) or recomputed from the logged
history (the predictor, `LogModel`), with the same update rules:
  - delays: the effective throttle/steering at row k is the commanded one at t_k - delay,
    linearly interpolated between samples (held at the first sample before the start of a
    segment); over the step it moves linearly to its value at t_k+1 - delay;
  - steer_lag: z_k+1 = u_k+1 - tau r + (z_k - u_k + tau r) exp(-Ts/tau), the exact solution
    of tau dz/dt = u - z for an input u moving linearly (rate r) over the step; z_0 = u_0;
  - tire_relaxation: alpha_eff_k = alpha_k + (alpha_eff_k-1 - alpha_k) exp(-Ts vx*/length), the
    exact first-order relaxation with the slip angle held at its value at the end of the
    interval; the step then uses the slip angles shifted by alpha_eff_k - alpha_k (the
    shift enters as an offset to Gf, Gr), held over the step; alpha_eff_-1 = alpha_0;
  - tire_wear needs only the time since the start of the log.
The vehicle state keeps the commanded throttle and steering (what the controller sets and
the log records); the effective ones are used only inside the step.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from ddyn.errors import DdynError
from ddyn.model import integrators, mathns
from ddyn.model import single_track as model
from ddyn.model.single_track import N_COEFF, N_INPUT, N_STATE, KnownParams

G = 9.81
ELLIPSE_FLOOR = 0.1          # the friction ellipse never takes away more than 90 % of Fry
EFFECT_NAMES = ("steer_delay", "throttle_delay", "steer_lag", "bank_angle", "grade", "downforce",
                "combined_slip", "tire_relaxation", "tire_wear", "yaw_rate_bias", "mass_offset")
# drivetrain effects for vx gaps (issue 14); kept out of EFFECT_NAMES, the own-model benchmark's effect set
DRIVETRAIN = ("throttle_map", "brake_gain", "power_limit", "gear_step")
# gear_step: a road car's five-speed gearbox, upshifting at these speeds (m/s); the drive force in gear n is
# (1 + step)^(GEAR_REF - n) times the nominal's. The shift speeds are the car's gearbox table (known to its
# owner, like its mass); what the candidate estimates is the force step between gears. Each shift is a smooth
# ramp GEAR_RAMP m/s wide (written with fmax only, for the numpy, torch and CasADi backends).
GEAR_SHIFTS = (8.0, 14.0, 20.0, 27.0)
GEAR_REF = 3
GEAR_RAMP = 1.0
ALL_EFFECTS = EFFECT_NAMES + DRIVETRAIN
MAIN_PARAM = {"steer_delay": "delay", "throttle_delay": "delay", "steer_lag": "tau", "bank_angle": "angle",
              "grade": "angle", "downforce": "k", "combined_slip": "coupling", "tire_relaxation": "length",
              "tire_wear": "rate", "yaw_rate_bias": "bias", "mass_offset": "fraction",
              "throttle_map": "shape", "brake_gain": "fraction", "power_limit": "power", "gear_step": "step"}
UNITS = {"steer_delay": "s", "throttle_delay": "s", "steer_lag": "s", "bank_angle": "rad", "grade": "rad",
         "downforce": "s2/m2", "combined_slip": "-", "tire_relaxation": "m", "tire_wear": "1/s",
         "yaw_rate_bias": "rad/s", "mass_offset": "-", "throttle_map": "-", "brake_gain": "-", "power_limit": "W",
         "gear_step": "-"}
PROFILE_PARAMS = ("profile", "amplitude", "wavelength", "phase", "breaks", "channel")
PROFILES = ("constant", "sinusoid", "piecewise", "linear", "channel")


# ----------------------------------------------------------------------------------------------- specs

@dataclass(frozen=True)
class Effect:
    effect: str
    params: dict = field(default_factory=dict)

    @property
    def value(self) -> float:
        return float(self.params.get(MAIN_PARAM[self.effect], 0.0))

    def to_dict(self) -> dict:
        return {"effect": self.effect, "params": dict(self.params)}


def _check(e: Effect) -> Effect:
    if e.effect not in MAIN_PARAM:
        raise DdynError(f"unknown effect {e.effect!r}; expected one of {', '.join(ALL_EFFECTS)}")
    allowed = {MAIN_PARAM[e.effect]} | (set(PROFILE_PARAMS) if e.effect in ("bank_angle", "grade") else set())
    bad = sorted(set(e.params) - allowed)
    if bad:
        raise DdynError(f"effect {e.effect}: unknown parameter(s) {', '.join(bad)}; expected {', '.join(sorted(allowed))}")
    for k, v in e.params.items():
        if k in ("profile", "breaks", "channel"):
            continue
        if not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise DdynError(f"effect {e.effect}: parameter {k} must be a finite number, got {v!r}")
    if e.params.get("profile", "constant") not in PROFILES:
        raise DdynError(f"effect {e.effect}: profile must be one of {', '.join(PROFILES)}")
    if e.params.get("profile") in ("piecewise", "linear"):
        br = e.params.get("breaks")
        try:
            ok = len(br) >= 1 and all(len(b) == 2 and all(math.isfinite(float(x)) for x in b) for b in br)
        except TypeError:
            ok = False
        if not ok:
            raise DdynError(f"effect {e.effect}: a piecewise or linear profile needs breaks [[s0, angle0], [s1, angle1], ...]")
    if e.params.get("profile") == "channel" and not isinstance(e.params.get("channel"), str):
        raise DdynError(f"effect {e.effect}: a channel profile needs the logged channel's name (channel=roll)")
    if e.effect in ("steer_delay", "throttle_delay", "steer_lag", "tire_relaxation", "power_limit") and e.value < 0:
        raise DdynError(f"effect {e.effect}: {MAIN_PARAM[e.effect]} must be non-negative, got {e.value}")
    if e.effect in ("brake_gain", "gear_step") and not e.value > -1:
        raise DdynError(f"effect {e.effect}: {MAIN_PARAM[e.effect]} must exceed -1, got {e.value}")
    if e.effect == "mass_offset" and not e.value > -1:
        raise DdynError(f"effect mass_offset: fraction must exceed -1, got {e.value}")
    return e


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_effects(spec) -> list[Effect]:
    """Effects from JSON text, key=value text, a dict, a list of dicts/Effects, or None (no effects)."""
    if spec is None:
        return []
    if isinstance(spec, Effect):
        return [_check(spec)]
    if isinstance(spec, (list, tuple)):
        out: list[Effect] = []
        for item in spec:
            out += parse_effects(item)
        names = [e.effect for e in out]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise DdynError(f"effect(s) given twice: {', '.join(dup)}")
        return out
    if isinstance(spec, dict):
        if "effect" in spec:
            params = spec.get("params", {})
            if not isinstance(params, dict):
                raise DdynError(f"effect {spec['effect']}: params must be an object")
            return [_check(Effect(str(spec["effect"]), dict(params)))]
        return parse_effects([{"effect": k, "params": v if isinstance(v, dict) else {MAIN_PARAM.get(k, "value"): v}}
                              for k, v in spec.items()])
    text = str(spec).strip()
    if not text:
        return []
    if text[0] in "[{":
        try:
            return parse_effects(json.loads(text))
        except json.JSONDecodeError as e:
            raise DdynError(f"--effects: not valid JSON: {e}") from None
    params: dict[str, dict] = {}
    for token in text.replace(",", " ").split():
        if "=" not in token:
            raise DdynError(f"--effects: expected name=value or name.param=value, got {token!r}")
        key, val = token.split("=", 1)
        name, _, param = key.partition(".")
        if name not in MAIN_PARAM:
            raise DdynError(f"unknown effect {name!r}; expected one of {', '.join(ALL_EFFECTS)}")
        slot = params.setdefault(name, {})
        if (param or MAIN_PARAM[name]) in slot:
            raise DdynError(f"--effects: {key} given twice")
        slot[param or MAIN_PARAM[name]] = _value(val)
    return parse_effects([{"effect": k, "params": v} for k, v in params.items()])


def effects_json(effects: Sequence[Effect]) -> str:
    return json.dumps([e.to_dict() for e in effects], sort_keys=True)


# ----------------------------------------------------------------------------------------------- profiles

@dataclass(frozen=True)
class Profile:
    """An angle as a function of track position s (bank_angle, grade)."""

    angle: float = 0.0
    kind: str = "constant"
    amplitude: float = 0.0
    wavelength: float | None = None
    phase: float = 0.0
    breaks: tuple = ()
    channel: str | None = None

    @classmethod
    def of(cls, params: dict) -> "Profile":
        return cls(float(params.get("angle", 0.0)), params.get("profile", "constant"),
                   float(params.get("amplitude", 0.0)),
                   None if params.get("wavelength") is None else float(params["wavelength"]),
                   float(params.get("phase", 0.0)),
                   tuple(sorted((float(a), float(b)) for a, b in params.get("breaks", ()))),
                   params.get("channel"))

    def active(self) -> bool:
        return self.angle != 0.0 or (self.kind in ("sinusoid", "channel") and self.amplitude != 0.0) or \
            (self.kind in ("piecewise", "linear") and any(b != 0.0 for _, b in self.breaks))

    def needs_position(self) -> bool:
        return self.kind not in ("constant", "channel")

    def at(self, s, track_length: float | None = None):
        if self.kind == "constant":
            return self.angle
        if self.kind == "channel":
            raise DdynError(f"a bank/grade profile from the logged channel {self.channel!r} exists on a log only")
        if s is None:
            raise DdynError(f"a {self.kind} bank/grade profile needs the track position s")
        s = np.asarray(s, dtype=float)
        if self.kind == "sinusoid":
            lam = self.wavelength or track_length
            if not lam:
                raise DdynError("a sinusoid profile needs a wavelength (or a track length)")
            return self.angle + self.amplitude * np.sin(2.0 * np.pi * s / lam + self.phase)
        starts = np.array([b[0] for b in self.breaks])
        angles = np.array([b[1] for b in self.breaks])
        if self.kind == "linear":
            if track_length:
                return np.interp(np.mod(s, track_length), starts, angles, period=track_length)
            return np.interp(s, starts, angles)
        if track_length:
            s = np.mod(s, track_length)
        i = np.searchsorted(starts, s, side="right") - 1   # before the first break: the last one (periodic)
        return angles[i]


# ----------------------------------------------------------------------------------------------- the effect set

@dataclass(frozen=True)
class EffectSet:
    """The active effects as plain values (0 / None: off)."""

    steer_delay: float = 0.0
    throttle_delay: float = 0.0
    steer_lag: float = 0.0
    bank: Profile | None = None
    grade: Profile | None = None
    downforce: float = 0.0
    combined_slip: float = 0.0
    relaxation: float = 0.0
    wear: float = 0.0
    yaw_bias: float = 0.0
    mass_offset: float = 0.0
    throttle_map: float = 0.0
    brake_gain: float = 0.0
    power_limit: float = 0.0
    gear_step: float = 0.0
    # mass_offset scales the yaw inertia Iz with the mass (a car scaled as a whole, the tyre peak forces refitted
    # with the load: then it changes only the longitudinal response); off: Iz unchanged (the effect's definition
    # above, what the own-model benchmark simulates). Set by `diagnose --mass-inertia`.
    mass_inertia: bool = False

    @classmethod
    def of(cls, effects) -> "EffectSet":
        kw: dict[str, Any] = {}
        field_of = {"steer_delay": "steer_delay", "throttle_delay": "throttle_delay", "steer_lag": "steer_lag",
                    "downforce": "downforce", "combined_slip": "combined_slip", "tire_relaxation": "relaxation",
                    "tire_wear": "wear", "yaw_rate_bias": "yaw_bias", "mass_offset": "mass_offset",
                    "throttle_map": "throttle_map", "brake_gain": "brake_gain", "power_limit": "power_limit",
                    "gear_step": "gear_step"}
        for e in parse_effects(effects) if not isinstance(effects, EffectSet) else []:
            if e.effect in ("bank_angle", "grade"):
                prof = Profile.of(e.params)
                kw["bank" if e.effect == "bank_angle" else "grade"] = prof if prof.active() else None
            else:
                kw[field_of[e.effect]] = e.value
        return effects if isinstance(effects, EffectSet) else cls(**kw)

    @classmethod
    def from_values(cls, values: dict[str, float]) -> "EffectSet":
        """From {effect name: main parameter} (bank and grade constant): what the diagnosis fits."""
        return cls.of([{"effect": k, "params": {MAIN_PARAM[k]: float(v)}} for k, v in values.items()])

    def active(self) -> bool:
        return any((self.steer_delay, self.throttle_delay, self.steer_lag, self.bank, self.grade, self.downforce,
                    self.combined_slip, self.relaxation, self.wear, self.yaw_bias, self.mass_offset,
                    self.throttle_map, self.brake_gain, self.power_limit, self.gear_step))

    def shapes_inputs(self) -> bool:
        return bool(self.steer_delay or self.throttle_delay or self.steer_lag)


@dataclass
class Aux:
    """Per-step quantities the derivative needs besides state, inputs and coefficients."""

    time: Any = None            # s since the start of the log (tire_wear)
    slip_offset: Any = None     # (d alpha_f, d alpha_r) from tyre relaxation
    bank: Any = None            # rad at the row's track position
    grade: Any = None


# ----------------------------------------------------------------------------------------------- the dynamics

def derivatives(ns: mathns.MathNamespace, state: Sequence, inputs: Sequence, coeffs: Sequence, p: KnownParams,
                fx: EffectSet, aux: Aux) -> tuple:
    """ddyn.model.single_track.derivatives with the effects of fx composed in (state: effective throttle/steering)."""
    vx = state[3]
    c = list(coeffs)
    scale = None
    if fx.downforce:
        scale = 1.0 + fx.downforce * vx * vx
    if fx.wear:
        w = ns.exp(-fx.wear * aux.time)
        scale = w if scale is None else scale * w
    if scale is not None:
        c[2], c[8] = c[2] * scale, c[8] * scale
    if aux.slip_offset is not None:
        c[4], c[10] = c[4] + aux.slip_offset[0], c[10] + aux.slip_offset[1]
    f = model.forces(ns, state, c, p)
    Frx = f.Frx
    if fx.throttle_map or fx.brake_gain or fx.power_limit or fx.gear_step:
        Frx = Frx + _drive_change(ns, state[6], vx, c[12], c[13], fx, p)
    Fry = f.Fry
    if fx.combined_slip:
        x = fx.combined_slip * Frx / c[8]
        Fry = Fry * ns.sqrt(ns.fmax(1.0 - x * x, ELLIPSE_FLOOR ** 2))
    q = p._replace(mass=p.mass * (1.0 + fx.mass_offset)) if fx.mass_offset else p
    iz = c[16] * (1.0 + fx.mass_offset) if fx.mass_inertia else c[16]
    d = list(model.rigid_body(ns, state, inputs, f.Ffy, Fry, Frx, iz, q))
    if aux.grade is not None:
        d[3] = d[3] - G * ns.sin(aux.grade)
    if aux.bank is not None:
        d[4] = d[4] + G * ns.sin(aux.bank)
    return tuple(d)


def _drive_change(ns: mathns.MathNamespace, T, vx, Cm1, Cm2, fx: EffectSet, p: KnownParams):
    """Change of the drive term (Cm1 - Cm2 vx) T under the drivetrain effects (written with fmax only, so that
    numpy, torch and CasADi all take it)."""
    if p.drivetrain == "power_limited":
        raise ValueError("the drivetrain effects act on the drive term (Cm1 - Cm2 vx) T; the power_limited "
                         "drivetrain's Cm1, Cm2 mean a traction cap and a power, so they do not apply to it")
    gain = Cm1 - Cm2 * vx
    Tp = ns.fmax(T, 0.0)                 # throttle part
    Tb = T - Tp                          # brake part (<= 0)
    Tp_eff = Tp * (1.0 + fx.throttle_map * (1.0 + ns.fmax(-Tp, -1.0)))   # T (1 - min(T, 1))
    if fx.gear_step:
        Tp_eff = Tp_eff * gear_factor(ns, vx, fx.gear_step)
    Teff = Tp_eff + (1.0 + fx.brake_gain) * Tb
    drive = gain * Teff
    if fx.power_limit:
        cap = fx.power_limit / ns.fmax(vx, p.v_min)
        drive = drive - ns.fmax(drive - cap, 0.0)
    return drive - gain * T


def gear_factor(ns: mathns.MathNamespace, vx, step: float):
    """(1 + step)^(GEAR_REF - gear(vx)), the gear counted with smooth ramps at GEAR_SHIFTS."""
    gear = 1.0
    for v in GEAR_SHIFTS:
        z = (vx - v) / GEAR_RAMP + 0.5
        gear = gear + ns.fmax(z, 0.0) - ns.fmax(z - 1.0, 0.0)
    return ns.exp(math.log(1.0 + step) * (GEAR_REF - gear))


@dataclass
class Channels:
    """Effective throttle and steering at the start of a step and their rates over it."""

    throttle: Any
    steering: Any
    dthrottle: Any
    dsteering: Any


def _split(a, n):
    return tuple(a[..., i] for i in range(n))


def step_numpy(state, inputs, coeffs, p: KnownParams, dt: float, method: str, substeps: int, fx: EffectSet,
               ch: Channels | None, aux: Aux) -> np.ndarray:
    """Next state (batched numpy): the model with effects, effective inputs ch; commanded T, delta integrate
    from `inputs` exactly as in the nominal step."""
    ns = mathns.NUMPY
    s = _split(np.asarray(state, float), N_STATE)
    u = _split(np.asarray(inputs, float), N_INPUT)
    c = _split(np.asarray(coeffs, float), N_COEFF)
    if ch is None:
        eff, eff_u = s, u
    else:
        eff, eff_u = s[:6] + (ch.throttle, ch.steering), (ch.dthrottle, ch.dsteering)
    out = integrators.step(lambda z: derivatives(ns, z, eff_u, c, p, fx, aux), eff, dt, method, substeps)
    if ch is not None:
        out = out[:6] + integrators.step(lambda z: u, (s[6], s[7]), dt, method, substeps)
    return np.stack(np.broadcast_arrays(*out), axis=-1)


# ----------------------------------------------------------------------------------------------- memory rules

def lag_update(z, u0, u1, tau: float, dt: float):
    """Exact first-order lag over one step with the input moving linearly from u0 to u1."""
    r = (u1 - u0) / dt
    return u1 - tau * r + (z - u0 + tau * r) * math.exp(-dt / tau)


def delayed(t, values, delay: float, t_query=None):
    """values (sampled at times t, held before t[0]) at t_query - delay (default t_query = t)."""
    tq = t if t_query is None else t_query
    return np.interp(np.asarray(tq, float) - delay, t, values)


def relax_factor(vx, length: float, dt: float, v_min: float):
    return np.exp(-dt * np.maximum(np.abs(vx), v_min) / length)


def segment_channels(t, T, delta, fx: EffectSet, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Effective throttle and steering at each sample of one segment (times t, commanded T, delta)."""
    Te = delayed(t, T, fx.throttle_delay) if fx.throttle_delay else np.asarray(T, float)
    de = delayed(t, delta, fx.steer_delay) if fx.steer_delay else np.asarray(delta, float)
    if fx.steer_lag:
        z = np.empty(len(de))
        z[0] = de[0]
        zi, ul = float(de[0]), de.tolist()
        for k in range(len(ul) - 1):
            zi = lag_update(zi, ul[k], ul[k + 1], fx.steer_lag, dt)
            z[k + 1] = zi
        de = z
    return Te, de


# ----------------------------------------------------------------------------------------------- simulator plant

class Plant:
    """The plant with effects for the closed-loop simulator: carries the memory from step to step."""

    def __init__(self, fx: EffectSet, p: KnownParams, dt: float, method: str, substeps: int,
                 track_length: float | None = None):
        self.fx, self.p, self.dt, self.method, self.substeps = fx, p, dt, method, substeps
        self.track_length = track_length
        self.T_hist: list[float] = []
        self.d_hist: list[float] = []
        self.z: float | None = None          # lag state (effective steering)
        self.alpha_eff = None                # relaxation memory (front, rear)
        self.window = int(max(fx.steer_delay, fx.throttle_delay) / dt) + 3

    def _channels(self, k: int, T: float, delta: float, T1: float, d1: float, inputs) -> Channels:
        fx, dt = self.fx, self.dt
        self.T_hist.append(T)
        self.d_hist.append(delta)
        j0 = max(0, k + 1 - self.window)
        t = np.arange(j0, k + 2) * dt
        tq = np.arange(k, k + 2) * dt
        if fx.throttle_delay:
            Te = delayed(t, self.T_hist[j0:] + [T1], fx.throttle_delay, tq)
        else:
            Te = (T, T1)
        if fx.steer_delay:
            de = delayed(t, self.d_hist[j0:] + [d1], fx.steer_delay, tq)
        else:
            de = (delta, d1)
        if fx.steer_lag:
            if self.z is None:
                self.z = float(de[0])
            z0 = self.z
            self.z = lag_update(z0, float(de[0]), float(de[1]), fx.steer_lag, dt)
            de = (z0, self.z)
        dT = (float(Te[1]) - float(Te[0])) / dt if fx.throttle_delay else float(inputs[0])
        dd = (float(de[1]) - float(de[0])) / dt if (fx.steer_delay or fx.steer_lag) else float(inputs[1])
        return Channels(float(Te[0]), float(de[0]), dT, dd)

    def step(self, k: int, state: np.ndarray, inputs: np.ndarray, coeffs: np.ndarray, s: float | None) -> np.ndarray:
        fx, p, dt = self.fx, self.p, self.dt
        T1, d1 = integrators.step(lambda z: tuple(inputs), (state[6], state[7]), dt, self.method, self.substeps)
        ch = (self._channels(k, float(state[6]), float(state[7]), float(T1), float(d1), inputs)
              if fx.shapes_inputs() else None)
        aux = Aux(time=k * dt)
        if fx.bank is not None:
            aux.bank = fx.bank.at(s, self.track_length)
        if fx.grade is not None:
            aux.grade = fx.grade.at(s, self.track_length)
        if fx.relaxation:
            delta_eff = state[7] if ch is None else ch.steering
            a = np.array(model.slip_angles(mathns.NUMPY, state[3], state[4], state[5], delta_eff,
                                           coeffs[4], coeffs[10], p))
            if self.alpha_eff is None:
                self.alpha_eff = a
            b = float(relax_factor(state[3], fx.relaxation, dt, p.v_min))
            off = (self.alpha_eff - a) * b
            self.alpha_eff = a + off
            aux.slip_offset = (off[0], off[1])
        return step_numpy(state, inputs, coeffs, p, dt, self.method, self.substeps, fx, ch, aux)

    def measure(self, states: np.ndarray) -> np.ndarray:
        """Recorded states from true ones (sensor effects: yaw_rate_bias)."""
        out = states.copy()
        if self.fx.yaw_bias:
            out[:, 5] += self.fx.yaw_bias
        return out


# ----------------------------------------------------------------------------------------------- predictor on a log

class LogModel:
    """The model with effects evaluated on a logged history, vectorised over rows.

    coeffs: (17,) or (N, 17) per row (e.g. a DDM's estimates). One-step predictions use
    the memory reconstructed from the log (delays and lag from the logged commanded inputs,
    relaxation from the logged states); rollouts carry the relaxation memory forward.
    """

    def __init__(self, time, segment, states, inputs, p: KnownParams, dt: float, method: str = "euler",
                 substeps: int = 1, extras: dict | None = None):
        self.time, self.segment = np.asarray(time, float), np.asarray(segment)
        # track position per row (bank/grade profiles along the track) and the lap length (None: not periodic);
        # set by the caller that knows the track (ddyn.gap.selection)
        self.position: np.ndarray | None = None
        self.track_length: float | None = None
        self.extras = dict(extras or {})   # logged channels a "channel" profile reads (roll)
        self.states, self.inputs = np.asarray(states, float), np.asarray(inputs, float)
        self.p, self.dt, self.method, self.substeps = p, dt, method, substeps
        n = len(self.time)
        bounds = np.flatnonzero(np.r_[True, self.segment[1:] != self.segment[:-1], True])
        self.segments = [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        self.t_rel = np.empty(n)
        for a, b in self.segments:
            self.t_rel[a:b] = self.time[a:b] - self.time[a]
        self.t_log = self.time - self.time[0]

    @classmethod
    def of(cls, ds, p: KnownParams, method: str = "euler", substeps: int = 1) -> "LogModel":
        return cls(ds.time, ds.segment, ds.states, ds.inputs, p, ds.sample_time, method, substeps, ds.extras)

    def channels(self, fx: EffectSet) -> Channels | None:
        if not fx.shapes_inputs():
            return None
        n = len(self.time)
        Te, de = np.empty(n), np.empty(n)
        for a, b in self.segments:
            Te[a:b], de[a:b] = segment_channels(self.t_rel[a:b], self.states[a:b, 6], self.states[a:b, 7], fx, self.dt)
        nxt = np.minimum(np.arange(n) + 1, n - 1)
        rate = lambda v: (v[nxt] - v) / self.dt  # noqa: E731  (last row of a segment is never stepped from)
        dT = rate(Te) if fx.throttle_delay else self.inputs[:, 0]
        dd = rate(de) if (fx.steer_delay or fx.steer_lag) else self.inputs[:, 1]
        return Channels(Te, de, dT, dd)

    def true_states(self, fx: EffectSet) -> np.ndarray:
        if not fx.yaw_bias:
            return self.states
        s = self.states.copy()
        s[:, 5] -= fx.yaw_bias
        return s

    def _alpha(self, states, steering, coeffs):
        c = np.broadcast_to(coeffs, states.shape[:-1] + (N_COEFF,))
        return np.stack(model.slip_angles(mathns.NUMPY, states[..., 3], states[..., 4], states[..., 5], steering,
                                          c[..., 4], c[..., 10], self.p), axis=-1)

    def relaxation_memory(self, fx: EffectSet, states, ch: Channels | None, coeffs) -> np.ndarray:
        """alpha_eff per row (N, 2) from the logged history."""
        steer = states[:, 7] if ch is None else ch.steering
        a = self._alpha(states, steer, coeffs)
        b = relax_factor(states[:, 3], fx.relaxation, self.dt, self.p.v_min)
        out = np.empty_like(a)
        al, bl = a.tolist(), b.tolist()
        for s0, s1 in self.segments:
            mf, mr = al[s0]
            for k in range(s0, s1):
                af, ar = al[k]
                mf = af + (mf - af) * bl[k]
                mr = ar + (mr - ar) * bl[k]
                out[k] = (mf, mr)
        return out

    def _aux(self, fx: EffectSet, rows, offset=None) -> Aux:
        aux = Aux(time=self.t_log[rows] if fx.wear else None, slip_offset=offset)
        for name, prof in (("bank", fx.bank), ("grade", fx.grade)):
            if prof is None:
                continue
            if prof.kind == "channel":
                if prof.channel not in self.extras:
                    raise DdynError(f"{name} from the logged channel {prof.channel!r}: the log has no such channel")
                setattr(aux, name, prof.amplitude * np.asarray(self.extras[prof.channel], float)[rows])
            elif prof.needs_position():
                if self.position is None:
                    raise DdynError(f"a {prof.kind} {name} profile needs the track position of each row")
                setattr(aux, name, prof.at(self.position[rows], self.track_length))
            else:
                setattr(aux, name, prof.angle)
        return aux

    def _ch(self, ch: Channels | None, rows) -> Channels | None:
        return None if ch is None else Channels(ch.throttle[rows], ch.steering[rows], ch.dthrottle[rows],
                                                ch.dsteering[rows])

    def one_step(self, fx: EffectSet, rows: np.ndarray, coeffs) -> np.ndarray:
        """Predicted measured (vx, vy, omega) at rows + 1 from rows (which must not end a segment)."""
        states = self.true_states(fx)
        ch = self.channels(fx)
        c = coeffs[rows] if np.ndim(coeffs) == 2 else coeffs
        offset = None
        if fx.relaxation:
            cfull = coeffs
            mem = self.relaxation_memory(fx, states, ch, cfull)
            steer = states[rows, 7] if ch is None else ch.steering[rows]
            a = self._alpha(states[rows], steer, c)
            off = mem[rows] - a
            offset = (off[:, 0], off[:, 1])
        nxt = step_numpy(states[rows], self.inputs[rows], c, self.p, self.dt, self.method, self.substeps, fx,
                         self._ch(ch, rows), self._aux(fx, rows, offset))
        out = nxt[:, 3:6].copy()
        out[:, 2] += fx.yaw_bias
        return out

    def rollout(self, fx: EffectSet, starts: np.ndarray, steps: int, coeffs, whole_state: bool = False) -> np.ndarray:
        """Positions (steps, n, 2) predicted from each start row with the logged inputs; coefficients held
        at the start row's. whole_state: the whole measured state (steps, n, 8) instead (omega as the sensor reads it)."""
        states = self.true_states(fx)
        ch = self.channels(fx)
        c = coeffs[starts] if np.ndim(coeffs) == 2 else coeffs
        x = states[starts].copy()
        mem = None
        if fx.relaxation:
            full = self.relaxation_memory(fx, states, ch, coeffs)
            prev = np.maximum(starts - 1, 0)
            first = np.isin(starts, [a for a, _ in self.segments])
            steer0 = states[starts, 7] if ch is None else ch.steering[starts]
            mem = np.where(first[:, None], self._alpha(x, steer0, c), full[prev])
        out = np.empty((steps, len(starts), N_STATE if whole_state else 2))
        for j in range(steps):
            rows = starts + j
            chj = self._ch(ch, rows)
            offset = None
            if mem is not None:
                a = self._alpha(x, x[:, 7] if chj is None else chj.steering, c)
                mem = a + (mem - a) * relax_factor(x[:, 3], fx.relaxation, self.dt, self.p.v_min)[:, None]
                off = mem - a
                offset = (off[:, 0], off[:, 1])
            x = step_numpy(x, self.inputs[rows], c, self.p, self.dt, self.method, self.substeps, fx, chj,
                           self._aux(fx, rows, offset))
            out[j] = x if whole_state else x[:, :2]
        if whole_state:
            out[..., 5] += fx.yaw_bias
        return out


def with_value(fx: EffectSet, name: str, value: float) -> EffectSet:
    """fx with one effect's main parameter set (bank/grade constant)."""
    other = EffectSet.from_values({name: value})
    field_name = {"bank_angle": "bank", "grade": "grade", "tire_relaxation": "relaxation", "tire_wear": "wear",
                  "yaw_rate_bias": "yaw_bias"}.get(name, name)
    return replace(fx, **{field_name: getattr(other, field_name)})
