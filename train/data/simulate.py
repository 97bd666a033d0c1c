"""Closed-loop simulation on a track: the source of synthetic training data.

A driver (pure pursuit on the track's centre line for steering, PI on speed through
the drivetrain's inverse for throttle, with a speed profile limited by the path's
curvature and the tyres' friction) drives the one vehicle model (ddyn.model.single_track via
ddyn.model.backends.step_numpy, the vehicle's true coefficients) at the vehicle's sample
time. A seeded, band-limited excitation perturbs the steering and throttle commands
and the speed target, so the data reach into the tyres' non-linear range (sliding),
not only steady cornering.

Commands become input rates: dthrottle = (T_cmd - T) / Ts, clipped first to the
rate limits and then so that T stays within its absolute limits (likewise steering).
Row k of the result holds the state at t_k and the input applied over [t_k, t_k+1],
so stepping row k with the same method reproduces row k+1 exactly (without noise).

Measurement noise (noise_scale > 0) is added to the recorded x, y, yaw, vx, vy,
omega only (std = noise_scale * vehicle.sensor_noise_std[channel]); the plant and
the controller never see it, and the noise-free values are kept as extras true_*.
Everything is deterministic given the seed: independent random streams drive the
excitation and the noise, so adding noise does not change the trajectory.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass

import numpy as np

from ddyn.data import vehicle_ref
from ddyn.data.dataset import Dataset, write_canonical
from ddyn.errors import DdynError
from ddyn.model import backends
from ddyn.model.effects import EffectSet, Plant, effects_json, parse_effects
from ddyn.model import mathns
from ddyn.model.single_track import BRAKE_GAIN_FORMS, COEFF_NAMES, N_STATE, STATE_NAMES, drivetrain_force
from ddyn.model.track_files import open_track
from ddyn.model.tracks import Track
from ddyn.model.vehicle import Vehicle
from ddyn.model.vehicle import load as load_vehicle
from ddyn.paths import check_writable

G = 9.81
NOISY_CHANNELS = ("x", "y", "yaw", "vx", "vy", "omega")
DEFAULT_TARGET_SPEED = {"orca_1_43": 2.5, "av21": 34.0}
DEFAULT_GRIP = 0.8


@dataclass(frozen=True)
class DriverSettings:
    """Tuning of the driver, scaled from the vehicle where no value is given."""

    target_speed: float       # cap of the speed profile (m/s)
    grip: float               # fraction of the tyres' friction limit (Df + Dr) / m used for cornering
    max_grip: float           # the speed excitation raises cornering speeds up to this fraction at most
    brake_fraction: float     # fraction of the drivetrain's braking capability planned with
    lookahead_min: float      # m
    lookahead_time: float     # s (lookahead = max(min, time * vx))
    speed_preview: float      # s: the speed target is read this far ahead
    kp: float                 # 1/s   speed error -> commanded acceleration
    ki: float                 # 1/s^2
    steer_excitation: float   # rad, std of the steering perturbation at excitation 1
    throttle_excitation: float  # std of the throttle perturbation at excitation 1
    speed_excitation: float   # relative std of the speed-target scaling at excitation 1
    excitation_speed: float   # m/s: above this speed the steering perturbation shrinks as 1/v^2
    yaw_gain: float           # yaw-rate feedback on top of pure pursuit (0: plain pure pursuit; above
                              # about 1 it excites the Euler plant's lightly damped lateral mode: chatter)


def driver_settings(vehicle: Vehicle, target_speed: float | None = None, grip: float | None = None) -> DriverSettings:
    wheelbase = vehicle.known.lf + vehicle.known.lr
    t_lo, t_hi = vehicle.input_limits["throttle"]
    s_lo, s_hi = vehicle.input_limits["steering"]
    if target_speed is None:
        target_speed = DEFAULT_TARGET_SPEED.get(vehicle.name, 0.75 * vehicle.max_speed)
    t_char = math.sqrt(wheelbase / G)    # the car's natural time scale (Froude scaling)
    return DriverSettings(
        target_speed=float(target_speed),
        grip=DEFAULT_GRIP if grip is None else float(grip),
        max_grip=0.9,
        brake_fraction=0.7,
        lookahead_min=3.0 * wheelbase,
        lookahead_time=2.0 * t_char,
        speed_preview=2.0 * t_char,
        kp=3.0,
        ki=1.0,
        steer_excitation=0.12 * 0.5 * (s_hi - s_lo),
        throttle_excitation=0.12 * (t_hi - t_lo),
        speed_excitation=0.08,
        excitation_speed=1.6 * math.sqrt(G * wheelbase),
        yaw_gain=0.75,
    )


class BandNoise:
    """Unit-variance low-pass Gaussian noise, generated in fixed blocks (deterministic per stream).

    A second-order Butterworth filter of white noise, cut-off `fraction` of the
    Nyquist frequency; the filter starts from a burnt-in state so the sequence is
    stationary from its first sample.
    """

    BLOCK = 1024

    def __init__(self, rng: np.random.Generator, fraction: float):
        from scipy import signal

        self.rng = rng
        self.b, self.a = signal.butter(2, fraction)
        impulse = np.zeros(int(40 / fraction) + 100)
        impulse[0] = 1.0
        self.gain = 1.0 / math.sqrt(float(np.sum(signal.lfilter(self.b, self.a, impulse) ** 2)))
        self.zi = np.zeros(max(len(self.a), len(self.b)) - 1)
        self._lfilter = signal.lfilter
        self._fill(burn_in=int(10 / fraction))
        self._fill()

    def _fill(self, burn_in: int = 0):
        n = burn_in or self.BLOCK
        out, self.zi = self._lfilter(self.b, self.a, self.rng.standard_normal(n), zi=self.zi)
        self.buffer = (out * self.gain).tolist()
        self.pos = 0

    def next(self) -> float:
        if self.pos >= len(self.buffer):
            self._fill()
        v = self.buffer[self.pos]
        self.pos += 1
        return v


def speed_profile(track: Track, vehicle: Vehicle, coeffs: np.ndarray, settings: DriverSettings) -> np.ndarray:
    """Target speed at each centre-line point: friction-limited in curves, braking-limited before them."""
    p = vehicle.known
    c = dict(zip(COEFF_NAMES, (float(v) for v in coeffs)))
    a_lat = settings.grip * (abs(c["Df"]) + abs(c["Dr"])) / p.mass
    kappa = np.abs(track.curvature)
    v_curve = np.sqrt(a_lat / np.maximum(kappa, 1e-9))
    v_curve = np.minimum(v_curve, settings.target_speed)
    # braking capability with the lowest throttle, at standstill (the weakest case when Cd >= 0)
    t_lo = vehicle.input_limits["throttle"][0]
    a_brake = -float(drivetrain_force(0.0, t_lo, c["Cm1"], c["Cm2"], c["Cr0"], c["Cd"], mathns.NUMPY, p)) / p.mass
    a_brake = settings.brake_fraction * max(a_brake, 1e-3 * a_lat)
    # v(s_i)^2 <= min_{j >= i} v_curve(s_j)^2 + 2 a_brake (s_j - s_i): a reverse running minimum,
    # over two laps so the constraint wraps around the start line
    s2 = np.concatenate([track.s, track.s + track.length])
    v2 = np.concatenate([v_curve, v_curve]) ** 2
    key = v2 + 2.0 * a_brake * s2
    run_min = np.minimum.accumulate(key[::-1])[::-1]
    return np.sqrt(np.maximum(run_min[:track.n] - 2.0 * a_brake * track.s, 0.0))


def _wrap_s(ds: float, length: float) -> float:
    return (ds + 0.5 * length) % length - 0.5 * length


def _resolve(vehicle, track) -> tuple[Vehicle, Track]:
    if isinstance(vehicle, str):
        vehicle = load_vehicle(vehicle)
    if isinstance(track, str):
        track = open_track(track, vehicle.name)
    return vehicle, track


def simulate(vehicle: Vehicle | str, track: Track | str, duration: float | None = None, laps: float | None = None,
             method: str = "euler", substeps: int | None = None, seed: int = 0, noise_scale: float = 0.0,
             target_speed: float | None = None, excitation: float = 1.0, coeffs: np.ndarray | None = None,
             start_speed: float | None = None, progress: bool = True, grip: float | None = None,
             start_s: float = 0.0, offtrack_margin: float | None = None, offtrack_time: float = 0.5,
             driver: dict | None = None, effects=None) -> Dataset:
    """Drive `vehicle` around `track` in closed loop and record a canonical Dataset.

    Stops after `laps` completed laps (progress along the centre line from the start,
    however the start lies) or `duration` seconds, whichever comes first (one lap if
    neither is given). method "euler" or "rk4" (substeps default vehicle.rk4_substeps).
    target_speed caps the speed profile; grip is the used fraction of the friction
    limit; excitation scales the random perturbations (0: none). start_speed defaults
    to the profile's speed at the start. Raises DdynError when the car stays beyond a
    bound by more than offtrack_margin (default a quarter of the track width) for
    offtrack_time seconds, or the state becomes non-finite. driver overrides fields of
    DriverSettings (see driver_settings for the defaults). effects: unmodelled effects of the
    plant (ddyn.model.effects: a list of {"effect", "params"}, JSON or key=value text); None or
    all-zero effects leave the nominal plant exactly as it is. Active effects are recorded in
    the metadata key `effects` (JSON).
    """
    vehicle, track = _resolve(vehicle, track)
    if method not in ("euler", "rk4"):
        raise DdynError(f"unknown method {method!r}; expected euler or rk4")
    if substeps is None:
        substeps = vehicle.rk4_substeps if method == "rk4" else 1
    if substeps < 1:
        raise DdynError(f"substeps must be at least 1, got {substeps}")
    if method == "euler" and substeps != 1:
        raise DdynError("substeps only apply to rk4 (the Euler chain is one step per sample)")
    if laps is None and duration is None:
        laps = 1
    if laps is not None and not laps > 0:
        raise DdynError(f"laps must be positive, got {laps}")
    if duration is not None and not duration > 0:
        raise DdynError(f"duration must be positive, got {duration}")
    if noise_scale < 0 or excitation < 0:
        raise DdynError("noise scale and excitation must be non-negative")
    if noise_scale > 0:
        missing = [c for c in NOISY_CHANNELS if c not in vehicle.sensor_noise_std]
        if missing:
            raise DdynError(f"vehicle {vehicle.name!r} has no sensor_noise_std for {', '.join(missing)}")
    if coeffs is None:
        coeffs = vehicle.true_vector()
    coeffs = np.asarray(coeffs, dtype=float).copy()
    settings = driver_settings(vehicle, target_speed, grip)
    if driver:
        try:
            settings = dataclasses.replace(settings, **driver)
        except TypeError as e:
            raise DdynError(f"driver settings: {e}") from None
    if not settings.target_speed > 0:
        raise DdynError(f"target speed must be positive, got {settings.target_speed}")

    p = vehicle.known
    Ts = vehicle.sample_time
    effect_list = parse_effects(effects)
    plant = None
    if EffectSet.of(effect_list).active():
        plant = Plant(EffectSet.of(effect_list), p, Ts, method, substeps, track.length)
    wheelbase = p.lf + p.lr
    t_lo, t_hi = vehicle.input_limits["throttle"]
    d_lo, d_hi = vehicle.input_limits["steering"]
    dt_lo, dt_hi = vehicle.input_limits["dthrottle"]
    dd_lo, dd_hi = vehicle.input_limits["dsteering"]
    # keep the integrated throttle/steering a hair inside their limits despite rounding in the plant
    t_lo_in, t_hi_in = t_lo + 1e-12 * (t_hi - t_lo), t_hi - 1e-12 * (t_hi - t_lo)
    d_lo_in, d_hi_in = d_lo + 1e-12 * (d_hi - d_lo), d_hi - 1e-12 * (d_hi - d_lo)
    drive = [float(coeffs[COEFF_NAMES.index(k)]) for k in ("Cm1", "Cm2", "Cr0", "Cd")]
    mass = p.mass

    profile = speed_profile(track, vehicle, coeffs, settings)
    preview_frac = np.linspace(0.0, 1.0, 6)
    # the speed perturbation may push cornering up to max_grip of the friction limit, not beyond
    scale_max = math.sqrt(max(settings.max_grip / settings.grip, 1.0))
    L = track.length
    margin = 0.25 * track.width if offtrack_margin is None else float(offtrack_margin)
    window = max(4.0 * settings.lookahead_min, 0.05 * L)
    # stop runaway runs that make no progress (laps only): generous bound on the time needed
    max_time = duration if duration is not None else 10.0 * laps * L / float(np.mean(profile)) + 10.0

    seeds = np.random.SeedSequence(seed).spawn(4)
    ex_steer = BandNoise(np.random.default_rng(seeds[0]), 0.08)
    ex_throttle = BandNoise(np.random.default_rng(seeds[1]), 0.04)
    ex_speed = BandNoise(np.random.default_rng(seeds[2]), 0.004)
    noise_rng = np.random.default_rng(seeds[3])

    def throttle_for(v: float, accel: float) -> float:
        # the throttle whose drivetrain force gives mass * accel (the force is affine in the throttle on
        # each side of zero; the papers' form has one slope, the powertrain form the brake gain below zero)
        f0 = drivetrain_force(v, 0.0, *drive)
        gain = drivetrain_force(v, 1.0, *drive) - f0
        want = mass * accel - f0
        if p.drivetrain in BRAKE_GAIN_FORMS and want < 0.0:
            return want / p.brake_gain
        return want / gain if gain > 0.0 else t_hi

    # initial state: on the centre line at start_s, heading along it
    s0 = float(start_s) % L
    x0, y0 = (float(v) for v in track.position(s0))
    yaw0 = float(track.heading_at(s0))
    v_start = float(track.interpolate(profile, s0)) if start_speed is None else float(start_speed)
    state = np.array([x0, y0, yaw0, v_start, 0.0, 0.0,
                      min(max(throttle_for(v_start, 0.0), t_lo_in), t_hi_in),
                      min(max(math.atan(wheelbase * float(track.curvature_at(s0))), d_lo_in), d_hi_in)])

    n_max = int(math.ceil(max_time / Ts)) + 2
    states = np.empty((n_max, N_STATE))
    inputs = np.empty((n_max, 2))
    s_prev = s0
    travelled = 0.0
    integ = 0.0
    off_time = 0.0
    laps_done = 0
    k = 0
    bar = _progress_bar(progress, laps, duration, L, Ts)
    try:
        while True:
            if not np.all(np.isfinite(state)):
                raise DdynError(f"state became non-finite at t = {k * Ts:.3f} s (step {k}): {state.tolist()}")
            x, y, yaw, vx, vy, omega, T, delta = state.tolist()
            s_arr, lat_arr = track.project(x, y, s_hint=s_prev, window=window)
            s, lat = float(s_arr), float(lat_arr)
            ds = _wrap_s(s - s_prev, L)
            travelled += ds
            s_prev = s
            if bar is not None:
                done = min(max(travelled, 0.0), bar.total) if laps is not None else min(k + 1, bar.total)
                if done > bar.n:
                    bar.update(done - bar.n)
            wl, wr = track.half_widths(s)
            outside = max(lat - float(wl), -lat - float(wr))
            if outside > margin:
                off_time += Ts
                if off_time > offtrack_time or outside > 2.0 * track.width + margin:
                    raise DdynError(
                        f"car left the track {track.name!r} at t = {k * Ts:.2f} s, s = {s:.2f} m of {L:.2f} m "
                        f"(lap {laps_done + 1}), x = {x:.3f}, y = {y:.3f}: {outside:.3f} m beyond the "
                        f"{'left' if lat > 0 else 'right'} bound for {off_time:.2f} s (vx {vx:.2f} m/s, "
                        f"vy {vy:.2f} m/s); try a lower --target-speed or --excitation")
            else:
                off_time = 0.0

            # ---- driver
            # steering: pure pursuit on the centre line
            lookahead = max(settings.lookahead_min, settings.lookahead_time * vx)
            gx, gy = track.position(s + lookahead)
            dx, dy = float(gx) - x, float(gy) - y
            alpha = math.atan2(dy, dx) - yaw
            ld = math.hypot(dx, dy)
            kappa_cmd = 2.0 * math.sin(alpha) / ld
            delta_cmd = math.atan(wheelbase * kappa_cmd)
            # yaw-rate feedback: steer more when the car yaws less than the pursuit curvature asks
            # (understeer), less or against it when it yaws more (oversteer, the start of a spin)
            v_yaw = max(vx, settings.lookahead_min / settings.lookahead_time)
            delta_cmd += settings.yaw_gain * wheelbase * (kappa_cmd - omega / v_yaw)
            # perturbation sized for a lateral acceleration ~ v^2 delta / wheelbase independent of speed
            steer_amp = settings.steer_excitation * min(1.0, (settings.excitation_speed / max(vx, 1e-6)) ** 2)
            delta_cmd += excitation * steer_amp * ex_steer.next()
            # speed: PI on the commanded acceleration, through the drivetrain's inverse
            scale = min(1.0 + excitation * settings.speed_excitation * ex_speed.next(), scale_max)
            # the lowest target over the preview distance (the profile already brakes ahead of curves;
            # the preview covers the controller's lag without looking past the end of a curve)
            v_ref = float(np.min(track.interpolate(profile, s + preview_frac * settings.speed_preview * max(vx, 0.0))))
            v_ref *= scale
            err = v_ref - vx
            a_cmd = settings.kp * err + settings.ki * integ
            T_cmd = throttle_for(vx, a_cmd) + excitation * settings.throttle_excitation * ex_throttle.next()
            if (t_lo < T_cmd < t_hi) or (T_cmd >= t_hi and err < 0) or (T_cmd <= t_lo and err > 0):
                integ += err * Ts           # anti-windup: integrate only when it does not deepen saturation
            # commands -> rates: rate limits first, then the absolute limits of the integrated state
            dT = min(max((T_cmd - T) / Ts, dt_lo), dt_hi)
            dT = min(max(dT, (t_lo_in - T) / Ts), (t_hi_in - T) / Ts)
            dD = min(max((delta_cmd - delta) / Ts, dd_lo), dd_hi)
            dD = min(max(dD, (d_lo_in - delta) / Ts), (d_hi_in - delta) / Ts)

            states[k] = state
            inputs[k] = (dT, dD)
            k += 1
            laps_done = int(math.floor(travelled / L + 1e-9))
            if laps is not None and travelled >= laps * L:
                break
            if duration is not None and k * Ts >= duration - 1e-9:
                break
            if k * Ts > max_time or k >= n_max:
                raise DdynError(f"too slow: {travelled:.2f} m of {(laps or 0) * L:.2f} m after {k * Ts:.1f} s "
                                f"(the car stalled or drives backwards near s = {s:.2f} m)")
            if plant is None:
                state = backends.step_numpy(state, np.array([dT, dD]), coeffs, p, Ts, method, substeps)
            else:
                state = plant.step(k - 1, state, np.array([dT, dD]), coeffs, s)
    finally:
        if bar is not None:
            bar.close()

    states = states[:k].copy()
    inputs = inputs[:k].copy()
    extras: dict[str, np.ndarray] = {}
    if plant is not None and plant.fx.yaw_bias:
        extras["true_omega"] = states[:, 5].copy()
        states = plant.measure(states)
    if noise_scale > 0:
        std = np.array([noise_scale * vehicle.sensor_noise_std[c] for c in NOISY_CHANNELS])
        idx = [STATE_NAMES.index(c) for c in NOISY_CHANNELS]
        extras = {f"true_{c}": states[:, i].copy() for c, i in zip(NOISY_CHANNELS, idx)} | extras
        states[:, idx] += noise_rng.standard_normal((k, len(idx))) * std
    time = np.arange(k) * Ts
    completed = travelled / L
    src = (f"ddyn simulate: {vehicle.name} on track {track.name}, pure pursuit + PI, method {method}"
           f"{f' x{substeps}' if method == 'rk4' else ''}, seed {seed}, noise {noise_scale:g}, "
           f"excitation {excitation:g}, target speed {settings.target_speed:g} m/s")
    metadata = {
        "method": method, "substeps": str(substeps), "seed": str(seed), "noise_scale": repr(float(noise_scale)),
        "excitation": repr(float(excitation)), "target_speed": repr(settings.target_speed),
        "grip": repr(settings.grip), "track": track.name, "track_length": repr(L),
        "laps": str(int(math.floor(completed + 1e-9))), "progress_laps": f"{completed:.6f}",
        "duration": repr(float((k - 1) * Ts)),
        # the vehicle file itself, so the log finds it again wherever it lives (ddyn.data.vehicle_ref)
        **vehicle_ref.metadata_for(vehicle),
        # the plant's coefficients (COEFF_NAMES order): the ground truth evaluation compares estimates with
        "plant_coefficients": json.dumps([float(c) for c in coeffs]),
    }
    if plant is not None:
        metadata["effects"] = effects_json(effect_list)
    return Dataset(time=time, segment=np.zeros(k, dtype=np.int64), states=states, inputs=inputs,
                   sample_time=Ts, vehicle=vehicle.name, source=src, extras=extras, metadata=metadata)


def _progress_bar(enabled: bool, laps, duration, length, Ts):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        return None
    if laps is not None:
        return tqdm(total=laps * length, unit="m", desc="simulate", disable=not sys.stderr.isatty(),
                    bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} m [{elapsed}<{remaining}]")
    return tqdm(total=int(math.ceil(duration / Ts - 1e-9)), unit="step", desc="simulate",
                disable=not sys.stderr.isatty())


def summary(ds: Dataset, track: Track | None = None) -> dict[str, float]:
    """Headline numbers of a simulated dataset (on the noise-free truth where present)."""
    col = lambda c: ds.extras.get(f"true_{c}", ds.column(c))  # noqa: E731
    speed = np.hypot(col("vx"), col("vy"))
    out = {
        "rows": float(len(ds)), "duration": float(ds.time[-1] - ds.time[0]) if len(ds) else 0.0,
        "laps": float(ds.metadata.get("laps", "nan")),
        "mean_speed": float(speed.mean()), "max_speed": float(speed.max()),
        "max_abs_vy": float(np.abs(col("vy")).max()), "max_abs_omega": float(np.abs(col("omega")).max()),
    }
    if track is not None:
        _, lat = track.project(col("x"), col("y"))
        out["max_lateral_offset"] = float(np.abs(lat).max())
    return out


def _run(args: argparse.Namespace) -> int:
    check_writable(args.output, "-o/--output")
    vehicle, track = _resolve(args.vehicle, args.track)
    laps = args.laps
    if laps is None and args.duration is None:
        laps = 2
    ds = simulate(vehicle, track, duration=args.duration, laps=laps, method=args.method, substeps=args.substeps,
                  seed=args.seed, noise_scale=args.noise, target_speed=args.target_speed,
                  excitation=args.excitation, progress=not args.quiet, effects=args.effects)
    path = write_canonical(ds, args.output)
    s = summary(ds, track)
    print(f"wrote {path}: {len(ds)} rows, {s['duration']:.2f} s, {ds.metadata['progress_laps']} laps "
          f"({ds.metadata['laps']} completed) of {track.name} ({track.length:.2f} m)")
    print(f"  speed mean {s['mean_speed']:.2f} m/s, max {s['max_speed']:.2f} m/s; max |vy| {s['max_abs_vy']:.3f} m/s, "
          f"max |omega| {s['max_abs_omega']:.3f} rad/s; max lateral offset {s['max_lateral_offset']:.3f} m "
          f"(half width {0.5 * track.width:.3f} m)")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("simulate", help="drive a vehicle around a track in closed loop; write a dataset",
                              description=__doc__.splitlines()[0])
    p.add_argument("--vehicle", required=True, help="vehicle name (train/vehicles) or JSON path")
    p.add_argument("--track", required=True,
                   help="ethz, ethzMobil, putnam, random:SEED, or a user's files (docs/tracks.md)")
    stop = p.add_mutually_exclusive_group()
    stop.add_argument("--laps", type=float, default=None, help="laps to drive (default 2)")
    stop.add_argument("--duration", type=float, default=None, help="seconds to drive instead of laps")
    p.add_argument("--method", choices=("euler", "rk4"), default="euler")
    p.add_argument("--substeps", type=int, default=None, help="RK4 sub-steps (default: the vehicle's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise", type=float, default=0.0, metavar="SCALE",
                   help="measurement noise as a multiple of the vehicle's sensor_noise_std (default 0)")
    p.add_argument("--target-speed", type=float, default=None, metavar="V", help="cap of the speed profile, m/s")
    p.add_argument("--excitation", type=float, default=1.0, metavar="A",
                   help="amplitude of the random steering/throttle/speed perturbations (0: none; default 1)")
    p.add_argument("--effects", default=None, metavar="SPEC",
                   help="unmodelled effects of the plant (train/model/effects.py), JSON or key=value, e.g. "
                        "'steer_delay=0.04' or '[{\"effect\":\"bank_angle\",\"params\":{\"angle\":0.05}}]'")
    p.add_argument("-o", "--output", required=True, help="output CSV (canonical dataset format)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)
