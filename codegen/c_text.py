"""How generated C writes a number: the one format both generators use (exact, NaN for non-finite)."""
from __future__ import annotations

import numpy as np


def c_double(x: float) -> str:
    """A double literal that reads back to the same value (repr is shortest round-trip)."""
    return repr(float(x)) if np.isfinite(x) else "NAN"
