"""SIL laps beyond the true-coefficient ones: a trained network in the controller, and a bus that
drops frames. Plant and controller node in one process (frames through memory)."""
from __future__ import annotations

import torch

from ddyn.data import simulate
from ddyn.learn import checkpoint
from ddyn.learn.export import export
from ddyn.learn.training import TrainConfig, train
from ddyn.model import tracks
from ddyn.sil import run as sil


def test_a_lap_with_a_trained_network(orca, mobil, tmp_path, shared_data):
    """A DDM trained here (two clean laps of ETHZ, a short training), exported, built into the SIL
    controller, drives ETHZMobil: the network's coefficients steer the car (not the fallbacks) and the
    lap completes inside the bounds."""
    torch.set_num_threads(1)
    ds = simulate.simulate(orca, tracks.load_track("ethz"), laps=2, seed=3, progress=False)
    r = train(ds, orca, TrainConfig(epochs=20, lbfgs_iterations=1500, hidden=16, batch_size=128, seed=5),
              progress=False)
    ckpt = checkpoint.save(checkpoint.make(r, orca, ds.content_hash(), "two clean laps of ETHZ", len(ds)),
                           tmp_path / "ddm.ckpt")
    export(ckpt, tmp_path / "export", torch_export=False)
    spec = sil.SilSpec(vehicle=orca, track=mobil, coeffs_plant=orca.true_vector(), coeffs_controller=None,
                       nominal=orca.true_vector(), speed_scale=0.9, max_time=15.0)
    m = sil.run_sil(spec, tmp_path / "run", tmp_path / "export", where="inprocess")
    assert m["lap_completed"], m["end_reason"]
    assert m["violations"] == 0
    ctl = m["controller"]
    counts = ctl["status_counts"]
    assert counts["DDYN_CTRL_COEFF_FIXED"] == 0 and counts["DDYN_CTRL_NET_FAULT"] == 0
    fallbacks = counts["DDYN_CTRL_COEFF_LAST_GOOD"] + counts["DDYN_CTRL_COEFF_NOMINAL"]
    assert fallbacks < 0.05 * ctl["periods"], counts          # the network drove the lap
    assert ctl["safe_periods"] == 0


def _lossy_lap(orca, mobil, tmp_path, faults: dict) -> dict:
    spec = sil.SilSpec(vehicle=orca, track=mobil, coeffs_plant=orca.true_vector(),
                       coeffs_controller=orca.true_vector(), nominal=orca.true_vector(), speed_scale=1.0,
                       max_time=15.0, faults=faults)
    return sil.run_sil(spec, tmp_path, None, where="inprocess")


def test_a_lap_on_a_bus_that_drops_frames(orca, mobil, tmp_path, shared_data):
    """5 % of the frames lost in both directions, at the raceline's full speed (issue 16): the
    controller notices them (degraded-bus mode, docs/controller.md) and completes the lap inside the
    bounds without a safe command."""
    m = _lossy_lap(orca, mobil, tmp_path, {"drop": 0.05})
    frames = m["controller"]["frames"]
    assert frames["lost"] > 0.02 * frames["ok"], frames          # the faults happened
    counts = m["controller"]["status_counts"]
    assert counts["DDYN_CTRL_BUS_DEGRADED"] > 0.5 * m["controller"]["periods"], counts  # and were noticed
    assert m["lap_completed"], m["end_reason"]
    assert m["violations"] == 0
    assert m["controller"]["safe_periods"] == 0


def test_a_lap_on_a_bus_that_delays_frames(orca, mobil, tmp_path, shared_data):
    """Every frame held back by up to two periods (40 ms), both directions, at full speed: frames
    overtake each other; the controller dates the readings by their counters, places them on its
    trajectory and plans from the state when its late command takes effect. Before the degraded-bus
    mode this lap had 4 violations (docs/sil.md)."""
    m = _lossy_lap(orca, mobil, tmp_path, {"delay": 0.04})
    ctl = m["controller"]
    assert ctl["frames"]["late"] > 0.05 * ctl["frames"]["ok"], ctl["frames"]  # frames overtook others
    assert ctl["status_counts"]["DDYN_CTRL_BUS_DEGRADED"] > 0.5 * ctl["periods"]
    assert m["lap_completed"], m["end_reason"]
    assert m["violations"] == 0
    # rejected readings, then a sensor fault near the end of the lap (the weakness docs/sil.md names: the
    # commands' own delay is not measured). Since the filter restarts on the readings after a blind spell
    # (controller.c reanchor, issue 35 item 4: what makes the lap after a plant restart complete), that fault
    # restarts the filter once, and the restart holds the safe command until 10 healthy periods have passed
    # (measured: 11 safe periods, lap 6.036 s; before the reanchor 3 periods, 5.811 s): one restart, not a stop
    assert ctl["status_counts"]["DDYN_CTRL_RECOVERED"] <= 1
    assert ctl["safe_periods"] <= 12
