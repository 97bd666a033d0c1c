"""`ddyn study sil-oracle`: the controller told the true effect over tracks, effects and noise seeds (the settings of
the closed loop that are not the diagnosis's are chosen with it). The study lives with the SIL it drives
(ddyn.sil.oracle); this registers it among the studies."""
from __future__ import annotations

from ddyn.sil.oracle import register  # noqa: F401  (the study's parser: `ddyn study sil-oracle`)
