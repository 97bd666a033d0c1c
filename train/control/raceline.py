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
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.paths import REPO
from ddyn.model.single_track import derivatives
from ddyn.model.track_frame import frame
from ddyn.model.track_files import is_named, open_track, track_digest
from ddyn.model.tracks import Raceline, Track
from ddyn.model.vehicle import Vehicle, footprint
from ddyn.model.vehicle import load as load_vehicle

RACELINE_DIR = Path(__file__).resolve().parents[1] / "racelines"  # train/racelines
START_SPEED = 1.5  # m/s: the standing start's intervals (warm start below it) take start_substeps
USER_RACELINE_DIR = REPO / "out" / "racelines"


@dataclass(frozen=True)
class RacelineSettings:
    intervals: int = 0            # N; 0: one per `spacing` of centre line
    spacing: float = 0.03         # m of centre line per interval when intervals is 0 (the data's point spacing)
    margin: float = 0.03          # m between the footprint and the bounds (the MPC keeps 0.02: room to track)
    vx0: float = 0.1              # m/s at the start line (the paper's closed-loop start)
    vx_min: float = 0.05          # m/s: the car never stops (the slip model is not meant for standstill)
    regularisation: float = 1e-4  # weight of the input rates (s^-1 per (unit/s)^2): removes chattering
    max_iterations: int = 3000
    start_substeps: int = 1       # x the plant's RK4 sub-steps in the standing start's intervals
    expand: bool = False          # SX-expand the NLP: faster per iteration, but ETHZ at 400 intervals took 2.7 GB
    flying: bool = False          # a flying lap: every state periodic (the lap after the first), no standing start
    grip: float = 1.0             # x the tyres' peak forces Df, Dr in the line's model: a reserve the MPC can use
    max_sideslip: float = 0.0     # rad, |atan(vy / vx)| bound (0: none); keeps the line out of drifts the MPC cannot track

    def as_dict(self) -> dict:
        return asdict(self)


def settings_for(vehicle_name: str, **given) -> RacelineSettings:
    """The defaults, the vehicle's own settings over them (train/vehicles/mpc/), then `given` (None: not given)."""
    from ddyn.control.vehicle_settings import overrides

    fields = {**overrides(vehicle_name, "raceline"), **{k: v for k, v in given.items() if v is not None}}
    try:
        return RacelineSettings(**fields)
    except TypeError as e:
        raise DdynError(f"raceline settings of {vehicle_name!r}: {e}") from None


def resolved(settings: RacelineSettings, track: Track) -> RacelineSettings:
    """The settings with the number of intervals fixed (what a re-solve needs to reproduce a line)."""
    if settings.intervals > 0:
        return settings
    return replace(settings, intervals=max(50, int(round(track.length / settings.spacing))))


def default_flying(vehicle_name: str) -> bool:
    """Whether the vehicle's own line is a flying lap (its settings file; the 1:43 car: a standing start)."""
    return settings_for(vehicle_name).flying


def default_path(vehicle_name: str, track: str | Track, flying: bool | None = None) -> Path:
    """Where a vehicle's line on a track is kept: train/racelines/ (committed) for the shared data's
    tracks, out/racelines/ for a user's or a random track (computed on demand, never committed).
    flying None: the vehicle's own kind of line; the other kind gets a suffix (_flying, _standing)."""
    suffix = "" if flying is None or flying == default_flying(vehicle_name) else ("_flying" if flying else "_standing")
    if isinstance(track, str) or (is_named(track.name) and not track.files):
        name = track if isinstance(track, str) else track.name
        return RACELINE_DIR / f"{vehicle_name}_{name}{suffix}.npz"
    return USER_RACELINE_DIR / f"{vehicle_name}_{track.name}{suffix}.npz"


def speed_profile(vehicle: Vehicle, kappa: np.ndarray, ds: float, vx0: float | None, grip: float = 1.0) -> np.ndarray:
    """A curvature-limited speed at the m frame points plus the closing point (the warm start).

    v <= sqrt(a_lat / |kappa|) with a_lat a fraction of the tyres' peak force over the mass, under
    the drivetrain's top speed; then a forward pass (drivetrain acceleration from vx0) and a
    backward pass (braking at a_lat). Only a guess: IPOPT starts from a lap the car could nearly
    drive instead of a constant speed that leaves the track in the first hairpin.
    """
    from ddyn.control.drive_limits import longitudinal_force, top_speed

    c, mass = vehicle.true_coefficients, float(vehicle.known.mass)
    a_lat = 0.6 * grip * (c["Df"] + c["Dr"]) / mass
    top = top_speed(vehicle)
    k = longitudinal_force(vehicle, 0.0, 1.0)       # full pedal from rest
    v = np.minimum(0.9 * top, np.sqrt(a_lat / np.maximum(np.abs(kappa), 1e-6)))
    v = np.append(v, v[0])
    a_acc = 0.5 * k / mass
    if vx0 is not None:
        v[0] = vx0
    for _ in range(1 if vx0 is not None else 2):
        if vx0 is None:
            v[0] = min(v[0], v[-1])
        for i in range(len(v) - 1):
            v[i + 1] = min(v[i + 1], np.sqrt(v[i] ** 2 + 2 * a_acc * ds))
        if vx0 is None:
            v[-1] = min(v[-1], v[0])
        for i in range(len(v) - 2, -1, -1):
            v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * a_lat * ds))
    return np.maximum(v, vx0 if vx0 is not None else 0.0)


def solve(vehicle: Vehicle, track: Track, settings: RacelineSettings = RacelineSettings(),
          verbose: bool = False) -> dict:
    """Solve the minimum-time lap; returns the arrays and the solver's report."""
    import casadi as ca

    from ddyn.model.mathns import get as get_ns
    if vehicle.true_coefficients is None:
        raise DdynError(f"vehicle {vehicle.name!r} has no true coefficients to drive with")
    ns = get_ns("casadi")
    N = resolved(settings, track).intervals
    length_fp, width_fp = footprint(vehicle.name)
    fr = frame(track, N)
    ds = fr.length / N
    kap = fr.kappa  # each interval is an arc: a constant, not a function of s
    from ddyn.model.single_track import COEFF_NAMES
    coeffs = [float(c) * (settings.grip if name in ("Df", "Dr") else 1.0)
              for name, c in zip(COEFF_NAMES, vehicle.true_vector())]

    X = ca.SX.sym("X", 8)  # (s, n, mu, vx, vy, omega, throttle, steering); s counts from the interval's start
    U = ca.SX.sym("U", 2)
    k = ca.SX.sym("kappa")
    s, n, mu, vx, vy, omega, thr, steer = [X[i] for i in range(8)]
    sdot = (vx * ca.cos(mu) - vy * ca.sin(mu)) / (1 - n * k)
    body = derivatives(ns, (0, 0, 0, vx, vy, omega, thr, steer), (U[0], U[1]), coeffs, vehicle.known)
    f = ca.Function("f", [X, U, k], [ca.vertcat(sdot, vx * ca.sin(mu) + vy * ca.cos(mu), omega - k * sdot,
                                                *body[3:])])
    h = ca.SX.sym("h")

    def rk4(m: int):
        xs = X
        for _ in range(m):
            k1 = f(xs, U, k)
            k2 = f(xs + h / m / 2 * k1, U, k)
            k3 = f(xs + h / m / 2 * k2, U, k)
            k4 = f(xs + h / m * k3, U, k)
            xs = xs + h / m / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return ca.Function("step", [X, U, h, k], [xs])

    # The plant's integrator (RK4, the vehicle's sub-steps): where the car is fast an interval lasts
    # about one sample. From the standing start an interval of ds lasts up to ~0.5 s, one RK4 step
    # that is inaccurate in the low-speed tyre dynamics; start_substeps multiplies the sub-steps of
    # the intervals whose warm-start speed is below START_SPEED (docs/tracks.md: 1 by default,
    # 2 fixes random track 201's start but fails on random track 3 and finds a slower ETHZ optimum).
    v_guess = speed_profile(vehicle, fr.kappa, ds, None if settings.flying else settings.vx0, settings.grip)
    fast = np.nonzero(v_guess[:-1] >= START_SPEED)[0]
    n_start = N if settings.start_substeps == 1 else max(1, int(fast[0]) if len(fast) else N)
    pieces = [(0, n_start, settings.start_substeps * vehicle.rk4_substeps), (n_start, N, vehicle.rk4_substeps)]
    maps = [(a, b, rk4(m).map(b - a)) for a, b, m in pieces if b > a]

    def step(x, u, hh, kk):
        return ca.horzcat(*[fn(x[:, a:b], u[:, a:b], hh[:, a:b], kk[:, a:b]) for a, b, fn in maps])

    # Each interval covers a fixed ds of the centre line in its own free time H_k: the track's
    # curvature and widths are per-interval constants, and the lap time is sum(H).
    opti = ca.Opti()
    Xv = opti.variable(7, N + 1)  # (n, mu, vx, vy, omega, throttle, steering) at the frame's points
    Uv = opti.variable(2, N)
    H = opti.variable(1, N)
    nxt = step(ca.vertcat(ca.DM.zeros(1, N), Xv[:, :-1]), Uv, H, ca.DM(kap).T)
    opti.subject_to(nxt[0, :] == ds)
    opti.subject_to(Xv[:, 1:] == nxt[1:, :])
    lim = vehicle.input_limits
    opti.subject_to(opti.bounded(lim["throttle"][0], Xv[5, :], lim["throttle"][1]))
    opti.subject_to(opti.bounded(lim["steering"][0], Xv[6, :], lim["steering"][1]))
    opti.subject_to(opti.bounded(lim["dthrottle"][0], Uv[0, :], lim["dthrottle"][1]))
    opti.subject_to(opti.bounded(lim["dsteering"][0], Uv[1, :], lim["dsteering"][1]))
    opti.subject_to(Xv[2, :] >= settings.vx_min)
    if settings.max_sideslip > 0.0:
        tb = float(np.tan(settings.max_sideslip))
        opti.subject_to(Xv[3, :] <= tb * Xv[2, :])
        opti.subject_to(Xv[3, :] >= -tb * Xv[2, :])
    opti.subject_to(opti.bounded(-1.2, Xv[1, :], 1.2))  # heading error: keeps the curvilinear frame valid
    opti.subject_to(opti.bounded(1e-4, H, 2.0 * ds / settings.vx_min))
    wl = ca.DM(np.append(fr.wl, fr.wl[0])).T - settings.margin
    wr = ca.DM(np.append(fr.wr, fr.wr[0])).T - settings.margin
    for sign in (-1.0, 1.0):
        along = sign * 0.5 * length_fp * ca.sin(Xv[1, :])
        across = 0.5 * width_fp * ca.cos(Xv[1, :])
        opti.subject_to(Xv[0, :] + along + across <= wl)
        opti.subject_to(Xv[0, :] + along - across >= -wr)
    if settings.flying:  # the lap after the first: it ends in the state it started in
        opti.subject_to(Xv[:, N] == Xv[:, 0])
    else:
        opti.subject_to(Xv[2:, 0] == ca.DM([settings.vx0, 0, 0, 0, 0]))
        opti.subject_to(Xv[0, N] == Xv[0, 0])  # the line closes in position and heading
        opti.subject_to(Xv[1, N] == Xv[1, 0])
    opti.minimize(ca.sum2(H) + settings.regularisation * ca.sum2(ca.sum1(Uv ** 2) * H))

    # warm start: the centre line at a curvature-limited speed
    v0 = v_guess
    kn = np.append(kap, kap[0])
    wheelbase = float(vehicle.known.lf + vehicle.known.lr)
    opti.set_initial(Xv[2, :], v0)
    opti.set_initial(Xv[4, :], v0 * kn)
    opti.set_initial(Xv[5, :], np.full(N + 1, 0.3))
    opti.set_initial(Xv[6, :], np.clip(np.arctan(wheelbase * kn), *lim["steering"]))
    opti.set_initial(H, 2 * ds / (v0[:-1] + v0[1:]))
    opti.solver("ipopt", {"print_time": False, "expand": settings.expand},
                {"max_iter": settings.max_iterations, "mu_strategy": "adaptive", "print_level": 5 if verbose else 0,
                 "sb": "yes", "tol": 1e-8, "acceptable_tol": 1e-6})
    t0 = time.perf_counter()
    try:
        sol = opti.solve()
        stats, get = sol.stats(), sol.value
    except RuntimeError as e:
        stats = opti.stats()
        raise DdynError(f"raceline: IPOPT did not solve the lap on {track.name!r} "
                        f"({stats.get('return_status', e)}) after {stats.get('iter_count')} iterations") from None
    seconds = time.perf_counter() - t0
    Hs = np.asarray(get(H)).reshape(N)
    Xs = np.vstack([np.append(fr.s, fr.length), np.asarray(get(Xv)).reshape(7, N + 1)])
    return {"X": Xs, "U": np.asarray(get(Uv)).reshape(2, N), "H": Hs, "T": float(Hs.sum()), "frame": fr,
            "iterations": int(stats["iter_count"]), "status": str(stats["return_status"]),
            "solve_seconds": seconds}


def raceline_arrays(vehicle: Vehicle, track: Track, result: dict, settings: RacelineSettings) -> dict:
    """The arrays of a raceline file: one lap, the end point (= the start) dropped."""
    X, U, T, fr = result["X"], result["U"], result["T"], result["frame"]
    N = U.shape[1]
    x, y = fr.to_xy(X[1, :N])
    meta = {"vehicle": vehicle.name, "vehicle_digest": vehicle.digest, "track": track.name,
            "track_digest": track_digest(track), "lap_time_s": T, "settings": settings.as_dict(), "ipopt_status": result["status"],
            "ipopt_iterations": result["iterations"], "command": "ddyn mpc raceline",
            "formulation": "fixed arc-length intervals of a smoothed centre spline, free time per interval"}
    return {"x": x, "y": y, "time": np.concatenate(([0.0], np.cumsum(result["H"])[:-1])),
            "speed": np.hypot(X[3], X[4])[:N], "inputs": U[:, : N - 1], "yaw": fr.heading + X[2, :N],
            "states": X[:, :N], "meta": np.array(json.dumps(meta))}


def save(path: Path, arrays: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def load_for(vehicle_name: str, track: Track, flying: bool | None = None) -> Raceline | None:
    """The computed line of this vehicle on this track, if one is committed; else None."""
    path = default_path(vehicle_name, track, flying)
    if not path.is_file():
        return None
    digest = meta_of(path).get("track_digest")
    if digest is not None and digest != track_digest(track):
        return None  # a line for another track of the same name (a user's file): not this one
    with np.load(path) as z:
        return Raceline(z["x"], z["y"], z["time"], z["speed"], z["inputs"], str(path))


def line_for(track: Track, vehicle_name: str, flying: bool | None = None) -> Raceline:
    """The line a vehicle races on a track: its computed line when committed, else the data's line
    (flying: the flying-lap line, which must have been computed: ddyn mpc raceline --flying)."""
    line = load_for(vehicle_name, track, flying)
    if line is None and flying is not None and flying != default_flying(vehicle_name):
        raise DdynError(f"no {'flying' if flying else 'standing'}-lap line of {vehicle_name!r} on {track.name!r} "
                        f"(compute it: ddyn mpc raceline --vehicle {vehicle_name} --track ... "
                        f"--{'' if flying else 'no-'}flying)")
    if line is None:
        line = track.raceline
    if line is None:
        raise DdynError(f"track {track.name!r} has no raceline for {vehicle_name!r} (compute one: ddyn mpc raceline "
                        f"--vehicle {vehicle_name} --track TRACK, TRACK this track's name or file)")
    return line


def is_flying(track: Track, vehicle_name: str) -> bool:
    """Whether the vehicle's own line on a track is a flying lap: then a closed loop starts rolling, at
    the line's speed, as the full-scale car's races do (a 1:43 car on its flying line still starts from
    standstill: the flying line is for the laps after the first)."""
    if load_for(vehicle_name, track) is None:
        return False
    return bool(meta_of(default_path(vehicle_name, track)).get("settings", {}).get("flying", False))


LINES = {"default": None, "flying": True, "standing": False}  # --line: the vehicle's own, or a kind


def meta_of(path: Path) -> dict:
    with np.load(path) as z:
        return json.loads(str(z["meta"]))


def _run(args: argparse.Namespace) -> int:
    vehicle = load_vehicle(args.vehicle)
    track = open_track(args.track, vehicle.name)
    settings = resolved(settings_for(vehicle.name, intervals=args.intervals, spacing=args.spacing,
                                     margin=args.margin, vx0=args.vx0, start_substeps=args.start_substeps,
                                     flying=args.flying, grip=args.grip, max_sideslip=args.max_sideslip), track)
    result = solve(vehicle, track, settings, verbose=args.verbose)
    arrays = raceline_arrays(vehicle, track, result, settings)
    out = Path(args.out) if args.out else default_path(vehicle.name, track, settings.flying)
    save(out, arrays)
    worst = float(np.min(track.boundary_distance(arrays["x"], arrays["y"])))
    start = "flying" if settings.flying else f"from vx0 = {settings.vx0} m/s"
    print(f"raceline: {vehicle.name} on {track.name}: lap {result['T']:.3f} s {start}, "
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
    p.add_argument("--intervals", type=int, default=None,
                   help="shooting intervals (default: one per --spacing of centre line)")
    p.add_argument("--margin", type=float, default=None,
                   help=f"m between footprint and bounds (default {d.margin}, or the vehicle's: train/vehicles/mpc/)")
    p.add_argument("--vx0", type=float, default=None, help=f"start speed of a standing start (default {d.vx0})")
    p.add_argument("--spacing", type=float, default=None,
                   help=f"m of centre line per interval when --intervals is 0 (default {d.spacing}, or the vehicle's)")
    p.add_argument("--flying", action=argparse.BooleanOptionalAction, default=None,
                   help="a flying lap (every state periodic: the laps after the first) instead of a standing "
                        "start (default: standing, or the vehicle's)")
    p.add_argument("--grip", type=float, default=None,
                   help=f"x the tyres' peak forces in the line's model (default {d.grip}, or the vehicle's)")
    p.add_argument("--max-sideslip", type=float, default=None,
                   help=f"rad, bound on the line's sideslip atan(vy/vx) (default {d.max_sideslip}: none; or the vehicle's)")
    p.add_argument("--start-substeps", type=int, default=None,
                   help=f"x the RK4 sub-steps in the standing start's intervals (default {d.start_substeps}; docs/tracks.md)")
    p.add_argument("--out", default=None, help="npz to write (default: the committed train/racelines/ file)")
    p.add_argument("--verbose", action="store_true", help="IPOPT's iteration log")
    p.set_defaults(func=_run)
