"""The car's EKF (c_src/src/ekf.c) on simulated sensor data with known noise: consistent and better than raw.

Monte Carlo (Bar-Shalom's test): M runs of a truth that follows the model with process
noise of exactly the filter's Q, sensors at their own rates with known Gaussian noise.
At each step the NEES (6 physical states) and, per sensor, the NIS averaged over the M
runs must lie inside the two-sided 95 % chi-square interval for M x dof degrees of
freedom at least 90 % of the time (95 % expected). Then the filtered position, yaw rate
and speed must beat the raw GNSS, gyro and rear wheel speed.
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from ddyn.data import simulate
from ddyn.model import backends, mathns, tracks, vehicle
from ddyn.model.sensors import MEASUREMENTS, measure
from ddyn.paths import BUILD

REPO = Path(__file__).resolve().parents[2]
TOOL = BUILD / "c_src" / "ddyn_ekf_replay"
RUNS, STEPS = 20, 250
Q = np.array([1e-10, 1e-10, 1e-10, 1e-6, 1e-6, 1e-4, 1e-12, 1e-12])
P0 = np.array([1e-4, 1e-4, 1e-4, 1e-3, 1e-4, 1e-2, 1e-10, 1e-10])
# sensor: (every n steps, noise std per component)
SENSORS = {"gnss_position": (5, [0.005, 0.005]), "heading": (5, [0.01]), "yaw_rate": (1, [0.05]),
           "acceleration": (1, [0.2, 0.2]), "wheel_speed": (1, [0.02, 0.02]), "steering": (2, [0.002])}
KIND = {name: i for i, name in enumerate(MEASUREMENTS)}


def _fmt(a) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(a))


@pytest.fixture(scope="module")
def runs(shared_data):
    if not TOOL.is_file():
        pytest.fail(f"{TOOL} missing: build the C side first (scripts/test.sh does)")
    v = vehicle.load("orca_1_43")
    c = v.true_vector()
    ds = simulate.simulate(v, tracks.load_track("ethz"), duration=STEPS * v.sample_time + 1, seed=9, progress=False)
    inputs = ds.inputs[:STEPS]
    out = []
    for run in range(RUNS):
        rng = np.random.default_rng(run)
        truth = [ds.states[0]]
        for k in range(STEPS):
            nxt = backends.step_numpy(truth[-1], inputs[k], c, v.known, v.sample_time)
            truth.append(nxt + rng.standard_normal(8) * np.sqrt(Q))
        truth = np.array(truth)
        x0 = truth[0] + rng.standard_normal(8) * np.sqrt(P0)
        lines, raw = [f"I {_fmt(x0)} {_fmt(P0)} {_fmt(Q)}"], {n: [] for n in SENSORS}
        for k in range(STEPS):
            lines.append(f"P {_fmt(inputs[k])} {_fmt(c)}")
            for name, (every, std) in SENSORS.items():
                if (k + 1) % every == 0:
                    h = np.array(measure(mathns.NUMPY, name, truth[k + 1], c, v.known))
                    z = h + rng.standard_normal(len(h)) * std
                    raw[name].append((k + 1, z))
                    lines.append(f"M {KIND[name]} {_fmt(c)} {_fmt(z)} {_fmt(np.square(std))}")
            lines.append("O")
        proc = subprocess.run([str(TOOL), v.name, "euler"], input="\n".join(lines) + "\n", capture_output=True,
                              text=True)
        assert proc.returncode == 0, proc.stderr
        est, nis = [], {n: [] for n in SENSORS}
        order = iter([name for k in range(STEPS) for name, (every, _) in SENSORS.items() if (k + 1) % every == 0])
        for row in proc.stdout.splitlines():
            if row.startswith("nis"):
                nis[next(order)].append(float(row.split()[1]))
            else:
                est.append(np.array(row.split(), dtype=float))
        est = np.array(est)
        out.append({"truth": truth[1:], "x": est[:, :8], "P": est[:, 8:].reshape(-1, 8, 8).transpose(0, 2, 1),
                    "nis": nis, "raw": raw})
    return out


def _inside(avg: np.ndarray, dof: int) -> float:
    lo, hi = chi2.ppf(0.025, RUNS * dof) / RUNS, chi2.ppf(0.975, RUNS * dof) / RUNS
    return float(np.mean((avg >= lo) & (avg <= hi)))


def test_nees_inside_chi_square_bounds(runs):
    idx = slice(0, 6)
    nees = []
    for r in runs:
        e = r["truth"][:, idx] - r["x"][:, idx]
        e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
        nees.append(np.einsum("ki,kij,kj->k", e, np.linalg.inv(r["P"][:, idx, idx]), e))
    share = _inside(np.mean(nees, axis=0)[20:], 6)  # after the initial transient
    assert share >= 0.9, f"averaged NEES inside its 95 % bounds only {share:.0%} of the time"


@pytest.mark.parametrize("name", list(SENSORS))
def test_nis_inside_chi_square_bounds(runs, name):
    avg = np.mean([r["nis"][name] for r in runs], axis=0)
    share = _inside(avg, MEASUREMENTS[name])
    assert share >= 0.9, f"{name}: averaged NIS inside its 95 % bounds only {share:.0%} of the time"


def test_filter_beats_raw_sensors(runs):
    def rmse(a):
        return float(np.sqrt(np.mean(np.square(a))))

    pos_raw, pos_f, wz_raw, wz_f, v_raw, v_f = [], [], [], [], [], []
    for r in runs:
        for k, z in r["raw"]["gnss_position"]:
            pos_raw.append(z - r["truth"][k - 1, :2])
            pos_f.append(r["x"][k - 1, :2] - r["truth"][k - 1, :2])
        for k, z in r["raw"]["yaw_rate"]:
            wz_raw.append(z[0] - r["truth"][k - 1, 5])
            wz_f.append(r["x"][k - 1, 5] - r["truth"][k - 1, 5])
        for k, z in r["raw"]["wheel_speed"]:
            v_raw.append(z[1] - r["truth"][k - 1, 3])
            v_f.append(r["x"][k - 1, 3] - r["truth"][k - 1, 3])
    assert rmse(pos_f) < 0.7 * rmse(pos_raw), (rmse(pos_f), rmse(pos_raw))
    assert rmse(wz_f) < 0.7 * rmse(wz_raw), (rmse(wz_f), rmse(wz_raw))
    assert rmse(v_f) < 0.7 * rmse(v_raw), (rmse(v_f), rmse(v_raw))
