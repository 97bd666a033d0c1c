"""The report of a diagnosis: diagnosis.md, the plots (where.png, residuals.png, which.png) and diagnosis.json (the
dict `diagnose()` returns without its private series; its keys are listed in ddyn.gap.selection)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ddyn.gap.config import ANY_OTHER
from ddyn.gap.problem import CHANNELS, UNITS


def public(diag: dict) -> dict:
    """The diagnosis without its private series (the keys starting with "_")."""
    return {k: v for k, v in diag.items() if not k.startswith("_")}



def _fmt(x) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.3g}" if 1e-2 <= abs(x) < 1e4 or x == 0 else f"{x:.3e}"


def _roll_line(d: dict) -> str:
    r = d["data"].get("roll_channel")
    if r is None:
        return ("Roll channel: none logged (bank only from the fitted profiles)."
                + _pitch_line(d["data"].get("pitch_channel")))
    p = d["data"].get("pitch_channel")
    return f"Roll channel: {_channel_use(r, 'bank_from_roll')} ({r['reason']})." + _pitch_line(p)


def _channel_use(c: dict, candidate: str) -> str:
    """What the diagnosis did with a channel: a flat one is plausible but gives no bank (grade) to read."""
    if c.get("flat"):
        return f"plausible but flat, {candidate} not tried"
    return f"plausible, {candidate} tried" if c["plausible"] else "NOT plausible, not used"


def _pitch_line(p: dict | None) -> str:
    if p is None:
        return ""
    return f" Pitch channel: {_channel_use(p, 'grade_from_pitch')} ({p['reason']})."


def _calibration_lines(d: dict) -> list[str]:
    c = d.get("calibration")
    if not c:
        return []
    if not c.get("name"):
        return [f"**Uncalibrated**: {c['why']}. Without a calibration the plain evidence rule decides: a named effect "
                "is one that pays for itself on the held-out data, not one whose false-alarm rate was measured.", ""]
    if c.get("kind") == "travelling":
        shares = ", ".join(f"{e} {_fmt(v)}" for e, v in (c.get("decision_shares") or {}).items()
                           if v is not None and e != ANY_OTHER)
        margins = ", ".join(f"{e} {_fmt(v)}" for e, v in (c.get("family_margins_per_row") or {}).items()
                            if v and e != ANY_OTHER)
        return [f"Calibrated by {c['name']} ({c['why']}): a family is claimed when its dBIC is below minus its "
                f"margin per held-out row times {d['split']['heldout_rows']} rows ({margins or 'none above 0'}) and "
                f"its estimate reaches its decision level, a share of its size that matters ({shares or 'none'}); "
                "every other effect reported, never claimed.", ""]
    limits = ", ".join(f"{e} {_fmt(v)}" for e, v in c["decision_levels"].items() if v is not None and e != ANY_OTHER)
    return [f"Calibrated by {c['name']} ({c['why']}): evidence margin dBIC < -{c['margin']:.3g}; decision levels "
            f"{limits or 'none'}; every other effect reported, never claimed.", ""]


def limits_lines(d: dict) -> list[str]:
    """This log's own detection limits (ddyn.gap.limits), one sentence per effect family, and the effects that
    paid but were not claimed."""
    lim = d.get("limits") or {}
    out = []
    if lim:
        out += [f"## What this log can show (evidence margin {d['gate']['min_evidence']:.4g})", ""]
        out += [f"- {v['sentence']}" for v in lim.values()] + [""]
    un = d["model"].get("unclaimed") or []
    if un:
        out += ["Paid on the held-out data but not claimed (kept in the model while the search went on): "
                + ", ".join(f"{e['effect']} {next(iter(e['params']))} = {_fmt(next(iter(e['params'].values())))}"
                            for e in un) + ".", ""]
    return out


def markdown(d: dict, figures: list[str]) -> str:
    m = d["model"]
    h = m["heldout"]
    lines = [f"# Diagnosis of {d['data']['source']}", "",
             f"Nominal: {d['nominal']['source']} ({d['nominal']['method']}); {d['data']['rows']} rows; "
             f"fit on {d['split']['fit_rows']}, held out {d['split']['heldout_rows']} (from t = "
             f"{d['split']['heldout_from_time']:.1f} s).", "",
             f"**Selected: {', '.join(d['selected']) if d['selected'] else 'none'}** — {d['verdict']}", "",
             *_calibration_lines(d), _roll_line(d), "",
             *limits_lines(d),
             "## How far (held-out)", "",
             "| | vx (m/s) | vy (m/s) | omega (rad/s) | ADE (m) | FDE (m) |", "|---|---|---|---|---|---|",
             "| nominal | " + " | ".join(_fmt(h["rmse_before"][c]) for c in CHANNELS)
             + f" | {_fmt(h['ade_before'])} | {_fmt(h['fde_before'])} |",
             "| with selected effects | " + " | ".join(_fmt(h["rmse_after"][c]) for c in CHANNELS)
             + f" | {_fmt(h['ade_after'])} | {_fmt(h['fde_after'])} |", "",
             f"Gap closed: {_fmt(m['gap_closed_pct'])} % of the held-out error above the estimated noise floor, "
             f"which is {_fmt(m['error_reduction_pct'])} % of the whole normalised one-step error (the refitted "
             f"nominal's error is {d['gate']['ratio']:.3g}x the noise floor"
             + (f"; no-gap gate at {d['gate']['threshold']:g}x: {'closed' if d['gate']['gated'] else 'open'}"
                if d['gate']['threshold'] is not None else "") + ").", "",
             "## Where (nominal model, whole log)", ""]
    w = d["where"]
    lines += ["| nominal | vx (m/s) | vy (m/s) | omega (rad/s) |", "|---|---|---|---|"]
    for label, key in (("one-step RMSE", "one_step_rmse"), ("noise floor (est.)", "noise_floor_rmse"),
                       (f"multi-step RMSE ({w['horizon_steps']} steps)", "multi_step_rmse"),
                       ("multi-step RMSE at the horizon", "multi_step_final_rmse")):
        if w.get(key):
            lines.append(f"| {label} | " + " | ".join(_fmt(w[key][c]) for c in CHANNELS) + " |")
    lines += [""] + [f"- {s}" for s in w["summary"]]
    lines += ["", "## Which (each candidate alone against the refitted nominal, best first)", "",
              "| effect | estimate | +- | dBIC | gap closed % | vx | vy | omega | ADE |",
              "|---|---|---|---|---|---|---|---|---|"]
    for c in d["candidates"]:
        (pn, pv), = c["params"].items()
        hh = c["heldout"]
        edge = " (at bound)" if c["at_bound"] else ""
        lines.append(f"| {c['effect']}{' **' if c['significant'] else ''} | {pn} = {_fmt(pv)} {c['unit']}{edge} | "
                     f"{_fmt(c['uncertainty'][pn])} | {c['delta_bic']:.1f} | {_fmt(c['gap_closed_pct'])} | "
                     + " | ".join(_fmt(hh["rmse_after"][ch]) for ch in CHANNELS) + f" | {_fmt(hh['ade_after'])} |")
    lines += ["", "dBIC < 0 (marked **): the effect pays for its parameter on the held-out part. Tyre peak forces "
              f"({', '.join(d['nominal']['refit_under_every_hypothesis']) or 'none'}) are refitted under every "
              "hypothesis. \"at bound\": the estimate sits on an edge of its search range, so the effect is "
              "standing in for some other mismatch and its value is a bound, not an estimate.", ""]
    lines += [f"![{Path(f).stem}]({Path(f).name})" for f in figures]
    return "\n".join(lines) + "\n"


def plots(d: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = d["_series"]
    w = s["where"]
    paths = []
    facs = d["where"]["factors"]
    n = len(facs)
    fig, axes = plt.subplots((n + 1) // 2, 2, figsize=(12, 2.6 * ((n + 1) // 2)))
    for ax, (name, bins) in zip(axes.ravel(), facs.items()):
        x = np.arange(len(bins))
        ax.bar(x - 0.2, [b["samples_share"] for b in bins], 0.4, label="samples", color="0.7")
        ax.bar(x + 0.2, [b["error_share"] for b in bins], 0.4, label="one-step error", color="C3")
        ax.set_xticks(x, [b["bin"].split(" (")[0] for b in bins], rotation=20, fontsize=7)
        ax.set_title(name.replace("_", " "), fontsize=9)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle("Where: share of samples and of the nominal model's one-step error")
    fig.tight_layout()
    paths.append(out / "where.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, axes = plt.subplots(3, 1, figsize=(11, 7), sharex=True)
    for i, (ax, c) in enumerate(zip(axes, CHANNELS)):
        ax.plot(w["time"], w["res"][:, i], lw=0.6, color="0.5", label="nominal (whole log)")
        ax.plot(s["held_time"], s["res_after"][:, i], lw=0.6, color="C0", label="with selected effects (held out)")
        ax.set_ylabel(f"{c} residual ({UNITS[c]})")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("One-step residuals")
    fig.tight_layout()
    paths.append(out / "residuals.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    cands = d["candidates"]
    y = np.arange(len(cands))
    ax1.barh(y, [max(min(-c["delta_bic"], 1e6), -1e6) for c in cands],
             color=["C2" if c["significant"] else "0.6" for c in cands])
    ax1.set_yticks(y, [c["effect"] for c in cands])
    ax1.invert_yaxis()
    ax1.set_xscale("symlog")
    ax1.set_xlabel("-dBIC on held-out data (> 0: pays for itself)")
    ax1.set_title("Which effect")
    sc = ax2.scatter(w["x"], w["y"], c=np.log10(w["err"] + 1e-12), s=3, cmap="magma")
    ax2.set_aspect("equal")
    ax2.set_title("Where on the track: log10 normalised one-step error")
    fig.colorbar(sc, ax=ax2)
    fig.tight_layout()
    paths.append(out / "which.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    return [str(p) for p in paths]


def write_report(d: dict, out: str | Path, with_plots: bool = True) -> dict[str, str]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = plots(d, out) if with_plots else []
    (out / "diagnosis.json").write_text(json.dumps(public(d), indent=2, default=float))
    (out / "diagnosis.md").write_text(markdown(d, figs))
    return {"json": str(out / "diagnosis.json"), "markdown": str(out / "diagnosis.md"), "figures": figs}


# ----------------------------------------------------------------------------------------------- CLI
