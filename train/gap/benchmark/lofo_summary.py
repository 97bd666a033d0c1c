"""The leave-one-family-out study's headline against the issue's targets: the worst family on each, never the mean.

Reads the folds ddyn.gap.benchmark.lofo recorded (nothing is re-run), so a recorded study can be summarised again
(`ddyn gap lofo --from-results`).
"""
from __future__ import annotations

MIN_SCORED = 60         # scored logs per family the issue asks for, so that one log moves a rate by < 2 points
TARGETS = {"first_right": 0.95, "claims_no_claim_logs": 0.05, "claimable": 8, "delay_vs_lag": 0.90,
           "param_error_median": 0.15, "limits_found": 0.90, "limit_at_or_below_size": 0.90}


def _share(a: int, b: int) -> float | None:
    return a / b if b else None


def summary(doc: dict) -> dict:
    """{target: {worst value, the family it is, met}} over the folds, plus per-family first-effect rates."""
    rows = {}
    for fam, f in doc["folds"].items():
        s, cal = f["score"], f["calibration"]
        lh = s["limits_hold"]
        rows[fam] = {
            "first_right": s["first_right_rate"],
            "claims_no_claim_logs": _share(s["effect_free_claimed"] + s["below_size_claimed"],
                                           s["effect_free"] + s["below_size"]),
            "effect_free_claimed": _share(s["effect_free_claimed"], s["effect_free"]),
            "claimable": sum(v is not None for v in cal["decision_levels"].values()),
            "delay_vs_lag": _share(s["delay_vs_lag"]["right"], s["delay_vs_lag"]["told"]),
            "param_error_median": s["param_error_median"],
            "limits_found": _share(lh["found"], lh["above_stated_limit"]),
            "limit_at_or_below_size": _share(lh["limit_at_or_below_size"], lh["limit_statements"]),
            "scored": s["scored"],
        }
    worst = {}
    for key, target in TARGETS.items():
        vals = [(v[key], fam) for fam, v in rows.items() if v[key] is not None]
        if not vals:
            worst[key] = {"value": None, "family": None, "met": False}
            continue
        high_is_bad = key in ("claims_no_claim_logs", "param_error_median")
        value, fam = max(vals) if high_is_bad else min(vals)
        met = value <= target if high_is_bad else value >= target
        worst[key] = {"value": value, "family": fam, "target": target, "met": bool(met)}
    return {"per_family": rows, "worst": worst,
            "targets_met": sum(w["met"] for w in worst.values()), "targets": len(TARGETS),
            "scored_logs": sum(v["scored"] for v in rows.values()),
            # the issue asks for at least MIN_SCORED scored logs in every family: the fewest says whether it has them
            "scored_min": min((v["scored"] for v in rows.values()), default=0), "min_scored": MIN_SCORED,
            "logs": sum(f["score"]["logs"] for f in doc["folds"].values())}


def markdown(sm: dict) -> str:
    names = {"first_right": "first effect right (>= 95 %)",
             "claims_no_claim_logs": "claims on effect-free and below-size logs (<= 5 %)",
             "claimable": "effect families claimable (>= 8)", "delay_vs_lag": "delay vs lag (>= 90 %)",
             "param_error_median": "median parameter error (<= 15 %)",
             "limits_found": "found above the stated limit (>= 90 %)",
             "limit_at_or_below_size": "stated limit at or below the size that matters (>= 90 %)"}
    lines = ["| target (worst family) | value | family | met |", "|---|---|---|---|"]
    for key, w in sm["worst"].items():
        v = w["value"]
        text = "-" if v is None else (f"{v:g}" if key == "claimable" else f"{100 * v:.0f} %")
        lines.append(f"| {names[key]} | {text} | {w['family'] or '-'} | {'yes' if w['met'] else '**no**'} |")
    if "scored_min" in sm:
        lines += ["", f"Fewest scored logs of a family: {sm['scored_min']} (at least {sm['min_scored']} asked)."]
    return "\n".join(lines) + "\n"
