"""The second independent plant: CommonRoad's multi-body model (PyPI commonroad-vehicle-models).

Why: the single-track drift model of ddyn.plants.commonroad_st shares the project model's structure (one
tyre per axle, a rigid body in the plane). `vehiclemodels.vehicle_dynamics_mb` does not: 29 states, a sprung
mass that rolls and pitches on springs and dampers over two unsprung axles, four wheels each with its own spin,
load and combined-slip Pacejka tyre, so lateral load transfer and roll steer act as on a real car. A diagnosis
that holds on it holds on more than one other author's simplification.

Everything around the right-hand side is commonroad_st.make_log (the driver, the DBW hold at its rate,
the effects, the noise, the log format); this module supplies the model (MbModel) and the additions the
multi-body model needs in its own coordinates:
  - mass_offset scales every mass and inertia of parameters_vehicle2 (sprung, unsprung, roll, pitch, yaw);
  - downforce k: a vertical force m g k v^2 on the sprung mass at its centre of gravity (the tyre loads grow by
    1 + k v^2 once the springs settle; no inertia is added);
  - drag and rolling resistance along the body's x; bank and grade as gravity on every mass (the sprung mass
    and both unsprung axles move sideways separately in this model);
  - the logged roll channel (LogSettings.roll_channel) is the road's bank plus the body's own roll state
    (x[6]: negative, out of the turn, in a left turn), not a fixed roll gradient.

State mapping (CommonRoad mb -> canonical): x, y = x[0], x[1]; yaw = x[4]; vx = x[3] and vy = x[10] (the
sprung mass's body-frame velocities); omega = x[5]. Wheel angle x[2]; body roll x[6] (extras true_body_roll).

Integration: RK4 at commonroad_st.PLANT_RATE (1 kHz), as the single-track plant; about 27 us per
right-hand side in pure Python, so a 60 s log costs about 7-10 s (the step's convergence check:
convergence()).
"""
from __future__ import annotations

import math

from ddyn.plants import commonroad_st as CP
from ddyn.errors import CarLostError

try:
    from vehiclemodels import vehicle_dynamics_mb as _mb_module
    from vehiclemodels.init_mb import init_mb
except ImportError:  # pragma: no cover - CP.require_commonroad() says so
    _mb_module = None

# the vehicle file the MB plant's logs are diagnosed with (the parameters mapped onto the single-track model)
NOMINAL_VEHICLE = CP.NOMINAL_VEHICLE.parent / "commonroad_vehicle2_mb.json"
MASSES = ("m", "m_s", "m_uf", "m_ur", "I_z", "I_Phi_s", "I_y_s", "I_xz_s", "I_uf", "I_ur")


class MbModel:
    """CommonRoad's multi-body model for commonroad_st.make_log(model=MbModel())."""

    name = "mb"
    label = "commonroad vehicle_dynamics_mb"
    tyres = 4
    rolls = True                       # a body roll state (x[6]): the roll channel's lean

    def scale_mass(self, p, factor: float) -> None:
        for k in MASSES:
            setattr(p, k, getattr(p, k) * factor)

    def init(self, px, py, delta0, v0, psi0, p) -> list:
        return init_mb([px, py, delta0, v0, psi0, 0.0, 0.0], p)

    def observe(self, x) -> tuple:
        """(X, Y, wheel angle, yaw, vx, vy, yaw rate, body roll)"""
        return x[0], x[1], x[2], x[4], x[3], x[10], x[5], x[6]

    def clamp(self, x) -> None:
        for i in range(23, 27):        # as CommonRoad: no negative wheel spin
            x[i] = max(x[i], 0.0)

    def speed(self, x) -> float:
        return math.hypot(x[3], x[10])

    def rhs(self, x, u, env) -> tuple[list, list]:
        p = env.p
        try:
            if env.hook is None:
                f, kin = _mb_module.vehicle_dynamics_mb(list(x), u, p), []
            else:
                f, kin = env.hook.call(_mb_module.vehicle_dynamics_mb, list(x), u, p, env.alpha_eff)
        except ArithmeticError as e:    # a spinning car reaches a wheel speed of zero (the package divides by it)
            raise CarLostError(f"the multi-body plant diverged (the car spun: vx {x[3]:.2f}, vy {x[10]:.2f} m/s): {e}")
        vx = x[3]
        v2 = vx * vx + x[10] * x[10]
        if env.downforce:
            # z points down in this model (dz/dt = g - sum of the upward forces / m_s)
            f[12] += CP.G * env.downforce * v2 * p.m / p.m_s
        c = env.consts
        f[3] += -(c.drag * v2 + (c.rolling if vx > 0.5 else 0.0)) / p.m - CP.G * math.sin(env.grade)
        if env.bank:
            a_y = CP.G * math.sin(env.bank)
            f[10] += a_y
            f[15] += a_y
            f[20] += a_y
        return f, kin


def make_log(track="putnam", effects: CP.PlantEffects = CP.PlantEffects(), seed: int = 0,
             settings: CP.LogSettings = CP.LogSettings(), nominal=None, params: str = "vehicle2"):
    """One log of the multi-body plant (commonroad_st.make_log with MbModel) with the CommonRoad parameter set
    params (commonroad_st.PARAMETER_SETS); nominal None: commonroad_st.nominal_vehicle("mb", params)
    (NOMINAL_VEHICLE for vehicle2)."""
    CP.check_parameter_set(params)
    CP.require_commonroad()
    return CP.make_log(track, effects, seed, settings, nominal, model=MbModel(), params=params)


def convergence(duration: float = 10.0, seed: int = 3, rates=(500.0, 1000.0, 2000.0)) -> dict:
    """The noise-free log at several plant rates: the largest difference of each logged channel from the
    finest rate's (the step size check behind PLANT_RATE), and the seconds a 60 s log takes at each rate."""
    import numpy as np

    import time

    out, ref = {}, None
    logs, seconds = {}, {}
    for r in sorted(rates, reverse=True):
        t0 = time.perf_counter()
        ds = make_log("putnam", CP.PlantEffects(), seed, CP.LogSettings(duration=duration, noise_scale=0.0,
                                                                         plant_rate=r))
        seconds[r] = time.perf_counter() - t0
        logs[r] = ds.states[:, :6]
    ref = logs[max(rates)]
    for r, s in logs.items():
        out[r] = {"seconds_per_60s_log": seconds[r] * 60.0 / duration}
        if r != max(rates):
            out[r] |= {c: float(np.max(np.abs(s[:, i] - ref[:, i]))) for i, c in enumerate(CP.NOISY)}
    return out
