"""LCM telemetry: the C publisher's messages arrive in a log that `ddyn import` turns back
into the dataset they came from; bad logs are refused naming the file and the event.

The C side is the host tool ddyn_telemetry_replay (it links c_src/linux/telemetry_lcm.c);
logs are written by LCM's file:// provider, by lcm-logger over UDP multicast, or by
lcm.EventLog with the generated Python types.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import ddyn.cli
from ddyn.data import lcm_types, simulate
from ddyn.data.dataset import write_canonical
from ddyn.data.importers import detect_format, load_any
from ddyn.data.lcm_import import read_events
from ddyn.data.lcm_replay import DEFAULT_TOOL, replay
from ddyn.errors import DataError, DdynError
from ddyn.model import tracks, vehicle
from ddyn.model.single_track import COEFF_NAMES, STATE_NAMES

lcm = pytest.importorskip("lcm", reason="LCM MISSING: the `lcm` package (requirements.lock) is not installed")


@pytest.fixture(scope="module")
def tool() -> Path:
    if not DEFAULT_TOOL.is_file():
        pytest.fail(f"{DEFAULT_TOOL} missing: build the C side with DDYN_WITH_LCM=ON first (scripts/test.sh does)")
    return DEFAULT_TOOL


@pytest.fixture(scope="module")
def sim():
    """3 s of the ORCA car with a covariance and coefficients that vary, one pinned at a guard bound."""
    v = vehicle.load("orca_1_43")
    ds = simulate.simulate(v, tracks.load_track("ethz"), duration=3.0, seed=4, progress=False)
    rng = np.random.default_rng(0)
    for i, n in enumerate(STATE_NAMES):
        ds.extras[f"var_{n}"] = rng.uniform(1e-6, 1e-2, len(ds)) * (i + 1)
    c = v.true_vector() * rng.uniform(0.95, 1.05, (len(ds), len(COEFF_NAMES)))
    c[:, COEFF_NAMES.index("Cd")] = v.ranges["Cd"][1]          # pinned at its upper bound
    c[:, COEFF_NAMES.index("Bf")] = v.ranges["Bf"][0] + 0.01   # within 2 % of the range above the lower bound
    for j, n in enumerate(COEFF_NAMES):
        ds.extras[f"c_{n}"] = c[:, j]
    return ds


def _log(tmp_path: Path, ds, tool: Path, name: str = "run.lcm", **kw) -> Path:
    out = tmp_path / name
    replay(ds, f"file://{out}?mode=w", tool, **kw)
    return out


def test_published_values_come_back_from_the_log(tmp_path, sim, tool):
    log = _log(tmp_path, sim, tool, rates={"plan": 50.0})
    assert detect_format(log) == "lcm_log"
    back = load_any(log)
    assert back.vehicle == "orca_1_43" and back.sample_time == sim.sample_time
    assert len(back) == len(sim) and np.all(back.segment == 0)
    np.testing.assert_array_equal(back.states, sim.states)      # doubles survive text -> C -> LCM -> Python
    np.testing.assert_allclose(back.time, sim.time - sim.time[0], rtol=0, atol=1e-12)
    # the rates are the forward differences of throttle and steering: the simulator's own inputs
    np.testing.assert_allclose(back.inputs[:-1], sim.inputs[:-1], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(back.inputs[-1], back.inputs[-2])
    for n in STATE_NAMES:
        np.testing.assert_array_equal(back.extras[f"var_{n}"], sim.extras[f"var_{n}"])
    for n in COEFF_NAMES:
        np.testing.assert_array_equal(back.extras[f"c_{n}"], sim.extras[f"c_{n}"])
    # flags recomputed here: within 2 % of the range of a bound (Bf, Cd as set; the true Er = -0.019 is
    # within 0.04 of its upper bound 0 too)
    v = vehicle.load("orca_1_43")
    lo, hi = (np.array([v.ranges[n][i] for n in COEFF_NAMES]) for i in (0, 1))
    c = np.column_stack([sim.extras[f"c_{n}"] for n in COEFF_NAMES])
    bits = 1 << np.arange(len(COEFF_NAMES))
    np.testing.assert_array_equal(back.extras["sat_lo_mask"], ((c <= lo + 0.02 * (hi - lo)) * bits).sum(axis=1))
    np.testing.assert_array_equal(back.extras["sat_hi_mask"], ((c >= hi - 0.02 * (hi - lo)) * bits).sum(axis=1))
    assert np.all(back.extras["sat_lo_mask"].astype(int) & (1 << COEFF_NAMES.index("Bf")))
    assert np.all(back.extras["sat_hi_mask"].astype(int) & (1 << COEFF_NAMES.index("Cd")))
    assert np.all(back.extras["mpc_status"] == 0) and np.all(back.extras["mpc_cost"] == 0)
    np.testing.assert_allclose(back.extras["clock_s"], back.time, atol=1e-6)
    assert np.all(back.extras["faults_active"] == 0)
    assert "loop_total_s" not in back.extras   # timing at a fifth of the control rate by default


def test_replay_publishes_its_own_loop_timing(tmp_path, sim, tool):
    back = load_any(_log(tmp_path, sim, tool, rates={"timing": 50.0}))
    assert np.all(back.extras["loop_total_s"] > 0) and np.all(back.extras["loop_total_s"] < 1.0)
    np.testing.assert_allclose(back.extras["loop_period_s"][1:], sim.sample_time, rtol=1e-9)
    assert back.extras["loop_period_s"][0] == 0.0


def test_decimated_channels_are_noted_not_columns(tmp_path, sim, tool):
    log = _log(tmp_path, sim, tool, rates={"coeffs": 10.0})   # every 5th of the 50 Hz steps
    back = load_any(log)
    assert "c_Bf" not in back.extras and "mpc_cost" not in back.extras   # plan: a fifth by default
    assert "DDYN_COEFFS: 30 message(s), none at 120 of 150 state steps" in back.metadata["extras_notes"]
    assert "DDYN_COEFFS=30" in back.metadata["messages"]


def test_state_at_a_lower_rate_does_not_fit_the_vehicle(tmp_path, sim, tool):
    log = _log(tmp_path, sim, tool, rates={"state": 25.0})
    with pytest.raises(DataError, match="sample time is 0.04 s"):
        load_any(log, vehicle="orca_1_43")
    assert load_any(log).vehicle == "av21"   # 0.04 s is the AV-21's sample time: that is the vehicle inferred


def test_channel_prefix(tmp_path, sim, tool):
    log = _log(tmp_path, sim, tool, prefix="CAR2_")
    with pytest.raises(DataError, match="0 state estimate"):
        load_any(log)
    assert len(load_any(log, channel_prefix="CAR2_")) == len(sim)


# ---- logs written from Python with the generated types


def _state(step: int, utime: int, vx: float = 2.0):
    m = lcm_types.types().state_estimate_t()
    m.step, m.utime = step, utime
    m.x, m.vx, m.throttle, m.steering = 0.1 * step, vx, 0.01 * step, -0.002 * step
    m.cov_diag = [1e-4] * 8
    return m


def _write(path: Path, events) -> Path:
    log = lcm.EventLog(str(path), "w", overwrite=True)
    for channel, msg in events:
        log.write_event(0, channel, msg if isinstance(msg, bytes) else msg.encode())
    log.close()
    return path


def test_lost_messages_start_new_segments(tmp_path):
    steps = [0, 1, 2, 3, 5, 6, 7, 10, 11]   # 4, 8 and 9 lost
    log = _write(tmp_path / "gaps.lcm", [("DDYN_STATE", _state(s, 1_000_000 + 20_000 * s)) for s in steps]
                 + [("OTHER", b"\x01\x02")])
    ds = load_any(log)
    assert list(ds.segment) == [0, 0, 0, 0, 1, 1, 1, 2, 2]
    np.testing.assert_allclose(ds.time, 0.02 * np.array(steps), atol=1e-12)
    np.testing.assert_allclose(ds.inputs[:, 0], 0.5)   # throttle grows 0.01 per step of 0.02 s
    assert ds.metadata["ignored_channels"] == "OTHER=1"


def test_timing_and_faults_become_columns(tmp_path):
    t = lcm_types.types()
    events = []
    for s in range(4):
        events.append(("DDYN_STATE", _state(s, 20_000 * s)))
        timing = t.loop_timing_t()
        timing.step, timing.period_s, timing.total_s, timing.deadline_s = s, 0.02, 0.004 * (s + 1), 0.015
        timing.deadline_missed = timing.total_s > timing.deadline_s
        events.append(("DDYN_TIMING", timing))
        faults = t.faults_t()
        faults.step, faults.active = s, (-(2 ** 31)) if s == 2 else s   # bit 31 arrives as a negative int32
        events.append(("DDYN_FAULTS", faults))
    ds = load_any(_write(tmp_path / "tf.lcm", events))
    np.testing.assert_allclose(ds.extras["loop_total_s"], [0.004, 0.008, 0.012, 0.016])
    assert list(ds.extras["deadline_missed"]) == [0, 0, 0, 1]
    assert list(ds.extras["faults_active"]) == [0, 1, 2 ** 31, 3]


def test_min_vx_drops_slow_rows(tmp_path):
    log = _write(tmp_path / "slow.lcm",
                 [("DDYN_STATE", _state(s, 20_000 * s, vx=0.0 if s < 3 else 2.0)) for s in range(8)])
    assert len(load_any(log)) == 8
    ds = load_any(log, min_vx=1.0)
    assert len(ds) == 5 and ds.time[0] == pytest.approx(0.06)


def test_steps_that_go_back_are_refused_by_event(tmp_path):
    log = _write(tmp_path / "restart.lcm", [("DDYN_STATE", _state(s, 20_000 * s)) for s in (0, 1, 2)]
                 + [("DDYN_COEFFS", lcm_types.types().guard_coeffs_t())]
                 + [("DDYN_STATE", _state(0, 80_000))])
    with pytest.raises(DataError, match=r"restart.lcm: event 5: state estimate of step 0 after step 2"):
        load_any(log)


# ---- corrupt and truncated logs


@pytest.fixture()
def good_log(tmp_path):
    return _write(tmp_path / "good.lcm", [("DDYN_STATE", _state(s, 20_000 * s)) for s in range(6)])


def _offsets(path: Path) -> list[int]:
    return [offset for _, offset, _, _ in read_events(path)]


def test_truncated_log_names_the_event(good_log):
    offsets = _offsets(good_log)
    data = good_log.read_bytes()
    for cut, event in ((offsets[4] + 10, 5), (offsets[4] + 40, 5), (len(data) - 1, 6), (4, 1)):
        good_log.write_bytes(data[:cut])
        with pytest.raises(DataError, match=rf"good.lcm: event {event} \(byte offset {offsets[event - 1]}\): "
                                            "truncated"):
            load_any(good_log, fmt="lcm_log")


def test_garbage_between_events_names_the_event(good_log):
    offsets = _offsets(good_log)
    data = good_log.read_bytes()
    good_log.write_bytes(data[:offsets[2]] + b"\x00junk\xff" + data[offsets[2]:])
    with pytest.raises(DataError, match=rf"event 3 \(byte offset {offsets[2]}\): corrupt: found 0x006a756e where the event sync word"):
        load_any(good_log)


def test_corrupt_payload_names_the_event(good_log):
    offsets = _offsets(good_log)
    data = bytearray(good_log.read_bytes())
    payload = offsets[3] + 28 + len("DDYN_STATE")
    data[payload] ^= 0xFF                       # the type's fingerprint
    good_log.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"event 4 \(byte offset \d+\), channel DDYN_STATE: does not decode as "
                                        "state_estimate_t"):
        load_any(good_log)


def test_wrong_data_length_names_the_event(good_log):
    offsets = _offsets(good_log)
    data = bytearray(good_log.read_bytes())
    at = offsets[1] + 24                        # the data length field of event 2
    length = int.from_bytes(data[at:at + 4], "big")
    # framing and decoding disagree: event 3 starts 8 bytes early
    data[at:at + 4] = (length - 8).to_bytes(4, "big")
    good_log.write_bytes(bytes(data))
    with pytest.raises(DataError, match=rf"event 3 \(byte offset {offsets[2] - 8}\): corrupt: found 0x"):
        load_any(good_log)
    # consistent framing, but a payload 8 bytes short of its type
    good_log.write_bytes(bytes(data[:offsets[2] - 8] + data[offsets[2]:]))
    with pytest.raises(DataError, match=rf"event 2 \(byte offset {offsets[1]}\), channel DDYN_STATE: does not "
                                        "decode as state_estimate_t"):
        load_any(good_log)


def test_non_finite_state_is_refused(tmp_path):
    bad = _state(2, 40_000)
    bad.vy = float("nan")
    log = _write(tmp_path / "nan.lcm", [("DDYN_STATE", _state(s, 20_000 * s)) for s in (0, 1)] + [("DDYN_STATE", bad)])
    with pytest.raises(DataError, match=r"event 3: state estimate vy is nan"):
        load_any(log)


# ---- over the network: lcm-logger on UDP multicast


def test_lcm_logger_over_udp_multicast(tmp_path, sim, tool, multicast_route):
    """lcm-logger (the binary itself: the venv's lcm-logger is a Python wrapper that SIGKILLs the logger on
    SIGINT, which loses its unflushed tail) records a paced replay over UDP multicast. The logger's start
    and stop are those of `ddyn sil run` on a host: it is started and polled until it listens (its socket
    on the port, the group joined), and drained before SIGINT; no fixed waits. An empty log is a failure."""
    from ddyn.sil.run import start_host_logger, stop_host_logger
    proc, url = start_host_logger(tmp_path)
    try:
        replay(sim, url, tool, speed=5.0)   # paced: a burst would overrun the logger's socket buffer
    finally:
        rc = stop_host_logger(proc, url)
    assert rc == 0
    out = tmp_path / "controller.lcm"
    assert out.exists() and out.stat().st_size > 0, (
        f"lcm-logger received nothing over {url} although the route for {multicast_route} is set "
        f"({(tmp_path / 'lcm-logger.stdout').read_text()[-500:]})")
    back = load_any(out)
    # UDP may still drop messages on a loaded host: those that arrived are exact, a loss starts a segment
    first = int(back.metadata["utime_start"]) * 1e-6   # the replay's utime is the row's time in microseconds
    steps = np.rint((first + back.time - sim.time[0]) / sim.sample_time).astype(int)
    np.testing.assert_array_equal(back.states, sim.states[steps])
    assert len(np.unique(back.segment)) == 1 + int(np.sum(np.diff(steps) != 1))


# ---- the command line


def run_cli(argv: list[str], monkeypatch) -> int:
    monkeypatch.setattr(ddyn.cli, "COMMANDS", ddyn.cli.commands_named("import", "lcm"))
    return ddyn.cli.main(argv)


def test_cli_replay_then_import(tmp_path, monkeypatch, capsys, sim, tool):
    src = write_canonical(sim, tmp_path / "sim.csv")
    log, out = tmp_path / "run.lcm", tmp_path / "back.csv"
    assert run_cli(["lcm", "replay", str(src), "-o", str(log), "--rate", "coeffs=10"], monkeypatch) == 0
    assert "COEFFS published 30 skipped 120 errors 0" in capsys.readouterr().out
    assert run_cli(["import", str(log), "-o", str(out)], monkeypatch) == 0
    assert "150 rows, 1 segment(s)" in capsys.readouterr().out
    back = load_any(out)
    np.testing.assert_array_equal(back.states, sim.states)
    assert back.metadata["import_format"] == "lcm_log" and back.vehicle == "orca_1_43"
    log.write_bytes(log.read_bytes()[:-7])
    assert run_cli(["import", str(log), "-o", str(out)], monkeypatch) == 2
    assert re.search(r"run.lcm: event \d+ \(byte offset \d+\): truncated", capsys.readouterr().err)
    assert run_cli(["lcm", "replay", str(src), "-o", str(log), "--rate", "nonsense=1"], monkeypatch) == 2


# ---- fuzzing: whatever the bytes, a DdynError or a sane dataset


@pytest.fixture(scope="module")
def fuzz_log(tmp_path_factory) -> bytes:
    t = lcm_types.types()
    events = []
    for s in range(6):
        events.append(("DDYN_STATE", _state(s, 20_000 * s)))
        c = t.guard_coeffs_t()
        c.step, c.coeffs, c.lo, c.hi = s, [1.0] * 17, [0.0] * 17, [2.0] * 17
        events.append(("DDYN_COEFFS", c))
        p = t.mpc_plan_t()
        p.step, p.horizon, p.n_states, p.status_name = s, 2, 3, "ok"
        p.states, p.inputs = [[0.5] * 8] * 3, [[0.1, 0.2]] * 2
        events.append(("DDYN_PLAN", p))
    return _write(tmp_path_factory.mktemp("lcmfuzz") / "fuzz.lcm", events).read_bytes()


@st.composite
def mutated(draw, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "cut", "insert", "delete"]))
        at = draw(st.integers(0, max(len(b) - 1, 0)))
        if op == "flip" and b:
            b[at] ^= draw(st.integers(1, 255))
        elif op == "cut":
            del b[at:]
        elif op == "insert":
            b[at:at] = draw(st.binary(min_size=1, max_size=12))
        elif b:
            del b[at:at + draw(st.integers(1, 40))]
    return bytes(b)


@given(data=st.data())
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_fuzzed_logs_give_a_data_error_or_a_sane_dataset(tmp_path, fuzz_log, data):
    path = tmp_path / "f.lcm"
    path.write_bytes(data.draw(mutated(fuzz_log)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # an overflow nobody expected would otherwise pass as inf
        try:
            ds = load_any(path, fmt="lcm_log", vehicle="orca_1_43")
        except DdynError:
            return
    for name, values in [("time", ds.time), ("states", ds.states), ("inputs", ds.inputs), *ds.extras.items()]:
        assert np.all(np.isfinite(values)), name
    assert len(ds) >= 2 and np.all(np.diff(ds.time) > 0) and np.all(np.diff(ds.segment) >= 0)
