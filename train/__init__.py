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
"""
