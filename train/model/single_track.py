"""The dynamic single-track vehicle model, written once.

Table I of the Deep Dynamics paper (Chrosniak et al., 2024), as the BayesRace
simulator implements it. State (8): x, y, yaw, vx, vy, omega, throttle T, steering
delta; input (2): dT, ddelta (rates; T and delta are integrated states). Unknown
coefficients (17, order COEFF_NAMES): Pacejka B, C, D, E, G (horizontal shift),
K (vertical shift) per axle, drivetrain Cm1, Cm2, Cr0, Cd, and yaw inertia Iz.
Known: mass m, CoG-to-axle distances lf, lr.

    alpha_f = delta - atan2(omega lf + vy, vx*) + Gf
    alpha_r =        atan2(omega lr - vy, vx*) + Gr
    F_y     = K + D sin(C atan(B a - E (B a - atan(B a))))     per axle, a = alpha
    F_rx    = (Cm1 - Cm2 vx) T - Cr0 - Cd vx^2                 drivetrain "papers" (default)
    F_rx    = (Cm1 - Cm2 vx) T+ + Kb T- - Cr0 - Cd vx^2         drivetrain "powertrain"
              (T+ = max(T, 0), T- = min(T, 0); Kb the vehicle file's known brake_gain)
    F_rx    = min(Cm1, T+ Cm2 / vx*) + Kb T- - Cr0 - Cd vx^2       drivetrain "power_limited"
              (the slots' meanings change: Cm1 the traction cap in N, Cm2 the wheel power in W at full
              pedal; vx* = max(|vx|, v_min))
    dvx     = (F_rx - F_fy sin(delta)) / m + vy omega
    dvy     = (F_ry + F_fy cos(delta)) / m - vx omega
    domega  = (F_fy lf cos(delta) - F_ry lr) / Iz

Low speed. The slip angles divide lateral by longitudinal speed. Instead of
dividing, the model uses atan2 with the denominator vx* = max(|vx|, v_min), where
v_min is a vehicle constant (see the vehicle files). For |vx| >= v_min this is
exactly the paper's atan((omega lf + vy)/vx) for forward motion (the BayesRace
code uses atan2(., |vx|) as well); below v_min the denominator is held at v_min so
slip angles stay finite and bounded by pi/2, and every backend returns the same
finite values and gradients at vx = 0. The model is not meant to be accurate
there (tyre slip theory fails at standstill); it is only meant to be defined.

Every function takes a MathNamespace `ns` (ddyn.model.mathns) and scalar-like
components (numpy arrays, torch tensors or CasADi SX), so the same code serves
simulation, training and code generation. Nothing else re-types these equations.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Sequence

from ddyn.model.mathns import MathNamespace

STATE_NAMES = ("x", "y", "yaw", "vx", "vy", "omega", "throttle", "steering")
INPUT_NAMES = ("dthrottle", "dsteering")
COEFF_NAMES = (
    "Bf", "Cf", "Df", "Ef", "Gf", "Kf",
    "Br", "Cr", "Dr", "Er", "Gr", "Kr",
    "Cm1", "Cm2", "Cr0", "Cd", "Iz",
)
N_STATE, N_INPUT, N_COEFF = len(STATE_NAMES), len(INPUT_NAMES), len(COEFF_NAMES)
# indices of the velocity channels that the networks predict
VELOCITY_INDEX = (3, 4, 5)


# The drivetrain forms a vehicle file can choose ("drivetrain"). "papers": the Deep Dynamics papers'
# F_rx = (Cm1 - Cm2 vx) T - Cr0 - Cd vx^2 for both signs of T. "powertrain": a real car whose negative
# input is brake pressure (the RACECAR logs' -brake/2757.9 kPa) acting through its own gain, not
# through the engine's Cm1 - Cm2 vx: on the AV-21's Putnam log one gain for both pedals explains
# R^2 = 0.469 of the one-step vx change on the training part, a separate brake gain 0.548
# (`ddyn study drivetrain`, docs/model.md). "power_limited" (issue 36): the powertrain's brake, but a
# drive whose extrapolation in speed is physical: the pedal's share of the wheel power over speed
# (T+ Cm2 / vx*, Cm2 in W at full pedal), at most a traction cap (Cm1, N); Cr0 (N) is the resistance at
# zero pedal, Cd (kg/m) the aero drag. The same 17 coefficient slots, so networks, guard, export and codegen
# keep their shapes; the slots' meanings and ranges are documented in the vehicle file
# (train/vehicles/av21_power.json).
DRIVETRAINS = ("papers", "powertrain", "power_limited")
# the forms with a known brake gain below zero throttle (KnownParams.brake_gain)
BRAKE_GAIN_FORMS = ("powertrain", "power_limited")


class KnownParams(NamedTuple):
    """Quantities measured on the car, not estimated: mass (kg), lf, lr (m), v_min (m/s); the
    drivetrain form (DRIVETRAINS) and, for the BRAKE_GAIN_FORMS, the brake gain (N per unit of brake input)."""

    mass: float
    lf: float
    lr: float
    v_min: float
    drivetrain: str = "papers"
    brake_gain: float = 0.0


class Forces(NamedTuple):
    alpha_f: Any
    alpha_r: Any
    Ffy: Any
    Fry: Any
    Frx: Any


def pacejka(ns: MathNamespace, alpha, B, C, D, E, K):
    """Simplified Pacejka magic formula with vertical shift K (horizontal shift is in alpha)."""
    Ba = B * alpha
    return K + D * ns.sin(C * ns.atan(Ba - E * (Ba - ns.atan(Ba))))


def slip_angles(ns: MathNamespace, vx, vy, omega, delta, Gf, Gr, p: KnownParams):
    vx_star = ns.fmax(ns.abs(vx), p.v_min)
    alpha_f = delta - ns.atan2(omega * p.lf + vy, vx_star) + Gf
    alpha_r = ns.atan2(omega * p.lr - vy, vx_star) + Gr
    return alpha_f, alpha_r


def drivetrain_force(vx, T, Cm1, Cm2, Cr0, Cd, ns: MathNamespace | None = None, p: KnownParams | None = None):
    """Longitudinal force at the rear axle from throttle T: the papers' form unless p chooses
    "powertrain" or "power_limited" (then ns is needed for max). The papers' expression is kept as it was,
    term for term, so its results are bit-identical to before the choice existed."""
    if p is None or p.drivetrain == "papers":
        return (Cm1 - Cm2 * vx) * T - Cr0 - Cd * vx * vx
    if p.drivetrain not in DRIVETRAINS:
        raise ValueError(f"unknown drivetrain {p.drivetrain!r}; expected one of {', '.join(DRIVETRAINS)}")
    if ns is None:
        raise ValueError(f"the {p.drivetrain} drivetrain needs a math namespace (for max)")
    T_drive = ns.fmax(T, 0.0)
    if p.drivetrain == "powertrain":
        return (Cm1 - Cm2 * vx) * T_drive + p.brake_gain * (T - T_drive) - Cr0 - Cd * vx * vx
    # power_limited: the pedal asks for a share of the wheel power, T+ Cm2 / vx*, and the tyres deliver at most
    # the traction cap Cm1 of it. The cap bounds the force delivered, not the full-pedal envelope: capping the
    # envelope (min(Cm1, Cm2 / vx*) T+, as before) made the force's slope in the pedal flat below Cm2 / Cm1,
    # where the Putnam log's slope keeps growing as 1 / vx (about 21 kN per unit of pedal at 7.5 m/s), and
    # held the cap on its bound. min(a, b) is written a - max(a - b, 0): every backend needs only fmax
    power_force = T_drive * Cm2 / ns.fmax(ns.abs(vx), p.v_min)
    drive = power_force - ns.fmax(power_force - Cm1, 0.0)
    return drive + p.brake_gain * (T - T_drive) - Cr0 - Cd * vx * vx


def forces(ns: MathNamespace, state: Sequence, coeffs: Sequence, p: KnownParams) -> Forces:
    _, _, _, vx, vy, omega, T, delta = state
    Bf, Cf, Df, Ef, Gf, Kf, Br, Cr, Dr, Er, Gr, Kr, Cm1, Cm2, Cr0, Cd, _ = coeffs
    alpha_f, alpha_r = slip_angles(ns, vx, vy, omega, delta, Gf, Gr, p)
    Ffy = pacejka(ns, alpha_f, Bf, Cf, Df, Ef, Kf)
    Fry = pacejka(ns, alpha_r, Br, Cr, Dr, Er, Kr)
    Frx = drivetrain_force(vx, T, Cm1, Cm2, Cr0, Cd, ns, p)
    return Forces(alpha_f, alpha_r, Ffy, Fry, Frx)


def rigid_body(ns: MathNamespace, state: Sequence, inputs: Sequence, Ffy, Fry, Frx, Iz, p: KnownParams) -> tuple:
    """State derivative given the axle forces: the single-track rigid body and the input integrators."""
    _, _, yaw, vx, vy, omega, _, delta = state
    dT, ddelta = inputs
    cos_yaw, sin_yaw = ns.cos(yaw), ns.sin(yaw)
    cos_d, sin_d = ns.cos(delta), ns.sin(delta)
    return (
        vx * cos_yaw - vy * sin_yaw,
        vx * sin_yaw + vy * cos_yaw,
        omega,
        (Frx - Ffy * sin_d) / p.mass + vy * omega,
        (Fry + Ffy * cos_d) / p.mass - vx * omega,
        (Ffy * p.lf * cos_d - Fry * p.lr) / Iz,
        dT,
        ddelta,
    )


def derivatives(ns: MathNamespace, state: Sequence, inputs: Sequence, coeffs: Sequence,
                p: KnownParams) -> tuple:
    """Continuous-time state derivative (8 components) of the single-track model."""
    f = forces(ns, state, coeffs, p)
    return rigid_body(ns, state, inputs, f.Ffy, f.Fry, f.Frx, coeffs[16], p)
