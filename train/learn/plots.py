"""Plots where a person would rather look than read: tyre curves and predictions over time."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on the car's tools or in CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ddyn.data.windows import TARGET_NAMES  # noqa: E402
from ddyn.model import mathns  # noqa: E402
from ddyn.model.single_track import pacejka  # noqa: E402

UNITS = {"vx": "m/s", "vy": "m/s", "omega": "rad/s"}


def _axle_curve(alpha: np.ndarray, coeffs: dict, axle: str, key: str) -> np.ndarray | None:
    names = [n + axle for n in "BCDE"]
    if not all(n in coeffs for n in names):
        return None
    B, C, D, E = (coeffs[n][key] for n in names)
    G = coeffs.get("G" + axle, {}).get(key, 0.0)
    K = coeffs.get("K" + axle, {}).get(key, 0.0)
    return pacejka(mathns.NUMPY, alpha + G, B, C, D, E, K)


def tyre_curves(metrics: dict, title: str, path: Path) -> Path:
    """Lateral force against slip angle, front and rear: estimated (mean) and true where known."""
    coeffs = metrics["coefficients"]
    alpha = np.linspace(-0.6, 0.6, 241)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, axle, name in zip(axes, "fr", ("front", "rear")):
        est = _axle_curve(alpha, coeffs, axle, "mean")
        if est is not None:
            ax.plot(alpha, est, label="estimated (mean)")
        if all("true" in coeffs.get(n + axle, {}) for n in "BCDE"):
            ax.plot(alpha, _axle_curve(alpha, coeffs, axle, "true"), "k--", label="true")
        ax.set_title(f"{name} axle")
        ax.set_xlabel("slip angle (rad)")
        ax.grid(True, alpha=0.3)
        ax.legend()
    axes[0].set_ylabel("lateral force (N)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def predictions(metrics: dict, title: str, path: Path, seconds: float = 20.0) -> Path:
    """Predicted against measured next vx, vy, omega over (the first `seconds` of) time."""
    s = metrics["_series"]
    t = s["time"] - s["time"][0]
    keep = t <= seconds
    fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    for i, (ax, name) in enumerate(zip(axes, TARGET_NAMES)):
        ax.plot(t[keep], s["target"][keep, i], "k", lw=1.2, label="measured")
        ax.plot(t[keep], s["pred"][keep, i], "C1", lw=0.9, label="predicted (one step)")
        ax.set_ylabel(f"{name} ({UNITS[name]})")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_evaluation(metrics: dict, ckpt: dict, out: Path) -> list[Path]:
    kind = ckpt["kind"].upper()
    return [tyre_curves(metrics, f"{kind}: lateral tyre force", out / "tyre_curves.png"),
            predictions(metrics, f"{kind}: next-step prediction", out / "predictions.png")]
