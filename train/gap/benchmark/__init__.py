"""ddyn.gap.benchmark: the diagnosis scored on logs with a hidden effect, one module per plant behind one interface
(base.py: plan the cases, run a case, score, render)."""
