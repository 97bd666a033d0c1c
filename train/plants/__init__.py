"""ddyn.plants: plants written independently of the project's model (CommonRoad's single-track drift model and
its multi-body model), used by the gap diagnosis's benchmarks, the training studies and the SIL checks."""
