"""The one model evaluated by numpy, torch and CasADi agrees to 1e-12 (float64)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ddyn.analysis import fidelity
from ddyn.model import backends, vehicle
from ddyn.model.sampling import random_cases
from ddyn.model.single_track import N_STATE

N_CASES = 4000
RTOL = 1e-12


@pytest.mark.parametrize("name", ["orca_1_43", "av21"])
@pytest.mark.parametrize("method", ["euler", "rk4"])
def test_numpy_torch_casadi_agree(name, method):
    diff = fidelity.backend_agreement(name, method, N_CASES)
    assert diff["torch"] <= RTOL and diff["casadi"] <= RTOL, diff


def test_low_speed_is_defined_and_continuous():
    """At and below v_min the slip angles use v_min: finite values, finite gradients, no jump at vx = 0."""
    v = vehicle.load("orca_1_43")
    c = v.true_vector()
    base = np.array([0.0, 0.0, 0.0, 0.0, 0.02, 0.5, 0.3, 0.1])
    vxs = np.array([-1e-3, -1e-9, 0.0, 1e-9, 1e-3, v.known.v_min, 2 * v.known.v_min])
    x = np.tile(base, (len(vxs), 1))
    x[:, 3] = vxs
    xn = backends.step_numpy(x, np.zeros((len(vxs), 2)), c, v.known, v.sample_time)
    assert np.all(np.isfinite(xn))
    # no jump across zero: vy, omega derivatives are identical for |vx| below v_min up to the vx terms
    assert np.allclose(xn[1:4, 5], xn[2, 5], rtol=0, atol=1e-6)

    xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    out = backends.step_torch(xt, torch.zeros(len(vxs), 2, dtype=torch.float64),
                              torch.tensor(c, dtype=torch.float64), v.known, v.sample_time)
    out[:, 3:6].sum().backward()
    assert torch.isfinite(xt.grad).all(), "gradients at low speed must be finite"


def test_discretisations_converge_at_their_order():
    """Euler's error halves when the step halves (order 1); RK4's falls ~16x (order 4)."""
    v = vehicle.load("av21")
    x, u, c = random_cases(v, 50, np.random.default_rng(3))
    x[:, 3] = np.abs(x[:, 3]) + 5.0  # away from standstill, where the flow is smooth
    dt, vel = v.sample_time, slice(3, 6)
    exact = backends.step_numpy(x, u, c, v.known, dt, "rk4", 256)

    def err(method, n):
        if method == "rk4":
            y = backends.step_numpy(x, u, c, v.known, dt, "rk4", n)
        else:
            y = x
            for _ in range(n):
                y = backends.step_numpy(y, u, c, v.known, dt / n, "euler")
        return np.abs(y[:, vel] - exact[:, vel]).max()

    euler_ratio = err("euler", 100) / err("euler", 200)
    rk4_ratio = err("rk4", 8) / err("rk4", 16)
    assert 1.8 < euler_ratio < 2.2, euler_ratio
    assert 12 < rk4_ratio < 20, rk4_ratio


def test_state_dimension_checked():
    v = vehicle.load("orca_1_43")
    with pytest.raises(ValueError, match="last dimension must be 8"):
        backends.step_numpy(np.zeros(N_STATE - 1), np.zeros(2), v.true_vector(), v.known, 0.02)
