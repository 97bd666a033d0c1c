"""The ground velocity of a log from its GNSS positions and its IMU, without a vehicle model: what a car's INS/GNSS
post-processing gives (a kinematic Kalman filter and its Rauch-Tung-Striebel smoother).

Why: the study's user's log (ddyn.sil.loop.user_log) needs the lateral velocity vy. The controller's filter has one,
but its model is the nominal one, with no term for what the diagnosis looks for, and it bends the states toward "no
effect". Differencing the filter's positions (track_lateral_velocity) still carries that: its positions are the
model's between GNSS corrections. Measured on random:301 with a 100 ms steering lag in the plant, the log drive at 0.3
of the speed (`ddyn study sil-loop`): vy from the filter's positions was 0.016 m/s RMS off the plant's and the lag
fitted alone came out 17 % short; with the plant's own vy it came out right, and with this smoother's vy 3 % short.
On the banked oval (AV-21) the bank's turns came out 20.1 of 20 degrees (18.2 from the filter's positions).

The model (per segment of consecutive rows, period dt, the heading psi known per row):
    p' = v,   v' = R(psi) (a + b),   b' = white noise
with p, v the position and velocity over the ground (world frame), a the accelerometer's reading (body frame) and b
its offset (body frame), which also takes up what a flat, level accelerometer cannot see: gravity along a banked or
graded road. The GNSS positions are the measurements. Both noise levels come from the log itself: the GNSS's from the
second differences of the positions less the accelerometer's part, the accelerometer's from its reading's
period-to-period scatter (an upper bound: it includes the car's own jerk)."""
from __future__ import annotations

import numpy as np

# m/s^2 per sqrt(s): how fast the accelerometer's offset may move. A flat road needs none; a bank changes over a
# turn's entry. Set on the loop's ETHZMobil logs (50 and 100 ms lags, 40 ms delay, none), before the banked oval was
# run: vy 0.0046-0.0051 m/s RMS off the plant's at 0.3 against 0.0043-0.0044 at 0.03 (the filter's positions: 0.017).
BIAS_WALK = 0.3
MIN_GNSS_STD = 1e-4   # m: floor of the GNSS noise estimate (a noise-free log)
MIN_ACC_STD = 1e-3    # m/s^2: floor of the accelerometer noise estimate


def _rot(psi: float) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s], [s, c]])


def noise_levels(px, py, ax_w, ay_w, ax, ay, dt: float) -> tuple[float, float]:
    """(GNSS position noise, accelerometer noise), standard deviations, from one segment's rows. The GNSS's: each
    three successive positions' second divided difference less the accelerometer's (world frame) at the middle one,
    whose variance is the position noise's times a factor of the spacing (rows without a position are skipped)."""
    t = np.arange(len(px)) * dt
    have = np.flatnonzero(np.isfinite(px) & np.isfinite(py))
    num, den = 0.0, 0.0
    if len(have) >= 3:
        i0, i1, i2 = have[:-2], have[1:-1], have[2:]
        h1, h2 = t[i1] - t[i0], t[i2] - t[i1]
        w = 2.0 / (h1 + h2)
        factor = w ** 2 * (1.0 / h1 ** 2 + (1.0 / h1 + 1.0 / h2) ** 2 + 1.0 / h2 ** 2)
        for z, a in ((px, ax_w), (py, ay_w)):
            d = w * ((z[i2] - z[i1]) / h2 - (z[i1] - z[i0]) / h1) - a[i1]
            num += float(np.sum(d ** 2))
            den += float(np.sum(factor))
    gnss = float(np.sqrt(num / den)) if den > 0 else MIN_GNSS_STD
    da = np.concatenate([np.diff(ax), np.diff(ay)])
    acc = float(np.sqrt(np.mean(da ** 2) / 2.0)) if len(da) else MIN_ACC_STD
    return max(gnss, MIN_GNSS_STD), max(acc, MIN_ACC_STD)


def smooth_segment(px, py, ax, ay, psi, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """World-frame ground velocity (vx_w, vy_w) of one segment: filter forward, RTS backward. Rows without a GNSS
    position (NaN) are predicted through."""
    n = len(px)
    a_body = np.column_stack([ax, ay])
    rot = [_rot(p) for p in psi]
    a_w = np.array([r @ a for r, a in zip(rot, a_body)])
    sg, sa = noise_levels(px, py, a_w[:, 0], a_w[:, 1], ax, ay, dt)
    z = np.column_stack([px, py])
    first = np.flatnonzero(np.all(np.isfinite(z), axis=1))
    x = np.zeros(6)
    x[:2] = z[first[0]] if len(first) else 0.0
    if len(first) > 1:
        x[2:4] = (z[first[1]] - z[first[0]]) / (dt * (first[1] - first[0]))
    P = np.diag([sg ** 2, sg ** 2, 1.0, 1.0, 4.0, 4.0])
    H = np.zeros((2, 6))
    H[0, 0] = H[1, 1] = 1.0
    Rm = np.eye(2) * sg ** 2
    I6 = np.eye(6)
    xf, Pf = np.zeros((n, 6)), np.zeros((n, 6, 6))
    xp, Pp, Fs = np.zeros((n, 6)), np.zeros((n, 6, 6)), np.zeros((n, 6, 6))
    # the process noise, the same every period: the reading's white noise held over a period, the offset's walk
    G = np.vstack([0.5 * dt * dt * np.eye(2), dt * np.eye(2)])
    Q = np.zeros((6, 6))
    Q[:4, :4] = (G @ G.T) * (sa ** 2)
    Q[4:, 4:] = np.eye(2) * BIAS_WALK ** 2 * dt
    for k in range(n):
        if k > 0:
            R = rot[k - 1]
            F = I6.copy()
            F[0:2, 2:4] = dt * np.eye(2)
            F[0:2, 4:6] = 0.5 * dt * dt * R
            F[2:4, 4:6] = dt * R
            x = F @ x
            # the readings are samples of a continuous acceleration: linear between two rows (held at the earlier
            # one, vy came out a few ms late against the positions and the yaw rate, and steering delays fitted long)
            x[0:2] += dt * dt * (a_w[k - 1] / 3.0 + a_w[k] / 6.0)
            x[2:4] += 0.5 * dt * (a_w[k - 1] + a_w[k])
            P = F @ P @ F.T + Q
            Fs[k] = F
        xp[k], Pp[k] = x, P
        if np.all(np.isfinite(z[k])):
            S = H @ P @ H.T + Rm
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ (z[k] - x[:2])
            IKH = I6 - K @ H
            P = IKH @ P @ IKH.T + K @ Rm @ K.T   # Joseph form: stays symmetric and positive
        P = 0.5 * (P + P.T)
        xf[k], Pf[k] = x, P
    xs = xf.copy()
    for k in range(n - 2, -1, -1):
        C = np.linalg.solve(Pp[k + 1], Fs[k + 1] @ Pf[k]).T
        xs[k] = xf[k] + C @ (xs[k + 1] - xp[k + 1])
    return xs[:, 2], xs[:, 3]


def body_lateral_velocity(px, py, ax, ay, psi, segment, dt: float) -> np.ndarray:
    """vy (body frame) of every row: each segment smoothed on its own, its world velocity turned by psi. NaN where a
    segment has fewer than 3 GNSS positions."""
    px, py, ax, ay, psi = (np.asarray(a, dtype=float) for a in (px, py, ax, ay, psi))
    seg = np.asarray(segment)
    vy = np.full(len(px), np.nan)
    for g in np.unique(seg):
        m = np.flatnonzero(seg == g)
        if np.count_nonzero(np.isfinite(px[m]) & np.isfinite(py[m])) < 3:
            continue
        vxw, vyw = smooth_segment(px[m], py[m], ax[m], ay[m], psi[m], dt)
        vy[m] = -np.sin(psi[m]) * vxw + np.cos(psi[m]) * vyw
    return vy
