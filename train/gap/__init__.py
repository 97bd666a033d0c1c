"""ddyn.gap: the sim-to-real gap diagnosis (where a model is wrong, which unmodelled effect causes it, how far the
gap shrinks once it is modelled), its calibration and its benchmarks.

    from ddyn.gap import DiagnosisConfig, diagnose, nominal_from_vehicle, write_report
    d = diagnose(log, nominal_from_vehicle(vehicle, log), DiagnosisConfig.from_file("dbw"))

Modules by concern: config (DiagnosisConfig), candidates, problem (the fitting problem, the nominal), fit,
heldout (held-out scores, noise floor), where, selection (diagnose: evidence, greedy, claims), calibration (the
scoring rules and the calibration artifact), report (markdown, plots, diagnosis.json), cli (`ddyn gap ...`);
benchmark/ (plan, run a case, score, render, once per plant). The names below load on first use, so importing
the package costs nothing.
"""
from __future__ import annotations

import importlib

_PUBLIC = {
    "DiagnosisConfig": "ddyn.gap.config", "BenchmarkConfig": "ddyn.gap.config", "load_config": "ddyn.gap.config",
    "diagnose": "ddyn.gap.selection", "Nominal": "ddyn.gap.problem", "nominal_from_vehicle": "ddyn.gap.problem",
    "nominal_from_checkpoint": "ddyn.gap.problem", "track_for": "ddyn.gap.problem",
    "write_report": "ddyn.gap.report", "Calibration": "ddyn.gap.calibration",
    "load_calibration": ("ddyn.gap.calibration", "load"), "diagnose_log": "ddyn.gap.cli",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    target = _PUBLIC.get(name)
    if target is None:
        raise AttributeError(f"module 'ddyn.gap' has no attribute {name!r}")
    module, attr = target if isinstance(target, tuple) else (target, name)
    return getattr(importlib.import_module(module), attr)
