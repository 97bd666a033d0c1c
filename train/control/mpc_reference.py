"""The reference MPC: the same problem as the C one, solved to convergence with CasADi + IPOPT.

This is the papers' approach (a CasADi NLP handed to IPOPT every control period), built ONCE with
parameters and re-solved each step with a warm start: multiple shooting over the same prediction
step (ddyn.model.backends with the C MPC's discretisation), the same cost (position error to the
time-parameterised raceline reference weighted by Q, input rates by R, track slacks by the exact L1
plus quadratic penalty), the same bounds (input rates; throttle and steering as states, widened
to what the rate limits can reach when x0 lies outside them) and the same track half-planes
(ddyn.control.mpc_setup.TableGeometry repeats mpc.c's rules). The C MPC differs in how it solves: one
Gauss-Newton SQP step per period (real-time iteration) with a capped interior-point QP.

`solver="sqpmethod"` builds the same NLP for CasADi's SQP method with its qrqp QP solver instead.
"""
from __future__ import annotations

import time
from pathlib import Path

import casadi as ca
import numpy as np

from ddyn.control.mpc_setup import MpcSettings, TableGeometry, launch_accel, raceline_table
from ddyn.errors import DdynError
from ddyn.model import backends
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import N_COEFF, N_INPUT, N_STATE
from ddyn.model.tracks import Track

_SUBSTEPS = {"rk4_single": ("rk4", 1), "euler": ("euler", 1)}


def _step_expr(v, settings: MpcSettings, x, u, c):
    method, sub = _SUBSTEPS.get(settings.disc, ("rk4", v.rk4_substeps))
    return backends.casadi_step_expr(x, u, c, v.known, v.sample_time, method, sub)


class ReferenceMPC:
    """One parametric NLP, solved per control period. solve(x0) -> first input, plan, info."""

    def __init__(self, vehicle_name: str, table: dict, settings: MpcSettings, solver: str = "ipopt",
                 coeffs: np.ndarray | None = None):
        v = vehicle_mod.load(vehicle_name)
        self.v, self.s, self.geo = v, settings, TableGeometry(table)
        self.c = v.true_vector() if coeffs is None else np.asarray(coeffs, float)
        H, s = settings.horizon, settings
        lim = v.input_limits
        self.rate_lo = np.array([lim["dthrottle"][0], lim["dsteering"][0]])
        self.rate_hi = np.array([lim["dthrottle"][1], lim["dsteering"][1]])
        self.state_lo = np.array([lim["throttle"][0], lim["steering"][0]])
        self.state_hi = np.array([lim["throttle"][1], lim["steering"][1]])
        xs, us, cs = backends.casadi_symbols()
        f = ca.Function("f", [xs, us, cs], [_step_expr(v, s, xs, us, cs)])
        X = ca.SX.sym("X", N_STATE, H + 1)
        U = ca.SX.sym("U", N_INPUT, H)
        S = ca.SX.sym("S", H)
        P = ca.SX.sym("P", N_STATE + N_COEFF + 2 * H + 6 * H + 4 * H)
        x0 = P[:N_STATE]
        c = P[N_STATE:N_STATE + N_COEFF]
        o = N_STATE + N_COEFF
        ref = ca.reshape(P[o:o + 2 * H], 2, H)
        o += 2 * H
        plane = ca.reshape(P[o:o + 6 * H], 6, H)
        o += 6 * H
        sbound = ca.reshape(P[o:o + 4 * H], 4, H)  # lo T, lo d, hi T, hi d (widened)
        cost, g, lbg, ubg = 0, [X[:, 0] - x0], [np.zeros(N_STATE)], [np.zeros(N_STATE)]
        for k in range(H):
            g.append(X[:, k + 1] - f(X[:, k], U[:, k], c))
            lbg.append(np.zeros(N_STATE))
            ubg.append(np.zeros(N_STATE))
            w = s.q_terminal if k == H - 1 else 1.0
            e = X[0:2, k + 1] - ref[:, k]
            cost += w * (s.q_x * e[0] ** 2 + s.q_y * e[1] ** 2)
            cost += s.r_dthrottle * U[0, k] ** 2 + s.r_dsteering * U[1, k] ** 2
            cost += s.slack_l1 * S[k] + s.slack_l2 * S[k] ** 2
            lat = plane[2, k] * (X[0, k + 1] - plane[0, k]) + plane[3, k] * (X[1, k + 1] - plane[1, k])
            g += [lat - S[k] - plane[4, k], lat + S[k] + plane[5, k], X[6:8, k + 1] - sbound[0:2, k],
                  X[6:8, k + 1] - sbound[2:4, k]]
            lbg += [[-np.inf], [0.0], [0.0, 0.0], [-np.inf, -np.inf]]
            ubg += [[0.0], [np.inf], [np.inf, np.inf], [0.0, 0.0]]
        self.nx = N_STATE * (H + 1)
        z = ca.vertcat(ca.vec(X), ca.vec(U), S)
        nlp = {"x": z, "f": cost, "g": ca.vertcat(*g), "p": P}
        if solver == "ipopt":
            opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.tol": 1e-8,
                    "ipopt.max_iter": 300, "ipopt.warm_start_init_point": "no"}
        elif solver == "sqpmethod":
            opts = {"qpsol": "qrqp", "print_time": False, "print_header": False, "print_iteration": False,
                    "print_status": False, "qpsol_options": {"print_iter": False, "print_header": False,
                                                             "error_on_fail": False},
                    "max_iter": 50, "error_on_fail": False}
        else:
            raise ValueError(f"unknown solver {solver!r}")
        self.solver = ca.nlpsol("mpc", solver, nlp, opts)
        self.lbg, self.ubg = np.concatenate([np.ravel(a) for a in lbg]), np.concatenate([np.ravel(a) for a in ubg])
        lbx = np.concatenate([np.full(self.nx, -np.inf), np.tile(self.rate_lo, H), np.zeros(H)])
        ubx = np.concatenate([np.full(self.nx, np.inf), np.tile(self.rate_hi, H), np.full(H, np.inf)])
        self.lbx, self.ubx = lbx, ubx
        self.f = f
        self.u_plan = np.zeros((H, 2))
        self.z = None
        self.hint = -1

    def _simulate(self, x0: np.ndarray, U: np.ndarray) -> np.ndarray:
        xs = [np.asarray(x0, float)]
        for k in range(len(U)):
            xs.append(np.asarray(self.f(xs[-1], U[k], self.c)).ravel())
        return np.array(xs)

    def solve(self, x0: np.ndarray) -> tuple[np.ndarray, dict]:
        H, dt = self.s.horizon, self.v.sample_time
        u_lin = np.vstack([self.u_plan[1:], self.u_plan[-1:]])
        u_lin = np.clip(u_lin, self.rate_lo, self.rate_hi)
        x_lin = self._simulate(x0, u_lin)
        i0, refs, planes = self.geo.stage_geometry(x0, x_lin[:, :2], dt, self.hint,
                                                   launch_accel(self.v, self.c, x0, self.state_hi[0]))
        self.hint = i0
        k = np.arange(1, H + 1)[:, None]
        lo = np.minimum(self.state_lo, x0[6:8] + k * dt * self.rate_hi)
        hi = np.maximum(self.state_hi, x0[6:8] + k * dt * self.rate_lo)
        p = np.concatenate([x0, self.c, refs[1:].ravel(), planes[1:].ravel(), np.hstack([lo, hi]).ravel()])
        # warm start: the shifted previous plan (as the C MPC's linearisation point)
        z0 = np.concatenate([x_lin.ravel(), u_lin.ravel(), np.zeros(H)])
        t0 = time.perf_counter()
        sol = self.solver(x0=z0, p=p, lbx=self.lbx, ubx=self.ubx, lbg=self.lbg, ubg=self.ubg)
        elapsed = time.perf_counter() - t0
        z = np.asarray(sol["x"]).ravel()
        self.z = z
        U = z[self.nx:self.nx + 2 * H].reshape(H, 2)
        self.u_plan = np.clip(U, self.rate_lo, self.rate_hi)
        try:
            stats = self.solver.stats()
        except RuntimeError:  # a generated (external) solver keeps no statistics
            stats = {}
        return self.u_plan[0].copy(), {"solve_s": elapsed, "success": bool(stats.get("success", False)),
                                       "iterations": int(stats.get("iter_count", -1)),
                                       "plan_x": z[:self.nx].reshape(H + 1, N_STATE)}


def generate_solver(mpc: ReferenceMPC, cache_dir: Path) -> ca.Function:
    """CasADi's code generation of the whole sqpmethod + qrqp solver, compiled and loaded.

    The generated C (several MB) is compiled once per distinct text (cached under cache_dir by its
    hash; -O1 keeps the compile near a minute) and loaded with casadi.external.
    """
    import hashlib
    import subprocess
    import tempfile

    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        cg = ca.CodeGenerator("mpc_sqp.c", {"with_header": False})
        cg.add(mpc.solver)
        cg.generate(tmp + "/")
        text = (Path(tmp) / "mpc_sqp.c").read_bytes()
    lib = cache_dir / f"mpc_sqp_{hashlib.sha256(text).hexdigest()[:16]}.so"
    if not lib.is_file():
        src = lib.with_suffix(".c")
        src.write_bytes(text)
        proc = subprocess.run(["cc", "-O1", "-shared", "-fPIC", str(src), "-o", str(lib), "-lm"],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            raise DdynError(f"compiling the generated sqpmethod failed: {proc.stderr[-400:]}")
    return ca.external("mpc", str(lib))


def closed_loop(vehicle_name: str, track: Track, settings: MpcSettings, steps: int, solver: str = "ipopt",
                x0: np.ndarray | None = None, generated_dir: Path | None = None) -> dict:
    """Drive the plant (RK4 model step, true coefficients) with the reference MPC.

    solver "ipopt" or "sqpmethod"; with generated_dir, the sqpmethod solver is code-generated,
    compiled and loaded (generate_solver) instead of run by CasADi's virtual machine.
    """
    from ddyn.control.mpc_setup import start_state

    v = vehicle_mod.load(vehicle_name)
    table = raceline_table(track, vehicle_name, settings)
    mpc = ReferenceMPC(vehicle_name, table, settings, solver)
    if generated_dir is not None:
        mpc.solver = generate_solver(mpc, generated_dir)
    plant = backends.casadi_step_function(v.known, v.sample_time, "rk4", v.rk4_substeps)
    c = v.true_vector()
    x = start_state(table) if x0 is None else np.asarray(x0, float)
    xs, us, solve_ms, ok, iters = [x], [], [], [], []
    for _ in range(steps):
        u, info = mpc.solve(x)
        x = np.asarray(plant(x, u, c)).ravel()
        xs.append(x)
        us.append(u)
        solve_ms.append(info["solve_s"] * 1e3)
        ok.append(info["success"])
        iters.append(info["iterations"])
    return {"x": np.array(xs), "u": np.array(us), "solve_ms": np.array(solve_ms), "success": np.array(ok),
            "iterations": np.array(iters), "dt": v.sample_time}
