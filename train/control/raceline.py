"""`ddyn mpc raceline`: the time-optimal standing-start lap of a vehicle on a track (CasADi + IPOPT).

Why: the racing lines in the shared data were computed by another tool for another car model. On
ETHZMobil the data's line asks for 4.9 m/s where the ORCA drivetrain tops out near 4.3 m/s at full
throttle, and for accelerations it cannot make, so an MPC that tracks it lags its own reference all
lap. This module computes the line THIS vehicle model can drive: the minimum-time lap from vx0,
with the vehicle's input and rate limits, the car's footprint kept `margin` inside the bounds.

The optimal control problem (direct multiple shooting, free final time T, N equal intervals):

    min  T + reg * sum |u_k|^2 * T / N
    s.t. X_{k+1} = RK4(X_k, u_k, T/N)      with the vehicle's rk4_substeps (the plant's integrator)
         state X = (s, n, mu, vx, vy, omega, throttle, steering): the model's states with the pose
         in the centre line's frame: progress s, lateral offset n (left +), heading error mu;
             ds/dt  = (vx cos mu - vy sin mu) / (1 - n kappa(s))
             dn/dt  = vx sin mu + vy cos mu
             dmu/dt = omega - kappa(s) ds/dt
         the other six derivatives are ddyn.model.single_track.derivatives (the one vehicle model);
         input and rate limits of the vehicle file; vx >= vx_min;
         the footprint's four corners (n +- L/2 sin mu +- W/2 cos mu) inside the bounds - margin;
         start: s = 0, vx = vx0, vy = omega = 0, throttle = steering = 0; end: s = L;
         n and mu equal at start and end (the line closes).

The result is saved like the shared racing lines (x, y, time, speed, inputs; one lap, no repeated end
point) plus the settings, the solver's status and the vehicle/track it was computed for, so
train/control/mpc_setup.py can use it in place of the data's line. The committed line for the ORCA car on
ETHZMobil is train/racelines/orca_1_43_ethzMobil.npz, reproduced by `ddyn mpc raceline` (a test checks
that a fresh solve matches it).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.model.single_track import derivatives
from ddyn.model.tracks import Raceline, Track, load_track
from ddyn.model.vehicle import Vehicle
from ddyn.model.vehicle import load as load_vehicle

RACELINE_DIR = Path(__file__).resolve().parents[1] / "racelines"  # train/racelines


@dataclass(frozen=True)
class RacelineSettings:
    intervals: int = 300          # N: ~4 cm of centre line each on ETHZMobil
    margin: float = 0.03          # m between the footprint and the bounds (the MPC keeps 0.02: room to track)
    vx0: float = 0.1              # m/s at the start line (the paper's closed-loop start)
    vx_min: float = 0.05          # m/s: the car never stops (the slip model is not meant for standstill)
    regularisation: float = 1e-4  # weight of the input rates (s^-1 per (unit/s)^2): removes chattering
    max_iterations: int = 3000
    guess_speed: float = 1.5      # m/s: initial guess, a constant speed along the centre line

    def as_dict(self) -> dict:
        return asdict(self)


def default_path(vehicle_name: str, track_name: str) -> Path:
    return RACELINE_DIR / f"{vehicle_name}_{track_name}.npz"


def _footprint(vehicle_name: str) -> tuple[float, float]:
    from ddyn.model.vehicle import FOOTPRINT

    if vehicle_name not in FOOTPRINT:
        raise DdynError(f"no footprint known for vehicle {vehicle_name!r}")
    return FOOTPRINT[vehicle_name]


def _periodic_interpolant(ca, name: str, track: Track, values: np.ndarray):
    """A linear interpolant of per-centre-point values over s, extended one lap each side."""
    s = np.concatenate([track.s - track.length, track.s, track.s + track.length, [2 * track.length + track.s[0]]])
    v = np.concatenate([values, values, values, values[:1]])
    return ca.interpolant(name, "linear", [s], v)


def solve(vehicle: Vehicle, track: Track, settings: RacelineSettings = RacelineSettings(),
          verbose: bool = False) -> dict:
    """Solve the minimum-time lap; returns the arrays and the solver's report."""
    import casadi as ca

    from ddyn.model.mathns import get as get_ns
    if vehicle.true_coefficients is None:
        raise DdynError(f"vehicle {vehicle.name!r} has no true coefficients to drive with")
    ns = get_ns("casadi")
    N = settings.intervals
    length_fp, width_fp = _footprint(vehicle.name)
    kappa = _periodic_interpolant(ca, "kappa", track, track.curvature)
    wl_f = _periodic_interpolant(ca, "wl", track, track.half_width_left)
    wr_f = _periodic_interpolant(ca, "wr", track, track.half_width_right)
    coeffs = [float(c) for c in vehicle.true_vector()]

    X = ca.SX.sym("X", 8)
    U = ca.SX.sym("U", 2)
    s, n, mu, vx, vy, omega, thr, steer = [X[i] for i in range(8)]
    k = kappa(s)
    sdot = (vx * ca.cos(mu) - vy * ca.sin(mu)) / (1 - n * k)
    body = derivatives(ns, (0, 0, 0, vx, vy, omega, thr, steer), (U[0], U[1]), coeffs, vehicle.known)
    f = ca.Function("f", [X, U], [ca.vertcat(sdot, vx * ca.sin(mu) + vy * ca.cos(mu), omega - k * sdot,
                                             *body[3:])])
    h = ca.SX.sym("h")
    m = vehicle.rk4_substeps
    xs = X
    for _ in range(m):  # the plant's integrator: RK4 with the vehicle's sub-steps
        k1 = f(xs, U)
        k2 = f(xs + h / m / 2 * k1, U)
        k3 = f(xs + h / m / 2 * k2, U)
        k4 = f(xs + h / m * k3, U)
        xs = xs + h / m / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    step = ca.Function("step", [X, U, h], [xs]).map(N)

    opti = ca.Opti()
    Xv = opti.variable(8, N + 1)
    Uv = opti.variable(2, N)
    T = opti.variable()
    hk = T / N
    opti.subject_to(Xv[:, 1:] == step(Xv[:, :-1], Uv, ca.repmat(hk, 1, N)))
    lim = vehicle.input_limits
    opti.subject_to(opti.bounded(lim["throttle"][0], Xv[6, :], lim["throttle"][1]))
    opti.subject_to(opti.bounded(lim["steering"][0], Xv[7, :], lim["steering"][1]))
    opti.subject_to(opti.bounded(lim["dthrottle"][0], Uv[0, :], lim["dthrottle"][1]))
    opti.subject_to(opti.bounded(lim["dsteering"][0], Uv[1, :], lim["dsteering"][1]))
    opti.subject_to(Xv[3, :] >= settings.vx_min)
    opti.subject_to(opti.bounded(-1.2, Xv[2, :], 1.2))  # heading error: keeps the curvilinear frame valid
    wl = ca.horzcat(*[wl_f(Xv[0, i]) for i in range(N + 1)]) - settings.margin
    wr = ca.horzcat(*[wr_f(Xv[0, i]) for i in range(N + 1)]) - settings.margin
    for sign in (-1.0, 1.0):
        along = sign * 0.5 * length_fp * ca.sin(Xv[2, :])
        across = 0.5 * width_fp * ca.cos(Xv[2, :])
        opti.subject_to(Xv[1, :] + along + across <= wl)
        opti.subject_to(Xv[1, :] + along - across >= -wr)
    opti.subject_to(Xv[0, 0] == 0)
    opti.subject_to(Xv[3:, 0] == ca.DM([settings.vx0, 0, 0, 0, 0]))
    opti.subject_to(Xv[0, N] == track.length)
    opti.subject_to(Xv[1, N] == Xv[1, 0])
    opti.subject_to(Xv[2, N] == Xv[2, 0])
    opti.subject_to(opti.bounded(1.0, T, 60.0))
    opti.minimize(T + settings.regularisation * ca.sumsqr(Uv) * hk)

    # initial guess: constant speed along the centre line after a short ramp
    T0 = track.length / settings.guess_speed
    sg = np.linspace(0.0, track.length, N + 1)
    opti.set_initial(T, T0)
    opti.set_initial(Xv[0, :], sg)
    opti.set_initial(Xv[3, :], np.full(N + 1, settings.guess_speed))
    opti.set_initial(Xv[5, :], settings.guess_speed * track.curvature_at(sg))
    opti.set_initial(Xv[6, :], np.full(N + 1, 0.3))
    opti.solver("ipopt", {"print_time": False, "expand": True},
                {"max_iter": settings.max_iterations, "mu_strategy": "adaptive", "print_level": 5 if verbose else 0, "sb": "yes",
                 "tol": 1e-8, "acceptable_tol": 1e-6})
    t0 = time.perf_counter()
    try:
        sol = opti.solve()
        stats, get = sol.stats(), sol.value
    except RuntimeError as e:
        stats = opti.stats()
        raise DdynError(f"raceline: IPOPT did not solve the lap ({stats.get('return_status', e)}) after "
                        f"{stats.get('iter_count')} iterations") from None
    seconds = time.perf_counter() - t0
    Xs, Us, Ts = np.asarray(get(Xv)), np.asarray(get(Uv)).reshape(2, N), float(get(T))
    return {"X": Xs, "U": Us, "T": Ts, "iterations": int(stats["iter_count"]),
            "status": str(stats["return_status"]), "solve_seconds": seconds}


def to_cartesian(track: Track, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions and yaw of the car from (s, n, mu): the centre point plus n along its left normal."""
    s, n, mu = X[0], X[1], X[2]
    cx, cy = track.position(s)
    i, t = track._locate(s)
    # heading interpolated between the point headings (bisectors), so the normal turns smoothly
    h0, h1 = track.heading[i], track.heading[(i + 1) % track.n]
    head = h0 + t * np.angle(np.exp(1j * (h1 - h0)))
    x, y = cx - n * np.sin(head), cy + n * np.cos(head)
    return x, y, head + mu


def raceline_arrays(vehicle: Vehicle, track: Track, result: dict, settings: RacelineSettings) -> dict:
    """The arrays of a raceline file: one lap, the end point (= the start) dropped."""
    X, U, T = result["X"], result["U"], result["T"]
    N = U.shape[1]
    x, y, yaw = to_cartesian(track, X)
    meta = {"vehicle": vehicle.name, "vehicle_digest": vehicle.digest, "track": track.name,
            "lap_time_s": T, "settings": settings.as_dict(), "ipopt_status": result["status"],
            "ipopt_iterations": result["iterations"], "command": "ddyn mpc raceline"}
    return {"x": x[:N], "y": y[:N], "time": np.arange(N) * T / N, "speed": np.hypot(X[3], X[4])[:N],
            "inputs": U[:, : N - 1], "yaw": yaw[:N], "states": X[:, :N], "meta": np.array(json.dumps(meta))}


def save(path: Path, arrays: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def load_for(vehicle_name: str, track: Track) -> Raceline | None:
    """The computed line of this vehicle on this track, if one is committed; else None."""
    path = default_path(vehicle_name, track.name)
    if not path.is_file():
        return None
    with np.load(path) as z:
        return Raceline(z["x"], z["y"], z["time"], z["speed"], z["inputs"], str(path))


def line_for(track: Track, vehicle_name: str) -> Raceline:
    """The line a vehicle races on a track: its computed line when committed, else the data's line."""
    line = load_for(vehicle_name, track)
    if line is None:
        line = track.raceline
    if line is None:
        raise DdynError(f"track {track.name!r} has no raceline for {vehicle_name!r} (compute one: ddyn mpc raceline)")
    return line


def meta_of(path: Path) -> dict:
    with np.load(path) as z:
        return json.loads(str(z["meta"]))


def _run(args: argparse.Namespace) -> int:
    vehicle = load_vehicle(args.vehicle)
    track = load_track(args.track)
    settings = RacelineSettings(intervals=args.intervals, margin=args.margin, vx0=args.vx0)
    result = solve(vehicle, track, settings, verbose=args.verbose)
    arrays = raceline_arrays(vehicle, track, result, settings)
    out = Path(args.out) if args.out else default_path(vehicle.name, track.name)
    save(out, arrays)
    worst = float(np.min(track.boundary_distance(arrays["x"], arrays["y"])))
    print(f"raceline: {vehicle.name} on {track.name}: lap {result['T']:.3f} s from vx0 = {settings.vx0} m/s, "
          f"top speed {arrays['speed'].max():.2f} m/s, {result['iterations']} IPOPT iterations "
          f"({result['status']}, {result['solve_seconds']:.1f} s); centre of gravity >= {worst * 1000:.0f} mm "
          f"inside the bounds; wrote {out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("raceline", help="time-optimal standing-start lap of a vehicle (CasADi + IPOPT)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = RacelineSettings()
    p.add_argument("--vehicle", default="orca_1_43")
    p.add_argument("--track", default="ethzMobil")
    p.add_argument("--intervals", type=int, default=d.intervals)
    p.add_argument("--margin", type=float, default=d.margin, help="m between footprint and bounds")
    p.add_argument("--vx0", type=float, default=d.vx0)
    p.add_argument("--out", default=None, help="npz to write (default: the committed train/racelines/ file)")
    p.add_argument("--verbose", action="store_true", help="IPOPT's iteration log")
    p.set_defaults(func=_run)
