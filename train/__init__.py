"""ddyn: Deep Dynamics on the car, the offline side (Python).

Subpackages by concern, each importing only from those listed before it:

* `ddyn.model`: the one vehicle model (math namespaces, integrators, backends), vehicles,
  unmodelled effects, sensors, tracks;
* `ddyn.data`: the canonical dataset, importers, windows, simulation, LCM and CAN logs;
* `ddyn.learn`: networks, training, checkpoints, FTHD fine-tuning, the EKF layer, denoising,
  tuning, export of C weight tables;
* `ddyn.analysis`: evaluation, gap diagnosis and its benchmark, fidelity, crosschecks, plots;
* `ddyn.control`: MPC set-up, the IPOPT reference MPC, racing lines, closed-loop laps;
* `ddyn.sil`: software-in-the-loop laps over virtual CAN;
* `ddyn.studies`: the papers' tables (DDM/DPM, FTHD, denoising);
* `ddyn.bench`: timing of the C runtime against Python;
* `ddyn.codegen` (folder codegen/): C code generated with CasADi and cantools.

The command line is `ddyn` (ddyn.cli).

The public Python API is `ddyn.api` (load_log, load_vehicle, load_checkpoint, diagnose, generate_c,
run_mpc_lap, ...), its names also reachable as `ddyn.<name>`; examples/ shows each in a short script.
"""

# `import ddyn` stays cheap: the names of ddyn.api are looked up on first use (PEP 562 module __getattr__),
# so the package init imports no module of its own at import time (tests/python/test_package_layout.py)
__all__ = ["Checkpoint", "DdynError", "diagnose", "evaluate", "generate_c", "load_checkpoint", "load_log",
           "load_vehicle", "run_mpc_lap", "save_log", "simulate", "train"]


def __getattr__(name: str):
    if name in __all__:
        import importlib

        return getattr(importlib.import_module("ddyn.api"), name)
    raise AttributeError(f"module 'ddyn' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
