"""The Python side of the drive-by-wire protocol (train/data/can_protocol.py, train/data/can_log.py) against
the DBC, the measurement models, and the C decoder (ddyn_can_decode, built by CMake)."""
from __future__ import annotations

import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

import can
from ddyn.data import can_log, simulate
from ddyn.data import can_protocol as proto
from ddyn.model import mathns, sensors, tracks, vehicle
from ddyn.paths import BUILD

REPO = Path(__file__).resolve().parents[2]
TOOL = BUILD / "c_src" / "ddyn_can_decode"
C_RESULT = {None: "foreign_id", "unknown_frame": "unknown_id", "bad_length": "bad_length",
            "checksum": "checksum", "range": "range"}


@pytest.fixture(scope="module")
def sim():
    v = vehicle.load("av21")
    return simulate.simulate(v, tracks.load_track("putnam"), duration=3.0, seed=3, progress=False)


@pytest.fixture(scope="module")
def sim_log(sim, tmp_path_factory):
    path = tmp_path_factory.mktemp("can") / "sim.log"
    can_log.write_candump(can_log.dataset_frames(sim), path)
    return path


def test_checksum_is_crc8_sae_j1850():
    # the identifier 0x3231 contributes "12": with data "3456789" the catalogue check value 0x4B
    assert proto.checksum(0x3231, b"3456789\xAA") == 0x4B


def test_authenticator_mac_agrees_with_the_c_known_answer():
    # the vector of tests/c/test_dbw.c test_auth_mac_is_keyed_blake2b: hashlib's BLAKE2b here, Monocypher's there
    key, data = bytes(range(32)), bytes(range(1, 9))
    assert proto.auth_mac(key, 0x100, data, 0x0102030405060708) == 0xA3DC4D
    # the authenticator frame decodes with the DBC and carries the protected id, the low freshness bits, the MAC
    fid, payload = proto.authenticator(key, 0x111, data, (5 << 22) + 17, counter=3)
    assert fid == 0x113
    d = proto.decode(fid, payload)
    assert d.name == "SecOC_DBW" and d.counter == 3
    assert d.signals["AuthenticatedId"] == 0x11 and d.signals["Freshness"] == 17
    assert d.signals["Mac"] == proto.auth_mac(key, 0x111, data, (5 << 22) + 17)


def test_dbc_ranges_cover_both_cars():
    db = proto.database()
    steer = db.get_message_by_name("DBW_Command").get_signal_by_name("SteeringAngle")
    wheel = db.get_message_by_name("DBW_WheelSpeeds").get_signal_by_name("WheelSpeedFront")
    for name in ("orca_1_43", "av21"):
        v = vehicle.load(name)
        lo, hi = v.input_limits["steering"]
        assert steer.minimum <= lo and hi <= steer.maximum, name
        assert v.max_speed <= wheel.maximum, name


def test_export_import_round_trip_matches_the_measurement_models(sim, sim_log, tmp_path):
    table = can_log.decode_messages(can_log.read_candump(sim_log))
    assert table.frames == 6 * len(sim) and table.foreign == 0
    assert not any(table.issues.values()), table.issues
    v = vehicle.load("av21")
    st = sim.states.T
    ax, ay = sensors.measure(mathns.NUMPY, "acceleration", st, v.coefficient_vector("true"), v.known)
    db = proto.database()

    def half_lsb(msg, sig):
        return db.get_message_by_name(msg).get_signal_by_name(sig).scale / 2 + 1e-9

    imu, pos = table.message("IMU"), table.message("GNSS_Position")
    assert np.all(np.abs(imu["AccelX"] - ax) <= half_lsb("IMU", "AccelX"))
    assert np.all(np.abs(imu["AccelY"] - ay) <= half_lsb("IMU", "AccelY"))
    assert np.all(np.abs(imu["YawRate"] - sim.states[:, 5]) <= half_lsb("IMU", "YawRate"))
    assert np.all(np.abs(pos["PositionX"] - sim.states[:, 0]) <= half_lsb("GNSS_Position", "PositionX"))
    assert np.all(np.abs(table.message("DBW_Steering")["SteeringAngle"] - sim.states[:, 7])
                  <= half_lsb("DBW_Steering", "SteeringAngle"))
    assert np.array_equal(imu["counter"], np.arange(len(sim)) % 16)
    assert np.allclose(imu["time"], sim.time + 3 * can_log.FRAME_SPACING_S, atol=2e-6)
    written = can_log.write_table(table, tmp_path / "t")
    assert {f.name for f in written} >= {"IMU.csv", "GNSS_Position.csv", "issues.json"}
    header = (tmp_path / "t" / "IMU.csv").read_text().splitlines()[0]
    assert header == "time,counter,YawRate,AccelX,AccelY"


def _frame(fid, data):
    return can.Message(timestamp=0.0, arbitration_id=fid, is_extended_id=False, data=bytes(data))


def test_import_counts_each_defect_by_the_c_names():
    msgs = []
    for k in range(6):
        fid, data = proto.encode("IMU", {"YawRate": 0.1, "AccelX": 1.0, "AccelY": -1.0}, counter=k)
        msgs.append(_frame(fid, data))
    fid, data = proto.encode("IMU", {"YawRate": 0.1, "AccelX": 1.0, "AccelY": -1.0}, counter=5)
    msgs.append(_frame(fid, data))                                   # repeat of 5
    fid, data = proto.encode("IMU", {"YawRate": 0.1, "AccelX": 1.0, "AccelY": -1.0}, counter=9)
    msgs.append(_frame(fid, data))                                   # jump 5 -> 9
    bad = bytearray(data)
    bad[7] ^= 1
    msgs.append(_frame(fid, bad))                                    # checksum
    msgs.append(_frame(fid, data[:6]))                               # bad length
    msgs.append(_frame(0x13F, bytes(8)))                             # unknown, inside the block
    msgs.append(_frame(0x300, bytes(8)))                             # foreign
    hi = bytearray(proto.encode("GNSS_Heading", {"Heading": 0.0, "FixType": 4}, counter=0)[1])
    hi[0], hi[1] = 0x00, 0x7D                                        # raw 32000: 3.2 rad > 3.1416
    hi[7] = proto.checksum(0x131, hi)
    msgs.append(_frame(0x131, hi))                                   # range
    table = can_log.decode_messages(msgs)
    assert table.issues == {"unknown_frame": 1, "bad_length": 1, "checksum": 1, "range": 1,
                            "counter_jump": 1, "counter_repeat": 1, "error_frame": 0}
    assert table.foreign == 1
    assert len(table.message("IMU")["time"]) == 8


def test_python_and_c_decoders_agree_frame_by_frame(sim_log, tmp_path):
    """Every frame of a simulated log plus random frames (checksums fixed up, so the range checks
    decide) and broken ones: same verdict, same values, in C and in Python."""
    if not TOOL.is_file():
        pytest.fail(f"{TOOL} missing: build the C side first (scripts/test.sh does)")
    rng = np.random.default_rng(5)
    msgs = can_log.read_candump(sim_log)
    for _ in range(3000):
        fid = int(rng.choice([0x100, 0x110, 0x111, 0x112, 0x120, 0x130, 0x131, 0x13E, 0x0FF, 0x140]))
        data = bytearray(rng.integers(0, 256, 8, dtype=np.uint8).tobytes())
        if rng.random() < 0.9:
            data[7] = proto.checksum(fid, data)
        if rng.random() < 0.05:
            data = data[: int(rng.integers(0, 8))]
        msgs.append(_frame(fid, data))
    log = can_log.write_candump(msgs, tmp_path / "mixed.log")
    out = subprocess.run([str(TOOL)], stdin=open(log), capture_output=True, text=True, check=True).stdout.splitlines()
    assert len(out) == len(msgs)
    verdicts = {}
    for m, line in zip(msgs, out):
        parts = line.split()
        assert int(parts[0], 16) == m.arbitration_id
        try:
            d = proto.decode(m.arbitration_id, bytes(m.data))
            expected = "ok" if d is not None else "foreign_id"
        except proto.FrameError as e:
            d, expected = None, C_RESULT[e.kind]
        assert parts[1] == expected, (line, bytes(m.data).hex())
        verdicts[expected] = verdicts.get(expected, 0) + 1
        if expected == "ok":
            assert parts[2] == d.name and int(parts[3]) == d.counter
            c_values = dict(kv.split("=") for kv in parts[4:])
            for name, value in d.signals.items():
                assert float(c_values[name]) == pytest.approx(value, rel=1e-12, abs=1e-12), (d.name, name)
    # the random part reached every verdict, so the comparison covered each branch
    assert set(verdicts) == {"ok", "foreign_id", "unknown_id", "bad_length", "checksum", "range"}, verdicts


def test_replay_and_record_through_a_bus(sim_log, tmp_path):
    """python-can's in-process virtual bus stands in for vcan0 (no CAN in these kernels)."""
    short = can_log.write_candump(can_log.read_candump(sim_log)[:60], tmp_path / "short.log")
    rec_path = tmp_path / "rec.log"
    with can.Bus(interface="virtual", channel="ddyn-test") as tx, can.Bus(interface="virtual", channel="ddyn-test") as rx:
        counted = {}
        t = threading.Thread(target=lambda: counted.setdefault("n", can_log.record(rx, rec_path, duration=2.0)))
        t.start()
        sent = can_log.replay(short, tx, realtime=True)
        t.join()
    assert sent == 60 and counted["n"] == 60
    a, b = can_log.read_candump(short), can_log.read_candump(rec_path)
    assert [(m.arbitration_id, bytes(m.data)) for m in a] == [(m.arbitration_id, bytes(m.data)) for m in b]
    # the recorded pace is the log's: 60 frames over the log's span (15 rows of 40 ms)
    span_a, span_b = a[-1].timestamp - a[0].timestamp, b[-1].timestamp - b[0].timestamp
    assert span_b == pytest.approx(span_a, abs=0.05)


def test_cli_export_and_import(sim, tmp_path, capsys):
    from ddyn.cli import main
    from ddyn.data.dataset import write_canonical

    ds_path = write_canonical(sim, tmp_path / "sim.csv")
    assert main(["can", "export", str(ds_path), "-o", str(tmp_path / "x.log")]) == 0
    assert main(["can", "import", str(tmp_path / "x.log"), "-o", str(tmp_path / "tab")]) == 0
    assert "issues: none" in capsys.readouterr().out
    assert (tmp_path / "tab" / "GNSS_Heading.csv").is_file()
    assert main(["can", "import", str(tmp_path / "missing.log"), "-o", str(tmp_path / "tab")]) == 2


def test_can_bench_reports_c_and_python_side_by_side():
    from ddyn.bench import can as can_bench

    tool = BUILD / "c_src" / "ddyn_dbw_bench"
    if not tool.is_file():
        pytest.fail(f"{tool} missing: build the C side first (scripts/test.sh does)")
    rows = can_bench.run(tool, calls=1000, py_calls=200)
    assert [r["name"] for r in rows] == ["C dbw_on_frame", "C dbw_command_frame", "Python cantools decode"]
    for r in rows:
        assert 0 < r["median_ns"] <= r["p99_ns"] <= r["max_ns"], r
