"""`ddyn study drivetrain`: which drivetrain form fits a real log, and guard ranges for it from data.

On the training part of a time split (the first 80 % of the log, as `ddyn study ddm real`; the
held-out last 20 % is only reported, never fitted), for each drivetrain form of the model
(FIT_FORMS: ddyn.model.single_track.DRIVETRAINS but power_limited, whose ranges come from physics):

  1. one set of constant drivetrain coefficients (Cm1, Cm2, Cr0, Cd; for "powertrain" also the
     vehicle's known brake gain) by least squares on the one-step change of vx predicted by the one
     model (Euler, the vehicle's other coefficients at its true values: they enter vx only through
     the front tyre's F_fy sin(delta)); Cd is held inside the vehicle file's range (a physical prior:
     alone it is not separable from Cm2, both grow with speed);
  2. the share of the vx change the fitted form explains, R^2 = 1 - SSE / SS of (vx_next - vx), on
     the training part (the figure that chooses the form) and, for information, on the held-out part;
  3. guard ranges from the fit by the papers' own rule for nominal ranges ("drivetrain coefficients
     and Iz from half to double the true value", shared/data/README.md): [x / 2, 2 x]; Cd keeps the
     vehicle file's range (see 1).

With --model CKPT [CKPT ...] (DDMs trained on the same training part, e.g. several seeds), also the
ranges of the coefficients the DDMs' estimates press on (training part only; the union over the models,
union_of_moves): the rule of `ddyn denoise` (ddyn.learn.denoise.
suggest_ranges: a pinned side is extended, to half or double a positive bound or by half the width;
the other side is kept; a bound at zero and a coefficient pinned at both ends keep the vehicle file's
range: they are not identified, or serve as slack), and the tyre
curvature E's upper bound 1 (the magic formula's own condition E <= 1, Pacejka, Tyre and Vehicle
Dynamics, 2012, sec. 4.3.2) where the estimates press on the papers' 0: DIR/ranges_guard.json.

Also the tyres' measured slip offsets (slip_offsets): on the training part's straight running the
axles carry next to no lateral force, so the model's slip angle there is zero and the horizontal
shift G of each axle is minus the kinematic slip angle the log shows (a yaw misalignment of the
velocity sensor shows up here, on both axles alike). A physical check of G's range: it must hold
the measured offset and its spread. (Centring the range on the offset was tried on the Putnam log and
refuted on its training part: the DDM then pressed on the other bound, docs/learning.md.)

With --model, also the share of the DDM's estimates on the training part at each guard bound (the
figure a range rule may be chosen on; the held-out part's is `ddyn study ddm real`'s).

Writes DIR/drivetrain.json (fits, R^2, ranges) and DIR/ranges_<form>.json (a `ddyn train --ranges`
file). The numbers of train/vehicles/av21_powertrain.json come from this command.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from ddyn.data.dataset import Dataset
from ddyn.errors import DdynError
from ddyn.model import backends
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import COEFF_NAMES, DRIVETRAINS
from ddyn.paths import putnam_log

DRIVE = ("Cm1", "Cm2", "Cr0", "Cd")
# the forms this study fits and derives ranges for: those whose data-derived ranges it was written for. The
# power_limited form (issue 36) takes every range from the car's physics, fixed before any fit (av21_power.json)
FIT_FORMS = tuple(f for f in DRIVETRAINS if f != "power_limited")
TRAIN_FRACTION = 0.8
RULE = "papers' half-to-double rule around the training part's fit"


def split_rows(ds: Dataset, fraction: float = TRAIN_FRACTION) -> tuple[np.ndarray, np.ndarray]:
    """Row indices k with a next row k + 1 in the same segment, before the cut and from the cut on
    (no pair straddles the cut: the same split as `ddyn study ddm real`)."""
    cut = int(len(ds) * fraction)
    k = np.arange(len(ds) - 1)
    k = k[ds.segment[k] == ds.segment[k + 1]]
    return k[k + 1 < cut], k[k >= cut]


def _predict_vx(ds: Dataset, rows: np.ndarray, v: vehicle_mod.Vehicle, drive: np.ndarray, brake_gain: float,
                form: str) -> np.ndarray:
    c = v.true_vector().copy()
    for name, x in zip(DRIVE, drive):
        c[COEFF_NAMES.index(name)] = x
    p = v.known._replace(drivetrain=form, brake_gain=brake_gain if form == "powertrain" else 0.0)
    return backends.step_numpy(ds.states[rows], ds.inputs[rows], c, p, v.sample_time, "euler")[:, 3]


def r_squared(ds: Dataset, rows: np.ndarray, pred_vx: np.ndarray) -> float:
    change = ds.states[rows + 1, 3] - ds.states[rows, 3]
    sse = float(np.sum((ds.states[rows + 1, 3] - pred_vx) ** 2))
    return 1.0 - sse / float(np.sum((change - change.mean()) ** 2))


def fit_form(ds: Dataset, train_rows: np.ndarray, v: vehicle_mod.Vehicle, form: str) -> dict:
    """Constant drivetrain coefficients (and brake gain) of one form by least squares on the training rows."""
    cd_lo, cd_hi = v.ranges["Cd"]
    start = np.array([10.0 * v.known.mass,
                      0.1 * v.known.mass, 0.5 * v.known.mass, 0.5 * (cd_lo + cd_hi)])
    lo, hi = np.array([0.0, 0.0, 0.0, cd_lo]), np.array([np.inf, np.inf, np.inf, cd_hi])
    if form == "powertrain":
        start, lo, hi = np.append(start, 3.0 * v.known.mass), np.append(lo, 0.0), np.append(hi, np.inf)
    target = ds.states[train_rows + 1, 3]

    def residual(z):
        return _predict_vx(ds, train_rows, v, z[:4], z[4] if form == "powertrain" else 0.0, form) - target

    sol = least_squares(residual, start, bounds=(lo, hi), x_scale=np.maximum(np.abs(start), 1e-3))
    out = {name: float(x) for name, x in zip(DRIVE, sol.x[:4])}
    if form == "powertrain":
        out["brake_gain"] = float(sol.x[4])
    return out


def ranges_from_fit(fit: dict, v: vehicle_mod.Vehicle) -> dict:
    """[x / 2, 2 x] for Cm1, Cm2, Cr0 (the papers' rule); Cd keeps the vehicle file's range."""
    out = {name: [0.5 * fit[name], 2.0 * fit[name]] for name in ("Cm1", "Cm2", "Cr0") if fit[name] > 0.0}
    out["Cd"] = list(v.ranges["Cd"])
    return out


def run(ds: Dataset, v: vehicle_mod.Vehicle, fraction: float = TRAIN_FRACTION) -> dict:
    """fraction 1.0: ds is already the training part (then no held-out R^2)."""
    train_rows, test_rows = split_rows(ds, fraction)
    if len(train_rows) < 10 or (fraction < 1.0 and len(test_rows) < 10):
        raise DdynError(f"too few rows for a {TRAIN_FRACTION:.0%} time split ({len(ds)})")
    out = {"vehicle": v.name, "rows": {"train": int(len(train_rows)), "heldout": int(len(test_rows))}, "forms": {}}
    try:   # information, not needed for the fit: a log without straight running still gets its drivetrain
        out["slip_offsets"] = slip_offsets(ds, train_rows, v)
    except DdynError as e:
        out["slip_offsets"] = {"error": str(e)}
    out["pedal_by_speed"] = pedal_by_speed(ds, train_rows, v)
    for form in FIT_FORMS:
        fit = fit_form(ds, train_rows, v, form)
        drive = np.array([fit[n] for n in DRIVE])
        bg = fit.get("brake_gain", 0.0)
        out["forms"][form] = {
            "fit": fit,
            "r2_train": r_squared(ds, train_rows, _predict_vx(ds, train_rows, v, drive, bg, form)),
            "r2_heldout": (r_squared(ds, test_rows, _predict_vx(ds, test_rows, v, drive, bg, form))
                           if len(test_rows) else None),
            "ranges": ranges_from_fit(fit, v), "rule": RULE,
        }
    return out


# speed bands (m/s) of pedal_by_speed, and the fewest driven rows a band needs for its line
SPEED_BANDS = ((5.0, 10.0), (10.0, 15.0), (15.0, 20.0), (20.0, 25.0), (25.0, 30.0), (30.0, 40.0))
BAND_MIN_ROWS = 50


def pedal_by_speed(ds: Dataset, rows: np.ndarray, v: vehicle_mod.Vehicle) -> list[dict]:
    """How the drive force grows with the pedal, speed band by speed band, on the driven rows (throttle > 0) of
    rows: a straight line F = slope T + intercept through the longitudinal force the log shows,
    m ((vx[k+1] - vx[k]) / Ts - vy omega) (the single-track's vx equation without the front tyre's small
    F_fy sin(delta)). The form's evidence: a slope that falls as 1 / vx (slope times speed about constant) is a
    pedal that asks for a share of a power, a flat one a share of a force."""
    s0, s1 = ds.states[rows], ds.states[rows + 1]
    force = v.known.mass * ((s1[:, 3] - s0[:, 3]) / v.sample_time - s0[:, 4] * s0[:, 5])
    pedal, vx = s0[:, 6], s0[:, 3]
    out = []
    for lo, hi in SPEED_BANDS:
        sel = (pedal > 0) & (vx >= lo) & (vx < hi)
        if sel.sum() < BAND_MIN_ROWS or np.ptp(pedal[sel]) <= 0:
            continue
        slope, intercept = np.polyfit(pedal[sel], force[sel], 1)
        speed = float(np.mean(vx[sel]))
        out.append({"band": [lo, hi], "rows": int(sel.sum()), "mean_speed": speed, "pedal_max": float(pedal[sel].max()),
                    "slope": float(slope), "intercept": float(intercept), "slope_times_speed": float(slope * speed)})
    return out


# straight running: |lateral acceleration vx omega| at most this (m/s^2), at a speed of at least V_STRAIGHT.
# At 0.3 m/s^2 an AV-21 axle carries at most m lr / L 0.3 = 140 N, 0.0013 rad of slip at its cornering
# stiffness B C D of 110 kN/rad: the error of the offset measured, a tenth of the +-0.02 rad range.
AY_STRAIGHT = 0.3
V_STRAIGHT = 10.0


def slip_offsets(ds: Dataset, rows: np.ndarray, v: vehicle_mod.Vehicle) -> dict:
    """The horizontal shifts Gf, Gr that make both axles' slip angle zero on straight running (rows of ds,
    the training part): minus the median kinematic slip angle (the model's, ddyn.model.single_track.
    slip_angles with G = 0) over those rows, with its 5-95 % spread."""
    s = ds.states[rows]
    vx, vy, om, delta = s[:, 3], s[:, 4], s[:, 5], s[:, 7]
    straight = (vx >= V_STRAIGHT) & (np.abs(vx * om) <= AY_STRAIGHT)
    if straight.sum() < 50:
        raise DdynError(f"too little straight running to measure the slip offsets ({int(straight.sum())} rows)")
    kin = {"Gf": delta - np.arctan2(om * v.known.lf + vy, vx), "Gr": np.arctan2(om * v.known.lr - vy, vx)}
    out = {"rows": int(straight.sum()), "rule": f"vx >= {V_STRAIGHT} m/s, |vx omega| <= {AY_STRAIGHT} m/s^2"}
    for name, a in kin.items():
        p5, p50, p95 = np.percentile(-a[straight], [5, 50, 95])
        out[name] = {"offset": float(p50), "p05": float(p5), "p95": float(p95)}
    return out


E_MAX = 1.0   # Pacejka's condition on the curvature factor


def saturation(est: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 0.01) -> dict:
    """{coefficient: [share at the lower bound, share at the upper bound]} of the estimates (n, 17): within
    tol of the range width of a bound, as ddyn.learn.evaluate counts it on the held-out part."""
    band = tol * (hi - lo)
    return {n: [float(np.mean(est[:, i] <= lo[i] + band[i])), float(np.mean(est[:, i] >= hi[i] - band[i]))]
            for i, n in enumerate(COEFF_NAMES)}


def guard_ranges_from_model(ckpt_path: str | Path, train_part: Dataset) -> tuple[dict, dict]:
    """{coefficient: {"vehicle", "used", "why"}} for the coefficients the DDM's estimates on train_part
    press on (see the module docstring), and the estimates' saturation on train_part (saturation());
    the checkpoint's own ranges are the starting point."""
    import dataclasses

    from ddyn.learn import checkpoint
    from ddyn.learn.denoise import ddm_estimates, suggest_ranges

    model, ckpt = checkpoint.load(ckpt_path)
    v = checkpoint.vehicle_of(ckpt)
    r = ckpt["ranges"]
    v = dataclasses.replace(v, ranges={n: (lo, hi) for n, lo, hi in zip(r["names"], r["lo"], r["hi"])})
    est = ddm_estimates(model, train_part, ckpt["config"]["tau"])
    out = moved_bounds(suggest_ranges(est, v)["coefficients"], v.ranges)
    return out, saturation(est, np.asarray(r["lo"]), np.asarray(r["hi"]))


def union_of_moves(moves: list[dict]) -> dict:
    """Several models' moved_bounds() (DDMs of the same ranges and training part, e.g. other seeds) as one:
    per coefficient the widest side any of them asks for (a bound one seed presses on is a bound the
    training part presses on; which seed shows it is chance, docs/learning.md's seed check)."""
    out: dict = {}
    for m in moves:
        for name, g in m.items():
            if name not in out:
                out[name] = {"vehicle": list(g["vehicle"]), "used": list(g["used"]), "why": [g["why"]]}
            else:
                u = out[name]["used"]
                out[name]["used"] = [min(u[0], g["used"][0]), max(u[1], g["used"][1])]
                out[name]["why"].append(g["why"])
    for g in out.values():
        g["why"] = "; ".join(sorted(set(g["why"]))) + f" ({len(g['why'])} of {len(moves)} models)"
    return out


def moved_bounds(suggestions: dict, ranges: dict) -> dict:
    """{coefficient: {"vehicle", "used", "why"}} from ddyn.learn.denoise.suggest_ranges' "coefficients":
    a side the estimates are pinned on moves as the rule extends it, the other side stays; a coefficient
    pinned at both ends keeps its range (slack); E's upper bound goes from the papers' 0 to 1 when
    pressed on, and never beyond 1 (the magic formula's E <= 1)."""
    out = {}
    for name, s in suggestions.items():
        lo, hi = ranges[name]
        if name in ("Ef", "Er") and hi == 0.0 and s["pinned"] in ("high", "both"):
            out[name] = {"vehicle": [lo, hi], "used": [lo, E_MAX], "why": "E <= 1 (Pacejka), pressed on 0"}
        elif s["pinned"] in ("low", "high"):
            used = [s["suggested"][0], hi] if s["pinned"] == "low" else [lo, s["suggested"][1]]
            if name in ("Ef", "Er"):
                used[1] = min(used[1], E_MAX)
            if used != [lo, hi]:
                out[name] = {"vehicle": [lo, hi], "used": used, "why": f"ddyn denoise's rule, pinned {s['pinned']}"}
    return out


def markdown(res: dict) -> str:
    lines = [f"Drivetrain forms on {res['vehicle']}'s log: fit on the first {TRAIN_FRACTION:.0%} "
             f"({res['rows']['train']} steps), R^2 of the one-step vx change",
             "", "| form | R^2 training part | R^2 held-out (information) | Cm1 | Cm2 | Cr0 | Cd | brake gain |",
             "|---|---|---|---|---|---|---|---|"]
    for form, r in res["forms"].items():
        f = r["fit"]
        lines.append(f"| {form} | {r['r2_train']:.3f} | {r['r2_heldout']:.3f} | {f['Cm1']:.4g} | {f['Cm2']:.4g} | "
                     f"{f['Cr0']:.4g} | {f['Cd']:.3g} | {f.get('brake_gain', float('nan')):.4g} |")
    if res.get("pedal_by_speed"):
        lines += ["", "Drive force per unit of pedal by speed band (driven rows of the same part; a slope times speed "
                  "about constant: the pedal asks for a share of a power)", "",
                  "| speed band (m/s) | rows | largest pedal | slope (N per unit) | intercept (N) "
                  "| slope x speed (kW) |",
                  "|---|---|---|---|---|---|"]
        for b in res["pedal_by_speed"]:
            lines.append(f"| {b['band'][0]:g}-{b['band'][1]:g} | {b['rows']} | {b['pedal_max']:.2f} | "
                         f"{b['slope']:.0f} | {b['intercept']:.0f} | {b['slope_times_speed'] / 1000:.0f} |")
    return "\n".join(lines)


def _run(args) -> int:
    from ddyn.data.importers import load_any

    src = Path(args.data) if args.data else putnam_log()
    if not src.is_file():
        raise DdynError(f"log not found: {src}")
    v = vehicle_mod.load(args.vehicle)
    ds = load_any(src, vehicle=v.variant_of or v.name)
    res = run(ds, v)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "drivetrain.json").write_text(json.dumps(res, indent=2))
    for form, r in res["forms"].items():
        (out / f"ranges_{form}.json").write_text(json.dumps(r["ranges"], indent=2))
    if args.model:
        cut = int(len(ds) * TRAIN_FRACTION)
        per_model = []
        for path in args.model:
            guard, sat = guard_ranges_from_model(path, ds.subset(slice(0, cut)))
            per_model.append({"model": str(path), "guard_ranges": guard, "training_saturation": sat})
            print(f"{path}: training part, share of the DDM's estimates at a guard bound (low / high, over 1 %): "
                  + ", ".join(f"{k} {100 * a:.1f} / {100 * b:.1f} %" for k, (a, b) in sat.items() if a + b > 0.01))
        guard = union_of_moves([m["guard_ranges"] for m in per_model])
        res["guard_ranges"], res["per_model"] = guard, per_model
        (out / "drivetrain.json").write_text(json.dumps(res, indent=2))
        (out / "ranges_guard.json").write_text(json.dumps({k: g["used"] for k, g in guard.items()}, indent=2))
        for k, g in guard.items():
            print(f"guard range {k}: {g['vehicle']} -> [{g['used'][0]:.4g}, {g['used'][1]:.4g}] ({g['why']})")
    print(markdown(res))
    so = res["slip_offsets"]
    if "error" in so:
        print(f"slip offsets: not measured: {so['error']}")
    for name in () if "error" in so else ("Gf", "Gr"):
        lo, hi = v.ranges[name]
        print(f"slip offset {name}: {so[name]['offset']:+.4f} rad (5-95 % {so[name]['p05']:+.4f} .. {so[name]['p95']:+.4f}, "
              f"{so['rows']} straight rows of the training part: {so['rule']}); {v.name}'s range [{lo:+.4f}, {hi:+.4f}]")
    for form, r in res["forms"].items():
        print(f"{form}: ranges ({RULE}) " + ", ".join(f"{k} [{a:.4g}, {b:.4g}]" for k, (a, b) in r["ranges"].items())
              + f" -> {out / f'ranges_{form}.json'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("drivetrain", help="drivetrain forms on a real log: fit, R^2, guard ranges from data")
    p.add_argument("--data", help="a RACECAR CSV (default: the shared Putnam log)")
    p.add_argument("--vehicle", default="av21", help="vehicle file whose other coefficients and Cd range are used")
    p.add_argument("--model", nargs="+", help="DDM checkpoints trained on the training part (e.g. several seeds): "
                   "their estimates' saturation there, and the union of the bounds they press on")
    p.add_argument("--out", default="out/study/drivetrain", help="output directory (default: %(default)s)")
    p.set_defaults(func=_run)
