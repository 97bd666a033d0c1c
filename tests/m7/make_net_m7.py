"""Regenerate tests/m7/generated/net_m7: the network of the Cortex-M7 firmware test (docs/m7.md).

    python tests/m7/make_net_m7.py        (the project's venv; needs only numpy and ddyn)

The test fixture network (tests/c/generated/net_fixture) is random: in the closed loop its coefficients
make the controller's own feedback (history -> coefficients -> EKF and MPC -> command -> history)
unstable, so that a last-bit difference between two C libraries' sin/cos grows by ~100x per period
and no two builds' commands can be compared after a few periods. This network has the fixture's
shape and weights except the output head: its weights are scaled by HEAD_SCALE and its bias set so
that the guarded output lo + (hi - lo) * sigmoid(z) sits at the vehicle's true coefficients (with a
small dependence on the history). The inference runs the same code and operations as any export of
this shape; its numbers are synthetic, not a trained model.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

from ddyn.model import vehicle
from ddyn.model.single_track import COEFF_NAMES

HERE = Path(__file__).resolve().parent
SRC = HERE.parent / "c" / "generated" / "net_fixture"
OUT = HERE / "generated" / "net_m7"
HEAD_SCALE = 0.01
VEHICLE = "orca_1_43"


def _array(text: str, name: str) -> tuple[re.Match, list[float]]:
    m = re.search(r"(static const ddyn_net_real " + name + r"\[\d+\] = \{)([^}]*)(\};)", text)
    if m is None:
        raise SystemExit(f"{name} not found in {SRC}/ddyn_net_weights.c")
    return m, [float(v.strip().rstrip("f")) for v in m.group(2).split(",") if v.strip()]


def _c_array(values: list[float]) -> str:
    rows = [", ".join(f"{v!r}f" if math.isfinite(v) else "0.0f" for v in values[i:i + 6])
            for i in range(0, len(values), 6)]
    return "\n    " + ",\n    ".join(rows) + "\n"


def main() -> None:
    text = (SRC / "ddyn_net_weights.c").read_text()
    v = vehicle.load(VEHICLE)
    c_true = [v.true_coefficients[k] for k in COEFF_NAMES]
    _, lo = _array(text, "ddyn_net_lo")
    _, hi = _array(text, "ddyn_net_hi")
    m_w, head_w = _array(text, "ddyn_net_head_w")
    text = text[:m_w.start(2)] + _c_array([HEAD_SCALE * w for w in head_w]) + text[m_w.end(2):]
    bias = []
    for c, a, b in zip(c_true, lo, hi):
        p = (c - a) / (b - a)
        if not 0.0 < p < 1.0:
            raise SystemExit(f"true coefficient {c} outside the network's guard range [{a}, {b}]")
        bias.append(math.log(p / (1.0 - p)))
    m_b, _ = _array(text, "ddyn_net_head_b")
    text = text[:m_b.start(2)] + _c_array(bias) + text[m_b.end(2):]
    header = ("/* GENERATED FILE - DO NOT EDIT. Regenerate: python tests/m7/make_net_m7.py\n"
              " * The fixture network (tests/c/generated/net_fixture) with its output head scaled by "
              f"{HEAD_SCALE} and\n * its head bias at the {VEHICLE} true coefficients: synthetic weights "
              "for the Cortex-M7 firmware test.\n * Derived from: ")
    text = text.replace("/* GENERATED FILE - DO NOT EDIT.\n * ", header, 1)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "ddyn_net_weights.c").write_text(text)
    (OUT / "ddyn_net_config.h").write_text((SRC / "ddyn_net_config.h").read_text())
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
