"""The one vehicle model against code this project did not write: CommonRoad's vehicle models (PyPI
commonroad-vehicle-models). The Pacejka E, G, K terms against its magic formula with horizontal and
vertical shift, and the AV-21's single-track dynamics against its linear single-track model at small
slip, where the two must agree (DYN-PP-ETHZ, the one outside reference before, has E = G = K = 0)."""
from __future__ import annotations

import math

import numpy as np
from vehiclemodels.utils.tire_model import formula_lateral
from vehiclemodels.utils.tireParameters import TireParameters
from vehiclemodels.vehicle_dynamics_st import vehicle_dynamics_st
from vehiclemodels.vehicle_parameters import setup_vehicle_parameters

from ddyn.model import mathns, vehicle
from ddyn.model.backends import derivatives_numpy
from ddyn.model.single_track import COEFF_NAMES, pacejka


def _commonroad_tyre(B, C, D, E, G, K, Fz):
    """CommonRoad's lateral magic formula with our B, C, D, E, G, K: D = mu Fz, B = K_y / (C D),
    horizontal shift p_hy1 = G, vertical shift p_vy1 Fz = K. Its shifts carry sign(camber): a camber
    of +1e-12 rad turns them on without changing anything else (p_hy3 = p_vy3 = p_dy3 = 0)."""
    p = TireParameters()
    p.p_cy1, p.p_dy1, p.p_ey1 = C, D / Fz, E
    p.p_ky1 = B * C * D / Fz
    p.p_hy1, p.p_hy3, p.p_vy1, p.p_vy3, p.p_dy3 = G, 0.0, K / Fz, 0.0, 0.0
    return lambda alpha: formula_lateral(alpha, 1e-12, Fz, p)[0]


def test_pacejka_with_e_g_k_matches_commonroads_magic_formula():
    rng = np.random.default_rng(2026)
    for name in ("orca_1_43", "av21"):
        v = vehicle.load(name)
        c = dict(zip(COEFF_NAMES, v.true_vector()))
        fz = v.known.mass * 9.81 / 2
        for axle in "fr":
            B, C, D, E, G, K = (c[k + axle] for k in "BCDEGK")
            assert E != 0 and G != 0 and K != 0, "the check is about E, G, K"
            theirs = _commonroad_tyre(B, C, D, E, G, K, fz)
            alpha = rng.uniform(-0.3, 0.3, 200)
            ours = pacejka(mathns.NUMPY, alpha + G, B, C, D, E, K)      # the model puts G into the slip angle
            ref = np.array([theirs(a) for a in alpha])
            assert np.allclose(ours, ref, rtol=1e-12, atol=1e-12 * abs(D)), (name, axle)
            # and the terms matter: dropping any of them is seen
            for bad in (pacejka(mathns.NUMPY, alpha + G, B, C, D, 0.0, K), pacejka(mathns.NUMPY, alpha, B, C, D, E, K),
                        pacejka(mathns.NUMPY, alpha + G, B, C, D, E, 0.0)):
                assert np.max(np.abs(bad - ref)) > 1e-6 * abs(D)


def test_av21_single_track_matches_commonroads_at_small_slip():
    """Yaw and side-slip rates of the AV-21 (its mass, lf, lr, Iz) against CommonRoad's single-track
    model with linear tyres, at small slip where Pacejka is linear: front and rear cornering stiffness
    B C D per normal load equal (CommonRoad uses one tyre for both axles), no longitudinal force."""
    v = vehicle.load("av21")
    m, lf, lr = v.known.mass, v.known.lf, v.known.lr
    g, mu, bc = 9.81, 1.6, 12.0                       # friction and B C: a stiff racing tyre
    c = dict(zip(COEFF_NAMES, v.true_vector()))
    c.update(Bf=bc / 1.45, Cf=1.45, Df=mu * m * g * lr / (lf + lr), Ef=-0.5, Gf=0.0, Kf=0.0,
             Br=bc / 1.45, Cr=1.45, Dr=mu * m * g * lf / (lf + lr), Er=-0.5, Gr=0.0, Kr=0.0,
             Cm1=0.0, Cm2=0.0, Cr0=0.0, Cd=0.0)
    coeffs = np.array([c[k] for k in COEFF_NAMES])
    p = setup_vehicle_parameters(vehicle_id=2)
    p.m, p.a, p.b, p.I_z = m, lf, lr, c["Iz"]
    p.tire.p_dy1, p.tire.p_ky1 = mu, -bc * mu          # C_S = -p_ky1 / p_dy1 = B C per unit normal load
    p.steering.min, p.steering.max, p.steering.v_min, p.steering.v_max = -1.0, 1.0, -10.0, 10.0
    p.longitudinal.v_max, p.longitudinal.a_max = 100.0, 100.0
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(50):
        speed, beta, yaw_rate, delta = rng.uniform(15, 60), rng.uniform(-2e-3, 2e-3), rng.uniform(-2e-3, 2e-3), \
            rng.uniform(-2e-3, 2e-3)
        vx, vy = speed * math.cos(beta), speed * math.sin(beta)
        ours = derivatives_numpy(np.array([0, 0, 0, vx, vy, yaw_rate, 0.0, delta]), np.zeros(2), coeffs, v.known)
        d_vx, d_vy, d_omega = ours[3], ours[4], ours[5]
        d_beta = (vx * d_vy - vy * d_vx) / (vx ** 2 + vy ** 2)
        theirs = vehicle_dynamics_st([0, 0, delta, speed, 0, yaw_rate, beta], [0.0, 0.0], p)
        scale_omega = abs(theirs[5]) + 1e-3 * abs(yaw_rate) + 1e-6
        scale_beta = abs(theirs[6]) + 1e-3 * abs(yaw_rate) + 1e-6
        worst = max(worst, abs(d_omega - theirs[5]) / scale_omega, abs(d_beta - theirs[6]) / scale_beta)
    # cubic slip terms and the small-angle forms differ at the 1e-5 level for slips of 1e-3 rad
    assert worst < 1e-3, worst
    # a wrong inertia is seen: the check can fail
    wrong = coeffs.copy()
    wrong[COEFF_NAMES.index("Iz")] *= 1.1
    ours = derivatives_numpy(np.array([0, 0, 0, 30.0, 0.03, 1e-3, 0.0, 1e-3]), np.zeros(2), wrong, v.known)
    theirs = vehicle_dynamics_st([0, 0, 1e-3, math.hypot(30.0, 0.03), 0, 1e-3, math.atan2(0.03, 30.0)], [0.0, 0.0], p)
    assert abs(ours[5] - theirs[5]) > 0.05 * abs(theirs[5])
