"""The nothing-changes reference (ddyn.learn.reference): exact on constant motion, the hand-computed error
where the motion changes, segments respected, and scored on the windows `ddyn evaluate` scores a model on."""
import numpy as np
import pytest

from ddyn.data.dataset import Dataset
from ddyn.learn.reference import arc_displacement, constant_motion_errors, format_reference

DT = 0.04


def _dataset(vx, vy, omega, segment=None, x0=1.0, y0=-2.0, yaw0=0.3) -> Dataset:
    """A log whose positions and heading are the exact integral of the given per-row body velocities and yaw
    rate, each held over its sample (what the reference assumes within one step)."""
    n = len(vx)
    states = np.zeros((n, 8))
    states[0, :3] = x0, y0, yaw0
    for k in range(n - 1):
        dx, dy = arc_displacement(vx[k], vy[k], omega[k], states[k, 2], DT)
        states[k + 1, :3] = states[k, 0] + dx, states[k, 1] + dy, states[k, 2] + DT * omega[k]
    states[:, 3], states[:, 4], states[:, 5] = vx, vy, omega
    seg = np.zeros(n, dtype=np.int64) if segment is None else segment
    return Dataset(np.arange(n) * DT, seg, states, np.zeros((n, 2)), DT, "av21")


def test_the_arc_matches_a_fine_numerical_integration():
    vx, vy, omega, yaw = 12.0, 0.7, 0.35, 2.9
    t, m = 0.6, 60000
    s = (np.arange(m) + 0.5) * t / m                    # midpoint rule: error far below the tolerance
    heading = yaw + omega * s
    want = (np.sum(np.cos(heading) * vx - np.sin(heading) * vy) * t / m,
            np.sum(np.sin(heading) * vx + np.cos(heading) * vy) * t / m)
    assert np.allclose(arc_displacement(vx, vy, omega, yaw, t), want, atol=1e-8)


@pytest.mark.parametrize("omega", [0.0, 1e-12, -3e-8])
def test_a_vanishing_yaw_rate_is_a_straight_line(omega):
    dx, dy = arc_displacement(10.0, 1.0, omega, 0.5, 0.6)
    straight = (0.6 * (10.0 * np.cos(0.5) - 1.0 * np.sin(0.5)), 0.6 * (10.0 * np.sin(0.5) + 1.0 * np.cos(0.5)))
    assert np.allclose((dx, dy), straight, atol=1e-9)


def test_constant_motion_is_predicted_exactly():
    n = 200
    ds = _dataset(np.full(n, 14.0), np.full(n, -0.4), np.full(n, 0.25))
    r = constant_motion_errors(ds, tau=3, steps=15)
    assert r["samples"] == n - 3 and r["starts"] == n - 15 - 2
    assert max(r["rmse"].values()) < 1e-12 and r["ade"] < 1e-9 and r["fde"] < 1e-9


def test_the_error_of_a_speeding_car_is_what_the_kinematics_give():
    # vx grows by a per row on a straight: the one-step vx error is a, and after j steps the position is
    # DT * a * j (j - 1) / 2 ahead of the reference's
    n, a, steps = 120, 0.05, 15
    ds = _dataset(10.0 + a * np.arange(n), np.zeros(n), np.zeros(n))
    r = constant_motion_errors(ds, tau=1, steps=steps)
    assert r["rmse"]["vx"] == pytest.approx(a) and r["rmse"]["vy"] == 0 and r["rmse"]["omega"] == 0
    j = np.arange(1, steps + 1)
    assert r["ade"] == pytest.approx(np.mean(DT * a * j * (j - 1) / 2))
    assert r["fde"] == pytest.approx(DT * a * steps * (steps - 1) / 2)
    assert "vx 5.000e-02" in format_reference(r)


def test_no_window_or_start_reads_across_a_segment():
    # two segments of different constant motion, the second starting far away: scored within each, the
    # reference is exact; a window across the cut would see a jump of 5 m/s and 40 m
    first = _dataset(np.full(60, 8.0), np.zeros(60), np.full(60, 0.1))
    second = _dataset(np.full(60, 13.0), np.full(60, 0.2), np.full(60, -0.3), x0=40.0)
    ds = Dataset(np.r_[first.time, second.time + 10], np.r_[np.zeros(60), np.ones(60)].astype(np.int64),
                 np.r_[first.states, second.states], np.zeros((120, 2)), DT, "av21")
    r = constant_motion_errors(ds, tau=2, steps=10)
    assert r["samples"] == 2 * (60 - 2) and r["starts"] == 2 * (60 - 1 - 10)
    assert max(r["rmse"].values()) < 1e-12 and r["fde"] < 1e-9


def test_a_log_too_short_for_the_horizon_has_no_position_figures():
    ds = _dataset(np.full(8, 5.0), np.zeros(8), np.zeros(8))
    r = constant_motion_errors(ds, tau=1, steps=15)
    assert r["starts"] == 0 and np.isnan(r["ade"]) and r["rmse"]["vx"] == 0
