"""What the C MPC and its Python reference share: settings, the raceline table, reference geometry.

The raceline table (`raceline_table`) is what ddyn_mpc_set_track takes: a closed raceline resampled
at uniform spacing, its speed profile (floored, so the reference never stalls), and the usable room
from each point to the left and right track bounds along the centre line's normal, reduced by the
car's half footprint and a margin. `stage_geometry` repeats c_src/src/mpc.c's reference rules
exactly (projection, time-parameterised references, half-planes at the projections of a predicted
trajectory) so the IPOPT reference MPC solves the same problem the C one linearises.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ddyn.control.raceline import line_for
from ddyn.model.tracks import Track, resample_closed
from ddyn.model.vehicle import footprint

LOCAL_WINDOW, STAGE_WINDOW = 40, 10  # as in mpc.c


@dataclass(frozen=True)
class MpcSettings:
    """Cost weights and solver limits (the C defaults are in ddyn_mpc_default_config)."""

    horizon: int = 20
    disc: str = "rk4_single"   # prediction: rk4_single (generated for the MPC), euler, rk4 (the plant)
    q_x: float = 1000.0
    q_y: float = 1000.0
    q_terminal: float = 10.0
    r_dthrottle: float = 1e-3
    r_dsteering: float = 1.0    # chosen on random tracks 0-19, held out on 200-219 (docs/tracks.md)
    slack_l1: float = 1e4
    slack_l2: float = 1e5
    qp_max_iterations: int = 30
    qp_tolerance: float = 1e-6
    margin: float = 0.03        # m, kept between the footprint's half width and the bounds (docs/tracks.md)
    speed_floor: float = 0.5    # m/s, lowest reference speed
    speed_scale: float = 1.0    # reference speed = raceline speed * this (docs/mpc.md, tuning)
    lateral_grip: float = 0.0   # > 0: reference speed <= sqrt(this * (Df + Dr) / mass / |curvature|) of the table's
                                # path: the tracker's share of the tyres' peak lateral force (0: no cap)
    brake_limit: float = 0.0    # > 0: the reference decelerates at most this * (full brake + drag) / mass
                                # (a backward pass): no tyre scrub or drift asked for (0: no limit)
    spacing: float = 0.025      # m, raceline table spacing
    line: str = "default"       # the vehicle's own line, or "flying" / "standing" (ddyn.control.raceline.LINES)

    def as_dict(self) -> dict:
        return asdict(self)


def settings_for(vehicle_name: str, **given) -> MpcSettings:
    """The defaults (the 1:43 car's), the vehicle's own settings over them (train/vehicles/mpc/), then
    `given` (None: not given)."""
    from ddyn.control.vehicle_settings import overrides
    from ddyn.errors import DdynError

    fields = {**overrides(vehicle_name, "mpc"), **{k: v for k, v in given.items() if v is not None}}
    try:
        return MpcSettings(**fields)
    except TypeError as e:
        raise DdynError(f"MPC settings of {vehicle_name!r}: {e}") from None


def raceline_table(track: Track, vehicle_name: str, settings: MpcSettings) -> dict[str, np.ndarray]:
    """The closed raceline table for ddyn_mpc_set_track: x, y, speed, room_left, room_right.

    The speed profile is the raceline's own (a standing-start lap: low at the start line, floored
    at settings.speed_floor), so later laps slow down through the start area as the first did.
    It is times settings.speed_scale and, where settings ask (lateral_grip, brake_limit: the AV-21),
    capped to what a position tracker can follow (tracker_speed_limit).
    """
    from ddyn.control.raceline import LINES
    if settings.line not in LINES:
        raise ValueError(f"line {settings.line!r}: expected one of {', '.join(LINES)}")
    rl = line_for(track, vehicle_name, LINES[settings.line])
    pts = np.column_stack([rl.x, rl.y])
    speed_rl = np.asarray(rl.speed, float)
    # The raceline files run on past one lap (ethzMobil's "long" line: a standing-start lap plus
    # 1.8 m). The table is its first lap, closed by the short segment back to the start.
    # Progress is unwrapped, so a line starting just behind the start line (a computed one) is not cut.
    s_c, _ = track.project(pts[:, 0], pts[:, 1])
    ds_c = (np.diff(s_c) + 0.5 * track.length) % track.length - 0.5 * track.length
    past = np.nonzero(np.cumsum(ds_c) >= track.length - 1e-9)[0]
    if len(past):
        pts, speed_rl = pts[: past[0] + 1], speed_rl[: past[0] + 1]
    seg = np.hypot(*np.diff(np.vstack([pts, pts[:1]]), axis=0).T)
    s_pts = np.concatenate(([0.0], np.cumsum(seg)))
    total = s_pts[-1]
    n = int(round(total / settings.spacing))
    xy = resample_closed(pts, n)
    s_new = np.arange(n) * (total / n)
    # across the closing segment the speed continues at the lap's final value
    speed = np.maximum(settings.speed_scale * np.interp(s_new, s_pts, np.concatenate([speed_rl, speed_rl[-1:]])),
                       settings.speed_floor)
    if settings.lateral_grip > 0.0 or settings.brake_limit > 0.0:
        speed = np.maximum(tracker_speed_limit(xy, speed, vehicle_name, settings), settings.speed_floor)
    # room along the normal: centre-line half widths at the projection, minus the lateral offset
    s_c, lat = track.project(xy[:, 0], xy[:, 1])
    wl, wr = track.half_widths(s_c)
    half = 0.5 * footprint(vehicle_name)[1] + settings.margin
    return {"x": xy[:, 0], "y": xy[:, 1], "speed": speed, "room_left": wl - lat - half,
            "room_right": wr + lat - half}


def tracker_speed_limit(xy: np.ndarray, speed: np.ndarray, vehicle_name: str, settings: MpcSettings) -> np.ndarray:
    """The closed table's reference speed lowered to what a position tracker can follow with the vehicle's
    true coefficients (its vehicle file), as settings ask:

    lateral_grip: at most sqrt(lateral_grip * (Df + Dr) / mass / |kappa|), kappa the path's curvature over
    the circle through the points two either side (a chord of ~4 spacings: the 3 m table's position noise of
    a few mm would otherwise read as curvature);
    brake_limit: a backward pass (three times round the closed table) so that between consecutive points
    v_i^2 <= v_{i+1}^2 + 2 ds brake_limit F_brake(v_{i+1}) / mass, F_brake the drivetrain's force at full brake
    and the drag at v_{i+1} (ddyn.control.drive_limits; the papers' form: (Cm1 - Cm2 v) + Cr0 + Cd v^2). A
    line may brake harder (its tyres' lateral force projected onto the path: steering at the
    lock with the front tyre past its peak, sideslip at its bound; the AV-21's Putnam line does, docs/tracks.md);
    a tracker that follows positions does not find that, falls behind the reference and reaches the corner
    too fast."""
    from ddyn.control.drive_limits import longitudinal_force
    from ddyn.model.vehicle import load as load_vehicle
    v = load_vehicle(vehicle_name)
    c, mass = v.true_coefficients, float(v.known.mass)
    out = np.asarray(speed, float).copy()
    if settings.lateral_grip > 0.0:
        a, b = np.roll(xy, 2, axis=0), np.roll(xy, -2, axis=0)
        ab, bc, ca = xy - a, b - xy, a - b
        cross = ab[:, 0] * bc[:, 1] - ab[:, 1] * bc[:, 0]
        kappa = 2.0 * np.abs(cross) / (np.linalg.norm(ab, axis=1) * np.linalg.norm(bc, axis=1) *
                                       np.linalg.norm(ca, axis=1))
        out = np.minimum(out, np.sqrt(settings.lateral_grip * (c["Df"] + c["Dr"]) / mass / np.maximum(kappa, 1e-9)))
    if settings.brake_limit > 0.0:
        ds = np.hypot(*(np.roll(xy, -1, axis=0) - xy).T)
        n = len(out)
        for _ in range(3):
            for i in range(n - 1, -1, -1):
                nxt = out[(i + 1) % n]
                decel = settings.brake_limit * -longitudinal_force(v, nxt, -1.0) / mass
                out[i] = min(out[i], np.sqrt(nxt * nxt + 2.0 * ds[i] * decel))
    return out


class TableGeometry:
    """The C MPC's raceline geometry (project, advance, point at) in numpy, for the Python reference."""

    def __init__(self, table: dict[str, np.ndarray]):
        self.x, self.y = table["x"], table["y"]
        self.speed, self.wl, self.wr = table["speed"], table["room_left"], table["room_right"]
        self.n = len(self.x)
        self.dx = np.roll(self.x, -1) - self.x
        self.dy = np.roll(self.y, -1) - self.y
        self.len = np.hypot(self.dx, self.dy)
        self.s = np.concatenate(([0.0], np.cumsum(self.len)[:-1]))

    def project(self, px: float, py: float, hint: int, window: int = LOCAL_WINDOW) -> tuple[int, float]:
        if hint < 0:
            idx = np.arange(self.n)
        else:
            count = min(2 * window + 1, self.n)
            idx = (hint - (count - 1) // 2 + np.arange(count)) % self.n
        rx, ry = px - self.x[idx], py - self.y[idx]
        u = np.clip((rx * self.dx[idx] + ry * self.dy[idx]) / self.len[idx] ** 2, 0.0, 1.0)
        d = (rx - u * self.dx[idx]) ** 2 + (ry - u * self.dy[idx]) ** 2
        k = int(np.argmin(d))
        return int(idx[k]), float(u[k])

    def at(self, i: int, u: float) -> dict:
        j = (i + 1) % self.n
        return {"x": self.x[i] + u * self.dx[i], "y": self.y[i] + u * self.dy[i],
                "tx": self.dx[i] / self.len[i], "ty": self.dy[i] / self.len[i],
                "speed": self.speed[i] + u * (self.speed[j] - self.speed[i]),
                "wl": self.wl[i] + u * (self.wl[j] - self.wl[i]), "wr": self.wr[i] + u * (self.wr[j] - self.wr[i]),
                "s": self.s[i] + u * self.len[i]}

    def advance(self, i: int, u: float, ds: float) -> tuple[int, float]:
        for _ in range(self.n):
            left = (1.0 - u) * self.len[i]
            if ds <= left:
                return i, u + ds / self.len[i]
            ds -= left
            i, u = (i + 1) % self.n, 0.0
        return i, u

    def stage_geometry(self, x0: np.ndarray, predicted_xy: np.ndarray, dt: float, hint: int,
                       accel: float = 0.0):
        """As mpc.c: cost references (H+1, 2) and half-planes (H+1, 6: anchor, normal, room l, r). accel: what
        the car can gain per second from x0's speed (launch_accel; 0: no bound): the cost point moves on at the
        line's speed but no faster than x0's speed + accel (k + 1) dt over interval k (mpc.c's references)."""
        i0, u0 = self.project(x0[0], x0[1], hint)
        refs, planes = [], []
        i, u, ic = i0, u0, i0
        v0 = max(float(x0[3]), 0.0)
        for k in range(len(predicted_xy)):
            p = self.at(i, u)
            refs.append((p["x"], p["y"]))
            v = p["speed"]
            if accel > 0.0:
                v = min(v, v0 + accel * (k + 1) * dt)
            i, u = self.advance(i, u, v * dt)
            ic, uc = self.project(predicted_xy[k, 0], predicted_xy[k, 1], ic, LOCAL_WINDOW if k == 0 else STAGE_WINDOW)
            c = self.at(ic, uc)
            planes.append((c["x"], c["y"], -c["ty"], c["tx"], c["wl"], c["wr"]))
        return i0, np.array(refs), np.array(planes)


def launch_accel(vehicle, coeffs: np.ndarray, x0: np.ndarray, throttle_max: float) -> float:
    """As mpc.c's launch_accel: the model's dvx/dt at x0's speed, full throttle, driving straight (vy = omega =
    steering = 0); 0 when not a finite positive number."""
    from ddyn.model.backends import derivatives_numpy
    x = np.zeros(8)
    x[3] = max(float(x0[3]), 0.0)
    x[6] = throttle_max
    a = float(derivatives_numpy(x, np.zeros(2), np.asarray(coeffs, float), vehicle.known)[3])
    return a if np.isfinite(a) and a > 0.0 else 0.0


def start_state(table: dict[str, np.ndarray], speed: float = 0.1) -> np.ndarray:
    """Near standstill at the raceline's first point, heading along it."""
    yaw = np.arctan2(table["y"][1] - table["y"][0], table["x"][1] - table["x"][0])
    return np.array([table["x"][0], table["y"][0], yaw, speed, 0.0, 0.0, 0.0, 0.0])


def perturbed_start(table: dict[str, np.ndarray], speed: float, lateral: float = 0.0,
                    heading: float = 0.0) -> np.ndarray:
    """start_state moved `lateral` m to the left of the raceline and turned by `heading` rad."""
    x0 = start_state(table, speed)
    yaw = x0[2]
    x0[0] -= np.sin(yaw) * lateral
    x0[1] += np.cos(yaw) * lateral
    x0[2] += heading
    return x0
