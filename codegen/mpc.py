"""`ddyn codegen model`, MPC part: the MPC's prediction step and each vehicle's input limits.

c_src/generated/ddyn_mpc_model.c/.h  ddyn_<vehicle>_mpc_step(x, u, c, road) -> x_next, A, B: one RK4 step
    over the whole sample time (a single sub-step) with its Jacobians wrt x and u, in one function.
    road = (bank, grade) (rad, held over the step): the road at the stage's track position, the bank's
    lateral gravity g sin(bank) on dvy (+ to the left) and the grade's longitudinal -g sin(grade) on dvx
    (+ uphill) from ddyn.model.effects.derivatives (Aux.bank, Aux.grade, no other effect), the terms the
    Python model carries; (0, 0) is the flat road's step (issue 34: a bank- and grade-aware controller).
    Why: the plant's RK4 Jacobian function (4 sub-steps, and dx/dc, which the MPC does not need)
    costs ~9 us per call, 20 of them per MPC step; the single-step one is 4x cheaper and stays
    within ~0.5 mm of the 4-sub-step RK4 over 10 steps at the 1:43 car's racing speeds (Euler at the
    same cost is off by centimetres). docs/mpc.md has the measurement.
c_src/generated/ddyn_mpc_limits.h    the vehicle file's input_limits (rates dthrottle, dsteering,
    states throttle, steering), for ddyn_mpc_default_config, plus the table of the functions above.
Byte-reproducible, with the banner of the model code (hashes of the model sources and vehicle files).
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import casadi as ca

from ddyn.codegen.c_text import c_double
from ddyn.model import backends, effects, integrators, mathns
from ddyn.model.single_track import N_COEFF, N_INPUT, N_STATE
from ddyn.model.vehicle import Vehicle

MPC_RK4_SUBSTEPS = 1


def mpc_step_expr(x, u, c, road, v: Vehicle):
    """The MPC's step: RK4 of the model on the road (bank, grade) (ddyn.model.effects, no other effect)."""
    ns = mathns.get("casadi")
    uu, cc = tuple(u[i] for i in range(N_INPUT)), tuple(c[i] for i in range(N_COEFF))
    fx, aux = effects.EffectSet(), effects.Aux(bank=road[0], grade=road[1])

    def f(s):
        return effects.derivatives(ns, s, uu, cc, v.known, fx, aux)

    return ca.vertcat(*integrators.step(f, tuple(x[i] for i in range(N_STATE)), v.sample_time, "rk4",
                                        MPC_RK4_SUBSTEPS))


def mpc_step_function(v: Vehicle) -> ca.Function:
    x, u, c = backends.casadi_symbols()
    road = ca.SX.sym("road", 2)   # (bank, grade)
    nxt = mpc_step_expr(x, u, c, road, v)
    return ca.Function(f"ddyn_{v.name}_mpc_step", [x, u, c, road],
                       [nxt, ca.densify(ca.jacobian(nxt, x)), ca.densify(ca.jacobian(nxt, u))],
                       ["x", "u", "c", "road"], ["x_next", "A", "B"])


def generate_step(vehicles: list[Vehicle], out: Path, banner, options: dict) -> tuple[list[Path], list[ca.Function]]:
    funcs = [mpc_step_function(v) for v in vehicles]
    cg = ca.CodeGenerator("ddyn_mpc_model.c", options)
    for f in funcs:
        cg.add(f)
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        cg.generate(tmp + "/")
        for ext in (".c", ".h"):
            text = (Path(tmp) / f"ddyn_mpc_model{ext}").read_text()
            target = Path(out) / f"ddyn_mpc_model{ext}"
            what = ("The MPC's prediction step: single-step RK4, the road's bank and grade an input (ddyn.model.effects), "
                    "Jacobians wrt x, u.")
            target.write_text(banner(what, vehicles) + text)
            written.append(target)
    return written, funcs

# order of the four limits in each table row (lo, hi each)
LIMIT_ORDER = ("dthrottle", "dsteering", "throttle", "steering")


def generate(vehicles: list[Vehicle], out: Path, banner, options: dict) -> list[Path]:
    written, funcs = generate_step(vehicles, out, banner, options)
    return written + generate_limits(vehicles, out, banner, funcs)


def generate_limits(vehicles: list[Vehicle], out: Path, banner, funcs: list[ca.Function]) -> list[Path]:
    lines = [banner("Input limits of each vehicle (vehicle files' input_limits) for the MPC defaults.", vehicles),
             "#ifndef DDYN_MPC_LIMITS_H", "#define DDYN_MPC_LIMITS_H", "",
             '#include "ddyn/model.h"', '#include "ddyn_mpc_model.h"', "",
             "/* work sizes of the MPC step functions */",
             f"#define DDYN_MPC_STEP_SZ_W {max(max(f.sz_w() for f in funcs), 1)}",
             f"#define DDYN_MPC_STEP_SZ_IW {max(max(f.sz_iw() for f in funcs), 1)}",
             f"#define DDYN_MPC_STEP_SUBSTEPS {MPC_RK4_SUBSTEPS}", "",
             "/* one row per vehicle: name, lo, hi of " + ", ".join(LIMIT_ORDER) + ", the MPC step */",
             "typedef struct {", "    const char *name;", "    double lo_hi[4][2];", "    ddyn_casadi_fn step;",
             "} ddyn_mpc_vehicle_limits;", "",
             f"#define DDYN_MPC_LIMITS_COUNT {len(vehicles)}",
             "static const ddyn_mpc_vehicle_limits ddyn_mpc_limits[DDYN_MPC_LIMITS_COUNT] = {"]
    for v in vehicles:
        rows = ", ".join("{" + f"{c_double(v.input_limits[k][0])}, {c_double(v.input_limits[k][1])}" + "}"
                         for k in LIMIT_ORDER)
        lines.append(f'    {{"{v.name}", {{{rows}}}, ddyn_{v.name}_mpc_step}},')
    lines += ["};", "", "#endif", ""]
    path = Path(out) / "ddyn_mpc_limits.h"
    path.write_text("\n".join(lines))
    return [path]
