"""`ddyn sil run`: software-in-the-loop laps, the plant and the controller as two processes over vcan.

The plant (firmware_sim/, `ddyn_sil_plant`) plays the car: the generated vehicle model under RK4
sub-steps, actuators with their limits, sensors at the DBC's rates with the vehicle file's noise,
the drive-by-wire unit with its watchdog, and the track (progress, lap times, footprint
violations). The controller (`ddyn_controller`, the car's own executable, with the JSON
configuration of docs/deploy.md written here as controller.json) is the c_src runtime built as its own
executable: EKF -> history -> guard network -> MPC -> DBW command. The two talk ONLY through CAN
frames (can/ddyn_dbw.dbc) on vcan0: directly on a host that has vcan, otherwise inside a small qemu
guest (the kernel, modules and busybox of scripts/vcan_guest; the plant is static, the controller
and lcm-logger come with their shared libraries).

The plant runs in lock-step with the controller by default (it waits, in wall time, for the
command that answers each position frame, so laps run as fast as the controller allows and the
result does not depend on the machine's load); `--realtime F` paces it at F times real time instead.

Outputs (in --out): sil_metrics.json (lap times, average speed, violations, tracking error,
controller loop time median/p99/max, deadline misses, DBW and bus counts, fault timings),
trajectory.csv, controller_log.csv, controller.lcm (the controller's telemetry as it published it
live over LCM during the run, recorded by lcm-logger; converted from its CSV log only as a
labelled fallback: --where inprocess, or a build without LCM), lap.png, and the exact configs both
processes ran with.
"""
from __future__ import annotations

import argparse
import base64
import fcntl
import hashlib
import importlib.util
import json
import math
import os
import re
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ddyn.control.raceline import line_for
from ddyn.errors import DdynError
from ddyn.model.single_track import COEFF_NAMES
from ddyn.model.track_files import is_named, open_track, write_track
from ddyn.model.tracks import Track
from ddyn.model.vehicle import Vehicle
from ddyn.model.vehicle import load as load_vehicle
from ddyn.paths import REPO, shared_data_dir

# Plant-side effects (firmware_sim/include/fsim/plant.hpp); the other effects of train/model/effects.py
# change the tyre or gravity terms inside the model and are not offered by the plant.
PLANT_EFFECTS = ("steer_delay", "throttle_delay", "steer_lag", "mass_offset", "downforce", "yaw_rate_bias")
# The car's footprint (length, width), m: the MPC's (train/control/mpc_setup.py).
from ddyn.model.vehicle import FOOTPRINT  # noqa: E402

# Sensor rates: the DBC's cycle times (GNSS 20 ms, IMU/wheel speeds/steering 10 ms).
SENSOR_RATES = {"gnss_position": 50.0, "heading": 50.0, "yaw_rate": 100.0, "acceleration": 100.0,
                "wheel_speed": 100.0, "steering": 100.0}
SENSOR_ORDER = ("gnss_position", "heading", "yaw_rate", "acceleration", "wheel_speed", "steering")
# DBW frames in ddyn_dbw_frame order and how many control periods (50 Hz) each may be missing
# before the controller commands the safe stop: more than one period for the 100 Hz frames (two
# frames in a row lost), more than two for the 50 Hz GNSS frames. Without frames the controller
# runs a period on its own timer 1.5 periods after the last one, then every period, so a silent
# bus gives the safe command about 50 ms after the last position frame (the target is 100 ms); a bus losing 5 % of its frames
# rarely trips it (three GNSS frames in a row: about 1e-4 per period).
FRAME_STALE_PERIODS = {"command": 0, "steering": 1, "status": 1, "wheel_speeds": 1, "imu": 1,
                       "gnss_position": 2, "gnss_heading": 2}
FILTER_ACCEL_STD = 1.0
# the filter's process noise per period (x, y, yaw, vx, vy, omega, throttle, steering), as
# train/bench/controller.py (the velocities' stands for the error of a step with estimated
# coefficients), except throttle and steering: 1e-5 (std 3 mrad per period) instead of 1e-10, so
# that the filter follows the steering sensor when a command frame is lost on the bus and the
# actuator lags its commanded rate by a period (with 1e-10 it refuses the sensor instead)
FILTER_PROCESS_NOISE = (1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-2, 1e-5, 1e-5)
# the controller's known actuation delays (controller.json control.delay, s; ddyn/controller.h)
CONTROLLER_DELAY_KEYS = ("steer", "throttle")
# the controller's known steering lag (controller.json control.lag, s: the time constant; ddyn/controller.h)
CONTROLLER_LAG_KEYS = ("steer",)
FAULT_KEYS = ("drop", "delay", "corrupt", "silent", "silent_at", "kill_controller", "restart_plant")
SENSOR_OF_FRAME = {"imu": ("yaw_rate", "acceleration"), "gnss": ("gnss_position", "heading"),
                   "gnss_position": ("gnss_position",), "gnss_heading": ("heading",),
                   "wheel_speeds": ("wheel_speed",), "steering": ("steering",)}


# ---------------------------------------------------------------------------------------------- specs

def parse_kv(text: str | None, allowed: tuple[str, ...], what: str) -> dict:
    """`a=1,b=x` or `a=1 b=x` into a dict (numbers as float)."""
    out: dict = {}
    if not text:
        return out
    for item in re.split(r"[,\s]+", text.strip()):
        if not item:
            continue
        if "=" not in item:
            raise DdynError(f"{what}: expected key=value, got {item!r}")
        k, v = item.split("=", 1)
        if k not in allowed:
            raise DdynError(f"{what}: unknown key {k!r}; expected one of {', '.join(allowed)}")
        try:
            out[k] = float(v)
        except ValueError:
            out[k] = v
    return out


def parse_effects(text: str | None) -> dict[str, float]:
    fx = parse_kv(text, PLANT_EFFECTS, "--effects")
    for k, v in fx.items():
        if not isinstance(v, float):
            raise DdynError(f"--effects: {k} needs a number, got {v!r}")
    return fx


def _parse_seconds(text: str | None, keys, flag: str) -> dict[str, float]:
    d = parse_kv(text, keys, flag)
    for k, v in d.items():
        if not isinstance(v, float) or not math.isfinite(v) or v < 0.0:
            raise DdynError(f"{flag}: {k} needs a number of seconds >= 0, got {v!r}")
    return d


def parse_controller_delays(text: str | None) -> dict[str, float]:
    """`steer=0.04,throttle=0.1` (seconds >= 0) for --controller-delays."""
    return _parse_seconds(text, CONTROLLER_DELAY_KEYS, "--controller-delays")


def parse_controller_lag(text: str | None) -> dict[str, float]:
    """`steer=0.05` (seconds >= 0, the time constant) for --controller-lag."""
    return _parse_seconds(text, CONTROLLER_LAG_KEYS, "--controller-lag")


def parse_faults(text: str | None) -> dict:
    f = parse_kv(text, FAULT_KEYS, "--faults")
    if "silent" in f and f["silent"] not in SENSOR_OF_FRAME:
        raise DdynError(f"--faults: silent={f['silent']!r}; expected one of {', '.join(SENSOR_OF_FRAME)}")
    if "silent" in f and "silent_at" not in f:
        raise DdynError("--faults: silent=... needs silent_at=SECONDS")
    if "drop" in f and not 0.0 <= f["drop"] < 1.0:
        raise DdynError("--faults: drop is a fraction in [0, 1)")
    return f


# ---------------------------------------------------------------------------------------------- track

def raceline_table(track: Track, vehicle: Vehicle, speed_scale: float | None = None,
                   margin: float | None = None, line: str | None = None) -> np.ndarray:
    """Rows x, y, speed, room_left, room_right of the raceline the MPC tracks.

    The MPC's own table (train/control/mpc_setup.py, what ddyn mpc lap tunes with): the raceline's first lap,
    closed, resampled every 2.5 cm, its speed profile times speed_scale floored at 0.5 m/s, the room
    to the bounds less half the car's width and `margin`.
    """
    from ddyn.control.mpc_setup import raceline_table as mpc_table
    from ddyn.control.mpc_setup import settings_for
    # the vehicle's own table settings (spacing, margin, speed floor and scale: train/vehicles/mpc/), then the options
    t = mpc_table(track, vehicle.name, settings_for(vehicle.name, speed_scale=speed_scale, margin=margin,
                                                                 line=line))
    return np.column_stack([t["x"], t["y"], t["speed"], t["room_left"], t["room_right"]])


def start_state(track: Track, vx0: float | None, vehicle_name: str, table: np.ndarray | None = None,
                line: str | None = None) -> list[float]:
    """The car at the raceline's first point, heading along it, at vx0 (None: a flying line's rolling
    start at the reference speed of the table's first row, else 0.1 m/s)."""
    if vx0 is None:
        from ddyn.control.raceline import is_flying
        vx0 = float(table[0, 2]) if table is not None and is_flying(track, vehicle_name) else 0.1
    from ddyn.control.raceline import LINES
    rl = line_for(track, vehicle_name, LINES[line or "default"])
    x0, y0 = float(rl.x[0]), float(rl.y[0])
    k = 1
    while np.hypot(rl.x[k] - x0, rl.y[k] - y0) < 1e-6:
        k += 1
    yaw = math.atan2(float(rl.y[k]) - y0, float(rl.x[k]) - x0)
    return [x0, y0, yaw, vx0, 0.0, 0.0, 0.0, 0.0]


# ---------------------------------------------------------------------------------------------- configs

def sensor_noise(vehicle: Vehicle, scale: float) -> dict[str, list[float]]:
    """Per sensor kind, the noise std of each component: the vehicle file's where it has one."""
    n = vehicle.sensor_noise_std
    pos = [n.get("x", 0.0), n.get("y", 0.0)]
    vx = n.get("vx", 0.0)
    # the accelerometer and the steering sensor are not in the vehicle files: chosen here as a
    # typical MEMS accelerometer's 0.05 m/s^2 (scaled with the car: 1 % of the tyre limit of the
    # 1:43 car) and a 0.1 % of full-range steering encoder
    acc = 0.05 if vehicle.name == "orca_1_43" else 0.1
    steer = 0.001 * (vehicle.input_limits["steering"][1] - vehicle.input_limits["steering"][0])
    table = {"gnss_position": pos, "heading": [n.get("yaw", 0.0), 0.0], "yaw_rate": [n.get("omega", 0.0), 0.0],
             "acceleration": [acc, acc], "wheel_speed": [vx, vx], "steering": [steer, 0.0]}
    return {k: [scale * v for v in vals] for k, vals in table.items()}


@dataclass
class SilSpec:
    vehicle: Vehicle
    track: Track
    coeffs_plant: np.ndarray
    coeffs_controller: np.ndarray | None       # fixed coefficients (None: the network's)
    nominal: np.ndarray
    laps: int = 1
    vx0: float | None = None                   # None: 0.1 m/s, or a flying line's rolling start
    effects: dict = field(default_factory=dict)
    faults: dict = field(default_factory=dict)
    noise_scale: float = 1.0
    speed_scale: float | None = None           # None: the vehicle's (train/vehicles/mpc/), else 1.0
    margin: float | None = None                # None: the vehicle's, else 0.03 m
    line: str | None = None                    # the racing line: None the vehicle's own, "flying", "standing"
    realtime: float = 0.0
    max_time: float | None = None
    seed: int = 1
    deadline: float | None = None              # DBW watchdog, s; None: the vehicle's periods (4: 80 ms at 50 Hz)
    throttle: str = "mpc"                      # "mpc" (the MPC plans it) or "pid" (PID on the speed error)
    pid_gains: tuple | None = None             # (kp, ki, kd, preview s); None: the controller's defaults
    checkpoint_hash: str | None = None         # sha256 of the network's checkpoint: a controller built for
                                               # another is refused (coefficients.checkpoint_hash)
    prepare: bool = True                       # the MPC's preparation after each command (RTI split)
    pacing: str = "frame"                      # the controller's realtime.pacing: frame, or timer (needs realtime > 0)
    rt_priority: int = 0                       # realtime.priority: SCHED_FIFO priority, 0 = none
    rt_cpu: int = -1                           # realtime.cpu: the CPU to pin the controller to, -1 = none
    auth: bool = False                         # frame authentication (docs/can.md) on both sides with the
                                               # build's fixed TEST key (plant.json auth.key_file, can.key_file)
    forged_steering: tuple | None = None       # (t0, t1) s: an attacker's forged steering commands in that
                                               # window of simulated time (ddyn_sil_inprocess only)
    controller_delays: dict = field(default_factory=dict)  # the actuation delays the controller compensates,
                                               # s: {"steer": .., "throttle": ..} (control.delay; none: {})
    controller_lag: dict = field(default_factory=dict)  # the steering lag the controller compensates, s (the
                                               # time constant): {"steer": ..} (control.lag; none: {})
    controller_mass_offset: float = 0.0        # the mass offset the controller knows (control.mass_offset: the
                                               # car's mass is (1 + it) times the model's; 0: none)
    controller_downforce: float = 0.0          # the downforce k the controller knows (control.downforce, s^2/m^2:
                                               # the tyre peaks 1 + k vx^2 times the model's; 0: none)
    effects_from: dict | None = None           # the diagnosis the delays came from (ddyn.sil.effects
                                               # ControllerEffects.summary()): controller.json `effects`
    road_bank: bool = True                     # a track with its own banking (Track.bank: the oval) banks the
                                               # plant's road (plant.json road_bank); False: driven flat
    controller_bank: bool = False              # the controller knows the road's bank (control.bank: the track's
                                               # own profile along the raceline, raceline.csv's 6th column)
    road_grade: bool = True                    # a track with its own grade (Track.grade: ddyn.model.road_grade)
                                               # grades the plant's road (plant.json road_grade); False: level
    controller_grade: bool = False             # the controller knows the road's grade (control.grade: the track's
                                               # own profile along the raceline, raceline.csv's grade column)

    @classmethod
    def true_car(cls, vehicle: Vehicle, track: Track, **settings) -> "SilSpec":
        """The car driven with its own true coefficients in the plant, the controller and the nominal (what
        `--coeffs true` gives); settings: any other field."""
        c = vehicle.true_vector()
        return cls(vehicle=vehicle, track=track, coeffs_plant=c, coeffs_controller=c, nominal=c, **settings)


def dbw_deadline(spec: SilSpec) -> float:
    from ddyn.control.vehicle_settings import overrides
    if spec.deadline is not None:
        return spec.deadline
    return overrides(spec.vehicle.name, "sil").get("dbw_deadline_periods", 4) * spec.vehicle.sample_time


# the plant's DBW_Status rate (Hz): the DBC's 10 ms
STATUS_RATE = 100.0


def sensor_rates(v) -> dict:
    """The plant's rate (Hz) per sensor. A position frame starts a control period (firmware_sim/controller):
    GNSS comes once a period, 50 Hz for the 1:43 car as the DBC's cycle time, 25 Hz for the AV-21 (at 50 Hz
    its controller ran two 40 ms periods per 40 ms and its filter, ahead of the car, rejected every position)."""
    return dict(SENSOR_RATES, gnss_position=1.0 / v.sample_time, heading=1.0 / v.sample_time)


def frame_cycles_ms(v) -> dict:
    """The controller's can.cycle_ms: the cycle each frame comes at from this plant, which dates its frames
    (the DBC's cycle times are the 1:43 car's; dated at 20 ms, the AV-21's 40 ms GNSS frames made every
    clean period look late: issue 34)."""
    r = sensor_rates(v)
    hz = {"steering": r["steering"], "status": STATUS_RATE, "wheel_speeds": r["wheel_speed"], "imu": r["yaw_rate"],
          "gnss_position": r["gnss_position"], "gnss_heading": r["heading"]}
    return {"command": 0, **{k: int(round(1000.0 / f)) for k, f in hz.items()}}


def plant_config(spec: SilSpec, track_dir: str, out_dir: str, table: np.ndarray | None = None,
                 key_file: str | None = None) -> dict:
    v = spec.vehicle
    lim = v.input_limits
    noise = sensor_noise(v, spec.noise_scale)
    rates = sensor_rates(v)
    sensors = {k: {"rate": rates[k], "noise": noise[k]} for k in SENSOR_ORDER}
    f = spec.faults
    if "silent" in f:
        for k in SENSOR_OF_FRAME[f["silent"]]:
            sensors[k]["silent_from"] = float(f["silent_at"])
    length, width = FOOTPRINT.get(v.name, (0.0, 0.0))
    max_time = spec.max_time or max(20.0, 6.0 * spec.laps * spec.track.length / max(0.5, spec.speed_scale or 1.0))
    cfg = {
        "vehicle": v.name, "coefficients": [float(c) for c in spec.coeffs_plant],
        "limits": {"throttle_min": lim["throttle"][0], "throttle_max": lim["throttle"][1],
                   "steer_min": lim["steering"][0], "steer_max": lim["steering"][1],
                   "dthrottle_max": lim["dthrottle"][1], "dsteer_max": lim["dsteering"][1]},
        "effects": {k: float(val) for k, val in spec.effects.items()},
        "substep": min(1e-3, v.sample_time / 20.0),
        "track_dir": track_dir, "track": spec.track.name,
        "footprint": {"length": length, "width": width},
        "start": start_state(spec.track, spec.vx0, spec.vehicle.name, table, spec.line),
        "laps": spec.laps, "max_time": float(max_time),
        "realtime_factor": spec.realtime, "lockstep_timeout": 3.0,
        # the first command may take this long (wall s): an emulated guest starts the controller slowly, and
        # the AV-21's rolling start coasted off Putnam in 1.7 s before it came
        "start_timeout": 60.0,
        "sensors": sensors, "status_rate": STATUS_RATE, "seed": spec.seed,
        "dbw": {"deadline": dbw_deadline(spec), "rearm_count": 0},
        "faults": {"drop": f.get("drop", 0.0), "delay_max": f.get("delay", 0.0), "corrupt": f.get("corrupt", 0.0)},
        "out_dir": out_dir, "log_period": 0.01, "snapshot_period": 0.05,
    }
    bank = getattr(spec.track, "bank", None)
    if spec.road_bank and bank is not None:  # the world's banking, per centre-line point (the plant's track files)
        cfg["road_bank"] = [float(b) for b in bank]
    grade = getattr(spec.track, "grade", None)
    if spec.road_grade and grade is not None:  # the world's grade, per centre-line point
        cfg["road_grade"] = [float(g) for g in grade]
    if "restart_plant" in f:
        cfg["crash_at"] = float(f["restart_plant"])
    if key_file:  # frame authentication: the plant signs its frames and applies only verified commands
        cfg["auth"] = {"key_file": key_file}
    return cfg


def controller_start(spec: SilSpec, table: np.ndarray) -> list[float]:
    """The filter's initial state: the plant's start moved one period along its heading. The
    controller's first period comes with the first position frame, one period after the start (the
    plant samples when the time crosses a multiple of the period), and the filter does not predict
    in its first period. From 0.1 m/s that is 2 mm (1:43 car, 20 ms); on the AV-21's rolling start
    at 30 m/s it was 1.2 m, 30 standard deviations of the position reading: every reading was gated
    and the car braked in its safe state."""
    x = start_state(spec.track, spec.vx0, spec.vehicle.name, table, spec.line)
    dt = spec.vehicle.sample_time
    x[0] += x[3] * math.cos(x[2]) * dt
    x[1] += x[3] * math.sin(x[2]) * dt
    return x


# MpcSettings fields the controller's configuration takes (docs/deploy.md: mpc.*)
MPC_CONFIG_FIELDS = ("horizon", "q_x", "q_y", "q_terminal", "r_dthrottle", "r_dsteering", "slack_l1", "slack_l2")


def mpc_section(vehicle_name: str) -> dict:
    """The controller's `mpc` section: the vehicle's own weights and horizon (train/vehicles/mpc/, the same
    MpcSettings `ddyn mpc lap` drives with), all of them when its settings file sets any; empty when it sets
    none (the 1:43 car: the C defaults, its configuration as before)."""
    from ddyn.control.mpc_setup import settings_for
    from ddyn.control.vehicle_settings import overrides
    if not set(overrides(vehicle_name, "mpc")) & set(MPC_CONFIG_FIELDS):
        return {}
    s = settings_for(vehicle_name)
    return {"horizon": int(s.horizon), "q_pos": [float(s.q_x), float(s.q_y)], "q_terminal_scale": float(s.q_terminal),
            "r_rate": [float(s.r_dthrottle), float(s.r_dsteering)], "slack_l1": float(s.slack_l1),
            "slack_l2": float(s.slack_l2)}


CONTROLLER_CONFIG = "controller.json"
RACELINE_CSV = "raceline.csv"


def raceline_csv(table: np.ndarray, bank: np.ndarray | None = None, grade: np.ndarray | None = None) -> str:
    """The raceline file ddyn_controller reads (`raceline` key): x, y, speed, width_left, width_right, with a bank
    (control.bank) the road's bank (rad) at each row as a 6th column, then with a grade (control.grade) the road's
    grade (rad) as the next."""
    extra = [(name, col) for name, col in (("bank", bank), ("grade", grade)) if col is not None]
    head = ",".join(["x,y,speed,width_left,width_right"] + [name for name, _ in extra])
    rows = [head] + [",".join(repr(float(c)) for c in (*row, *(col[i] for _, col in extra)))
                     for i, row in enumerate(table)]
    return "\n".join(rows) + "\n"


def _road_column(track: Track, table: np.ndarray, name: str, how: str) -> np.ndarray:
    """The track's own road profile `name` (Track.bank or Track.grade, rad per centre-line point) at each raceline
    row: at the row's projection on the centre line. A track without it is refused (the column would be flat)."""
    values = getattr(track, name, None)
    if values is None:
        raise DdynError(f"the controller's {name} (control.{name}): track {track.name!r} has no {name} profile "
                        f"({how})")
    s, _ = track.project(table[:, 0], table[:, 1])
    return np.asarray(track.interpolate(np.asarray(values, float), s), float)


def raceline_bank(track: Track, table: np.ndarray) -> np.ndarray:
    """The track's own bank at each raceline row (ddyn.model.track_oval.bank_at's values)."""
    return _road_column(track, table, "bank", "Track.bank; the banked oval: --track oval")


def raceline_grade(track: Track, table: np.ndarray) -> np.ndarray:
    """The track's own grade at each raceline row (ddyn.model.road_grade.grade_at's values)."""
    return _road_column(track, table, "grade", "Track.grade: --road-grade A")


def controller_grade_column(spec: SilSpec, table: np.ndarray) -> np.ndarray | None:
    """raceline.csv's grade column (rad per row): the diagnosed grade (effects_from's, ddyn.sil.effects.grade_column),
    the track's own (controller_grade: the oracle), or None (a level road); both asked for is refused, as the
    bank's."""
    if spec.effects_from is not None and spec.controller_grade:
        raise DdynError("--controller-grade with --effects-from D: give one (the diagnosis sets the controller's "
                        "grade, and the controller refuses a grade its recorded effects do not give)")
    if (spec.effects_from or {}).get("grade") is not None:
        from ddyn.sil.effects import grade_column
        return grade_column(spec.effects_from, spec.track, table)
    return raceline_grade(spec.track, table) if spec.controller_grade else None


def controller_bank_column(spec: SilSpec, table: np.ndarray) -> np.ndarray | None:
    """raceline.csv's bank column (rad per row): the diagnosed bank (effects_from's, ddyn.sil.effects.bank_column),
    the track's own (controller_bank: the oracle), or None (a flat road). Both asked for is refused: the
    controller refuses a bank its recorded effects do not give."""
    diagnosed = (spec.effects_from or {}).get("bank")
    if spec.effects_from is not None and spec.controller_bank:
        raise DdynError("--controller-bank with --effects-from D: give one (the diagnosis sets the controller's "
                        "bank, and the controller refuses a bank its recorded effects do not give)")
    if diagnosed is not None:
        from ddyn.sil.effects import bank_column
        return bank_column(spec.effects_from, spec.track, table)
    return raceline_bank(spec.track, table) if spec.controller_bank else None


def controller_config(spec: SilSpec, out_dir: str, can: str = "vcan0", lcm_url: str = "",
                      table: np.ndarray | None = None, key_file: str | None = None) -> dict:
    """ddyn_controller's configuration for a SIL run (the car's format: docs/deploy.md). The raceline is
    RACELINE_CSV beside it; outputs go to out_dir (the folder of the run, /out in the guest). table: the
    raceline the run uses (computed from the spec when not given), for the filter's start. key_file: the
    frame authentication key as the controller sees it (can.key_file; None: none named)."""
    if table is None:
        table = raceline_table(spec.track, spec.vehicle, spec.speed_scale, margin=spec.margin, line=spec.line)
    v = spec.vehicle
    if spec.throttle not in ("mpc", "pid"):
        raise DdynError(f"throttle {spec.throttle!r}: expected mpc or pid")
    if spec.pid_gains is not None and (len(spec.pid_gains) != 4 or
                                       not all(math.isfinite(g) and g >= 0.0 for g in spec.pid_gains)):
        raise DdynError(f"PID gains {spec.pid_gains!r}: expected four finite numbers >= 0 (kp, ki, kd, preview)")
    if spec.pacing not in ("frame", "timer"):
        raise DdynError(f"pacing {spec.pacing!r}: expected frame or timer")
    if spec.pacing == "timer" and spec.realtime <= 0.0:
        raise DdynError("the timer pacing runs on the clock: it needs a plant in real time (--realtime 1)")
    noise = sensor_noise(v, spec.noise_scale)
    fixed = spec.coeffs_controller is not None

    def named(c) -> dict:
        return {k: float(x) for k, x in zip(COEFF_NAMES, c)}

    die = -1
    # lock-step: the controller's timer runs only after this much wall time without any frame (a
    # plant slowed by an emulator or a loaded machine is not a silent one); when the scenario is a
    # restarting plant, detection is what is measured: 1.5 periods, as in real time
    lockstep = 0.0 if spec.realtime > 0.0 else (1.5 * v.sample_time if "restart_plant" in spec.faults else 0.5)
    if "kill_controller" in spec.faults:
        die = int(round(float(spec.faults["kill_controller"]) / v.sample_time))
    coefficients: dict = {"source": "fixed" if fixed else "network"}
    if fixed:
        coefficients["fixed"] = named(spec.coeffs_controller)
    if spec.checkpoint_hash:
        coefficients["checkpoint_hash"] = spec.checkpoint_hash
    control: dict = {"period": float(v.sample_time), "throttle": spec.throttle, "prepare": spec.prepare}
    if spec.throttle == "pid" and spec.pid_gains is not None:
        control["pid"] = dict(zip(("kp", "ki", "kd", "preview"), (float(g) for g in spec.pid_gains)))
    unknown = set(spec.controller_delays) - set(CONTROLLER_DELAY_KEYS)
    if unknown:
        raise DdynError(f"controller delays: unknown {', '.join(sorted(unknown))}; expected steer, throttle")
    if any(float(d) != 0.0 for d in spec.controller_delays.values()):
        # written only when asked for: without it the file is the one of before
        control["delay"] = {"steering": float(spec.controller_delays.get("steer", 0.0)),
                            "throttle": float(spec.controller_delays.get("throttle", 0.0))}
    unknown = set(spec.controller_lag) - set(CONTROLLER_LAG_KEYS)
    if unknown:
        raise DdynError(f"controller lag: unknown {', '.join(sorted(unknown))}; expected steer")
    if any(float(d) != 0.0 for d in spec.controller_lag.values()):
        control["lag"] = {"steering": float(spec.controller_lag.get("steer", 0.0))}
    if spec.controller_mass_offset != 0.0:
        control["mass_offset"] = float(spec.controller_mass_offset)
    if spec.controller_downforce != 0.0:
        control["downforce"] = float(spec.controller_downforce)
    bank = controller_bank_column(spec, table)
    if bank is not None:  # the road's bank along the raceline (raceline.csv's 6th column)
        control["bank"] = True
    grade = controller_grade_column(spec, table)
    if grade is not None:  # the road's grade along the raceline (raceline.csv's next column)
        control["grade"] = True
    if spec.effects_from is not None:
        # recorded from the diagnosis (ddyn.sil.effects): the controller refuses the file if control.delay,
        # control.lag or control.bank differs (or the bank column's peak)
        control["delay"] = {"steering": float(spec.controller_delays.get("steer", 0.0)),
                            "throttle": float(spec.controller_delays.get("throttle", 0.0))}
        control["lag"] = {"steering": float(spec.controller_lag.get("steer", 0.0))}
        control["mass_offset"] = float(spec.controller_mass_offset)
        control["downforce"] = float(spec.controller_downforce)
    dims = {"gnss_position": 2, "heading": 1, "yaw_rate": 1, "acceleration": 2, "wheel_speed": 2, "steering": 1}
    can_cfg: dict = {"interface": can, "stale_periods": dict(FRAME_STALE_PERIODS), "cycle_ms": frame_cycles_ms(v)}
    if key_file:
        can_cfg["key_file"] = key_file
    cfg = {
        "vehicle": v.name,
        "nominal_coefficients": named(spec.nominal),
        "coefficients": coefficients,
        "can": can_cfg,
        "control": control,
        "filter": {
            "x0": [float(c) for c in controller_start(spec, table)],
            "process_noise": list(FILTER_PROCESS_NOISE),
            # the noise the filter assumes: twice the sensors' own (model error), 1 m/s^2 for the
            # accelerometer (its model goes through the estimated coefficients), as the controller's
            # closed-loop benchmark (train/bench/controller.py); a floor keeps R positive definite
            "sensor_std": {k: [max(FILTER_ACCEL_STD if k == "acceleration" else 2.0 * float(sd), 1e-4)
                               for sd in noise[k][:dims[k]]] for k in SENSOR_ORDER},
        },
        "raceline": RACELINE_CSV,
        "telemetry": {"lcm_url": lcm_url, "metrics": f"{out_dir}/controller_metrics.json",
                      "log": f"{out_dir}/controller_log.csv"},
        # by default the SIL's plant runs in lock-step: frame pacing; no SCHED_FIFO (the emulated guest's
        # two processes share its CPUs); memory locked as on the car
        "realtime": {"pacing": spec.pacing, "priority": int(spec.rt_priority), "cpu": int(spec.rt_cpu), "lock_memory": True,
                     "lockstep_silence": lockstep,
                     # the plant may take seconds to start in the emulated guest (Putnam's 2,877-point
                     # track: a controller that left after 3 s without a frame); the run's end stops it anyway
                     "idle_exit": 60.0},
        "sil": {"die_at_step": die},
    }
    if spec.effects_from is not None:
        from ddyn.sil.effects import record
        cfg["effects"] = record(spec.effects_from, bank, grade) | {"delay": dict(control["delay"]),
                                                             "lag": dict(control["lag"]),
                                                             "mass_offset": control["mass_offset"],
                                                             "downforce": control["downforce"]}
    mpc = mpc_section(v.name)
    if mpc:
        cfg["mpc"] = mpc
    return cfg


def write_controller_files(spec: SilSpec, table: np.ndarray, work: Path, out_dir: str, lcm_url: str = "",
                           key_file: str | None = None) -> Path:
    """controller.json and raceline.csv into the run's folder; the configuration's path."""
    (work / RACELINE_CSV).write_text(raceline_csv(table, controller_bank_column(spec, table),
                                                  controller_grade_column(spec, table)))
    path = work / CONTROLLER_CONFIG
    path.write_text(json.dumps(controller_config(spec, out_dir, lcm_url=lcm_url, table=table, key_file=key_file),
                               indent=1) + "\n")
    return path


# The frame authentication's key in a SIL run (--auth): the fixed TEST key the build makes at configure
# time (cmake/dbw_test_key.cmake; never a car's), named by both configs; in the guest a copy, mode 0600.
GUEST_KEY_FILE = "/sil/dbw_test.key"


def dbw_test_key(bins: Path) -> Path:
    """The build's test key (<build>/dbw_test_key/dbw_test.key) beside the SIL binaries' build."""
    key = bins.parent / "dbw_test_key" / "dbw_test.key"
    if not key.is_file():
        raise DdynError(f"{key} is missing: the build makes the frame authentication's test key at configure time "
                        "(cmake/dbw_test_key.cmake); reconfigure the SIL build")
    return key


def parse_window(text: str) -> tuple[float, float]:
    """`T0:T1` (simulated seconds, 0 <= T0 < T1) for --inject-forged-steering."""
    try:
        t0, t1 = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected T0:T1 (seconds)") from None
    if not (math.isfinite(t0) and math.isfinite(t1) and 0.0 <= t0 < t1):
        raise argparse.ArgumentTypeError(f"{text!r}: expected 0 <= T0 < T1")
    return t0, t1


def set_lcm_url(path: Path, url: str) -> bytes:
    """The configuration with telemetry.lcm_url set (the URL is known only when the run starts)."""
    cfg = json.loads(path.read_text())
    cfg["telemetry"]["lcm_url"] = url
    text = json.dumps(cfg, indent=1) + "\n"
    path.write_text(text)
    return text.encode()


# ---------------------------------------------------------------------------------------------- build

def build_binaries(export_dir: Path | None, build_root: Path | None = None, quiet: bool = True) -> Path:
    """Configure and build the SIL executables (the plant, ddyn_controller, the in-process variant) for the
    given network export in their own build dir."""
    net = export_dir if export_dir is not None else REPO / "tests" / "c" / "generated" / "net_fixture"
    key = hashlib.sha256(str(Path(net).resolve()).encode()).hexdigest()[:12]
    # DDYN_SIL_BUILD_DIR: another root for these builds (several checkouts or workers sharing a machine)
    build = (build_root or Path(os.environ.get("DDYN_SIL_BUILD_DIR") or REPO / "build-sil")) / key
    cmd = ["cmake", "-S", str(REPO), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release", "-DDDYN_BUILD_TESTS=OFF",
           f"-DDDYN_NET_EXPORT_DIR={Path(net).resolve()}"]
    build.mkdir(parents=True, exist_ok=True)
    # one build at a time per build dir: two studies run side by side configure the same dir before each run, and
    # two cmake configures racing there failed one run (CMakePackageConfigHelpers' configure_file, seen with two
    # `ddyn study sil-loop` at once); the second waits for the first and then finds the build up to date
    with open(build / ".ddyn_build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        for c in (cmd, ["cmake", "--build", str(build), "-j2", "--target", "ddyn_sil_plant", "ddyn_controller_app",
                        "ddyn_sil_inprocess"]):
            r = subprocess.run(c, capture_output=True, text=True)
            if r.returncode != 0:
                raise DdynError(f"building the SIL binaries failed: {' '.join(c)}\n{(r.stdout + r.stderr)[-3000:]}")
    return build / "firmware_sim"


def require_network(controller: Path, checkpoint_hash: str) -> None:
    """Refuse, before any run, a controller built for another checkpoint than the one named (the
    controller itself refuses it too: coefficients.checkpoint_hash of its configuration)."""
    r = subprocess.run([str(controller), "--checkpoint-hash"], capture_output=True, text=True)
    built = r.stdout.strip()
    if r.returncode != 0 or built != checkpoint_hash:
        raise DdynError(f"{controller} was built for checkpoint {built[:12] or '(unknown)'}..., not for the one given "
                        f"({checkpoint_hash[:12]}...): a stale build; rebuild it for the checkpoint's export")


def export_network(ckpt: Path, out: Path) -> Path:
    from ddyn.learn.export import export
    export(ckpt, out, torch_export=False)
    return out


# ---------------------------------------------------------------------------------------------- run

def host_has_vcan() -> bool:
    if Path("/sys/class/net/vcan0").exists():
        subprocess.run(["ip", "link", "set", "up", "vcan0"], capture_output=True)
        return True
    r = subprocess.run(["ip", "link", "add", "dev", "vcan0", "type", "vcan"], capture_output=True)
    if r.returncode != 0:
        return False
    return subprocess.run(["ip", "link", "set", "up", "vcan0"], capture_output=True).returncode == 0


# LCM telemetry of the SIL controller (docs/lcm.md): LCM's default multicast group, TTL 0 (never
# leaves the machine). In the guest the port is LCM's default; on a host it is a free one per run,
# so that two runs (or the car's own LCM traffic) never share a log.
LCM_GROUP = "239.255.76.67"
LCM_GUEST_PORT = 7667
LCM_LOG_NAME = "controller.lcm"


def lcm_url(port: int) -> str:
    return f"udpm://{LCM_GROUP}:{port}?ttl=0"


def controller_has_lcm(bins: Path) -> bool:
    """Whether the build's controller publishes LCM telemetry (configured with DDYN_WITH_LCM)."""
    cache = bins.parent / "CMakeCache.txt"
    return cache.is_file() and re.search(r"^DDYN_WITH_LCM:BOOL=(ON|1|TRUE|YES)$", cache.read_text(), re.M) is not None


def lcm_logger_binary() -> Path:
    """The lcm-logger of the pinned `lcm` package: the C binary itself (the venv's bin/lcm-logger is a
    Python wrapper that SIGKILLs the logger on SIGINT, which can lose the log's tail)."""
    from ddyn.data.lcm_types import lcm_module
    exe = Path(lcm_module().LCM_BIN_DIR).resolve() / "lcm-logger"
    if not exe.is_file():
        raise DdynError(f"lcm-logger not found at {exe}; reinstall the pinned `lcm` package (scripts/setup.sh)")
    return exe


def _udp_sockets(port: int) -> list[list[str]]:
    """The /proc/net/udp rows of sockets bound to a local port (fields split)."""
    rows = []
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        f = line.split()
        if len(f) > 4 and f[1].endswith(f":{port:04X}"):
            rows.append(f)
    return rows


def _free_udp_port() -> int:
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as so:
        so.bind(("", 0))
        return so.getsockname()[1]


def start_host_logger(work: Path) -> tuple[subprocess.Popen, str]:
    """lcm-logger on a free port of the multicast group, listening before it returns."""
    r = subprocess.run(["ip", "route", "get", LCM_GROUP], capture_output=True, text=True)
    if r.returncode != 0:
        raise DdynError(f"no route for LCM's multicast group {LCM_GROUP} on this host ({r.stderr.strip()}): the "
                        f"controller's telemetry could not be logged; add one, e.g. `ip route add {LCM_GROUP}/32 dev lo`")
    port = _free_udp_port()
    url = lcm_url(port)
    log = work / LCM_LOG_NAME
    log.unlink(missing_ok=True)
    proc = subprocess.Popen([str(lcm_logger_binary()), "--lcm-url", url, "-f", str(log)],
                            stdout=open(work / "lcm-logger.stdout", "w"), stderr=subprocess.STDOUT)
    group_hex = "".join(f"{int(b):02X}" for b in reversed(LCM_GROUP.split(".")))
    deadline = time.monotonic() + 60.0  # a generous cap on a loaded machine: the loop ends when it listens
    while not (_udp_sockets(port) and group_hex in Path("/proc/net/igmp").read_text()):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise DdynError(f"lcm-logger did not start listening on {url} "
                            f"({(work / 'lcm-logger.stdout').read_text()[-500:]})")
        time.sleep(0.05)
    return proc, url


def stop_host_logger(proc: subprocess.Popen, url: str) -> int:
    """Let the logger drain its socket, then SIGINT (it closes the log cleanly); its exit status."""
    port = int(url.rsplit(":", 1)[1].split("?")[0])
    deadline = time.monotonic() + 60.0  # caps, not waits: each loop ends as soon as its condition holds
    while time.monotonic() < deadline and any(int(f[4].split(":")[1], 16) for f in _udp_sockets(port)):
        time.sleep(0.05)
    # its reader thread hands the last datagrams to the writer: until the log has not grown for 0.3 s
    log = Path(proc.args[proc.args.index("-f") + 1]) if "-f" in proc.args else None
    last, since = -1, time.monotonic()
    while log is not None and time.monotonic() < deadline:
        size = log.stat().st_size if log.exists() else 0
        if size != last:
            last, since = size, time.monotonic()
        elif time.monotonic() - since >= 0.3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise DdynError("lcm-logger did not stop within 10 s of SIGINT") from None


def wait_until_ready(ctl: subprocess.Popen, stdout: Path, timeout: float = 120.0) -> None:
    """Until the controller listens on the bus (its "running" line comes after the socket is bound):
    a position frame the plant sent before would be lost, and the lock-step plant would wait it out."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and ctl.poll() is None:
        if stdout.is_file() and re.search(r"^ddyn_controller: running ", stdout.read_text(), re.M):
            return
        time.sleep(0.02)
    if ctl.poll() is not None:
        raise DdynError(f"the controller exited ({ctl.returncode}) before the run: {stdout.read_text()[-2000:]}")
    raise DdynError(f"the controller did not start listening within {timeout:.0f} s ({stdout})")


def run_host(bins: Path, work: Path, restart: bool, lcm: bool = False) -> dict:
    """Both processes on the host's vcan0; with lcm, the controller publishes its telemetry over UDP
    multicast and lcm-logger (started first) records it into controller.lcm."""
    t0 = time.monotonic()
    logger, url = start_host_logger(work) if lcm else (None, None)
    try:
        if url:
            set_lcm_url(work / CONTROLLER_CONFIG, url)
        ctl = subprocess.Popen([str(bins / "ddyn_controller"), str(work / CONTROLLER_CONFIG)],
                               stdout=open(work / "controller.stdout", "w"), stderr=subprocess.STDOUT)
        wait_until_ready(ctl, work / "controller.stdout")
        with open(work / "plant.stdout", "w") as out:
            rc = subprocess.call([str(bins / "ddyn_sil_plant"), str(work / "plant.json"), "--can", "vcan0"],
                                 stdout=out, stderr=subprocess.STDOUT)
            if rc == 3 and restart:
                time.sleep(0.5)
                rc = subprocess.call([str(bins / "ddyn_sil_plant"), str(work / "plant_resume.json"), "--can",
                                      "vcan0"], stdout=out, stderr=subprocess.STDOUT)
        if ctl.poll() is None:
            ctl.terminate()
        try:
            ctl.wait(timeout=10)
        except subprocess.TimeoutExpired:
            ctl.kill()
            ctl.wait()
    except BaseException:
        if logger is not None:
            logger.kill()
        raise
    out = {"where": "host vcan0", "plant_exit": rc, "controller_exit": ctl.returncode,
           "wall_time": time.monotonic() - t0}
    if logger is not None:  # after the controller has exited: its last messages are on the way
        out["lcm"] = {"url": url, "logger_exit": stop_host_logger(logger, url)}
    return out


def run_inprocess(bins: Path, work: Path, forged_steering: tuple | None = None) -> dict:
    """Plant and controller node in one process, frames through memory (not the SIL path: for
    development and host-native controller timings). forged_steering (t0, t1): an attacker's forged
    steering commands in that window of simulated time."""
    t0 = time.monotonic()
    extra = ["--inject-forged-steering", f"{forged_steering[0]!r}:{forged_steering[1]!r}"] if forged_steering else []
    with open(work / "plant.stdout", "w") as out:
        rc = subprocess.call([str(bins / "ddyn_sil_inprocess"), str(work / "plant.json"), str(work / CONTROLLER_CONFIG)]
                             + extra, stdout=out, stderr=subprocess.STDOUT)
    if rc != 0:
        raise DdynError(f"ddyn_sil_inprocess failed ({rc}): {(work / 'plant.stdout').read_text()[-2000:]}")
    return {"where": "in-process on the host (one process, frames through memory; not vcan)", "plant_exit": rc,
            "controller_exit": rc, "wall_time": time.monotonic() - t0}


GUEST_INIT = """#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev 2>/dev/null
echo "DDYN_GUEST_INIT_UPTIME: $(cut -d' ' -f1 /proc/uptime)"
for m in {modules}; do insmod /lib/modules/$m.ko || echo "DDYN_GUEST: insmod $m failed"; done
ip link add dev vcan0 type vcan && ip link set up vcan0 || echo "DDYN_GUEST: cannot create vcan0"
mkdir -p /out
export LD_LIBRARY_PATH={libdir}
{lcm_start}/sil/ddyn_controller /sil/controller.json > /out/controller.stdout 2>&1 &
cpid=$!
# the plant starts once the controller listens (its "running" line comes after the bus is bound): a
# position frame sent before would be lost and the lock-step plant would wait out its timeout
n=0
while ! grep -q '^ddyn_controller: running ' /out/controller.stdout 2>/dev/null && kill -0 $cpid 2>/dev/null; do
  n=$((n+1))
  if [ $n -gt 1200 ]; then echo "DDYN_GUEST: the controller is not ready after 60 s"; break; fi
  sleep 0.05
done
/sil/ddyn_sil_plant /sil/plant.json --can vcan0 > /out/plant.stdout 2>&1
rc=$?
if [ $rc -eq 3 ] && [ -f /sil/plant_resume.json ]; then
  sleep 0.5
  /sil/ddyn_sil_plant /sil/plant_resume.json --can vcan0 >> /out/plant.stdout 2>&1
  rc=$?
fi
kill -TERM $cpid 2>/dev/null
wait $cpid
crc=$?
{lcm_stop}echo "DDYN_GUEST_RUN_UPTIME: $(cut -d' ' -f1 /proc/uptime)"
for f in /out/*; do
  echo "DDYN_FILE_BEGIN $(basename $f)"
  gzip -c $f | base64
  echo "DDYN_FILE_END"
done
echo "DDYN_GUEST_PLANT_EXIT: $rc"
echo "DDYN_GUEST_CONTROLLER_EXIT: $crc"
echo "DDYN_GUEST_EXIT: $rc"
poweroff -f
"""
# LCM in the guest: loopback with multicast and a route for the group, lcm-logger (dynamically
# linked: its libraries are in the guest's GUEST_LIB_DIR) started first and listening (its socket on
# the port in /proc/net/udp, the group joined in /proc/net/igmp) before the controller starts; after
# the controller has exited, the logger drains its socket and is stopped with SIGINT, which closes
# the log cleanly; the log comes back with the other files of /out.
GUEST_LCM_START = """ip link set lo up && ip link set lo multicast on && ip route add {group}/32 dev lo || echo "DDYN_GUEST: cannot route {group} on lo"
/sil/lcm-logger --lcm-url '{url}' -f /out/{log} > /out/lcm-logger.stdout 2>&1 &
lpid=$!
n=0
while ! grep -q ':{port_hex} ' /proc/net/udp || ! grep -q '{group_hex}' /proc/net/igmp; do
  n=$((n+1))
  if [ $n -gt 600 ]; then echo "DDYN_GUEST: lcm-logger not listening after 60 s"; break; fi
  sleep 0.1
done
echo "DDYN_GUEST_LOGGER_READY: up $(cut -d' ' -f1 /proc/uptime) s, $n polls"
"""
GUEST_LCM_STOP = """n=0
while [ $n -lt 100 ]; do
  q=$(awk '$2 ~ /:{port_hex}$/ {{split($5, a, ":"); print a[2]}}' /proc/net/udp | head -n 1)
  [ "$q" = "00000000" ] && break
  n=$((n+1))
  sleep 0.1
done
sleep 0.3
kill -INT $lpid
wait $lpid
echo "DDYN_GUEST_LOGGER_EXIT: $?"
"""


def _guest_module():
    path = REPO / "scripts" / "vcan_guest" / "build_guest.py"
    if not path.is_file():
        raise DdynError(f"{path} is missing: the qemu guest tooling (scripts/vcan_guest) is needed without a host vcan")
    spec = importlib.util.spec_from_file_location("ddyn_build_guest", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# The guest's clock: by default a virtual clock driven by the instruction count (`-icount
# shift=2,sleep=off`: 4 ns per guest instruction, an emulated CPU of 250 MIPS; idle time skipped), as
# scripts/vcan_guest/run.sh does for the CAN tests. Everything the guest measures in time (the
# controller's lock-step silence, its timer periods, the plant's waits, a frame held back) is then
# counted in instructions, not taken from the host: a loaded host slows the run down but cannot change
# when a frame arrives relative to the guest's clocks, so a scenario's verdict does not follow the
# host's load (issue 35: the 40 ms delayed-bus lap gave 1 violation in one run and 0 in the next on
# the host clock). One vCPU: with -icount qemu runs its vCPUs in turns on one host thread anyway.
# DDYN_SIL_QEMU_CLOCK overrides the options ("" = the host's clock, two vCPUs, as before); KVM has no
# instruction counting and always runs on the host's clock.
GUEST_CLOCK_DEFAULT = "-icount shift=2,sleep=off"


def guest_clock(kvm: bool) -> list[str]:
    if kvm:
        return []
    return os.environ.get("DDYN_SIL_QEMU_CLOCK", GUEST_CLOCK_DEFAULT).split()


def run_guest(bins: Path, work: Path, track_dir: Path, track: str, kvm: bool, timeout: float,
              lcm: bool = False, key_file: Path | None = None) -> dict:
    """Both processes inside a qemu guest with vcan (the kernel, modules and busybox of scripts/vcan_guest);
    with lcm, the controller publishes its telemetry over UDP multicast on the guest's loopback and
    lcm-logger records it into controller.lcm (both dynamically linked, with their libraries)."""
    bg = _guest_module()
    cache = Path(os.environ.get("DDYN_VCAN_GUEST_DIR", REPO / "build" / "vcan-guest"))
    cache.mkdir(parents=True, exist_ok=True)
    try:
        meta = bg.prepare_kernel(cache)
    except Exception as e:  # the guest tooling's own errors name what is missing
        raise DdynError(f"cannot prepare the qemu guest's kernel: {e}") from None
    if not bg.BUSYBOX.is_file() or not bg.is_static_elf(bg.BUSYBOX):
        raise DdynError(f"{bg.BUSYBOX} is missing or not static: install busybox-static")
    if shutil.which("qemu-system-x86_64") is None:
        raise DdynError("qemu-system-x86_64 is not installed (scripts/setup.sh installs qemu-system-x86)")
    c = bg.Cpio()
    for d in ("bin", "proc", "sys", "dev", "lib", "lib/modules", "sil", "sil/tracks", "out"):
        c.dir(d)
    c.file("bin/busybox", bg.BUSYBOX.read_bytes())
    for m in meta["modules"]:
        c.file(f"lib/modules/{m}.ko", (cache / "modules" / f"{m}.ko").read_bytes(), 0o644)
    p = bins / "ddyn_sil_plant"
    if not bg.is_static_elf(p):
        raise DdynError(f"{p} is not statically linked; the guest has no libc")
    c.file("sil/ddyn_sil_plant", p.read_bytes())
    guest_bins = [bins / "ddyn_controller"] + ([lcm_logger_binary()] if lcm else [])
    try:  # dynamically linked ones (cJSON, LCM) come with their interpreter and libraries
        added = bg.add_binaries(c, "sil", guest_bins)
    except bg.GuestError as e:
        raise DdynError(f"cannot put the controller into the qemu guest: {e}") from None
    for part in ("center", "inner", "outer"):
        c.file(f"sil/tracks/{track}_{part}.txt", (track_dir / f"{track}_{part}.txt").read_bytes(), 0o644)
    url = lcm_url(LCM_GUEST_PORT)
    if lcm:
        set_lcm_url(work / CONTROLLER_CONFIG, url)
    for name in ("plant.json", "plant_resume.json", CONTROLLER_CONFIG, RACELINE_CSV):
        if (work / name).is_file():
            c.file(f"sil/{name}", (work / name).read_bytes(), 0o644)
    if key_file is not None:  # the key reader refuses a key others can read
        c.file(GUEST_KEY_FILE.lstrip("/"), key_file.read_bytes(), 0o600)
    fill = dict(libdir=bg.GUEST_LIB_DIR, group=LCM_GROUP, url=url, log=LCM_LOG_NAME,
                port_hex=f"{LCM_GUEST_PORT:04X}", group_hex="".join(f"{int(b):02X}" for b in reversed(LCM_GROUP.split("."))))
    c.file("init", GUEST_INIT.format(modules=" ".join(meta["modules"]), libdir=bg.GUEST_LIB_DIR,
                                     lcm_start=GUEST_LCM_START.format(**fill) if lcm else "",
                                     lcm_stop=GUEST_LCM_STOP.format(**fill) if lcm else "").encode())
    initramfs = work / "guest-initramfs.cpio.gz"
    import gzip
    cpio = c.finish()
    with open(initramfs, "wb") as f, gzip.GzipFile(fileobj=f, mode="wb", compresslevel=1, mtime=0) as gz:
        gz.write(cpio)
    sizes = {"initramfs_bytes": len(cpio), "initramfs_gz_bytes": initramfs.stat().st_size,
             "shared_library_bytes": added["bytes"], "dynamic": added["dynamic"]}
    clock = guest_clock(kvm)
    cmd = ["qemu-system-x86_64"] + (["-enable-kvm"] if kvm else []) + clock + [
        "-m", "512M", "-smp", "1" if clock else "2", "-nodefaults", "-no-reboot", "-display", "none", "-serial", "stdio",
        "-monitor", "none", "-kernel", str(cache / meta["vmlinux"]), "-initrd", str(initramfs),
        "-append", "console=ttyS0 quiet loglevel=3 panic=-1 rdinit=/init"]
    t0 = time.monotonic()
    try:
        r = subprocess.run(cmd, capture_output=True, timeout=timeout, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise DdynError(f"the qemu guest timed out after {timeout:.0f} s") from None
    wall = time.monotonic() - t0
    log = r.stdout.decode(errors="replace").replace("\r", "")
    if r.stderr:
        log += "\n[qemu stderr]\n" + r.stderr.decode(errors="replace")
    (work / "guest.log").write_text(log)
    initramfs.unlink()
    files = re.findall(r"DDYN_FILE_BEGIN (\S+)\n(.*?)DDYN_FILE_END", log, flags=re.S)
    import gzip as gz_mod
    for name, body in files:
        (work / name).write_bytes(gz_mod.decompress(base64.b64decode("".join(body.split()))))
    m = re.search(r"DDYN_GUEST_PLANT_EXIT: (\d+)", log)
    mc = re.search(r"DDYN_GUEST_CONTROLLER_EXIT: (\d+)", log)
    if m is None:
        raise DdynError(f"the qemu guest did not finish the run (log: {work / 'guest.log'}):\n{log[-2000:]}")
    for key, pat in (("init_uptime_s", "DDYN_GUEST_INIT_UPTIME"), ("run_done_uptime_s", "DDYN_GUEST_RUN_UPTIME")):
        mu = re.search(pat + r": ([0-9.]+)", log)
        sizes[key] = float(mu.group(1)) if mu else None
    where = "KVM" if kvm else ("software emulation, emulated time: " + " ".join(clock) if clock else
                               "software emulation, host clock")
    out = {"where": f"qemu guest vcan0 ({where})", "plant_exit": int(m.group(1)),
           "controller_exit": int(mc.group(1)) if mc else None, "wall_time": wall, "guest": sizes,
           "clock": "emulated" if clock else "host"}
    if lcm:
        ml = re.search(r"DDYN_GUEST_LOGGER_EXIT: (\d+)", log)
        mr = re.search(r"DDYN_GUEST_LOGGER_READY: up ([0-9.]+) s, (\d+) polls", log)
        out["lcm"] = {"url": url, "logger_exit": int(ml.group(1)) if ml else None,
                      "logger_ready_uptime_s": float(mr.group(1)) if mr else None}
    return out


# ---------------------------------------------------------------------------------------------- results

def read_csv(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        return {}
    with open(path) as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.size == 0:
        return {h: np.zeros(0) for h in header}
    return {h: data[:, i] for i, h in enumerate(header)}


def tracking_error(traj: dict, table: np.ndarray) -> dict:
    """Distance of the car's reference point to the raceline (closed polyline): mean, rms, max."""
    if not traj or len(traj["x"]) == 0:
        return {"mean": None, "rms": None, "max": None}
    from ddyn.model.tracks import distance_to_polyline
    d = distance_to_polyline(np.column_stack([traj["x"], traj["y"]]), table[:, :2])
    return {"mean": float(d.mean()), "rms": float(np.sqrt(np.mean(d * d))), "max": float(d.max())}


def lap_average_speeds(traj: dict, lap_times: list[float]) -> list[float]:
    """Per lap: the distance the car's centre of gravity drove in the lap over the lap time.

    The paper's figure (2.010 m/s x 5.38 s = 10.8 m on ETHZMobil, whose centre line is 12.85 m)
    is of this kind: the driven line, not the centre line, over the lap time."""
    if not traj or len(traj.get("t", [])) < 2:
        return []
    t = np.asarray(traj["t"], float)
    dist = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(traj["x"]), np.diff(traj["y"])))))
    ends = np.cumsum(lap_times)
    starts = np.concatenate(([0.0], ends[:-1]))
    return [float((np.interp(b, t, dist) - np.interp(a, t, dist)) / (b - a)) for a, b in zip(starts, ends)]


def summarise(work: Path, spec: SilSpec, table: np.ndarray, run: dict) -> dict:
    pm_path, cm_path = work / "plant_metrics.json", work / "controller_metrics.json"
    if not pm_path.is_file():
        tail = (work / "plant.stdout").read_text()[-2000:] if (work / "plant.stdout").is_file() else ""
        raise DdynError(f"the plant wrote no metrics (exit {run.get('plant_exit')}):\n{tail}")
    pm = json.loads(pm_path.read_text())
    cm = json.loads(cm_path.read_text()) if cm_path.is_file() else None
    traj = read_csv(work / "trajectory.csv")
    clog = read_csv(work / "controller_log.csv")
    laps = pm["lap_times"]
    out = {
        "vehicle": spec.vehicle.name, "track": spec.track.name, "laps_requested": spec.laps,
        "lap_completed": len(laps) >= spec.laps, "lap_times": laps,
        "average_speed": lap_average_speeds(traj, laps),
        "average_speed_centre_line": [spec.track.length / t for t in laps],
        "average_speed_driven": pm["average_speed"], "violations": pm["violations"],
        "time_outside": pm["time_outside"], "worst_clearance": pm["worst_clearance"],
        "end_reason": pm["end_reason"], "tracking_error": tracking_error(traj, table),
        "controller": None, "plant": pm, "run": run,
        "effects": spec.effects, "faults": spec.faults, "controller_delays": spec.controller_delays,
        "controller_lag": spec.controller_lag, "controller_mass_offset": spec.controller_mass_offset,
        "controller_downforce": spec.controller_downforce,
        "controller_effects": spec.effects_from,
        "road_bank": bool(pm.get("road_bank", False)),
        # the controller's bank: the track's own (--controller-bank) or a diagnosis's (--effects-from D)
        "controller_bank": spec.controller_bank or (spec.effects_from or {}).get("bank") is not None,
        "controller_bank_from": ("track" if spec.controller_bank else
                                 "diagnosis" if (spec.effects_from or {}).get("bank") is not None else None),
        "road_grade": bool(pm.get("road_grade", False)),
        "controller_grade": spec.controller_grade or (spec.effects_from or {}).get("grade") is not None,
        "coefficients": "fixed" if spec.coeffs_controller is not None else "network",
        "throttle": spec.throttle, "pid_gains": list(spec.pid_gains) if spec.pid_gains is not None else "default",
        # frame authentication: the plant's DBW unit's counts (commands accepted; forged, replayed, stale
        # refused) and the controller's (frames accepted and refused); the attacker's forged commands
        "auth": {"requested": spec.auth, "plant": pm.get("auth"), "controller": cm.get("auth") if cm else None},
    }
    if spec.forged_steering is not None:
        out["attack"] = {"forged_steering": list(spec.forged_steering),
                         "forged_commands_sent": (cm or {}).get("auth", {}).get("forged_commands_injected"),
                         "refused_by_the_dbw_unit": (pm.get("auth") or {}).get("forged")}
    if cm is not None:
        out["controller"] = {"loop_us": cm["loop_us"], "deadline_misses": cm["deadline_misses"],
                             "periods": cm["steps"], "safe_periods": cm["safe_steps"],
                             "timer_periods": cm["timer_steps"], "frames": cm["frames"],
                             "first_safe_latency": cm["first_safe_latency"],
                             "first_stale_latency": cm.get("first_stale_latency"),
                             "status_counts": cm["status_counts"],
                             "sensor_rejected": cm.get("sensor_rejected"), "sensor_nonfinite": cm.get("sensor_nonfinite"),
                             # ddyn_controller's: the preparation's time (RTI split), overruns, the
                             # real-time settings in effect, the network it ran
                             "prepare_us": cm.get("prepare_us"), "overruns": cm.get("overruns"),
                             "realtime": cm.get("realtime"), "checkpoint_hash": cm.get("checkpoint_hash")}
    # time to the safe state, where a fault required one
    f = spec.faults
    safe: dict = {}
    if "kill_controller" in f:
        safe["dbw_watchdog_latency"] = pm["dbw"]["first_trip_latency"]
        safe["dbw_trip_time"] = pm["dbw"]["first_trip_time"]
        safe["stopped_time"] = pm["dbw"]["stopped_time"]
    if "restart_plant" in f and cm is not None:
        # wall time from the last position frame to the controller's safe command for missing frames
        safe["controller_stale_latency_wall"] = cm.get("first_stale_latency")
    if "silent" in f and clog and len(clog.get("step", [])):
        # the first period commanded safe for the missing frames after the silence began
        # (controller periods -> seconds)
        t_ctl = clog["step"] * spec.vehicle.sample_time
        idx = np.nonzero((clog["stale"] > 0) & (t_ctl >= float(f["silent_at"])))[0]
        safe["controller_safe_after_silence"] = (float(t_ctl[idx[0]] - float(f["silent_at"]))
                                                 if len(idx) else None)
    if safe:
        out["safe_state"] = safe
    return out


def write_lcm_log(work: Path, period: float) -> Path | None:
    """FALLBACK ONLY: the controller's per-period CSV log converted to an LCM event log on the host
    (DDYN_STATE, DDYN_TIMING; lcmtypes/), for runs without a live publisher: `--where inprocess`
    (one process, no controller executable) or a build without LCM (DDYN_WITH_LCM=OFF). The SIL
    proper (guest or host vcan) records the controller's live telemetry instead (run_sil).
    Same message types and utime convention (the controller's period count times the period).
    """
    from ddyn.data.lcm_types import lcm_module, types
    clog = read_csv(work / "controller_log.csv")
    if not clog or len(clog.get("step", [])) == 0:
        return None
    lcm, t = lcm_module(), types()
    path = work / "controller.lcm"
    log = lcm.EventLog(str(path), "w", overwrite=True)
    misses, worst = 0, 0.0
    names = ("x", "y", "yaw", "vx", "vy", "omega", "throttle", "steering")
    for i in range(len(clog["step"])):
        step = int(clog["step"][i])
        utime = int(round(step * period * 1e6))
        m = t.state_estimate_t()
        m.utime, m.step = utime, step
        for n in names:
            setattr(m, n, float(clog[n][i]))
        m.cov_diag = [float(clog[f"P{k}"][i]) for k in range(8)]
        log.write_event(utime, "DDYN_STATE", m.encode())
        total = float(clog["loop_us"][i]) * 1e-6
        missed = total > period
        misses += int(missed)
        worst = max(worst, total)
        tm = t.loop_timing_t()
        tm.utime, tm.step, tm.period_s, tm.total_s, tm.deadline_s = utime, step, period, total, period
        tm.deadline_missed, tm.deadline_misses, tm.max_total_s = bool(missed), misses, worst
        tm.n_stages, tm.stage_names, tm.stage_s = 1, ["controller_step"], [total]
        log.write_event(utime, "DDYN_TIMING", tm.encode())
    log.close()
    return path


def lcm_log_summary(path: Path) -> dict:
    """Events per channel of an LCM log, its size, and the logger's receive-time span."""
    from ddyn.data.lcm_types import lcm_module
    lcm = lcm_module()
    counts: dict[str, int] = {}
    first = last = None
    log = lcm.EventLog(str(path), "r")
    for ev in log:
        counts[ev.channel] = counts.get(ev.channel, 0) + 1
        first = ev.timestamp if first is None else first
        last = ev.timestamp
    log.close()
    return {"path": str(path), "bytes": path.stat().st_size, "events": dict(sorted(counts.items())),
            "event_span_s": (last - first) * 1e-6 if first is not None else None}


def plot_lap(path: Path, track: Track, table: np.ndarray, work: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    traj = read_csv(work / "trajectory.csv")
    fig, ax = plt.subplots(figsize=(7, 6))
    for b in (track.left_bound, track.right_bound):
        bb = np.vstack([b, b[:1]])
        ax.plot(bb[:, 0], bb[:, 1], "k-", lw=1)
    rl = np.vstack([table[:, :2], table[:1, :2]])
    ax.plot(rl[:, 0], rl[:, 1], "--", color="0.6", lw=1, label="raceline")
    if traj and len(traj["x"]):
        v = np.hypot(traj["vx"], traj["vy"])
        sc = ax.scatter(traj["x"], traj["y"], c=v, s=3, cmap="viridis", label="car")
        fig.colorbar(sc, ax=ax, label="speed (m/s)")
        out = traj["clearance"] < 0
        if out.any():
            ax.plot(traj["x"][out], traj["y"][out], "rx", ms=4, label="footprint outside")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------- entry

def coefficients_from(which: str, vehicle: Vehicle) -> np.ndarray:
    """`true`, `reference_dataset`, or a JSON file {name: value} (missing names: the true value)."""
    if which in ("true", "reference_dataset"):
        return vehicle.coefficient_vector(which)
    p = Path(which)
    if not p.is_file():
        raise DdynError(f"--coeffs {which!r}: neither true/reference_dataset nor a JSON file")
    d = json.loads(p.read_text())
    d = d.get("coefficients", d)
    c = vehicle.true_vector().copy()
    for k, v in d.items():
        if k not in COEFF_NAMES:
            raise DdynError(f"{p}: unknown coefficient {k!r}")
        c[COEFF_NAMES.index(k)] = float(v)
    return c


def plant_track_dir(track: Track, out: Path) -> Path:
    """The folder the plant reads <name>_center/_inner/_outer.txt from: the shared data's for its
    own tracks, else the track as loaded here written into the run's folder (a user's files or a
    CSV with widths, a random track: the plant reads only the three-file format)."""
    shared = shared_data_dir() / "tracks"
    if is_named(track.name) and not track.files and (shared / f"{track.name}_center.txt").is_file():
        return shared  # putnam's are bounds in CSV (x, y, z): written like a user's track
    write_track(track, out / "track" / track.name)
    return out / "track"


def run_sil(spec: SilSpec, out: Path, export_dir: Path | None, where: str = "auto", kvm: bool | None = None,
            timeout: float = 600.0, title: str = "") -> dict:
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("plant_metrics.json", "controller_metrics.json", "trajectory.csv", "controller_log.csv",
                  "snapshot.json", "sil_metrics.json"):
        (out / stale).unlink(missing_ok=True)
    table = raceline_table(spec.track, spec.vehicle, spec.speed_scale, margin=spec.margin, line=spec.line)
    if len(table) > 1024:
        raise DdynError(f"raceline of {len(table)} points; the MPC holds at most 1024")
    if where == "inprocess" and spec.pacing != "frame":
        raise DdynError("--where inprocess has no clock of its own: only the frame pacing")
    if spec.forged_steering is not None and where != "inprocess":
        raise DdynError("--inject-forged-steering: the attacker is played by ddyn_sil_inprocess only (--where inprocess)")
    if spec.forged_steering is not None and "restart_plant" in spec.faults:
        raise DdynError("--inject-forged-steering: not with a restarting plant (in process)")
    bins = build_binaries(export_dir)
    key = dbw_test_key(bins) if spec.auth else None
    if spec.checkpoint_hash:
        require_network(bins / "ddyn_controller", spec.checkpoint_hash)
    track_dir = plant_track_dir(spec.track, out)
    use_host = where in ("host", "inprocess") or (where == "auto" and host_has_vcan())
    inside = "/out" if not use_host else str(out.resolve())
    key_seen = None if key is None else (str(key.resolve()) if use_host else GUEST_KEY_FILE)
    pc = plant_config(spec, "/sil/tracks" if not use_host else str(track_dir), inside, table, key_file=key_seen)
    (out / "plant.json").write_text(json.dumps(pc, indent=1) + "\n")
    (out / "plant_resume.json").unlink(missing_ok=True)
    if "restart_plant" in spec.faults:
        (out / "plant_resume.json").write_text(json.dumps(dict(pc, resume=f"{inside}/snapshot.json"), indent=1))
    (out / "controller.txt").unlink(missing_ok=True)  # the positional format of before: gone
    write_controller_files(spec, table, out, inside, key_file=key_seen)
    # the controller publishes its telemetry live over LCM (and lcm-logger records it) wherever it
    # runs as its own process in a build with LCM; otherwise its CSV log is converted (fallback)
    live = where != "inprocess" and controller_has_lcm(bins)
    (out / LCM_LOG_NAME).unlink(missing_ok=True)
    if where == "inprocess":
        run = run_inprocess(bins, out, spec.forged_steering)
    elif use_host:
        run = run_host(bins, out, "restart_plant" in spec.faults, lcm=live)
    else:
        if kvm is None:  # as scripts/vcan_guest: software emulation unless asked (KVM is not everywhere)
            kvm = os.environ.get("DDYN_VCAN_KVM", "0") == "1"
        run = run_guest(bins, out, track_dir, spec.track.name, kvm, timeout, lcm=live, key_file=key)
    metrics = summarise(out, spec, table, run)
    cm_path = out / "controller_metrics.json"
    if live:
        lcm_path = out / LCM_LOG_NAME
        if not lcm_path.is_file() or run["lcm"].get("logger_exit") != 0:
            raise DdynError(f"the live LCM log was not recorded (lcm-logger exit {run['lcm'].get('logger_exit')}, "
                            f"{lcm_path} {'exists' if lcm_path.is_file() else 'missing'}); see "
                            f"{out / ('guest.log' if 'guest' in run else 'lcm-logger.stdout')}")
        metrics["lcm"] = dict(source="live", publisher="ddyn_controller (c_src/linux/telemetry_lcm.c) over "
                              + run["lcm"]["url"], logger="lcm-logger " + ("in the guest" if "guest" in run else
                                                                             "on the host"),
                              **lcm_log_summary(lcm_path))
        if cm_path.is_file():  # absent when the controller was killed
            metrics["lcm"]["publisher_counts"] = json.loads(cm_path.read_text()).get("telemetry")
    else:
        lcm_path = write_lcm_log(out, spec.vehicle.sample_time)
        why = ("--where inprocess has no controller process" if where == "inprocess"
               else "the build has no LCM (DDYN_WITH_LCM=OFF)")
        metrics["lcm"] = dict(source="converted", publisher=f"FALLBACK: controller_log.csv converted on the host "
                              f"(train/sil/run.py write_lcm_log; {why})", logger=None,
                              **(lcm_log_summary(lcm_path) if lcm_path else {"path": None}))
    metrics["lcm_log"] = str(lcm_path) if lcm_path and lcm_path.is_file() else None
    (out / "sil_metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    laps = ", ".join(f"{t:.2f} s" for t in metrics["lap_times"]) or "none"
    plot_lap(out / "lap.png", spec.track, table, out,
             title or f"SIL {spec.vehicle.name} on {spec.track.name}: laps {laps}, "
                       f"{metrics['violations']} violation(s), {metrics['end_reason']}")
    return metrics


def make_random_track_line(vehicle, track, tname: str, line: str | None) -> None:
    """On a random track (`random:SEED`), the car's line of that kind computed once (out/racelines; None or
    "default": its own kind, "flying" / "standing": that lap's). Other tracks carry their lines."""
    if not tname.startswith("random:"):
        return
    from ddyn.control.mpc_tracks import optimum
    from ddyn.control.raceline import LINES, default_flying
    flying = LINES[line or "default"]
    optimum(vehicle.name, track, flying=default_flying(vehicle.name) if flying is None else flying)


def _run(args: argparse.Namespace) -> int:
    vehicle = load_vehicle(args.vehicle)
    track = open_track(args.track, vehicle.name)
    if args.road_grade is not None:
        from ddyn.model.road_grade import graded
        track = graded(track, args.road_grade)
    if args.line == "flying":
        # a random track's flying line made on demand, as the studies do (its own line is the track's)
        make_random_track_line(vehicle, track, args.track, args.line)
    export_dir = None
    fixed = None
    checkpoint_hash = None
    if args.model:
        from ddyn.learn import checkpoint
        ckpt = checkpoint.read(args.model)
        if ckpt["kind"] != "ddm":
            raise DdynError(f"{args.model} is a {ckpt['kind']} checkpoint: the car runs a DDM's guard network "
                            "(use --coeffs for fixed coefficients)")
        export_dir = export_network(Path(args.model), Path(args.out) / "export")
        checkpoint_hash = checkpoint.file_sha256(Path(args.model))  # the controller refuses another network
    else:
        fixed = coefficients_from(args.coeffs, vehicle)
    delays, effects_from = parse_controller_delays(args.controller_delays), None
    lag = parse_controller_lag(args.controller_lag)
    from ddyn.sil.effects import DOWNFORCE_RANGE, MASS_OFFSET_RANGE
    mass, downforce = args.controller_mass_offset, args.controller_downforce
    if not MASS_OFFSET_RANGE[0] <= mass <= MASS_OFFSET_RANGE[1]:
        raise DdynError(f"--controller-mass-offset: {mass:g} is outside [{MASS_OFFSET_RANGE[0]:g}, "
                        f"{MASS_OFFSET_RANGE[1]:g}] (the controller's control.mass_offset)")
    if not DOWNFORCE_RANGE[0] <= downforce <= DOWNFORCE_RANGE[1]:
        raise DdynError(f"--controller-downforce: {downforce:g} is outside [{DOWNFORCE_RANGE[0]:g}, "
                        f"{DOWNFORCE_RANGE[1]:g}] (the controller's control.downforce, s^2/m^2)")
    if args.effects_from:
        from ddyn.sil.effects import controller_effects
        if delays or lag or args.controller_bank or args.controller_grade or mass or downforce:
            raise DdynError("--effects-from and --controller-delays/--controller-lag/--controller-bank/"
                            "--controller-grade/--controller-mass-offset/--controller-downforce: give one (the "
                            "diagnosis sets the delays, the lag, the mass offset, the downforce, the bank and the "
                            "grade)")
        fx = controller_effects(args.effects_from, vehicle.sample_time)
        delays, lag, mass, effects_from = dict(fx.delays), dict(fx.lag), fx.mass_offset, fx.summary()
        downforce = fx.downforce
        for line in fx.lines() or ["nothing to apply"]:
            print(f"sil: effects from {args.effects_from}: {line}")
    spec = SilSpec(vehicle=vehicle, track=track, coeffs_plant=vehicle.true_vector(), coeffs_controller=fixed,
                   nominal=vehicle.true_vector(), laps=args.laps, vx0=args.vx0,
                   effects=parse_effects(args.effects), faults=parse_faults(args.faults),
                   noise_scale=args.noise, speed_scale=args.speed_scale, margin=args.margin, line=args.line,
                   realtime=args.realtime, max_time=args.max_time, seed=args.seed, throttle=args.throttle,
                   pid_gains=args.pid_gains, checkpoint_hash=checkpoint_hash, pacing=args.pacing, auth=args.auth,
                   forged_steering=args.inject_forged_steering,
                   controller_delays=delays, controller_lag=lag, controller_mass_offset=mass,
                   controller_downforce=downforce, effects_from=effects_from, road_bank=not args.flat_road, controller_bank=args.controller_bank,
                   controller_grade=args.controller_grade)
    if args.config_only:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        table = raceline_table(spec.track, spec.vehicle, spec.speed_scale, margin=spec.margin, line=spec.line)
        path = write_controller_files(spec, table, out, str(out.resolve()))
        control = json.loads(path.read_text())["control"]
        print(f"sil: wrote {path} and {out / RACELINE_CSV} (control.delay {control.get('delay', 'none')}, "
              f"control.lag {control.get('lag', 'none')}, control.mass_offset {control.get('mass_offset', 0)}, "
              f"control.downforce {control.get('downforce', 0)}, "
              f"control.bank {control.get('bank', False)}, control.grade {control.get('grade', False)}); not driven "
              "(--config-only)")
        return 0
    m = run_sil(spec, Path(args.out), export_dir, where=args.where, kvm=args.kvm, timeout=args.timeout)
    laps = ", ".join(f"{t:.3f} s" for t in m["lap_times"]) or "none"
    ctl = m["controller"] or {}
    lu = ctl.get("loop_us", {})
    print(f"sil: {m['run']['where']}: {m['end_reason']}; laps {laps}; violations {m['violations']}; "
          f"tracking error mean {m['tracking_error']['mean'] or float('nan'):.3f} m; controller loop "
          f"median {lu.get('median', float('nan')):.0f} us, p99 {lu.get('p99', float('nan')):.0f} us, "
          f"max {lu.get('max', float('nan')):.0f} us, {ctl.get('deadline_misses')} deadline misses")
    if m.get("attack"):
        a = m["attack"]
        print(f"sil: attack: {a['forged_commands_sent']} forged steering commands sent, "
              f"{a['refused_by_the_dbw_unit']} refused by the DBW unit (frame authentication "
              f"{'on' if (m['auth']['plant'] or {}).get('enabled') else 'off'})")
    print(f"sil: wrote {Path(args.out) / 'sil_metrics.json'} and lap.png")
    return 0


def add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle", default="orca_1_43", help="vehicle file name (default: %(default)s)")
    p.add_argument("--track", default="ethzMobil", help="track (default: %(default)s)")
    p.add_argument("--vx0", type=float, default=None,
                   help="initial speed, m/s (default: 0.1, or a flying line's rolling start at its reference speed)")
    p.add_argument("--noise", type=float, default=1.0, help="sensor noise scale (default: %(default)s)")
    p.add_argument("--speed-scale", type=float, default=None,
                   help="reference speed = raceline speed x this (default 1.0: the vehicle's own time-optimal "
                        "line, train/racelines/, is drivable at full speed; or the vehicle's, train/vehicles/mpc/)")
    p.add_argument("--margin", type=float, default=None,
                   help="room the MPC keeps between the car's side and the bounds, m (default: 0.03, or the "
                        "vehicle's)")
    p.add_argument("--line", choices=("default", "flying", "standing"), default=None,
                   help="the racing line: the vehicle's own (default), or its flying-lap line (for --laps > 1: the "
                        "laps after the first start at speed; on a random:SEED track made once when missing) or "
                        "standing-start line")
    p.add_argument("--realtime", type=float, default=0.0,
                   help="pace the plant at this multiple of real time (default 0: lock-step with the controller)")
    p.add_argument("--max-time", type=float, default=None, help="simulated seconds before giving up")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--where", choices=("auto", "host", "guest", "inprocess"), default="auto",
                   help="host vcan0, qemu guest, auto (host if it has vcan), or inprocess (one process, "
                        "frames through memory: not the SIL path; host-native timings)")
    p.add_argument("--kvm", action=argparse.BooleanOptionalAction, default=None,
                   help="qemu with KVM (default: DDYN_VCAN_KVM=1, else software emulation)")
    p.add_argument("--timeout", type=float, default=900.0, help="wall seconds for the guest run")


def register(subparsers) -> None:
    p = subparsers.add_parser("run", help="software-in-the-loop laps: plant and controller processes over vcan")
    who = p.add_mutually_exclusive_group()
    who.add_argument("--model", help="DDM checkpoint: the controller runs its guard network")
    who.add_argument("--coeffs", default="true",
                     help="fixed coefficients instead of a network: true, reference_dataset or a JSON file")
    p.add_argument("--laps", type=int, default=1)
    p.add_argument("--effects", help=f"plant effects, key=value ({', '.join(PLANT_EFFECTS)})")
    p.add_argument("--controller-delays", metavar="steer=S,throttle=S",
                   help="actuation delays the controller compensates, seconds (controller.json control.delay): its "
                        "filter predicts with the command acting on the car, its MPC plans from the state its new "
                        "command acts in; e.g. with --effects steer_delay=0.04 give steer=0.04 (default: none; at "
                        "most 6 control periods, DDYN_CTRL_MAX_DELAY_STEPS)")
    p.add_argument("--controller-lag", metavar="steer=S",
                   help="the steering lag the controller compensates, seconds: the time constant of the acting "
                        "steering's first-order lag behind its set-point (controller.json control.lag): its filter "
                        "predicts with the acting steering, its MPC plans from it and its first command inverts the "
                        "lag; e.g. with --effects steer_lag=0.05 give steer=0.05 (default: none)")
    p.add_argument("--controller-mass-offset", metavar="F", type=float, default=0.0,
                   help="the mass offset the controller knows: the car's mass is (1 + F) times the model's "
                        "(controller.json control.mass_offset, in [-0.5, 1]): its filter, pipe and MPC use the "
                        "coefficients scaled for that mass, and with F > 0 the line's speeds times 1 / sqrt(1 + F); "
                        "e.g. with --effects mass_offset=0.1 give 0.1 (default: 0)")
    p.add_argument("--controller-downforce", metavar="K", type=float, default=0.0,
                   help="the downforce the controller knows, s^2/m^2: the tyres' peak forces are 1 + K vx^2 times "
                        "the model's (controller.json control.downforce, in [0, 0.5]): its filter, pipe and MPC "
                        "stages use the coefficients of their own speed; the line's speeds are not raised; e.g. "
                        "with --effects downforce=0.02 give 0.02 (default: 0)")
    p.add_argument("--effects-from", metavar="D", default=None,
                   help="the controller's actuation delays, steering lag and road bank from a diagnosis (`ddyn gap "
                        "diagnose --out D`: the folder or its diagnosis.json): steer_delay -> control.delay.steering, "
                        "throttle_delay -> control.delay.throttle, steer_lag -> control.lag.steering, bank_angle or "
                        "bank_profile -> control.bank and raceline.csv's bank column (the profile at each row's track "
                        "position), grade or grade_profile -> control.grade and the grade column likewise, "
                        "mass_offset -> control.mass_offset and downforce -> control.downforce (each "
                        "when named first), every other effect named and not applied; recorded in controller.json (effects: "
                        "path, sha256; the controller refuses the file if control.delay, control.lag or the bank is "
                        "edited) and sil_metrics.json")
    p.add_argument("--controller-bank", action="store_true",
                   help="the controller knows the road's bank (controller.json control.bank): the track's own bank "
                        "profile (--track oval) at each raceline point, raceline.csv's 6th column; its filter and "
                        "MPC predict with the lateral gravity g sin(bank) at their track positions (default: off, "
                        "a flat road)")
    p.add_argument("--road-grade", metavar="A", type=float, default=None,
                   help="give the track hills: the road's grade (rad, + uphill) is A sin(2 pi 2 s / L) along the lap "
                        "(ddyn.model.road_grade; 0 < A <= 0.3), the world's, driven by the plant (plant.json "
                        "road_grade) (default: a level road)")
    p.add_argument("--controller-grade", action="store_true",
                   help="the controller knows the road's grade (controller.json control.grade): the track's own "
                        "grade profile (--road-grade) at each raceline point, raceline.csv's grade column; its filter "
                        "and MPC predict with the longitudinal gravity -g sin(grade) at their track positions "
                        "(default: off, a level road)")
    p.add_argument("--flat-road", action="store_true",
                   help="drive a banked track (--track oval) flat: the plant without the track's own bank (default: "
                        "a track with a bank profile banks the plant's road, plant.json road_bank)")
    p.add_argument("--config-only", action="store_true",
                   help="write controller.json and raceline.csv into --out and stop (no drive): e.g. the "
                        "configuration made from --effects-from D")
    p.add_argument("--faults", help="faults, key=value: drop=FRACTION delay=SECONDS corrupt=FRACTION "
                                    "silent=imu|gnss|gnss_position|gnss_heading|wheel_speeds|steering silent_at=S "
                                    "kill_controller=S restart_plant=S")
    p.add_argument("--out", default="out/sil", help="output directory (default: %(default)s)")
    p.add_argument("--pacing", choices=("frame", "timer"), default="frame",
                   help="the controller's pacing (docs/deploy.md): a period per position frame (default), or "
                        "absolute-deadline periods on its own clock (needs --realtime 1)")
    p.add_argument("--throttle", choices=("mpc", "pid"), default="mpc",
                   help="who sets the throttle: the MPC (default) or a PID on the speed error, the MPC then "
                        "planning only the steering (docs/controller.md)")
    p.add_argument("--pid-gains", type=parse_gains, default=None, metavar="KP,KI,KD[,PREVIEW]",
                   help="PID gains for --throttle pid, and the preview time (s) of its reference speed, 0 if "
                        "not given (default: the controller's, docs/sil.md)")
    p.add_argument("--auth", action="store_true",
                   help="authenticate every frame (AUTOSAR SecOC style, docs/can.md) on both sides with the build's "
                        "fixed TEST key (default: off, unless DDYN_DBW_KEY_FILE names a key for host runs)")
    p.add_argument("--inject-forged-steering", type=parse_window, default=None, metavar="T0:T1",
                   help="an attacker on the bus from T0 to T1 s of simulated time: after every command a forged one "
                        "(full left, full throttle, valid counter and CRC, no key); --where inprocess only")
    add_common(p)
    p.set_defaults(func=_run)


def parse_gains(text: str) -> tuple[float, float, float, float]:
    """`KP,KI,KD[,PREVIEW]` (numbers >= 0; preview 0 when left out) for --pid-gains."""
    try:
        g = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected KP,KI,KD[,PREVIEW]") from None
    if len(g) not in (3, 4) or not all(math.isfinite(v) and v >= 0.0 for v in g):
        raise argparse.ArgumentTypeError(f"{text!r}: expected three or four finite numbers >= 0 (KP,KI,KD[,PREVIEW])")
    return g if len(g) == 4 else g + (0.0,)
