"""A third independent plant family: a rigid-body car in the MuJoCo physics engine (PyPI mujoco).

Why: the two CommonRoad plants (ddyn.plants.commonroad_st, commonroad_mb) both compute their tyre forces with
a Pacejka magic formula, the same family of curve the project's model fits. Here there is no tyre curve at all:
the four wheels are rigid ellipsoids on hinges and every tyre force is MuJoCo's soft-contact friction (an
elliptic Coulomb cone, no load sensitivity, a contact "creep" set by the constraint impedance, not by a slip
stiffness). The sprung mass rides on four slide-joint suspensions (springs and dampers), so load transfer, body
roll, pitch and squat come out of the rigid-body dynamics. Nothing of ddyn.model integrates it.

The car (CAR below): a 1500 kg rear-wheel-drive saloon (1340 kg sprung, 4 x 40 kg unsprung), wheelbase 2.8 m
(lf 1.35, lr 1.45 from the whole car's centre of gravity), track 1.6 m, sprung CoG 0.50 m high, wheel radius
0.32 m, springs 38/30 kN/m front/rear (about 1.6 Hz), ~4 deg/g of roll, yaw inertia 2400 kg m^2, contact
friction 0.95 front / 1.10 rear (about 1 g of lateral grip, understeer at the limit), parallel steering of both front wheels by a position servo behind a
first-order filter (SERVO_TAU), an engine map of DRIVE_ACCEL at full pedal up to a power limit P_MAX, brakes
(BRAKE_ACCEL at full negative pedal, BRAKE_FRONT of it on the front wheels), aerodynamic drag and rolling
resistance as forces applied to the chassis.

How a log is made (the way commonroad_st.make_log makes one, and with its types PlantEffects, LogSettings):
  - MuJoCo integrates at LogSettings.plant_rate (timestep 1/plant_rate, implicitfast integrator);
  - the driver (pure pursuit with yaw-rate feedback, PI on speed: _driver, the structure of commonroad_st's)
    decides throttle and steering once per DBW tick on the true state; the DBW unit holds them; the log
    records the commanded values, dthrottle/dsteering are their forward differences;
  - the held commands (delayed per steer_delay / throttle_delay, commonroad_st._command_at) change only at
    known instants, so the engine is stepped in chunks (mj_step with nstep) between them and the log samples:
    the applied forces that depend on the state (drag, rolling resistance, downforce, the power limit's P/v,
    the brakes' direction, gravity tilted by the road under the car) are set at the start of each chunk and
    held over it (at most one log sample, 40 ms: the speed changes by < 0.3 m/s and the heading by < 0.05 rad
    in that time), which keeps the Python overhead per 60 s log to ~1500 chunk calls;
  - bank and grade: the ground is a flat plane and gravity is tilted by the road's bank (+: pulls the car to
    its left) and grade (+: uphill) at the car's track position, in the car's heading frame; the track's own
    banking (Track.bank, the oval) adds to the bank_angle effect's profile (commonroad_st.bank_profile);
  - LogSettings.roll_channel / pitch_channel: extras "roll" / "pitch", of the kinds of commonroad_st
    (CHANNEL_KINDS): "imu" (True) from the chassis's actual orientation: the road's bank plus the body's roll on
    its springs relative to the road (+: left side down, as commonroad_st), the road's grade plus the body's
    pitch (+: nose up), plus ROLL_NOISE / PITCH_NOISE; "map" a track map's bank / grade at the car's position
    (commonroad_st.map_channel); "broken" that orientation with an offset, drift, walk and jumps
    (commonroad_st.broken_channel); "none" (False) no channel. (Until issue 33's pitch channels every truthy
    value, "none", "map" and "broken" included, logged the IMU channel, so the campaign's MuJoCo logs all
    carried one);
  - every logged state gets white or AR(1) noise as in commonroad_st; yaw_rate_bias is added to the logged
    omega only.

State mapping: x, y = the chassis frame origin, placed at the whole car's centre of gravity; yaw = the heading
of the chassis's x axis (unwrapped); vx, vy = the origin's world velocity in the heading frame; omega = the
world yaw rate. The wheel angle is the mean of the two front steer joints (extras true_steering); the body's
roll relative to the road is extras true_body_roll.

Effects (SUPPORTED_EFFECTS), in physical form:
  steer_delay, throttle_delay   command histories (commonroad_st._command_at)
  steer_lag                     the steering filter's time constant max(SERVO_TAU, lag)
  mass_offset                   every body's mass and inertia (1 + f) times the nominal (total mass, Iz exact)
  downforce                     a downward force k m g vx^2 on the chassis (ddyn.model.effects: tyre loads
                                1 + k vx^2)
  bank_angle, grade             gravity tilted per chunk (profiles of commonroad_st)
  tire_wear                     the contact friction scaled by exp(-rate t) at each log sample
  yaw_rate_bias                 sensor only
  throttle_map                  the pedal reaches the engine as T^gamma (commonroad_st.equivalent_gamma)
  brake_gain                    brake torques (1 + g) times the nominal
  power_limit                   the engine's power limit in W instead of P_MAX
Not supported (DdynError):
  tire_relaxation               the tyres are rigid contacts: there is no carcass whose deflection could build
                                up over a relaxation length (a tyre model would have to replace the contact)
  gear_step                     the drivetrain is a direct torque map without a gearbox; a stepped gearbox with
                                its shift cuts is not modelled

The nominal vehicle file (NOMINAL_VEHICLE) is what a user would have for a car with no single-track equivalent:
the project's model identified on effect-free logs of this plant (`python -m ddyn.plants.mujoco_car --identify`,
which starts from the car's known mass, lf, lr, Iz and rough coefficients, START_VEHICLE), then the car's own
effects (ddyn.gap.baseline) on three effect-free logs at 18, 22 and 26 m/s: downforce comes first on the two
faster ones at one size (k 0.0017: the contact tyres' force grows with slip velocity, so with speed), so the file
carries it, with the tyre peaks scaled by the refit it was found with (Df, Dr times 0.59). The fit puts Iz at its
range's upper edge (4000 kg m^2 against the car's 2400: the DBW hold and servo lag the model does not have are
absorbed there) and Cr0 at zero (taken up by Cd); its one-step rms residual on a fresh effect-free 60 s log
(seed 9301) is at the sensor-noise floor: vx 0.072 m/s, vy 0.026 m/s, omega 0.0078 rad/s. The driver plans its
speed from fixed coefficients (DRIVER_COEFFICIENTS), never from the nominal file.

Cost: about 1.2-1.5 s of CPU per 60 s log (mj_step ~20 us per 1 ms step).
"""
from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np

from ddyn.data import vehicle_ref
from ddyn.data.dataset import Dataset
from ddyn.data.simulate import BandNoise, driver_settings, speed_profile
from ddyn.errors import CarLostError, DdynError
from ddyn.model.tracks import Track, load_track
from ddyn.model.vehicle import Vehicle
from ddyn.plants.commonroad_st import (PLANT_EFFECTS, LogSettings, PlantEffects, _command_at, bank_profile,
                                       broken_channel, channel_kind, equivalent_gamma, grade_profile,
                                       map_channel)

try:
    import mujoco
except ImportError as _e:  # pragma: no cover
    _IMPORT_ERROR: ImportError | None = _e
else:
    _IMPORT_ERROR = None

G = 9.81
NOMINAL_VEHICLE = Path(__file__).resolve().parents[1] / "vehicles" / "plants" / "mujoco_car.json"
NOISY = ("x", "y", "yaw", "vx", "vy", "omega")
UNSUPPORTED = {
    "tire_relaxation": "its tyres are rigid MuJoCo contacts with no carcass to relax over a length",
    "gear_step": "its drivetrain is a direct torque map without a gearbox",
}
SUPPORTED_EFFECTS = tuple(e for e in PLANT_EFFECTS if e not in UNSUPPORTED)

# ---- the car
CAR = dict(
    m_sprung=1340.0, m_knuckle=20.0, m_wheel=20.0,       # kg (total 1500)
    lf=1.35, lr=1.45, half_track=0.8,                   # m, from the whole car's CoG
    h_sprung=0.50, radius=0.32, wheel_width=0.22,        # m
    I_sprung=(550.0, 2100.0, 1985.0),                     # kg m^2 about the sprung CoG (roll, pitch, yaw)
    k_front=38000.0, k_rear=30000.0,                      # N/m
    c_front=2650.0, c_rear=2100.0,                        # N s/m
    travel=0.12,                                          # m of bump and droop
    friction_front=0.95, friction_rear=1.10,              # contact friction coefficients (wider rear tyres:
                                                          # the Coulomb contact has no load sensitivity, so
                                                          # this is what makes the car understeer at the limit)
)
IMPRATIO = 0.01              # friction-to-normal impedance ratio of the contacts: the contact creeps like a
                             # damper (lateral force ~ slip velocity), ~200 kN/rad per axle at 25 m/s
GROUND_FRICTION = 0.01      # the plane's own friction: MuJoCo uses the larger of a contact pair's
SERVO_TAU = 0.01             # s: the steering filter of the effect-free plant (its servo loop adds ~4 ms)
STEER_KP = 60000.0           # N m/rad: the steering servo (position actuator)
STEER_KV = 600.0             # N m s/rad
DRIVE_ACCEL = 4.0            # m/s^2 at full pedal for the nominal mass (the rear wheels' torque)
BRAKE_ACCEL = 4.0            # m/s^2 at full negative pedal (all four wheels)
BRAKE_FRONT = 0.6            # share of the braking torque on the front wheels
P_MAX = 150e3                # W: the engine's power limit (drive force <= P / v)
DRAG = 0.40                  # kg/m: 0.5 rho Cd A (rho 1.2, Cd A 0.67 m^2)
ROLLING = 0.012              # rolling-resistance coefficient (times m g)
ROLL_NOISE = 0.003           # rad: an EKF's roll noise
PITCH_NOISE = 0.003          # rad
SETTLE_TIME = 0.6            # s: the car settles on its springs at standstill before the log starts
IDENT_SEEDS = (9300, 9301)   # effect-free logs used for nothing but identifying the nominal
IDENT_DURATION = 120.0       # s per identification log
BASELINE_SEEDS = (9302, 9303, 9304)    # effect-free logs across the campaign's speeds for the car's own effects
BASELINE_SPEEDS = (18.0, 22.0, 26.0)   # m/s (ddyn.gap.baseline)
START_VEHICLE = {            # the rough coefficients the identification starts from (Df, Dr: mu m g lr / L ...)
    "Bf": 12.0, "Cf": 1.4, "Df": 7239.0, "Ef": 0.0, "Gf": 0.0, "Kf": 0.0,
    "Br": 12.0, "Cr": 1.4, "Dr": 7804.0, "Er": 0.0, "Gr": 0.0, "Kr": 0.0,
    "Cm1": 6000.0, "Cm2": 0.0, "Cr0": 177.0, "Cd": 0.4, "Iz": 2400.0,
}


# The driver's idea of the car (its speed profile's grip and drive): a property of the plant's driver, fixed, not the
# nominal a user identifies; were it read from the nominal file, every identification would change the logs it is
# identified on and every log a study has drawn. The values are the first identification's (seed 9300, 120 s).
DRIVER_COEFFICIENTS = {
    "Bf": 11.963747, "Cf": 1.809721, "Df": 5700.65587, "Ef": 0.0, "Gf": 0.0, "Kf": 0.0,
    "Br": 12.618084, "Cr": 2.703565, "Dr": 5981.926175, "Er": 0.0, "Gr": 0.0, "Kr": 0.0,
    "Cm1": 5862.340222, "Cm2": 0.0, "Cr0": 0.0, "Cd": 0.585549, "Iz": 4000.0,
}


def driver_vector() -> np.ndarray:
    from ddyn.model.single_track import COEFF_NAMES

    return np.array([DRIVER_COEFFICIENTS[n] for n in COEFF_NAMES], float)


def require_mujoco() -> None:
    if _IMPORT_ERROR is not None:
        raise DdynError(f"the MuJoCo plant needs the PyPI package mujoco (requirements.in; bash scripts/setup.sh "
                        f"installs it): {_IMPORT_ERROR}")


def car_mass(car: dict = CAR) -> float:
    return car["m_sprung"] + 4 * (car["m_knuckle"] + car["m_wheel"])


def mjcf(car: dict = CAR, scale: float = 1.0, servo_tau: float = SERVO_TAU, timestep: float = 1e-3) -> str:
    """The car as MJCF; scale multiplies every mass and inertia (mass_offset)."""
    c = car
    mu = c["m_knuckle"] + c["m_wheel"]
    ms = c["m_sprung"]
    # the sprung mass sits so that the whole car's CoG is at the chassis frame's origin (horizontally)
    xs = 2 * mu * (c["lr"] - c["lf"]) / ms
    r, h, w = c["radius"], c["h_sprung"], c["wheel_width"]
    mtot = car_mass(c)
    Ixx, Iyy, Izz = (scale * v for v in c["I_sprung"])
    # static corner loads of the nominal car: the springs' preload (springref) holds it at zero deflection
    front_w = mtot * G * c["lr"] / (c["lf"] + c["lr"]) / 2 - mu * G
    rear_w = mtot * G * c["lf"] / (c["lf"] + c["lr"]) / 2 - mu * G
    wheel_I = (c["m_wheel"] * (3 * r * r + w * w) / 12, c["m_wheel"] * r * r / 2)
    corners = []
    for name, x, y, k, d, load, front in (("fl", c["lf"], c["half_track"], c["k_front"], c["c_front"], front_w, 1),
                                          ("fr", c["lf"], -c["half_track"], c["k_front"], c["c_front"], front_w, 1),
                                          ("rl", -c["lr"], c["half_track"], c["k_rear"], c["c_rear"], rear_w, 0),
                                          ("rr", -c["lr"], -c["half_track"], c["k_rear"], c["c_rear"], rear_w, 0)):
        mu_tyre = c["friction_front"] if front else c["friction_rear"]
        steer = (f'<joint name="steer_{name}" type="hinge" axis="0 0 1" range="-0.6 0.6" armature="0.2" '
                 f'damping="5"/>') if front else ""
        corners.append(f"""
      <body name="knuckle_{name}" pos="{x} {y} {r - h}">
        <joint name="susp_{name}" type="slide" axis="0 0 1" stiffness="{k}" damping="{d}" springref="{-load / k}"
               range="{-c['travel']} {c['travel']}" limited="true"/>
        {steer}
        <inertial pos="0 0 0" mass="{scale * c['m_knuckle']}" diaginertia="{scale * 0.4} {scale * 0.4} {scale * 0.4}"/>
        <body name="wheel_{name}">
          <joint name="spin_{name}" type="hinge" axis="0 1 0" armature="{0.0 if front else 0.8}"/>
          <inertial pos="0 0 0" mass="{scale * c['m_wheel']}"
                    diaginertia="{scale * wheel_I[0]} {scale * wheel_I[1]} {scale * wheel_I[0]}"/>
          <geom name="tyre_{name}" type="ellipsoid" size="{r} {w / 2} {r}" contype="1" conaffinity="0"
                condim="3" friction="{mu_tyre} 0 0"/>
        </body>
      </body>""")
    act_steer = "".join(
        f'<general name="steer_{n}" joint="steer_{n}" dyntype="filterexact" dynprm="{servo_tau}" gaintype="fixed" '
        f'gainprm="{STEER_KP}" biastype="affine" biasprm="0 {-STEER_KP} {-STEER_KV}" ctrlrange="-0.6 0.6" '
        f'ctrllimited="true"/>' for n in ("fl", "fr"))
    act_torque = "".join(f'<motor name="torque_{n}" joint="spin_{n}" gear="1"/>' for n in ("fl", "fr", "rl", "rr"))
    return f"""<mujoco model="ddyn_mujoco_car">
  <option timestep="{timestep}" integrator="implicitfast" cone="elliptic" solver="Newton" iterations="30" impratio="{IMPRATIO}"
          tolerance="1e-10" gravity="0 0 {-G}"/>
  <default><geom solref="0.01 1" solimp="0.95 0.99 0.001"/></default>
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1" contype="0" conaffinity="1" friction="{GROUND_FRICTION} 0 0"/>
    <body name="chassis" pos="0 0 {h}">
      <freejoint name="root"/>
      <inertial pos="{xs} 0 0" mass="{scale * ms}" diaginertia="{Ixx} {Iyy} {Izz}"/>
      <geom type="box" size="2.2 0.85 0.3" contype="0" conaffinity="0" mass="0"/>{''.join(corners)}
    </body>
  </worldbody>
  <actuator>{act_steer}{act_torque}</actuator>
</mujoco>"""


class _Car:
    """The compiled model and the indices make_log needs."""

    def __init__(self, scale: float, servo_tau: float, timestep: float):
        require_mujoco()
        self.m = mujoco.MjModel.from_xml_string(mjcf(CAR, scale, servo_tau, timestep))
        self.d = mujoco.MjData(self.m)
        m = self.m
        jid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)
        self.chassis = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "chassis")
        self.steer_q = [m.jnt_qposadr[jid(f"steer_{n}")] for n in ("fl", "fr")]
        self.spin_v = [m.jnt_dofadr[jid(f"spin_{n}")] for n in ("fl", "fr", "rl", "rr")]
        self.tyres = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"tyre_{n}") for n in ("fl", "fr", "rl", "rr")]
        self.ground = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ground")
        self.friction = self.m.geom_friction[self.tyres, 0].copy()   # MuJoCo takes the larger of the pair's

    def wear(self, factor: float) -> None:
        """The tyres' friction times factor (the ground's is below every tyre's, so the tyre's is the pair's)."""
        self.m.geom_friction[self.tyres, 0] = self.friction * factor

    def place(self, X: float, Y: float, psi: float, v: float, steer: float) -> None:
        """The car at (X, Y) heading psi, rolling straight at v with its front wheels at `steer` (suspension and
        height as they settled)."""
        d = self.d
        d.qpos[0:2] = X, Y
        d.qpos[3:7] = math.cos(psi / 2), 0.0, 0.0, math.sin(psi / 2)
        d.qvel[:] = 0.0
        d.qvel[0:2] = v * math.cos(psi), v * math.sin(psi)
        for a in self.spin_v:
            d.qvel[a] = v / CAR["radius"]
        for a in self.steer_q:
            d.qpos[a] = steer
        d.act[:] = steer
        d.ctrl[0:2] = steer
        mujoco.mj_forward(self.m, d)

    def observe(self) -> tuple:
        """(X, Y, wheel angle, yaw, vx, vy, yaw rate, body roll (+: left down), body pitch (+: nose up)) with the
        body roll and pitch relative to the ground plane (the road)."""
        d = self.d
        R = d.xmat[self.chassis].reshape(3, 3)     # columns: the body axes in the world
        psi = math.atan2(R[1, 0], R[0, 0])
        vX, vY = d.qvel[0], d.qvel[1]
        c, s = math.cos(psi), math.sin(psi)
        omega = float(R[2] @ d.qvel[3:6])          # the free joint's angular velocity is in the body frame
        delta = 0.5 * (d.qpos[self.steer_q[0]] + d.qpos[self.steer_q[1]])
        roll = -math.atan2(R[2, 1], R[2, 2])
        pitch = math.asin(max(-1.0, min(1.0, R[2, 0])))
        return (float(d.qpos[0]), float(d.qpos[1]), float(delta), psi, c * vX + s * vY, -s * vX + c * vY,
                omega, roll, pitch)


def _driver(track: Track, ds, wheelbase: float, X: float, Y: float, psi: float, vx: float, omega: float,
            s: float, profile: np.ndarray, ex: tuple, excitation: float, integ: float, dbw: float,
            t_lim: tuple, preview: np.ndarray) -> tuple[float, float, float]:
    """commonroad_st's driver: pure pursuit with yaw-rate feedback plus steering excitation, PI on speed plus
    throttle excitation. Returns (steering wanted, throttle wanted, new integrator)."""
    look = max(ds.lookahead_min, ds.lookahead_time * vx)
    gx, gy = track.position(s + look)
    alpha = math.atan2(float(gy) - Y, float(gx) - X) - psi
    kappa_cmd = 2.0 * math.sin(alpha) / math.hypot(float(gx) - X, float(gy) - Y)
    d_new = math.atan(wheelbase * kappa_cmd)
    v_yaw = max(vx, ds.lookahead_min / ds.lookahead_time)
    d_new += ds.yaw_gain * wheelbase * (kappa_cmd - omega / v_yaw)
    amp = ds.steer_excitation * min(1.0, (ds.excitation_speed / max(vx, 1e-6)) ** 2)
    d_new += excitation * amp * ex[0]
    scale = 1.0 + excitation * ds.speed_excitation * ex[1]
    v_ref = scale * float(np.min(track.interpolate(profile, s + preview * ds.speed_preview * max(vx, 0))))
    err = v_ref - vx
    t_new = (ds.kp * err + ds.ki * integ) / DRIVE_ACCEL + excitation * ds.throttle_excitation * ex[2]
    if t_lim[0] < t_new < t_lim[1]:
        integ += err * dbw
    return d_new, t_new, integ


def check_effects(effects: PlantEffects) -> None:
    for f in fields(PlantEffects):
        v = getattr(effects, f.name)
        if f.name in UNSUPPORTED and v:
            raise DdynError(f"the MuJoCo car plant cannot make the effect {f.name}: {UNSUPPORTED[f.name]}")


def make_log(track: Track | str = "putnam", effects: PlantEffects = PlantEffects(), seed: int = 0,
             settings: LogSettings = LogSettings(), nominal: Vehicle | str | Path = NOMINAL_VEHICLE) -> Dataset:
    """One log of the MuJoCo car driven around `track` (see the module docstring)."""
    require_mujoco()
    check_effects(effects)
    roll_kind = channel_kind(settings.roll_channel, "roll_channel")
    pitch_kind = channel_kind(settings.pitch_channel, "pitch_channel")
    track = load_track(track) if isinstance(track, str) else track
    veh = vehicle_ref.as_vehicle(nominal) if not isinstance(nominal, Vehicle) else nominal
    Ts = veh.sample_time
    rate = float(settings.plant_rate)
    n_sub = int(round(Ts * rate))
    if n_sub < 1 or abs(n_sub / rate - Ts) > 1e-9:
        raise DdynError(f"the log's sample time {Ts} s is not a multiple of the plant's {1 / rate} s")
    dbw = float(settings.dbw_period or Ts)
    n_dbw = int(round(dbw * rate))
    if n_dbw < 1 or abs(n_dbw / rate - dbw) > 1e-9:
        raise DdynError(f"the DBW period {dbw} s is not a multiple of the plant's {1 / rate} s")
    h = 1.0 / rate
    scale = 1.0 + effects.mass_offset
    car = _Car(scale, max(SERVO_TAU, effects.steer_lag), h)
    m, d = car.m, car.d
    m_nom = car_mass()
    m_true = m_nom * scale
    gamma = equivalent_gamma(effects.throttle_map) if effects.throttle_map else 1.0
    p_max = effects.power_limit or P_MAX
    f_drive = m_nom * DRIVE_ACCEL                 # N at full pedal, whatever the mass
    f_brake = m_nom * BRAKE_ACCEL * (1.0 + effects.brake_gain)
    r = CAR["radius"]

    bank = bank_profile(track, effects.bank_angle) if effects.bank_angle else None
    world = getattr(track, "bank", None)
    if world is not None:
        world = np.asarray(world, float)
        bank = world if bank is None else world + bank
    grade = grade_profile(track, effects.grade, effects.grade_phase) if effects.grade else None

    ds_settings = driver_settings(veh, settings.target_speed, settings.driver_grip)
    profile = speed_profile(track, veh, driver_vector(), ds_settings)
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
    psi0 = float(track.heading_at(s0))
    v0 = float(track.interpolate(profile, s0))
    delta0 = math.atan(wheelbase * float(track.curvature_at(s0)))
    road = {"bank": float(track.interpolate(bank, s0)) if bank is not None else 0.0,
            "grade": float(track.interpolate(grade, s0)) if grade is not None else 0.0}

    def set_gravity(psi: float) -> None:
        # the road's bank (+: pulls to the car's left) and grade (+: uphill, pulls backwards) in the heading frame
        sb, sg = math.sin(road["bank"]), math.sin(road["grade"])
        a_lon, a_lat = -G * sg, G * sb
        m.opt.gravity[:] = (a_lon * math.cos(psi) - a_lat * math.sin(psi),
                            a_lon * math.sin(psi) + a_lat * math.cos(psi),
                            -G * math.sqrt(max(0.0, 1.0 - sb * sb - sg * sg)))

    # settle on the springs at standstill (held in place horizontally), then start rolling
    car.place(px, py, psi0, 0.0, delta0)
    set_gravity(psi0)
    mujoco.mj_step(m, d, nstep=int(round(SETTLE_TIME * rate)))
    z, quat = float(d.qpos[2]), d.qpos[3:7].copy()
    susp = d.qpos[7:].copy()
    d.time = 0.0
    car.place(px, py, psi0, v0, delta0)
    d.qpos[2] = z
    d.qpos[7:] = susp
    for a in car.steer_q:
        d.qpos[a] = delta0
    # keep the settled roll/pitch (the yaw is the track's)
    w, qx, qy, qz = quat
    roll0 = math.atan2(2 * (w * qx + qy * qz), 1 - 2 * (qx * qx + qy * qy))
    pitch0 = math.asin(max(-1.0, min(1.0, 2 * (w * qy - qz * qx))))
    cr, sr, cp, sp, cy, sy = (math.cos(roll0 / 2), math.sin(roll0 / 2), math.cos(pitch0 / 2), math.sin(pitch0 / 2),
                              math.cos(psi0 / 2), math.sin(psi0 / 2))
    d.qpos[3:7] = (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                   cr * cp * sy - sr * sp * cy)
    mujoco.mj_forward(m, d)

    n = int(round(settings.duration / Ts)) + 1
    rows = np.empty((n, 6))
    true_delta = np.empty(n)
    body_roll = np.zeros(n)
    body_pitch = np.zeros(n)
    road_bank = np.zeros(n)
    road_grade = np.zeros(n)
    s_rows = np.zeros(n)           # the car's track position at each row (a map channel's lookup)
    T_hist: list[float] = []
    D_hist: list[float] = []
    T_cmd, D_cmd = 0.0, delta0
    integ = 0.0
    s_prev = s0
    window = max(4.0 * ds_settings.lookahead_min, 0.05 * L)
    preview = np.linspace(0.0, 1.0, 6)
    n_steps = (n - 1) * n_sub
    psi_prev, psi_turns = psi0, 0.0
    ex = (0.0, 0.0, 0.0)
    s = lat = 0.0
    i = 0
    while True:
        t = i * h
        X, Y, delta, psi_w, vx, vy, omega, roll, pitch = car.observe()
        # unwrap the heading (continuous like the project's yaw)
        dpsi = psi_w - psi_prev
        psi_turns -= 2 * math.pi * round(dpsi / (2 * math.pi))
        psi_prev = psi_w
        psi = psi_w + psi_turns
        k, log_row = divmod(i, n_sub)
        if log_row == 0 or i % n_dbw == 0:
            if not all(math.isfinite(a) for a in (X, Y, vx, vy, omega)):
                raise CarLostError(f"the MuJoCo plant diverged at t = {t:.2f} s")
            s_arr, lat_arr = track.project(X, Y, s_hint=s_prev, window=window)
            s, lat = float(s_arr), float(lat_arr)
            s_prev = s
        if log_row == 0:
            ex = (ex_steer.next(), ex_speed.next(), ex_throttle.next())
        if i % n_dbw == 0:
            d_new, t_new, integ = _driver(track, ds_settings, wheelbase, X, Y, psi, vx, omega, s, profile, ex,
                                          settings.excitation, integ, dbw, (t_lo, t_hi), preview)
            T_cmd = min(max(T_cmd + min(max(t_new - T_cmd, -dt_max), dt_max), t_lo), t_hi)
            D_cmd = min(max(D_cmd + min(max(d_new - D_cmd, -dd_max), dd_max), d_lo), d_hi)
            T_hist.append(T_cmd)
            D_hist.append(D_cmd)
        if log_row == 0:
            rows[k] = (X, Y, psi, vx, vy, omega)
            true_delta[k] = delta
            body_roll[k] = roll
            body_pitch[k] = pitch
            s_rows[k] = s
            wl, wr = track.half_widths(s)
            if max(lat - float(wl), -lat - float(wr)) > 0.5 * track.width:
                raise CarLostError(f"the driver lost the MuJoCo car at t = {t:.2f} s, s = {s:.0f} m "
                                f"(seed {seed}, effects {effects.active()}); try a lower target speed")
            # held over the sample: the road under the car and the tyres' wear change slowly
            if bank is not None:
                road["bank"] = float(track.interpolate(bank, s))
            if grade is not None:
                road["grade"] = float(track.interpolate(grade, s))
            road_bank[k] = road["bank"]
            road_grade[k] = road["grade"]
            if effects.tire_wear:
                car.wear(math.exp(-effects.tire_wear * t))
        if i >= n_steps:
            break
        # ---- the next instant anything held changes: a log sample, a DBW tick, a delayed command reaching the
        # actuator
        nxt = min((k + 1) * n_sub, (i // n_dbw + 1) * n_dbw, n_steps)
        for delay in (effects.steer_delay, effects.throttle_delay):
            if delay:
                j = math.floor((t - delay) / dbw + 1e-9)
                nxt = min(nxt, max(i + 1, math.ceil(((j + 1) * dbw + delay) * rate - 1e-6)))
        steer_in = _command_at(D_hist, t, effects.steer_delay, dbw)
        pedal = _command_at(T_hist, t, effects.throttle_delay, dbw)
        # ---- the actuators and applied forces, held over the chunk
        d.ctrl[0] = d.ctrl[1] = steer_in
        v = math.hypot(vx, vy)
        torque = [0.0, 0.0, 0.0, 0.0]
        if pedal > 0:
            f = min(f_drive * pedal ** gamma, p_max / max(v, 1.0))
            torque[2] = torque[3] = 0.5 * f * r
        elif pedal < 0:
            fb = f_brake * -pedal
            for w_i, share in enumerate((BRAKE_FRONT / 2, BRAKE_FRONT / 2, (1 - BRAKE_FRONT) / 2,
                                         (1 - BRAKE_FRONT) / 2)):
                spin = d.qvel[car.spin_v[w_i]]
                torque[w_i] = -share * fb * r * max(-1.0, min(1.0, spin * r / 0.5))
        d.ctrl[2:6] = torque
        # drag and rolling resistance along the velocity, downforce straight down, at the CoG (frame origin)
        f_res = DRAG * v * v + (ROLLING * m_true * G if v > 0.5 else 0.0)
        fx, fy = (-f_res * d.qvel[0] / v, -f_res * d.qvel[1] / v) if v > 0.1 else (0.0, 0.0)
        d.xfrc_applied[car.chassis, 0:3] = fx, fy, -effects.downforce * m_true * G * vx * vx
        set_gravity(psi_w)
        mujoco.mj_step(m, d, nstep=nxt - i)
        i = nxt

    ticks = np.minimum((np.arange(n) * n_sub) // n_dbw, len(T_hist) - 1)
    T = np.array([T_hist[j] for j in ticks])
    D = np.array([D_hist[j] for j in ticks])
    states = np.column_stack([rows[:, :3], rows[:, 3:6], T, D])
    inputs = np.zeros((n, 2))
    inputs[:-1, 0] = np.diff(T) / Ts
    inputs[:-1, 1] = np.diff(D) / Ts
    extras = {f"true_{c}": rows[:, j].copy() for j, c in enumerate(NOISY)}
    extras["true_steering"] = true_delta
    extras["true_bank"] = road_bank
    extras["true_body_roll"] = body_roll
    # each channel its own random stream (those of commonroad_st), so the other channels are a log's without it
    if roll_kind == "imu":
        roll_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(5)[4])
        extras["roll"] = road_bank + body_roll + ROLL_NOISE * roll_rng.standard_normal(n)
    elif roll_kind == "map":
        extras["roll"] = map_channel(track, bank, s_rows)
    elif roll_kind == "broken":
        extras["roll"] = broken_channel(road_bank + body_roll, Ts,
                                        np.random.default_rng(np.random.SeedSequence(seed).spawn(7)[6]))
    if pitch_kind == "imu":
        pitch_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(6)[5])
        extras["pitch"] = road_grade + body_pitch + PITCH_NOISE * pitch_rng.standard_normal(n)
    elif pitch_kind == "map":
        extras["pitch"] = map_channel(track, grade, s_rows)
    elif pitch_kind == "broken":
        extras["pitch"] = broken_channel(road_grade + body_pitch, Ts,
                                         np.random.default_rng(np.random.SeedSequence(seed).spawn(8)[7]))
    noisy = states.copy()
    if settings.noise_scale > 0:
        std = np.array([settings.noise_scale * veh.sensor_noise_std[c] for c in NOISY])
        wn = noise_rng.standard_normal((n, 6))
        rho = float(settings.noise_color)
        if rho:
            for k in range(1, n):
                wn[k] = rho * wn[k - 1] + math.sqrt(1 - rho * rho) * wn[k]
        noisy[:, :6] += wn * std
    noisy[:, 5] += effects.yaw_rate_bias
    active = effects.active()
    metadata = {
        "plant": f"mujoco {mujoco.__version__} rigid-body car (contact tyres, suspension), "
                 f"{rate:g} Hz, DBW hold",
        "dbw_period": repr(dbw),
        "track": track.name, "seed": str(seed), "noise_scale": repr(float(settings.noise_scale)),
        "noise_color": repr(float(settings.noise_color)), "target_speed": repr(float(settings.target_speed)),
        "driver_grip": repr(float(ds_settings.grip)),
        "method": "rk4", "substeps": str(veh.rk4_substeps),
        "plant_effects": json.dumps(active),
        **vehicle_ref.metadata_for(veh),
    }
    src = f"mujoco car plant (1500 kg saloon) on {track.name}, seed {seed}, effects {active or 'none'}"
    return Dataset(time=np.arange(n) * Ts, segment=np.zeros(n, dtype=np.int64), states=noisy, inputs=inputs,
                   sample_time=Ts, vehicle=veh.name, source=src, extras=extras, metadata=metadata)


def start_vehicle() -> dict:
    """The vehicle file a user starts from: the car's known mass, lf, lr and Iz, rough coefficients."""
    m = car_mass()
    return {
        "name": "mujoco_car",
        "description": "the MuJoCo rigid-body car (ddyn.plants.mujoco_car): known mass, lf, lr, Iz and rough "
                       "coefficients, before identification",
        "sample_time": 0.04, "max_speed": 40.0, "evaluation_horizon": 0.6, "rk4_substeps": 2,
        "known": {"mass": m, "lf": CAR["lf"], "lr": CAR["lr"], "v_min": 0.5},
        "true_coefficients": dict(START_VEHICLE),
        "ranges": {
            "Bf": [3, 40], "Cf": [0.5, 2.5], "Df": [2000, 16000], "Ef": [-3, 0.9], "Gf": [-0.02, 0.02],
            "Kf": [-100, 100],
            "Br": [3, 40], "Cr": [0.5, 3.5], "Dr": [2000, 16000], "Er": [-3, 0.9], "Gr": [-0.02, 0.02],
            "Kr": [-100, 100],
            "Cm1": [3000, 15000], "Cm2": [0, 100], "Cr0": [0, 800], "Cd": [0.05, 1.5], "Iz": [1200, 4000]},
        "input_limits": {"throttle": [-1.0, 1.0], "steering": [-0.35, 0.35], "dthrottle": [-5.0, 5.0],
                         "dsteering": [-0.5, 0.5]},
        "sensor_noise_std": {"x": 0.02, "y": 0.02, "yaw": 0.002, "vx": 0.05, "vy": 0.02, "omega": 0.005},
        "sources": {
            "known": "ddyn.plants.mujoco_car.CAR: total mass 1500 kg, lf 1.25, lr 1.55 m from the whole car's CoG",
            "Iz (start)": "the whole car's yaw inertia, 2400 kg m^2 (sprung 1985 plus the wheels and knuckles)",
            "Df, Dr (start)": "contact friction 0.95 front, 1.10 rear times the static axle loads m g lr / L, m g lf / L",
            "Bf, Cf, Br, Cr, Ef, Er (start)": "rough: the plant has no tyre curve (rigid contacts)",
            "Cm1 (start)": "DRIVE_ACCEL 6 m/s^2 times the mass; the power limit 250 kW is not modelled",
            "Cr0, Cd (start)": "rolling resistance 0.012 m g, drag 0.4 kg/m",
            "input_limits": "steering +-0.35 rad at 0.5 rad/s (a saloon's rack); throttle rate as the AV-21",
            "sensor_noise_std": "as the AV-21 file: RTK GNSS + IMU fused at 100 Hz",
            "evaluation_horizon, max_speed, sample_time": "as the AV-21 (25 Hz log, 0.6 s horizon)"},
    }


def identification_log(seed: int, duration: float, vehicle_file=NOMINAL_VEHICLE) -> Dataset:
    """An effect-free log for the identification (default LogSettings but the duration)."""
    return make_log("putnam", PlantEffects(), seed, LogSettings(duration=duration), vehicle_file)


def one_step_fit(vehicle_file=NOMINAL_VEHICLE, seed: int = IDENT_SEEDS[1], duration: float = 60.0,
                 log: Dataset | None = None) -> dict:
    """The nominal's one-step prediction error on an effect-free log: per channel (vx, vy, omega) the rms
    residual, the channel's standard deviation and the rms of its one-sample change (what predicting "no
    change" would miss)."""
    from ddyn.gap.problem import Problem, nominal_from_vehicle
    from ddyn.model.vehicle import load as load_vehicle

    veh = load_vehicle(vehicle_file)
    log = log if log is not None else identification_log(seed, duration, vehicle_file)
    prob = Problem(log, nominal_from_vehicle(veh, log), 0.95)
    k = prob.rows_all
    res = prob.target[k + 1] - prob.predict({}, np.zeros(0), k)
    out = {}
    for j, c in enumerate(("vx", "vy", "omega")):
        out[c] = {"rms_residual": float(np.sqrt(np.mean(res[:, j] ** 2))),
                  "std": float(np.std(prob.target[k, j])),
                  "rms_change": float(np.sqrt(np.mean((prob.target[k + 1, j] - prob.target[k, j]) ** 2))),
                  "noise_std": float(veh.sensor_noise_std[c])}
    return out


def baseline_logs(vehicle_file) -> list:
    """Effect-free logs across the speeds a campaign drives (BASELINE_SEEDS, BASELINE_SPEEDS)."""
    return [make_log("putnam", PlantEffects(), seed, LogSettings(duration=IDENT_DURATION, target_speed=v),
                     vehicle_file) for seed, v in zip(BASELINE_SEEDS, BASELINE_SPEEDS)]


def _fit(start: dict, seed: int, hold: bool, tmp: Path) -> tuple:
    from ddyn.gap.benchmark.commonroad import identified_coefficients

    start_file = tmp / "mujoco_car.json"
    start_file.write_text(json.dumps(start, indent=2))
    return identified_coefficients(hold=hold, vehicle_file=start_file, seed=seed,
                                   make_ident_log=lambda s, d: identification_log(s, d, start_file))


def identify(out: Path = NOMINAL_VEHICLE, seed: int = IDENT_SEEDS[0], check_seed: int = IDENT_SEEDS[1],
             hold: bool = False) -> dict:
    """Write the nominal vehicle file: the project's 17 coefficients fitted (ddyn.gap.benchmark.commonroad.
    identified_coefficients) on an effect-free log (seed), starting from start_vehicle(); then the car's own
    effects (ddyn.gap.baseline: an effect the diagnosis claims first on most effect-free logs of baseline_logs) put
    in the file's "effects", the tyre peaks scaled by the refit it was found with; then the one-step fit on a fresh
    effect-free log (check_seed)."""
    import tempfile

    from ddyn.gap import baseline
    from ddyn.gap.benchmark.commonroad import IDENT_DURATION as BENCH_IDENT_DURATION
    from ddyn.model.single_track import COEFF_NAMES
    from ddyn.model.vehicle import load as load_vehicle

    start = start_vehicle()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        c, info = _fit(start, seed, hold, tmp)
        veh = dict(start, true_coefficients={n: float(round(v, 6)) for n, v in zip(COEFF_NAMES, c)})
        (tmp / "fitted.json").write_text(json.dumps(veh, indent=2))
        logs = baseline_logs(tmp / "fitted.json")
        claims = baseline.first_claims(logs, load_vehicle(tmp / "fitted.json"))
        own, named = baseline.consistent_effect(claims)
        after, factors = [], {}
        if own:
            # the effect with the tyre peaks' refit factors it was found with (ddyn.gap.baseline.refit_factors);
            # a refit of all 17 with it on the one identification log trades it against the tyre curve instead
            # (C at its range edge)
            own = {k: float(f"{v:.4g}") for k, v in own.items()}
            factors = baseline.refit_factors(named)
            coeffs = {n: float(round(v * factors.get(n, 1.0), 6)) for n, v in veh["true_coefficients"].items()}
            veh = dict(veh, effects=own, true_coefficients=coeffs)
            (tmp / "fitted.json").write_text(json.dumps(veh, indent=2))
            after = baseline.first_claims(logs, load_vehicle(tmp / "fitted.json"))
    seconds = time.perf_counter() - t0
    veh["description"] = (
        "the MuJoCo rigid-body car (ddyn.plants.mujoco_car: 1500 kg RWD saloon, contact tyres, suspension) as the "
        "project's single-track model: its 17 coefficients identified on an effect-free log of the plant "
        f"(seed {seed}, {BENCH_IDENT_DURATION:g} s on putnam, hold {hold}) and its own effects on effect-free logs "
        f"at {', '.join(f'{v:g}' for v in BASELINE_SPEEDS)} m/s (seeds {', '.join(map(str, BASELINE_SEEDS))}) by "
        "`python -m ddyn.plants.mujoco_car --identify` (ddyn.gap.benchmark.commonroad.identified_coefficients, "
        "ddyn.gap.baseline, starting from mujoco_car.start_vehicle())")
    out.write_text(json.dumps(veh, indent=2) + "\n")
    fit = one_step_fit(out, check_seed)

    def said(cl):
        return "; ".join("none" if x["effect"] is None else f"{x['effect']} {x['value']:.4g}" for x in cl)

    veh["sources"] = dict(veh["sources"])
    veh["sources"]["true_coefficients"] = (
        f"identified: seed {seed} ({BENCH_IDENT_DURATION:g} s, effect-free), at the range edge: "
        f"{', '.join(info['at_range_edge']) or 'none'}; one-step rms residual on a fresh 60 s log (seed "
        f"{check_seed}): " + ", ".join(f"{k} {v['rms_residual']:.4f} (channel std {v['std']:.3f}, one-sample "
                                       f"change {v['rms_change']:.4f})" for k, v in fit.items()))
    veh["sources"]["effects"] = (
        f"the first claims of the diagnosis on the effect-free logs (ddyn.gap.baseline): {said(claims)}"
        + (f"; the same one first at a consistent size on most logs, so the car's own: {own}; with it in the nominal "
           f"(Df, Dr times {', '.join(f'{n} {x:.3f}' for n, x in factors.items())}), the first claims are: {said(after)}" if own else
           "; no effect is first on most logs at one size: none is the car's own"))
    out.write_text(json.dumps(veh, indent=2) + "\n")
    return {"coefficients": veh["true_coefficients"], "effects": own, "claims": claims, "claims_after": after,
            "info": info, "seconds": seconds, "one_step": fit}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m ddyn.plants.mujoco_car", description=__doc__.split("\n")[0])
    ap.add_argument("--identify", action="store_true", help="remake the nominal vehicle file (NOMINAL_VEHICLE)")
    ap.add_argument("--seed", type=int, default=IDENT_SEEDS[0], help="the identification log's seed")
    ap.add_argument("--check-seed", type=int, default=IDENT_SEEDS[1], help="the one-step check's fresh log's seed")
    ap.add_argument("--time", action="store_true", help="seconds of CPU per 60 s effect-free log")
    a = ap.parse_args(argv)
    if a.identify:
        print(json.dumps(identify(NOMINAL_VEHICLE, a.seed, a.check_seed), indent=2))
    if a.time:
        t0 = time.process_time()
        make_log("putnam", PlantEffects(), 1, LogSettings(duration=60.0))
        print(f"{time.process_time() - t0:.2f} s of CPU per 60 s log")
    if not (a.identify or a.time):
        ap.print_help()


if __name__ == "__main__":
    main()
