"""Analysis: evaluation, sim-to-real gap diagnosis and its benchmark, fidelity, crosschecks, plots."""
