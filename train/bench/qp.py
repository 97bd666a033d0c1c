"""`ddyn bench qp`: the MPC's own QP solver (c_src/src/mpc_qp.c) against DAQP, PIQP and ProxQP (proxsuite).

The QPs are those of a closed-loop lap: ddyn_mpc_lap (c_src/tools/mpc_lap.c) drives the simulated car
with the C MPC and dumps every step's condensed QP (c_src/tools/qp_dump.h). ddyn_qp_replay
(c_src/tools/qp_replay.c) solves each with mpc_qp.c (the interior point, `qp_solver = ipm`: double, its
iteration cap and tolerance), with the float32 build of the same solver, tightly (50 iterations, 1e-10),
and with the runtime's DAQP path (c_src/src/mpc_qp_daqp.c, the default `qp_solver = daqp`: DAQP's core
on the static workspace, warm-started from the previous QP's working set shifted one stage). Here
each QP is written in standard form (variables z, s; objective 1/2 z'Hz + f'z + rho1 1's + rho2 s's;
bounds on z and s >= 0; the integrator rows; the soft rows as two one-sided rows each) and solved
by DAQP (dual active set, warm-started with the previous QP's multipliers), PIQP (proximal interior
point, cold) and ProxQP (proximal augmented Lagrangian, cold: warm-started from the previous result it
did not return on this lap).
Accuracy is measured against PIQP at eps_abs 1e-10, eps_rel 0 (its answers are feasible to round-off),
checked against ProxQP at 1e-10 (their objectives differ by ~1e-6 relative: these QPs are ill-conditioned
in the late stages' inputs, whose effect on the cost is small).
Times: mpc_qp.c in C (median of REPEATS solves of each QP), the libraries' own reported solve times
(without the Python call overhead), on this host.
"""
from __future__ import annotations

import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.paths import BUILD

DEFAULT_BUILD = BUILD / "c_src"
INF = 1e30  # DAQP's infinity; PIQP and ProxQP get np.inf
RUNS = ("ipm", "f32", "tight", "daqp", "daqp_cold")  # ddyn_qp_replay's runs, in its order


def read_dump(path: Path) -> list[dict]:
    """The QPs of a ddyn_mpc_lap dump (layout in c_src/tools/qp_dump.h)."""
    raw = np.fromfile(path, dtype="<f8")
    qps, i = [], 0
    while i < raw.size:
        m = int(raw[i]); n = 2 * m
        rec = {"H": m, "dt": raw[i + 1], "rho1": raw[i + 2], "rho2": raw[i + 3],
               "iterations": int(raw[i + 4]), "converged": int(raw[i + 5])}
        i += 6
        rec["hess"] = raw[i:i + n * n].reshape(n, n).T.copy(); i += n * n
        for k in ("grad", "lb", "ub", "hard_lo", "hard_hi"):
            rec[k] = raw[i:i + n]; i += n
        rec["soft_row"] = raw[i:i + m * n].reshape(m, n); i += m * n
        for k in ("soft_lo", "soft_hi"):
            rec[k] = raw[i:i + m]; i += m
        rec["z"] = raw[i:i + n]; i += n
        rec["slack"] = raw[i:i + m]; i += m
        qps.append(rec)
    return qps


def read_replay(path: Path, qps: list[dict]) -> dict:
    """ddyn_qp_replay's output: per run (ipm, f32, tight, daqp, daqp_cold) iterations, converged, us, x = (z, s)."""
    raw = np.fromfile(path, dtype="<f8")
    out = {k: {"iterations": [], "converged": [], "us": [], "x": []} for k in RUNS}
    i = 0
    for qp in qps:
        m = qp["H"]; size = 3 + 3 * m
        for k in RUNS:
            r = raw[i:i + size]; i += size
            out[k]["iterations"].append(int(r[0])); out[k]["converged"].append(int(r[1]))
            out[k]["us"].append(r[2]); out[k]["x"].append(r[3:].copy())
    return out


def standard_form(qp: dict) -> dict:
    """min 1/2 x'Px + q'x, x_l <= x <= x_u, g_l <= G x <= g_u with x = (z, s)."""
    m, n = qp["H"], 2 * qp["H"]
    P = np.zeros((n + m, n + m))
    P[:n, :n] = 0.5 * (qp["hess"] + qp["hess"].T)
    P[n:, n:] = 2.0 * qp["rho2"] * np.eye(m)
    q = np.concatenate([qp["grad"], np.full(m, qp["rho1"])])
    C = np.zeros((n, n + m))  # integrator rows: r = 2(k-1)+ch, dt * sum_{j<k} z[2j+ch]
    for k in range(1, m + 1):
        for ch in range(2):
            C[2 * (k - 1) + ch, [2 * j + ch for j in range(k)]] = qp["dt"]
    Gp = np.hstack([qp["soft_row"], np.eye(m)])   # g'z + s >= soft_lo
    Gm = np.hstack([qp["soft_row"], -np.eye(m)])  # g'z - s <= soft_hi
    G = np.vstack([C, Gp, Gm])
    g_l = np.concatenate([qp["hard_lo"], qp["soft_lo"], np.full(m, -INF)])  # +-INF: no bound
    g_u = np.concatenate([qp["hard_hi"], np.full(m, INF), qp["soft_hi"]])
    x_l = np.concatenate([qp["lb"], np.zeros(m)])
    x_u = np.concatenate([qp["ub"], np.full(m, INF)])
    return {"P": P, "q": q, "G": G, "g_l": g_l, "g_u": g_u, "x_l": x_l, "x_u": x_u}


def _inf(v: np.ndarray) -> np.ndarray:
    """PIQP: no bound is +-inf."""
    return np.where(v >= INF, np.inf, np.where(v <= -INF, -np.inf, v))


def _big(v: np.ndarray) -> np.ndarray:
    """ProxQP: no bound is +-1e20 (its dense solver crashed on inf here)."""
    return np.clip(v, -1e20, 1e20)


def objective(sf: dict, x: np.ndarray) -> float:
    return float(0.5 * x @ sf["P"] @ x + sf["q"] @ x)


def violation(sf: dict, x: np.ndarray) -> float:
    gx = sf["G"] @ x
    return float(max(np.max(sf["x_l"] - x), np.max(x - sf["x_u"]), np.max(sf["g_l"] - gx), np.max(gx - sf["g_u"]), 0.0))


def solve_proxqp(forms: list[dict], eps: float, warm: bool) -> dict:
    import proxsuite
    out = {"iterations": [], "us": [], "x": [], "converged": []}
    N, nin = forms[0]["P"].shape[0], forms[0]["G"].shape[0]
    solver = None
    for sf in forms:
        fresh = solver is None or not warm
        if fresh:
            solver = proxsuite.proxqp.dense.QP(N, 0, nin, True)
            solver.settings.eps_abs = eps
            solver.settings.eps_rel = 0.0
            solver.settings.max_iter = 10000
            solver.settings.compute_timings = True
            solver.init(sf["P"], sf["q"], None, None, sf["G"], _big(sf["g_l"]), _big(sf["g_u"]),
                        _big(sf["x_l"]), _big(sf["x_u"]))
        else:
            solver.update(sf["P"], sf["q"], None, None, sf["G"], _big(sf["g_l"]), _big(sf["g_u"]),
                          _big(sf["x_l"]), _big(sf["x_u"]))
        solver.solve()
        if warm and fresh:  # only once a result exists: set before the first solve, ProxQP 0.8.0 crashes
            solver.settings.initial_guess = proxsuite.proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
        r = solver.results
        out["iterations"].append(int(r.info.iter)); out["us"].append(float(r.info.solve_time))
        out["x"].append(np.array(r.x)); out["converged"].append(int(r.info.status == proxsuite.proxqp.PROXQP_SOLVED))
    return out


def solve_piqp(forms: list[dict], eps: float) -> dict:
    import piqp
    out = {"iterations": [], "us": [], "x": [], "converged": []}
    for sf in forms:
        s = piqp.DenseSolver()
        s.settings.eps_abs = eps
        s.settings.eps_rel = 0.0 if eps < 1e-8 else eps
        s.settings.max_iter = 1000
        s.settings.compute_timings = True
        s.setup(np.asfortranarray(sf["P"]), sf["q"], None, None, np.asfortranarray(sf["G"]), _inf(sf["g_l"]),
                _inf(sf["g_u"]), _inf(sf["x_l"]), _inf(sf["x_u"]))
        status = s.solve()
        out["iterations"].append(int(s.result.info.iter)); out["us"].append(1e6 * float(s.result.info.solve_time))
        out["x"].append(np.array(s.result.x)); out["converged"].append(int(status == piqp.PIQP_SOLVED))
    return out


def solve_daqp(forms: list[dict], warm: bool) -> dict:
    import daqp
    out = {"iterations": [], "us": [], "x": [], "converged": []}
    lam = None
    for sf in forms:
        kw = {"dual_start": lam} if warm and lam is not None else {}
        x, _, flag, info = daqp.solve(sf["P"], sf["q"], sf["G"], np.concatenate([sf["x_u"], sf["g_u"]]),
                                      np.concatenate([sf["x_l"], sf["g_l"]]), **kw)
        lam = np.array(info["lam"])
        out["iterations"].append(int(info["iterations"])); out["us"].append(1e6 * float(info["solve_time"]))
        out["x"].append(np.array(x)); out["converged"].append(int(flag == 1))
    return out


def accuracy(name: str, res: dict, forms: list[dict], ref: list[np.ndarray]) -> dict:
    f_ref = np.array([objective(sf, x) for sf, x in zip(forms, ref)])
    f = np.array([objective(sf, x) for sf, x in zip(forms, res["x"])])
    rel = np.abs(f - f_ref) / np.maximum(1.0, np.abs(f_ref))
    dz = np.array([np.max(np.abs(x[:len(x) * 2 // 3] - r[:len(r) * 2 // 3])) for x, r in zip(res["x"], ref)])
    du0 = np.array([np.max(np.abs(x[:2] - r[:2])) for x, r in zip(res["x"], ref)])
    viol = np.array([violation(sf, x) for sf, x in zip(forms, res["x"])])
    it = np.array(res["iterations"]); us = np.array(res["us"])
    ok = np.array(res["converged"], dtype=bool)  # a capped QP's iterate is not an answer (the runtime falls back)
    return {"solver": name, "n": len(forms), "converged": int(np.sum(res["converged"])),
            "iter_median": float(np.median(it)), "iter_max": int(it.max()),
            "iter_p99": float(np.percentile(it, 99)), "iter_total": int(it.sum()), "iter_over_30": int(np.sum(it > 30)),
            "us_median": float(np.median(us)), "us_p99": float(np.percentile(us, 99)), "us_max": float(us.max()),
            "obj_rel_err_median": float(np.median(rel)), "obj_rel_err_max": float(rel.max()),
            "z_err_median": float(np.median(dz)), "z_err_max": float(dz.max()),
            "u0_err_max": float(du0.max()), "violation_max": float(viol.max()),
            "obj_rel_err_max_converged": float(rel[ok].max()) if ok.any() else float("nan"),
            "u0_err_max_converged": float(du0[ok].max()) if ok.any() else float("nan"),
            "violation_max_converged": float(viol[ok].max()) if ok.any() else float("nan")}


def run(build: Path = DEFAULT_BUILD, steps: int = 1500, repeats: int = 20, track: str = "ethzMobil",
        vehicle: str = "orca_1_43", f32_build: Path | None = None, replay_cap: int | None = None) -> list[dict]:
    """f32_build: a build with -DDDYN_QP_FLOAT32=ON whose ddyn_qp_replay re-solves the same QPs (the
    runtime's DAQP path in float32). replay_cap: the C solvers' iteration cap in the replay (default the
    lap's, MpcSettings: 30), e.g. 50 to see how many iterations DAQP needs where 30 caps it."""
    from ddyn.control.mpc_lap import setup_text
    from ddyn.control.mpc_setup import MpcSettings, raceline_table, start_state
    from ddyn.model import vehicle as vehicle_mod
    from ddyn.model.tracks import load_track

    lap_tool, replay_tool = Path(build) / "ddyn_mpc_lap", Path(build) / "ddyn_qp_replay"
    for t in (lap_tool, replay_tool):
        if not t.is_file():
            raise DdynError(f"{t} not found: build with scripts/build.sh")
    settings = MpcSettings()
    cap = replay_cap or settings.qp_max_iterations
    v = vehicle_mod.load(vehicle)
    table = raceline_table(load_track(track), vehicle, settings)
    true = v.true_vector()
    text = setup_text(vehicle, table, settings, true, true, start_state(table), steps)
    with tempfile.TemporaryDirectory() as tmp:
        dump, rep = Path(tmp) / "qps.bin", Path(tmp) / "replay.bin"
        p = subprocess.run([str(lap_tool), str(dump)], input=text, capture_output=True, text=True)
        if p.returncode != 0:
            raise DdynError(f"{lap_tool}: {p.stderr.strip()}")
        p = subprocess.run([str(replay_tool), str(dump), str(repeats), str(cap),
                            repr(settings.qp_tolerance), str(rep)], capture_output=True, text=True)
        if p.returncode != 0:
            raise DdynError(f"{replay_tool}: {p.stderr.strip()}")
        qps = read_dump(dump)
        own = read_replay(rep, qps)
        own32 = None
        if f32_build is not None:
            tool32 = Path(f32_build) / "ddyn_qp_replay"
            p = subprocess.run([str(tool32), str(dump), str(repeats), str(cap),
                                repr(settings.qp_tolerance), str(rep)], capture_output=True, text=True)
            if p.returncode != 0:
                raise DdynError(f"{tool32}: {p.stderr.strip()}")
            own32 = read_replay(rep, qps)
    forms = [standard_form(qp) for qp in qps]
    ref = solve_piqp(forms, 1e-10)
    check = solve_proxqp(forms, 1e-10, warm=False)
    rows = [accuracy("reference: PIQP 0.6.4 at eps_abs 1e-10 (cold)", ref, forms, ref["x"]),
            accuracy("reference check: ProxQP 0.8.0 at eps_abs 1e-10 (cold) vs the reference", check, forms, ref["x"])]
    rows.append(accuracy(f"**runtime DAQP path** (mpc_qp_daqp.c: double, cap {cap}, warm: "
                         "previous working set shifted one stage)", own["daqp"], forms, ref["x"]))
    rows.append(accuracy(f"runtime DAQP path cold (cap {cap}: an empty working set for every QP)", own["daqp_cold"],
                         forms, ref["x"]))
    if own32 is not None:
        rows.append(accuracy("runtime DAQP path in float32 (DDYN_QP_FLOAT32: DAQP_SINGLE_PRECISION)", own32["daqp"],
                             forms, ref["x"]))
        rows.append(accuracy("runtime DAQP path float32 against double (not the reference)", own32["daqp"], forms,
                             own["daqp"]["x"]))
    rows.append(accuracy(f"mpc_qp.c (qp_solver = ipm: double, cap {cap}, tol "
                         f"{settings.qp_tolerance:g}, cold)", own["ipm"], forms, ref["x"]))
    rows.append(accuracy("mpc_qp.c float32 (same cap and tol)", own["f32"], forms, ref["x"]))
    rows.append(accuracy("mpc_qp.c float32 against mpc_qp.c double (not the reference)", own["f32"], forms,
                         own["ipm"]["x"]))
    rows.append(accuracy("mpc_qp.c tight (50 iterations, 1e-10)", own["tight"], forms, ref["x"]))
    rows.append(accuracy("DAQP 0.11.0 Python (slacks as variables, default tol, warm: previous multipliers)", solve_daqp(forms, True), forms, ref["x"]))
    rows.append(accuracy("PIQP 0.6.4 (eps_abs = eps_rel = 1e-6, cold)", solve_piqp(forms, 1e-6), forms, ref["x"]))
    # cold: ProxQP 0.8.0 warm-started with WARM_START_WITH_PREVIOUS_RESULT did not return (minutes on one QP of
    # this lap, also with max_iter 10,000)
    rows.append(accuracy("ProxQP 0.8.0 (eps_abs 1e-6, cold)", solve_proxqp(forms, 1e-6, False), forms, ref["x"]))
    return rows


def format_rows(rows: list[dict]) -> str:
    lines = ["| solver | converged | iterations median / p99 / max (total; QPs above 30) | time µs median / p99 / max | objective rel. error "
             "median / max | max abs z error median / max | first input max error | max violation | converged "
             "QPs only: objective error max / first input max error / max violation |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['solver']} | {r['converged']}/{r['n']} | {r['iter_median']:g} / {r['iter_p99']:g} / "
                     f"{r['iter_max']} ({r['iter_total']}; {r['iter_over_30']}) | "
                     f"{r['us_median']:.1f} / {r['us_p99']:.1f} / {r['us_max']:.1f} | {r['obj_rel_err_median']:.1e} / "
                     f"{r['obj_rel_err_max']:.1e} | {r['z_err_median']:.1e} / {r['z_err_max']:.1e} | "
                     f"{r['u0_err_max']:.1e} | {r['violation_max']:.1e} | {r['obj_rel_err_max_converged']:.1e} / "
                     f"{r['u0_err_max_converged']:.1e} / {r['violation_max_converged']:.1e} |")
    return "\n".join(lines)


def _run(args) -> int:
    rows = run(Path(args.build), args.steps, args.repeats, args.track,
               f32_build=Path(args.f32_build) if args.f32_build else None, replay_cap=args.replay_cap)
    print(format_rows(rows))
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


def register(subparsers) -> None:
    c = subparsers.add_parser("qp", help="the MPC's QP solver against DAQP, PIQP, ProxQP on a lap's QPs")
    c.add_argument("--build", default=str(DEFAULT_BUILD), help="directory with ddyn_mpc_lap, ddyn_qp_replay")
    c.add_argument("--steps", type=int, default=1500, help="closed-loop steps (one QP each)")
    c.add_argument("--repeats", type=int, default=20, help="timed solves of each QP by the C solvers")
    c.add_argument("--track", default="ethzMobil")
    c.add_argument("--f32-build", help="also the DAQP path of this -DDDYN_QP_FLOAT32=ON build's ddyn_qp_replay")
    c.add_argument("--replay-cap", type=int, help="iteration cap of the C solvers in the replay (default: the lap's, 30)")
    c.add_argument("--out", help="write the rows as JSON here")
    c.set_defaults(func=_run)
