"""Logs from an independent plant: CommonRoad's single-track drift model (PyPI commonroad-vehicle-models).

Why: `ddyn study gap` used to score the diagnosis on logs made by the very model code
that `ddyn diagnose` fits (an inverse crime). This module makes "real" logs with a
plant written by someone else: `vehiclemodels.vehicle_dynamics_std` (TUM CommonRoad:
single-track with load transfer, wheel spin dynamics, combined-slip Pacejka MF tyres,
a kinematic blend at walking speed) and its parameter set `parameters_vehicle2` (BMW
320i). Nothing of ddyn.model integrates it; ddyn.model only supplies the track, and
ddyn.data.simulate the driver's speed profile and excitation noise.

How a log is made (the way a car with a drive-by-wire unit is logged):
  - the plant is integrated with RK4 at PLANT_RATE (1 kHz);
  - the driver (pure pursuit with yaw-rate feedback, PI on speed; the same structure as
    ddyn.data.simulate) decides a throttle and a steering *angle* once per log sample;
    the DBW unit holds both constant until the next sample; the log records these
    commanded values (columns throttle, steering), dthrottle/dsteering are their
    forward differences, so the project's model sees them ramp while the plant sees steps;
  - the steering servo follows the (held, possibly delayed) command as a first-order lag
    with time constant SERVO_TAU (steer_lag: a slower servo) inside CommonRoad's steering
    rate limit; throttle T maps to a drive force m_nominal * ACCEL_SCALE * T, passed to
    CommonRoad as the acceleration that force gives the true mass (its input is an
    acceleration; a heavier car must accelerate less for the same pedal);
  - aerodynamic drag and rolling resistance (CommonRoad has neither) and road bank and grade
    are added as accelerations along and across the velocity after CommonRoad's right-hand side;
  - downforce raises the tyre loads without adding inertia: CommonRoad is called with a mass
    m (1 + k v^2) (its normal loads scale with it) and the accelerations it returns are
    scaled back by (1 + k v^2), the drive force is passed unchanged;
  - every logged state (x, y, yaw, vx, vy, omega) gets noise: white, or AR(1)-coloured;
  - a track with its own banking (Track.bank: the oval of ddyn.model.track_oval) banks the road for every
    log on it, on top of a drawn bank_angle effect; LogSettings.roll_channel logs an EKF-like roll
    (extras "roll": the road's bank minus the body's roll on its springs, ROLL_GRADIENT per g of lateral
    acceleration, plus ROLL_NOISE); LogSettings.pitch_channel an EKF-like pitch (extras "pitch": the road's
    grade plus the body's squat, PITCH_GRADIENT per g of longitudinal acceleration, plus PITCH_NOISE);
  - tyre wear scales CommonRoad's friction coefficients p_dx1, p_dy1 by exp(-rate t); a yaw-rate bias is
    added to the logged omega only (a sensor effect; the driver steers on the true state);
  - drivetrain effects: throttle_map (the pedal reaches the engine as T^gamma, a power law, not the
    project's quadratic candidate; the effect's value is the quadratic's shape that matches it best in least
    squares, equivalent_gamma), brake_gain (the braking force (1 + g) times the nominal), power_limit (the
    drive power in W instead of CommonRoad's own limit, a_max v_switch = 84 m^2/s^3 times the mass: 92 kW).

  - tire_relaxation: each tyre's slip angle relaxes to the kinematic one over the relaxation length (extra
    plant states; CommonRoad's own tyre formulas are evaluated at the relaxed angles, _TyreHook);
  - gear_step: a five-speed gearbox (GEAR_SHIFTS), drive force (1 + step)^(GEAR_REF - gear), SHIFT_TIME of
    torque interruption at each shift;
  - LogSettings.dbw_period: a DBW unit at another rate than the log (the driver decides at each DBW tick, the
    log records the command in force at each row);
  - the model is pluggable (StdModel here; StModel: vehicle_dynamics_st with linear tyres; ddyn.plants.commonroad_mb.MbModel:
    the multi-body model), make_log(model="std" | "st" | "mb");
  - the parameter set too (make_log(params=...), PARAMETER_SETS): CommonRoad's vehicle1 (Ford Escort), vehicle2 (BMW
    320i, the default), vehicle3 (VW Vanagon) and "av21" (the Dallara AV-21 built from vehicle2's object,
    _av21_parameters); the plant's additions (pedal scale, drag, rolling resistance, roll/pitch gradients) per set
    (SetConstants), vehicle2's the module constants; the nominal vehicle file of each (model, set):
    nominal_vehicle(), written by write_vehicle_files() (python -m ddyn.plants.commonroad_st --write-vehicles);
  - the roll and pitch channels have kinds (CHANNEL_KINDS): imu (above), map (a track map's bank/grade at the car's
    10 m cell), broken (like the real Putnam log's roll column: drift, random walk, jumps of radians).

State mapping (CommonRoad -> canonical): x, y; yaw = psi; vx = v cos(beta), vy = v sin(beta);
omega = psi_dot. The noise-free values and the actual wheel angle are kept as extras true_*.
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ddyn.data import vehicle_ref
from ddyn.data.dataset import Dataset
from ddyn.data.simulate import BandNoise, driver_settings, speed_profile
from ddyn.errors import CarLostError, DdynError
from ddyn.model.tracks import Track, load_track
from ddyn.model.vehicle import Vehicle

try:  # the independent plant is a declared dependency (requirements.in); say so loudly if it is missing
    from vehiclemodels import vehicle_dynamics_std as _std_module
    from vehiclemodels.init_std import init_std
    from vehiclemodels import vehicle_dynamics_st as _st_module
    from vehiclemodels.init_st import init_st
    from vehiclemodels.parameters_vehicle1 import parameters_vehicle1
    from vehiclemodels.parameters_vehicle2 import parameters_vehicle2
    from vehiclemodels.parameters_vehicle3 import parameters_vehicle3
except ImportError as _e:  # pragma: no cover
    _IMPORT_ERROR: ImportError | None = _e
else:
    _IMPORT_ERROR = None

G = 9.81
PLANT_RATE = 1000.0          # Hz: RK4 step of the plant
SERVO_TAU = 0.01             # s: the steering servo of the effect-free plant (fast, not instantaneous)
ACCEL_SCALE = 6.0            # m/s^2 at throttle 1 for the nominal mass (drive and brake)
DRAG = 0.4                   # kg/m: 0.5 rho Cd A of a saloon (rho 1.2, Cd A 0.67 m^2)
ROLLING = 161.0              # N: 1.5 % of the weight, the usual rolling-resistance coefficient
# these numbers mapped onto the project's model; kept out of train/vehicles (whose files every vehicle-wide tool
# iterates: C code generation, LCM import's sample-time match, fidelity) and loaded by path like any user's file
NOMINAL_VEHICLE = Path(__file__).resolve().parents[1] / "vehicles" / "plants" / "commonroad_vehicle2.json"
NOISY = ("x", "y", "yaw", "vx", "vy", "omega")
PLANT_EFFECTS = ("steer_delay", "throttle_delay", "steer_lag", "mass_offset", "downforce", "bank_angle", "grade",
                 "throttle_map", "brake_gain", "power_limit", "tire_wear", "yaw_rate_bias", "tire_relaxation",
                 "gear_step")
ROLL_GRADIENT = 0.05         # rad of body roll per g of lateral acceleration (a saloon's springs: ~3 deg/g)
ROLL_NOISE = 0.003           # rad: an EKF's roll noise
PITCH_GRADIENT = 0.02        # rad of body pitch (nose up) per g of longitudinal acceleration (squat; ~1 deg/g)
PITCH_NOISE = 0.003          # rad: an EKF's pitch noise
MIN_RELAXATION = 0.05        # m: sigma / v stays above the RK4 step up to 50 m/s (RK4 is stable down to 0.36 steps)
# the logged roll (pitch) channel's kinds (LogSettings.roll_channel, pitch_channel): False / "none", True / "imu" (an
# EKF's: road bank minus body roll plus noise), "map" (a track map's bank at the car's position, MAP_RESOLUTION m cells
# along the track, stored to MAP_ROUNDING rad), "broken" (the real Putnam log's roll column: a drifting random walk
# with jumps of the order of radians, mostly unrelated to the dynamics; BROKEN_*)
CHANNEL_KINDS = ("none", "imu", "map", "broken")
MAP_RESOLUTION = 10.0        # m along the centre line per map cell (the value at the cell's centre)
MAP_ROUNDING = 1e-3          # rad: the map's stored precision
BROKEN_WALK = 0.1            # rad / sqrt(s): random walk of the broken channel
BROKEN_DRIFT = (0.05, 0.15)  # rad/s: range of its steady drift rate (random sign)
BROKEN_JUMP_RATE = 0.05      # 1/s: jumps per second
BROKEN_JUMP = (0.5, 2.0)     # rad: range of a jump's size (random sign)


def require_commonroad() -> None:
    if _IMPORT_ERROR is not None:
        raise DdynError(f"the independent plant needs the PyPI package commonroad-vehicle-models "
                        f"(requirements.in; bash scripts/setup.sh installs it): {_IMPORT_ERROR}")


@dataclass(frozen=True)
class PlantEffects:
    """Effects in physical form on the CommonRoad plant; zero is off. Units as ddyn.model.effects."""

    steer_delay: float = 0.0     # s: the servo sees the steering command this much later
    throttle_delay: float = 0.0  # s: the drivetrain sees the throttle command this much later
    steer_lag: float = 0.0       # s: servo time constant (replaces SERVO_TAU when larger)
    mass_offset: float = 0.0     # fraction: true mass and yaw inertia are (1 + f) times the nominal
    downforce: float = 0.0       # s^2/m^2: tyre loads scaled by 1 + k v^2 (the project's downforce k)
    bank_angle: float = 0.0      # rad: peak bank; the profile follows the curvature (banked into turns)
    grade: float = 0.0           # rad: peak grade; sinusoid along the lap (GRADE_WAVES per lap)
    grade_phase: float = 0.0     # rad
    throttle_map: float = 0.0    # -: shape of the quadratic map closest to the plant's T^gamma (equivalent_gamma)
    brake_gain: float = 0.0      # fraction: braking force (1 + g) times the nominal
    power_limit: float = 0.0     # W: drive power limit replacing CommonRoad's (0: CommonRoad's own)
    tire_wear: float = 0.0       # 1/s: the tyres' friction (p_dx1, p_dy1) scaled by exp(-rate t), t from the log's start
    yaw_rate_bias: float = 0.0   # rad/s: the logged omega reads the true one plus this (the dynamics are unchanged)
    tire_relaxation: float = 0.0  # m: the tyres' slip angles lag the kinematic ones by the time sigma / v
    gear_step: float = 0.0       # -: a stepped gearbox (GEAR_SHIFTS), drive force (1 + step) more per lower gear

    def active(self) -> dict[str, float]:
        return {k: v for k, v in asdict(self).items() if k in PLANT_EFFECTS and v != 0.0}


GRADE_WAVES = 3


def shape_of_gamma(gamma: float) -> float:
    """The shape c of T + c T (1 - T) (the diagnosis's throttle_map) closest to T^gamma on [0, 1] in least
    squares: c = int (T^g - T) T (1 - T) dT / int T^2 (1 - T)^2 dT = 30 (1/(g+2) - 1/(g+3) - 1/12)."""
    return 30.0 * (1.0 / (gamma + 2.0) - 1.0 / (gamma + 3.0) - 1.0 / 12.0)


def equivalent_gamma(shape: float) -> float:
    """The power law T^gamma whose closest quadratic map has this shape (bisection; shape_of_gamma decreases)."""
    lo, hi = 0.05, 20.0
    if not shape_of_gamma(hi) <= shape <= shape_of_gamma(lo):
        raise DdynError(f"throttle_map shape {shape} is outside what a power-law pedal map gives "
                        f"({shape_of_gamma(hi):.2f} to {shape_of_gamma(lo):.2f})")
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if shape_of_gamma(mid) > shape else (lo, mid)
    return 0.5 * (lo + hi)


def bank_profile(track: Track, peak: float) -> np.ndarray:
    """Bank angle at each centre-line point: banked into the turns, steepest in the tightest (both signs
    on a road course), from the curvature smoothed over about 30 m so the road does not twist at each kink."""
    kappa = np.asarray(track.curvature, float)
    ds = float(track.length) / len(kappa)
    half = max(1, int(round(15.0 / ds)))
    kernel = np.ones(2 * half + 1) / (2 * half + 1)
    smooth = np.convolve(np.concatenate([kappa[-half:], kappa, kappa[:half]]), kernel, mode="valid")
    scale = float(np.max(np.abs(smooth))) or 1.0
    return peak * smooth / scale


def grade_profile(track: Track, peak: float, phase: float = 0.0) -> np.ndarray:
    """Grade along the lap: a sinusoid with GRADE_WAVES periods, so the road climbs and falls back to the start."""
    s = np.asarray(track.s, float)
    return peak * np.sin(2 * math.pi * GRADE_WAVES * s / float(track.length) + phase)


@dataclass(frozen=True)
class SetConstants:
    """What the plant adds to a CommonRoad parameter set (CommonRoad has no drag, rolling resistance, pedal map or
    body roll/pitch gradient for the single-track models): per parameter set, vehicle2's the module constants."""

    car: str                     # the car's name in log sources
    accel_scale: float           # m/s^2 at throttle 1 (drive and brake) for the set's mass
    drag: float                  # kg/m: 0.5 rho Cd A
    rolling: float               # N: 1.5 % of the weight
    roll_gradient: float         # rad of body roll per g of lateral acceleration (single-track models)
    pitch_gradient: float        # rad of body pitch per g of longitudinal acceleration


PARAMETER_SETS = {
    "vehicle1": SetConstants("Ford Escort", 5.0, 0.41, 180.0, 0.06, 0.025),
    "vehicle2": SetConstants("BMW 320i", ACCEL_SCALE, DRAG, ROLLING, ROLL_GRADIENT, PITCH_GRADIENT),
    "vehicle3": SetConstants("VW Vanagon", 4.5, 0.82, 218.0, 0.09, 0.03),
    "av21": SetConstants("Dallara AV-21", 6.0, 0.45, 116.0, 0.008, 0.005),
}
# where a constant comes from (the nominal vehicle files' sources cite these)
SET_SOURCES = {
    "vehicle1": "Ford Escort: 5 m/s^2 at full pedal (a small saloon); drag 0.5 rho Cd A with Cd 0.36, A 1.9 m^2; "
                "rolling 1.5 % of 1226 kg g; roll 0.06 rad/g, pitch 0.025 rad/g (soft springs)",
    "vehicle2": "BMW 320i: 6 m/s^2; drag 0.4 kg/m (Cd A 0.67 m^2); rolling 161 N (1.5 % of the weight); "
                "roll 0.05 rad/g, pitch 0.02 rad/g",
    "vehicle3": "VW Vanagon: 4.5 m/s^2 (a heavy van); drag 0.5 rho Cd A with Cd 0.44, A 3.1 m^2; rolling 1.5 % of "
                "1479 kg g; roll 0.09 rad/g, pitch 0.03 rad/g (tall, soft)",
    "av21": "Dallara AV-21: 6 m/s^2 as vehicle2 (rear drive with 42 % of the load on the rear axle: with more "
            "pedal authority the PI driver powers the rear out of Putnam's corners); drag 0.45 kg/m "
            "(the project's av21.json Cd); rolling 1.5 % of 790 kg g; roll 0.008 rad/g, pitch 0.005 rad/g "
            "(stiff race springs)",
}
AV21_MASS_RATIO = 790.0 / 1093.2952334674046    # the AV-21's mass over vehicle2's (MB masses, springs scale by it)


def _av21_parameters():
    """The Dallara AV-21 built from parameters_vehicle2: the project's mass and geometry (train/vehicles/av21.json,
    shared/data/README.md: m 790 kg, lf 1.248 m, lr 1.7328 m), yaw inertia 1000 kg m^2 (av21.json), a low centre of
    gravity, racing slicks (friction 1.3 as av21.json's D, cornering stiffness 25 per unit load as av21.json's B C D
    over its axle loads), a race car's power and brakes; the multi-body parts (sprung/unsprung masses and their
    inertias) scaled by the mass ratio, springs and dampers by the mass ratio times 4 (ride frequency doubled),
    wider track widths."""
    p = copy.deepcopy(parameters_vehicle2())
    r = AV21_MASS_RATIO
    p.l, p.w = 4.9, 1.9
    p.m, p.a, p.b, p.I_z = 790.0, 1.248, 1.7328, 1000.0
    p.h_s, p.h_cg = 0.30, 0.28
    for k in ("m_s", "m_uf", "m_ur", "I_Phi_s", "I_y_s", "I_uf", "I_ur"):
        setattr(p, k, getattr(p, k) * r)
    p.m_s = 790.0 - p.m_uf - p.m_ur                  # the total stays m
    for k in ("K_sf", "K_sdf", "K_sr", "K_sdr", "K_tsf", "K_tsr"):
        setattr(p, k, getattr(p, k) * r * 4.0)
    for k in ("K_ras", "K_rad"):
        setattr(p, k, getattr(p, k) * r)
    p.T_f, p.T_r = 1.70, 1.62
    p.D_f, p.D_r = 0.0, 0.0                          # no roll steer
    p.tire.p_dy1, p.tire.p_dx1, p.tire.p_ky1 = 1.3, 1.45, -25.0
    p.longitudinal.a_max = 13.0                      # braking limit of slicks (1.3 g)
    p.longitudinal.v_switch = 39.0                   # drive power a_max v_switch m = 400 kW
    p.longitudinal.v_max = 80.0
    p.steering.v_min, p.steering.v_max = -0.6, 0.6   # the AV-21 file's steering rate limit
    return p


PARAMETER_LABELS = {"vehicle1": "parameters_vehicle1", "vehicle2": "parameters_vehicle2",
                    "vehicle3": "parameters_vehicle3", "av21": "av21 (parameters_vehicle2 as a Dallara AV-21)"}


def check_parameter_set(params: str) -> SetConstants:
    if params not in PARAMETER_SETS:
        raise DdynError(f"unknown CommonRoad parameter set {params!r}; expected one of {', '.join(PARAMETER_SETS)}")
    return PARAMETER_SETS[params]


def commonroad_parameters(params: str = "vehicle2"):
    """A CommonRoad parameter set as a fresh dataclass object (make_log sets its m and I_z): parameters_vehicle1
    (Ford Escort), parameters_vehicle2 (BMW 320i, the default), parameters_vehicle3 (VW Vanagon) or "av21" (the
    Dallara AV-21 built from vehicle2's, _av21_parameters)."""
    check_parameter_set(params)
    require_commonroad()
    if params == "av21":
        return _av21_parameters()
    make = {"vehicle1": parameters_vehicle1, "vehicle2": parameters_vehicle2, "vehicle3": parameters_vehicle3}
    return copy.deepcopy(make[params]())


def channel_kind(value, name: str = "roll_channel") -> str:
    """A logged roll/pitch channel's kind: False or "none", True or "imu", "map", "broken"."""
    if value is False or value is None:
        return "none"
    if value is True:
        return "imu"
    if isinstance(value, str) and value in CHANNEL_KINDS:
        return value
    raise DdynError(f"{name} {value!r} is not one of False/none, True/imu, map, broken")


@dataclass
class _Env:
    """What the right-hand side needs besides the state and the held commands."""

    p: object                    # CommonRoad parameters (p.m is set per call for downforce)
    m_true: float
    m_nominal: float
    downforce: float
    servo_tau: float
    bank: float = 0.0            # rad at the current position (held over a log sample)
    grade: float = 0.0
    gamma: float = 1.0           # pedal map T^gamma (throttle)
    brake_gain: float = 0.0
    model: object = field(default_factory=lambda: StdModel())   # or ddyn.plants.commonroad_mb.MbModel
    n_model: int = 9             # the model's own states (relaxed slip angles follow them)
    hook: object = None          # _TyreHook when tyre relaxation is on
    relaxation: float = 0.0      # m
    alpha_eff: list = field(default_factory=list)
    gear_factor: float = 1.0     # drive force factor of the current gear (0 during a shift)
    consts: SetConstants = field(default_factory=lambda: PARAMETER_SETS["vehicle2"])


class _TyreHook:
    """Tyre relaxation in physical form: CommonRoad's tyres see slip angles that build up over the relaxation
    length (d alpha_eff / dt = (v / sigma) (alpha - alpha_eff)), not the kinematic ones.

    The package computes each tyre's kinematic slip angle inside its right-hand side and hands it to
    vehiclemodels.utils.tire_model; during a call this hook stands in for the three functions of that module
    that take a slip angle, records the kinematic angles (the i-th formula_lateral call is tyre i) and
    evaluates the package's own tyre formulas at the relaxed angles carried as extra plant states."""

    NAMES = ("formula_lateral", "formula_lateral_comb", "formula_longitudinal_comb")

    def __init__(self):
        from vehiclemodels.utils import tire_model
        self.module = tire_model
        self.orig = {n: getattr(tire_model, n) for n in self.NAMES}
        self.eff: list = []
        self.kin: list = []

    def _index(self, alpha) -> int:
        for i, a in enumerate(self.kin):
            if a is alpha:
                return i
        return self.kin.index(alpha)

    def lateral(self, alpha, gamma, F_z, p):
        self.kin.append(alpha)
        return self.orig["formula_lateral"](self.eff[len(self.kin) - 1], gamma, F_z, p)

    def lateral_comb(self, kappa, alpha, gamma, mu_y, F_z, F0_y, p):
        return self.orig["formula_lateral_comb"](kappa, self.eff[self._index(alpha)], gamma, mu_y, F_z, F0_y, p)

    def longitudinal_comb(self, kappa, alpha, F0_x, p):
        return self.orig["formula_longitudinal_comb"](kappa, self.eff[self._index(alpha)], F0_x, p)

    def call(self, fn, x, u, p, eff):
        """fn(x, u, p) with the tyres at the relaxed slip angles eff; returns (f, the kinematic angles)."""
        self.eff, self.kin = list(eff), []
        m = self.module
        m.formula_lateral, m.formula_lateral_comb, m.formula_longitudinal_comb = (
            self.lateral, self.lateral_comb, self.longitudinal_comb)
        try:
            f = fn(x, u, p)
        finally:
            for n, g in self.orig.items():
                setattr(m, n, g)
        return f, self.kin


# the stepped gearbox of the gear_step effect: upshift speeds (m/s), downshift GEAR_HYSTERESIS lower; the drive
# force in gear n is (1 + step)^(GEAR_REF - n) times the nominal's (a geometric ratio progression: lower gears
# pull harder), the nominal's throttle map holds in GEAR_REF; each shift cuts the drive for SHIFT_TIME
GEAR_SHIFTS = (8.0, 14.0, 20.0, 27.0)
GEAR_REF = 3
GEAR_HYSTERESIS = 1.0
SHIFT_TIME = 0.15


def gear_for(v: float, gear: int) -> int:
    """The gear after a possible shift at speed v (up at GEAR_SHIFTS, down GEAR_HYSTERESIS below them)."""
    while gear < len(GEAR_SHIFTS) + 1 and v >= GEAR_SHIFTS[gear - 1]:
        gear += 1
    while gear > 1 and v < GEAR_SHIFTS[gear - 2] - GEAR_HYSTERESIS:
        gear -= 1
    return gear


class StdModel:
    """CommonRoad's single-track drift model (9 states) with the additions of the module docstring."""

    name = "std"
    label = "commonroad vehicle_dynamics_std"
    tyres = 2

    @staticmethod
    def dynamics():
        return _std_module.vehicle_dynamics_std      # looked up per call (tests count the calls)

    def scale_mass(self, p, factor: float) -> None:
        p.I_z = p.I_z * factor          # the mass itself is env.m_true, set per call

    def init(self, px, py, delta0, v0, psi0, p) -> list:
        return init_std([px, py, delta0, v0, psi0, 0.0, 0.0], p)

    def observe(self, x) -> tuple:
        """(X, Y, wheel angle, yaw, vx, vy, yaw rate, body roll)"""
        v, beta = x[3], x[6]
        return x[0], x[1], x[2], x[4], v * math.cos(beta), v * math.sin(beta), x[5], None

    def clamp(self, x) -> None:
        x[7], x[8] = max(x[7], 0.0), max(x[8], 0.0)   # as CommonRoad: no negative wheel spin

    def rhs(self, x, u, env) -> tuple[list, list]:
        v, beta, psi_dot = x[3], x[6], x[5]
        q = 1.0 + env.downforce * v * v                  # tyre-load factor of downforce
        env.p.m = env.m_true * q
        u = [u[0], u[1] / q]                             # the drive force stays the same with the heavier m
        if env.hook is None:
            f, kin = self.dynamics()(list(x), u, env.p), []
        else:
            f, kin = env.hook.call(self.dynamics(), list(x), u, env.p, env.alpha_eff)
        # undo the downforce mass: forces / (m q) -> forces / m (yaw and wheel dynamics have no mass)
        f[3] *= q
        f[6] = -psi_dot + (f[6] + psi_dot) * q
        # drag and rolling resistance act along the velocity; gravity of bank (+: to the left) and grade (+: uphill)
        a_x = -G * math.sin(env.grade)
        a_y = G * math.sin(env.bank)
        cb, sb = math.cos(beta), math.sin(beta)
        c = env.consts
        f[3] += -(c.drag * v * v + (c.rolling if v > 0.5 else 0.0)) / env.m_true + a_x * cb + a_y * sb
        if v > 0.5:
            f[6] += (a_y * cb - a_x * sb) / v
        return f, kin

    def speed(self, x) -> float:
        return x[3]


class StModel(StdModel):
    """CommonRoad's single-track model vehicle_dynamics_st (7 states: x, y, wheel angle, v, yaw, yaw rate, slip
    angle): LINEAR tyres (lateral force mu C_S F_z alpha with C_S = -p_ky1 / p_dy1, no Pacejka curve, no
    saturation), longitudinal load transfer, no wheel spin states (the drive/brake is its acceleration input, as
    for std) and a kinematic model below 0.1 m/s. The additions (drag, rolling, bank, grade, downforce) are
    StdModel's; the tyre relaxation effect has no tyre formula to act through here."""

    name = "st"
    label = "commonroad vehicle_dynamics_st"

    @staticmethod
    def dynamics():
        return _st_module.vehicle_dynamics_st

    def init(self, px, py, delta0, v0, psi0, p) -> list:
        return list(init_st([px, py, delta0, v0, psi0, 0.0, 0.0]))

    def clamp(self, x) -> None:
        pass


MODELS = ("std", "st", "mb")


def plant_model(model=None):
    """A plant model object from make_log's model argument: None or "std" (StdModel), "st" (StModel), or a model
    object itself (ddyn.plants.commonroad_mb.MbModel: that module imports this one, so it is not named here)."""
    if model is None or model == "std":
        return StdModel()
    if model == "st":
        return StModel()
    if model == "mb":
        raise DdynError("the multi-body model: ddyn.plants.commonroad_mb.make_log (or model=MbModel())")
    if isinstance(model, str):
        raise DdynError(f"unknown CommonRoad plant model {model!r}; expected one of {', '.join(MODELS)}")
    return model


def plant_rhs(x: list, steer_target: float, throttle: float, env: "_Env") -> list:
    """d/dt of the plant's state (the model's states, then the relaxed slip angles when relaxation is on)
    under the held commands."""
    model = env.model
    n = env.n_model
    xm = x[:n]
    steer_rate = (steer_target - xm[2]) / env.servo_tau
    if throttle > 0:
        pedal = throttle ** env.gamma * env.gear_factor
    else:
        pedal = (1.0 + env.brake_gain) * throttle
    accel = env.m_nominal * env.consts.accel_scale * pedal / env.m_true   # the drive force, whatever the mass
    if env.hook is not None:
        env.alpha_eff = x[n:]
    f, kin = model.rhs(xm, [steer_rate, accel], env)
    if env.hook is not None:
        rate = max(model.speed(xm), 0.5) / env.relaxation
        f = list(f) + [rate * (a - e) for a, e in zip(kin, x[n:])]
    return f


def rk4_step(x: list, h: float, steer_target: float, throttle: float, env: "_Env") -> list:
    k1 = plant_rhs(x, steer_target, throttle, env)
    k2 = plant_rhs([a + 0.5 * h * b for a, b in zip(x, k1)], steer_target, throttle, env)
    k3 = plant_rhs([a + 0.5 * h * b for a, b in zip(x, k2)], steer_target, throttle, env)
    k4 = plant_rhs([a + h * b for a, b in zip(x, k3)], steer_target, throttle, env)
    out = [a + h / 6.0 * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(x, k1, k2, k3, k4)]
    env.model.clamp(out)
    return out


@dataclass(frozen=True)
class LogSettings:
    duration: float = 60.0       # s of log
    noise_scale: float = 1.0     # times the nominal vehicle's sensor_noise_std
    noise_color: float = 0.0     # AR(1) coefficient of the noise (0: white)
    target_speed: float = 24.0   # m/s cap of the speed profile
    excitation: float = 1.0
    start_s: float = 0.0
    extra: dict = field(default_factory=dict)
    roll_channel: bool | str = False   # log extras "roll": False/"none", True/"imu", "map", "broken" (CHANNEL_KINDS)
    pitch_channel: bool | str = False  # log extras "pitch", the same kinds (grade plus body pitch for "imu")
    dbw_period: float | None = None   # s between the DBW unit's commands (None: the log's sample time)
    driver_grip: float | None = None  # share of the nominal's grip the driver's speed profile uses (None: simulate's)
    plant_rate: float = PLANT_RATE    # Hz: the RK4 step (the convergence check runs others)


def map_channel(track: Track, profile, s_rows: np.ndarray) -> np.ndarray:
    """A track map's value of a road profile (bank, grade; None: a flat road) at the car's arc length: the value at
    the centre of the MAP_RESOLUTION cell the car is in, rounded to MAP_ROUNDING; a function of the position only,
    so it repeats lap after lap."""
    if profile is None:
        return np.zeros(len(s_rows))
    L = float(track.length)
    centre = ((np.floor(np.asarray(s_rows) % L / MAP_RESOLUTION) + 0.5) * MAP_RESOLUTION) % L
    return np.round(np.asarray(track.interpolate(np.asarray(profile, float), centre), float) / MAP_ROUNDING) \
        * MAP_ROUNDING


def broken_channel(truth: np.ndarray, Ts: float, rng: np.random.Generator) -> np.ndarray:
    """An untrustworthy angle channel like the real Putnam log's roll column (-1.9 to 2.3 rad): the truth plus an
    offset, a steady drift (BROKEN_DRIFT), a random walk (BROKEN_WALK) and jumps (BROKEN_JUMP_RATE, BROKEN_JUMP),
    wrapped to [-pi, pi)."""
    n = len(truth)
    t = np.arange(n) * Ts
    offset = rng.uniform(-1.0, 1.0)
    rate = rng.choice((-1.0, 1.0)) * rng.uniform(*BROKEN_DRIFT)
    walk = np.cumsum(rng.standard_normal(n)) * BROKEN_WALK * math.sqrt(Ts)
    jump = (rng.random(n) < BROKEN_JUMP_RATE * Ts) * rng.choice((-1.0, 1.0), n) * rng.uniform(*BROKEN_JUMP, n)
    out = np.asarray(truth, float) + offset + rate * t + walk + np.cumsum(jump)
    return (out + math.pi) % (2 * math.pi) - math.pi


def _command_at(history: list, t: float, delay: float, period: float) -> float:
    """The held command the actuator sees at time t: the one issued at the last DBW tick before t - delay."""
    k = int(math.floor((t - delay) / period + 1e-9))
    return history[min(max(k, 0), len(history) - 1)]


def make_log(track: Track | str = "putnam", effects: PlantEffects = PlantEffects(), seed: int = 0,
             settings: LogSettings = LogSettings(), nominal: Vehicle | str | Path | None = None,
             model=None, params: str = "vehicle2") -> Dataset:
    """One log of the CommonRoad plant driven around `track` (see the module docstring). model: "std" / StdModel()
    (default), "st" / StModel() (linear tyres) or "mb" / ddyn.plants.commonroad_mb.MbModel(); params: the CommonRoad
    parameter set (PARAMETER_SETS: vehicle1, vehicle2 (default), vehicle3, av21); nominal: the vehicle file the
    driver plans with and the log is made for (None: nominal_vehicle(model, params)). The plant's mass is the
    parameter set's."""
    consts = check_parameter_set(params)
    roll_kind = channel_kind(settings.roll_channel, "roll_channel")
    pitch_kind = channel_kind(settings.pitch_channel, "pitch_channel")
    require_commonroad()
    model = plant_model(model)
    if effects.tire_relaxation and model.name == "st":
        raise DdynError("tire_relaxation acts through CommonRoad's Pacejka tyres; vehicle_dynamics_st (model st) has "
                        "linear tyres without them")
    if nominal is None:
        nominal = nominal_vehicle(model.name, params)
    track = load_track(track) if isinstance(track, str) else track
    veh = vehicle_ref.as_vehicle(nominal) if not isinstance(nominal, Vehicle) else nominal
    Ts = veh.sample_time
    rate = float(settings.plant_rate)
    n_sub = int(round(Ts * rate))
    if abs(n_sub / rate - Ts) > 1e-9:
        raise DdynError(f"the log's sample time {Ts} s is not a multiple of the plant's {1 / rate} s")
    dbw = float(settings.dbw_period or Ts)
    n_dbw = int(round(dbw * rate))
    if n_dbw < 1 or abs(n_dbw / rate - dbw) > 1e-9:
        raise DdynError(f"the DBW period {dbw} s is not a multiple of the plant's {1 / rate} s")
    h = 1.0 / rate
    p = commonroad_parameters(params)
    m_nom = float(p.m)                # the plant's own mass (vehicle2's equals its nominal file's)
    model.scale_mass(p, 1.0 + effects.mass_offset)
    env = _Env(p=p, m_true=m_nom * (1.0 + effects.mass_offset), m_nominal=m_nom, downforce=effects.downforce,
               servo_tau=max(SERVO_TAU, effects.steer_lag),
               gamma=equivalent_gamma(effects.throttle_map) if effects.throttle_map else 1.0,
               brake_gain=effects.brake_gain, model=model, consts=consts)
    if effects.tire_relaxation:
        if effects.tire_relaxation < MIN_RELAXATION:
            raise DdynError(f"tyre relaxation length {effects.tire_relaxation} m: below {MIN_RELAXATION} m the "
                            f"relaxed slip angles are too fast for the {rate:g} Hz RK4 step (and for any tyre)")
        env.hook, env.relaxation = _TyreHook(), effects.tire_relaxation
    if effects.power_limit:
        # CommonRoad caps the acceleration at a_max v_switch / v above v_switch: the power a_max v_switch m
        p.longitudinal.v_switch = effects.power_limit / (env.m_true * p.longitudinal.a_max)
    grip = (p.tire.p_dx1, p.tire.p_dy1)     # tyre wear scales the friction coefficients from these
    bank = bank_profile(track, effects.bank_angle) if effects.bank_angle else None
    world = getattr(track, "bank", None)          # the track's own banking (the oval)
    if world is not None:
        world = np.asarray(world, float)
        bank = world if bank is None else world + bank
    grade = grade_profile(track, effects.grade, effects.grade_phase) if effects.grade else None

    ds_settings = driver_settings(veh, settings.target_speed, settings.driver_grip)
    profile = speed_profile(track, veh, veh.true_vector(), ds_settings)
    wheelbase = veh.known.lf + veh.known.lr
    t_lo, t_hi = veh.input_limits["throttle"]
    d_lo, d_hi = veh.input_limits["steering"]
    dt_max = veh.input_limits["dthrottle"][1] * dbw
    dd_max = veh.input_limits["dsteering"][1] * dbw
    seeds = np.random.SeedSequence(seed).spawn(4)
    ex_steer = BandNoise(np.random.default_rng(seeds[0]), 0.08)
    ex_throttle = BandNoise(np.random.default_rng(seeds[1]), 0.04)
    ex_speed = BandNoise(np.random.default_rng(seeds[2]), 0.004)
    noise_rng = np.random.default_rng(seeds[3])

    L = track.length
    s0 = float(settings.start_s) % L
    px, py = (float(v) for v in track.position(s0))
    v0 = float(track.interpolate(profile, s0))
    delta0 = math.atan(wheelbase * float(track.curvature_at(s0)))
    x = list(model.init(px, py, delta0, v0, float(track.heading_at(s0)), p))
    env.n_model = len(x)
    if env.hook is not None:
        x += [0.0] * model.tyres          # relaxed slip angles, from straight running
    n = int(round(settings.duration / Ts)) + 1
    rows = np.empty((n, 6))
    true_delta = np.empty(n)
    body_roll = np.zeros(n)
    road_bank = np.zeros(n)
    road_grade = np.zeros(n)
    s_rows = np.zeros(n)
    gears = np.zeros(n, dtype=np.int64)
    T_hist: list[float] = []
    D_hist: list[float] = []
    T_cmd, D_cmd = 0.0, delta0
    integ = 0.0
    s_prev = s0
    window = max(4.0 * ds_settings.lookahead_min, 0.05 * L)
    preview = np.linspace(0.0, 1.0, 6)
    gear, shift_until = None, -1.0
    n_steps = (n - 1) * n_sub
    for i in range(n_steps + 1):
        t = i * h
        X, Y, delta, psi, vx, vy, psi_dot, roll = model.observe(x)
        k, log_row = divmod(i, n_sub)
        if log_row == 0 or i % n_dbw == 0:
            if not all(math.isfinite(a) for a in x):
                raise CarLostError(f"the CommonRoad plant diverged at t = {t:.2f} s")
            s_arr, lat_arr = track.project(X, Y, s_hint=s_prev, window=window)
            s, lat = float(s_arr), float(lat_arr)
            s_prev = s
        if log_row == 0:
            # the excitation is drawn once per log sample whatever the DBW rate (the same driving spectrum)
            ex = (ex_steer.next(), ex_speed.next(), ex_throttle.next())
        if i % n_dbw == 0:
            # ---- driver (on the true state, once per DBW tick)
            look = max(ds_settings.lookahead_min, ds_settings.lookahead_time * vx)
            gx, gy = track.position(s + look)
            alpha = math.atan2(float(gy) - Y, float(gx) - X) - psi
            kappa_cmd = 2.0 * math.sin(alpha) / math.hypot(float(gx) - X, float(gy) - Y)
            d_new = math.atan(wheelbase * kappa_cmd)
            v_yaw = max(vx, ds_settings.lookahead_min / ds_settings.lookahead_time)
            d_new += ds_settings.yaw_gain * wheelbase * (kappa_cmd - psi_dot / v_yaw)
            amp = ds_settings.steer_excitation * min(1.0, (ds_settings.excitation_speed / max(vx, 1e-6)) ** 2)
            d_new += settings.excitation * amp * ex[0]
            scale = 1.0 + settings.excitation * ds_settings.speed_excitation * ex[1]
            v_ref = scale * float(np.min(track.interpolate(profile, s + preview * ds_settings.speed_preview
                                                           * max(vx, 0))))
            err = v_ref - vx
            t_new = (ds_settings.kp * err + ds_settings.ki * integ) / consts.accel_scale \
                + settings.excitation * ds_settings.throttle_excitation * ex[2]
            if t_lo < t_new < t_hi:
                integ += err * dbw
            # the DBW unit's rate and range limits (the log's rates stay inside the vehicle's input limits)
            T_cmd = min(max(T_cmd + min(max(t_new - T_cmd, -dt_max), dt_max), t_lo), t_hi)
            D_cmd = min(max(D_cmd + min(max(d_new - D_cmd, -dd_max), dd_max), d_lo), d_hi)
            T_hist.append(T_cmd)
            D_hist.append(D_cmd)
        if log_row == 0:
            rows[k] = (X, Y, psi, vx, vy, psi_dot)
            s_rows[k] = s
            true_delta[k] = delta
            body_roll[k] = roll or 0.0
            if bank is not None:
                road_bank[k] = float(track.interpolate(bank, s))
            wl, wr = track.half_widths(s)
            if max(lat - float(wl), -lat - float(wr)) > 0.5 * track.width:
                raise CarLostError(f"the driver lost the CommonRoad car at t = {t:.2f} s, s = {s:.0f} m "
                                f"(seed {seed}, effects {effects.active()}); try a lower target speed")
            # held over the sample: the road under the car and the tyres' wear change slowly
            if bank is not None:
                env.bank = road_bank[k]
            if effects.tire_wear:
                w = math.exp(-effects.tire_wear * t)
                p.tire.p_dx1, p.tire.p_dy1 = grip[0] * w, grip[1] * w
            if grade is not None:
                env.grade = float(track.interpolate(grade, s))
                road_grade[k] = env.grade
        if effects.gear_step:
            # the stepped gearbox: shift on the true speed, cut the drive while the clutch is open
            new = gear_for(vx, gear or 1)
            if gear is not None and new != gear:
                shift_until = t + SHIFT_TIME
            gear = new
            env.gear_factor = 0.0 if t < shift_until else (1.0 + effects.gear_step) ** (GEAR_REF - gear)
            if log_row == 0:
                gears[k] = gear
        if i == n_steps:
            break
        # ---- plant: one RK4 step with the held (possibly delayed) commands
        x = rk4_step(x, h, _command_at(D_hist, t, effects.steer_delay, dbw),
                     _command_at(T_hist, t, effects.throttle_delay, dbw), env)

    # the log records the command in force at each row (the DBW's latest)
    ticks = np.minimum((np.arange(n) * n_sub) // n_dbw, len(T_hist) - 1)
    T_hist = [T_hist[j] for j in ticks]
    D_hist = [D_hist[j] for j in ticks]
    T = np.array(T_hist)
    D = np.array(D_hist)
    states = np.column_stack([rows[:, :3], rows[:, 3:6], T, D])
    inputs = np.zeros((n, 2))
    inputs[:-1, 0] = np.diff(T) / Ts
    inputs[:-1, 1] = np.diff(D) / Ts
    extras = {f"true_{c}": rows[:, i].copy() for i, c in enumerate(NOISY)}
    extras["true_steering"] = true_delta
    extras["true_bank"] = road_bank
    rolls = getattr(model, "rolls", False)        # the model has a body roll state (the multi-body model)
    # the body leans out of the turn: against the lateral acceleration vx omega (a roll gradient where the model
    # has no roll state)
    lean = body_roll if rolls else -consts.roll_gradient * rows[:, 3] * rows[:, 5] / G
    if rolls or roll_kind != "none":
        extras["true_body_roll"] = lean
    if grade is not None or pitch_kind != "none":
        extras["true_grade"] = road_grade
    if effects.gear_step:
        extras["true_gear"] = gears.astype(float)
    if roll_kind == "imu":
        # bank minus body roll
        roll_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(5)[4])
        extras["roll"] = road_bank + lean + ROLL_NOISE * roll_rng.standard_normal(n)
    elif roll_kind == "map":
        extras["roll"] = map_channel(track, bank, s_rows)
    elif roll_kind == "broken":
        extras["roll"] = broken_channel(road_bank + lean, Ts,
                                        np.random.default_rng(np.random.SeedSequence(seed).spawn(7)[6]))
    if pitch_kind != "none":
        # grade (+: uphill, nose up) plus the body's squat under the longitudinal acceleration dvx/dt - vy omega
        # (nose up when accelerating); its own random stream, so the other channels are those of a log without it
        ax = np.gradient(rows[:, 3], Ts) - rows[:, 4] * rows[:, 5] if n > 1 else np.zeros(n)
        body_pitch = consts.pitch_gradient * ax / G
        if pitch_kind == "imu":
            pitch_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(6)[5])
            extras["pitch"] = road_grade + body_pitch + PITCH_NOISE * pitch_rng.standard_normal(n)
        elif pitch_kind == "map":
            extras["pitch"] = map_channel(track, grade, s_rows)
        else:
            extras["pitch"] = broken_channel(road_grade + body_pitch, Ts,
                                             np.random.default_rng(np.random.SeedSequence(seed).spawn(8)[7]))
    noisy = states.copy()
    if settings.noise_scale > 0:
        std = np.array([settings.noise_scale * veh.sensor_noise_std[c] for c in NOISY])
        w = noise_rng.standard_normal((n, 6))
        rho = float(settings.noise_color)
        if rho:
            # AR(1) with the same marginal std: n_k = rho n_k-1 + sqrt(1 - rho^2) w_k
            for k in range(1, n):
                w[k] = rho * w[k - 1] + math.sqrt(1 - rho * rho) * w[k]
        noisy[:, :6] += w * std
    noisy[:, 5] += effects.yaw_rate_bias      # a sensor bias: the driver and the dynamics see the true omega
    active = effects.active()
    metadata = {
        "plant": f"{model.label}, {PARAMETER_LABELS[params]}, RK4 at 1 kHz, DBW hold",
        "dbw_period": repr(dbw),
        "track": track.name, "seed": str(seed), "noise_scale": repr(float(settings.noise_scale)),
        "noise_color": repr(float(settings.noise_color)), "target_speed": repr(float(settings.target_speed)),
        "driver_grip": repr(float(ds_settings.grip)),
        "method": "rk4", "substeps": str(veh.rk4_substeps),
        # ground truth in the project's effect names (bank and grade: the peak of a profile)
        "plant_effects": json.dumps(active),
        **vehicle_ref.metadata_for(veh),
    }
    src = (f"commonroad plant ({model.label.split()[-1]}, {consts.car}) on {track.name}, seed {seed}, "
           f"effects {active or 'none'}")
    return Dataset(time=np.arange(n) * Ts, segment=np.zeros(n, dtype=np.int64), states=noisy, inputs=inputs,
                   sample_time=Ts, vehicle=veh.name, source=src, extras=extras, metadata=metadata)


# ---- the nominal vehicle files of the plant families: the plant's parameters mapped onto the project's model
PLANTS_DIR = NOMINAL_VEHICLE.parent
WRITE_COMMAND = "python -m ddyn.plants.commonroad_st --write-vehicles"
_MODEL_TEXT = {"std": "the independent plant (ddyn.plants.commonroad_st, vehicle_dynamics_std)",
               "st": "the linear-tyre single-track plant (ddyn.plants.commonroad_st, model st: vehicle_dynamics_st)",
               "mb": "the multi-body plant (ddyn.plants.commonroad_mb, vehicle_dynamics_mb)"}
LINEAR_FIT_POINTS = 200


def nominal_vehicle(model_name: str = "std", params: str = "vehicle2") -> Path:
    """The vehicle file the (model, parameter set) plant's logs are made for and diagnosed with: vehicle2 with std
    the original NOMINAL_VEHICLE, with mb commonroad_vehicle2_mb.json, else commonroad_<params>[_st|_mb].json
    (written by write_vehicle_files)."""
    check_parameter_set(params)
    if model_name not in MODELS:
        raise DdynError(f"unknown CommonRoad plant model {model_name!r}; expected one of {', '.join(MODELS)}")
    path = PLANTS_DIR / f"commonroad_{params}{'' if model_name == 'std' else '_' + model_name}.json"
    if not path.is_file():
        raise DdynError(f"{path} is missing; write it with {WRITE_COMMAND}")
    return path


def linear_tyre_fit(p) -> dict:
    """The project's Pacejka curve D sin(C atan(B a - E (B a - atan(B a)))) closest to vehicle_dynamics_st's linear
    tyre |p_ky1| F_z a per unit load: D fixed at the friction p_dy1 F_z (what the ST model calls mu, and what the
    driver's speed profile reads the grip from), B, C, E by least squares on LINEAR_FIT_POINTS evenly spaced slip
    angles in [0, a_max] inside the project's ranges (B 5-30, C 0.5-2, E -2-0.5); a_max = 0.9 p_dy1 / |p_ky1| is
    the slip at which the linear tyre carries 0.9 of the friction, the most the driver plans with (simulate's
    max_grip). The same B, C, E fit both axles (K and D both scale with the axle load)."""
    from scipy.optimize import least_squares

    mu, k = float(p.tire.p_dy1), abs(float(p.tire.p_ky1))
    a_max = 0.9 * mu / k
    a = np.linspace(0.0, a_max, LINEAR_FIT_POINTS)

    def res(x):
        B, C, E = x
        Ba = B * a
        return mu * np.sin(C * np.arctan(Ba - E * (Ba - np.arctan(Ba)))) - k * a

    r = least_squares(res, [k / (1.3 * mu), 1.3, -1.0], bounds=([5.0, 0.5, -2.0], [30.0, 2.0, 0.5]), xtol=1e-12,
                      ftol=1e-12)
    B, C, E = (float(v) for v in r.x)
    top = k * a_max
    return {"B": B, "C": C, "E": E, "a_max": a_max, "rms": float(np.sqrt(np.mean(r.fun ** 2)) / top),
            "max": float(np.max(np.abs(r.fun)) / top)}


def vehicle_document(model_name: str, params: str) -> dict:
    """The nominal vehicle file of the (model, parameter set) plant as a JSON document (write_vehicle_files)."""
    consts = check_parameter_set(params)
    p = commonroad_parameters(params)
    base = json.loads(NOMINAL_VEHICLE.read_text())
    m, lf, lr = float(p.m), float(p.a), float(p.b)
    L = lf + lr
    mu = float(p.tire.p_dy1)
    load_f, load_r = m * G * lr / L, m * G * lf / L
    name = f"commonroad_{params}{'' if model_name == 'std' else '_' + model_name}"
    label = PARAMETER_LABELS[params]
    doc = {"name": name,
           "description": f"CommonRoad {label} ({consts.car}) mapped onto the project's single-track model: the "
                          f"nominal model of {_MODEL_TEXT[model_name]}; written by `{WRITE_COMMAND}` "
                          f"(commonroad_st.write_vehicle_files)"}
    for k in ("sample_time", "max_speed", "evaluation_horizon", "rk4_substeps"):
        doc[k] = base[k]
    doc["known"] = {"mass": m, "lf": lf, "lr": lr, "v_min": 0.5}
    c = {"Gf": 0.0, "Kf": 0.0, "Gr": 0.0, "Kr": 0.0, "Cm1": round(m * consts.accel_scale, 2), "Cm2": 0.0,
         "Cr0": consts.rolling, "Cd": consts.drag, "Iz": float(p.I_z)}
    src = {}
    if model_name == "st":
        fit = linear_tyre_fit(p)
        B, C, E = round(fit["B"], 4), round(fit["C"], 4), round(fit["E"], 4)
        src["true Bf, Cf, Ef, Br, Cr, Er"] = (
            f"vehicle_dynamics_st's linear tyre F = |p_ky1| F_z alpha ({abs(p.tire.p_ky1):g} per unit load, no "
            f"saturation) matched by the project's magic formula: D fixed at p_dy1 F_z, B, C, E least squares on "
            f"{LINEAR_FIT_POINTS} slip angles evenly in [0, {fit['a_max']:.4f}] rad (0.9 p_dy1 / |p_ky1|: the "
            f"linear tyre at 0.9 of the friction, the driver's max_grip) within B 5-30, C 0.5-2, E -2-0.5 "
            f"(commonroad_st.linear_tyre_fit); rms error {100 * fit['rms']:.1f} %, largest {100 * fit['max']:.1f} % "
            f"of the force at the range's top. Beyond it the model saturates, the plant does not")
    else:
        B, C, E = round(abs(p.tire.p_ky1) / (p.tire.p_cy1 * mu), 3), float(p.tire.p_cy1), float(p.tire.p_ey1)
        src["true Bf, Cf, Ef, Br, Cr, Er"] = base["sources"]["true Bf, Cf, Ef, Br, Cr, Er"]
    c |= {"Bf": B, "Cf": C, "Ef": E, "Br": B, "Cr": C, "Er": E,
          "Df": round(mu * load_f, 2), "Dr": round(mu * load_r, 2)}
    doc["true_coefficients"] = {k: c[k] for k in base["true_coefficients"]}
    ranges = {}
    for k, (lo, hi) in base["ranges"].items():
        v = c[k]
        if not lo <= v <= hi:        # widen to half and double the truth
            lo, hi = min(lo, 0.5 * v, 2 * v), max(hi, 0.5 * v, 2 * v)
        ranges[k] = [lo, hi]
    doc["ranges"] = ranges
    limits = dict(base["input_limits"])
    if params == "av21":
        limits |= {"steering": [-0.25, 0.25], "dsteering": [-0.6, 0.6]}
    doc["input_limits"] = limits
    doc["sensor_noise_std"] = base["sensor_noise_std"]
    sources = {"known": f"CommonRoad {label}: m, a (lf), b (lr)"
                        + (" (the total of the sprung and unsprung masses)" if model_name == "mb" else ""),
               **src,
               "true Df, Dr": f"p_dy1 ({mu:g}) times the static axle load m g lr / L, m g lf / L"
                              + ("; the multi-body plant splits each axle's load over two wheels and shifts it "
                                 "through roll, so its axle grip in a turn is below this"
                                 if model_name == "mb" else ""),
               "true Gf, Kf, Gr, Kr": "zero: the shifts S_hy, S_vy vanish at camber 0 (none in the linear tyre)",
               "true Cm1, Cm2": f"the plant's throttle map (ddyn.plants.commonroad_st, PARAMETER_SETS[{params!r}]): "
                                f"drive force m {consts.accel_scale:g} m/s^2 T, no speed term; CommonRoad's power "
                                f"limit above v_switch is not modelled",
               "true Cr0, Cd": f"the rolling resistance ({consts.rolling:g} N) and drag ({consts.drag:g} kg/m) the "
                               f"plant adds ({SET_SOURCES[params]}); CommonRoad itself has none",
               "true Iz": "CommonRoad I_z" + (" (the AV-21's: train/vehicles/av21.json)" if params == "av21" else ""),
               "input_limits": ("steering +-0.25 rad and rate +-0.6 rad/s as train/vehicles/av21.json (the plant's "
                                "steering rate limit is set to 0.6 rad/s)" if params == "av21" else
                                "steering rate: CommonRoad's steering v_max 0.4 rad/s; angle +-0.3 rad")
                               + ", throttle rate as the AV-21",
               "ranges": "commonroad_vehicle2.json's, widened to half and double a truth outside them",
               "sensor_noise_std": base["sources"]["sensor_noise_std"],
               "evaluation_horizon, max_speed, sample_time": base["sources"]["evaluation_horizon, max_speed, "
                                                                         "sample_time"],
               "generated": f"`{WRITE_COMMAND}` (commonroad_st.vehicle_document({model_name!r}, {params!r}))"}
    doc["sources"] = sources
    return doc


def write_vehicle_files(directory: Path | None = None, models=MODELS, sets=tuple(PARAMETER_SETS)) -> list[Path]:
    """Write the nominal vehicle file of every (model, parameter set) but the two hand-made vehicle2 files (std, mb)
    into directory (default train/vehicles/plants); returns the paths written."""
    directory = Path(directory) if directory is not None else PLANTS_DIR
    out = []
    for model_name in models:
        for params in sets:
            if params == "vehicle2" and model_name in ("std", "mb"):
                continue
            doc = vehicle_document(model_name, params)
            path = directory / f"{doc['name']}.json"
            path.write_text(json.dumps(doc, indent=2) + "\n")
            out.append(path)
    return out


if __name__ == "__main__":   # pragma: no cover
    import sys

    if sys.argv[1:] != ["--write-vehicles"]:
        raise SystemExit(f"usage: {WRITE_COMMAND}")
    for path in write_vehicle_files():
        print(path)
