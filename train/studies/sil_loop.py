"""`ddyn study sil-loop`: the closed loop from the controller's own log to a controller rebuilt from its diagnosis
(issue 34 item 3). The study lives with the SIL it drives (ddyn.sil.loop); this registers it among the studies."""
from __future__ import annotations

from ddyn.sil.loop import register  # noqa: F401  (the study's parser: `ddyn study sil-loop`)
