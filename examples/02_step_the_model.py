"""02: load a vehicle and step the one single-track model with numpy, torch and CasADi.

Shows: ddyn.load_vehicle, the model's state/input/coefficient order (ddyn.model.single_track), one RK4 step of
the same Python model evaluated three ways (ddyn.model.backends) and how closely they agree, and a Jacobian
from torch autograd against CasADi's symbolic one.
Run:   .venv/bin/python examples/02_step_the_model.py [--vehicle orca_1_43] [--cases 200]
Takes a few seconds.
"""
import argparse

import casadi as ca
import numpy as np
import torch

import ddyn
from ddyn.model import backends
from ddyn.model.sampling import random_cases
from ddyn.model.single_track import COEFF_NAMES, INPUT_NAMES, STATE_NAMES

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--vehicle", default="orca_1_43")
parser.add_argument("--cases", type=int, default=200)
args = parser.parse_args()

car = ddyn.load_vehicle(args.vehicle)
k, dt, sub = car.known, car.sample_time, car.rk4_substeps
print(f"vehicle {car.name}: mass {k.mass:g} kg, lf {k.lf:g} m, lr {k.lr:g} m, sample time {dt:g} s, "
      f"RK4 sub-steps {sub}, drivetrain {k.drivetrain}")
print(f"state  {', '.join(STATE_NAMES)}\ninputs {', '.join(INPUT_NAMES)}\ncoeffs {', '.join(COEFF_NAMES)}")

# one state at speed, the vehicle file's true coefficients
x = np.array([0.0, 0.0, 0.0, 0.6 * car.max_speed, 0.05, 0.5, 0.3, 0.1])
u = np.array([0.5, -0.2])
c = car.true_vector()
nxt = backends.step_numpy(x, u, c, k, dt, "rk4", sub)
print("one RK4 step from vx {:.3f}: next vx {:.6f} vy {:.6f} omega {:.6f}".format(x[3], nxt[3], nxt[4], nxt[5]))

# many random cases over the vehicle's envelope, the three evaluations of the same model
X, U, C = random_cases(car, args.cases, np.random.default_rng(0))
a = backends.step_numpy(X, U, C, k, dt, "rk4", sub)
b = backends.step_torch(*(torch.tensor(v, dtype=torch.float64) for v in (X, U, C)), k, dt, "rk4", sub).numpy()
f = backends.casadi_step_function(k, dt, "rk4", sub)
cs = np.array(f.map(args.cases)(X.T, U.T, C.T)).T


def rel(p, q):
    return float(np.max(np.abs(p - q) / (np.abs(q) + 1.0)))


print(f"{args.cases} random cases: largest relative difference numpy-torch {rel(a, b):.2e}, numpy-CasADi "
      f"{rel(a, cs):.2e}")

# d x_next / d x: torch autograd against CasADi's symbolic Jacobian
J_torch = torch.autograd.functional.jacobian(
    lambda xx: backends.step_torch(xx, torch.tensor(u), torch.tensor(c), k, dt, "rk4", sub),
    torch.tensor(x)).numpy()
xs, us, cs_ = backends.casadi_symbols()
jac = ca.Function("step_dx", [xs, us, cs_], [ca.jacobian(backends.casadi_step_expr(xs, us, cs_, k, dt, "rk4", sub), xs)])
J_casadi = np.array(jac(x, u, c))
print(f"Jacobian d x_next / d x (8x8): largest difference torch-CasADi {np.max(np.abs(J_torch - J_casadi)):.2e}; "
      f"d vx_next / d vx = {J_casadi[3, 3]:.6f}")
