"""ddyn_controller's configuration file (firmware_sim/controller/controller_config.c, docs/deploy.md):
every refusal names its key, the defaults are printed back, and a network built for another checkpoint
is refused (issue 16 items 2 and 3).

The executables are the SIL build for the fixture network (tests/c/generated/net_fixture).
"""
from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest

from ddyn.errors import DdynError
from ddyn.model.single_track import COEFF_NAMES
from ddyn.model.tracks import load_track
from ddyn.model.vehicle import load as load_vehicle
from ddyn.paths import REPO
from ddyn.sil import run as sil

FIXTURE_NET = REPO / "tests" / "c" / "generated" / "net_fixture"


@pytest.fixture(scope="module")
def bins():
    return sil.build_binaries(None)


@pytest.fixture(scope="module")
def orca():
    return load_vehicle("orca_1_43")


@pytest.fixture(scope="module")
def spec(orca, shared_data):
    mobil = load_track("ethzMobil", shared_data)
    return sil.SilSpec(vehicle=orca, track=mobil, coeffs_plant=orca.true_vector(), coeffs_controller=None,
                       nominal=orca.true_vector())


@pytest.fixture
def good(spec, tmp_path) -> dict:
    """A valid configuration (what ddyn sil run writes), its raceline beside it in tmp_path."""
    path = sil.write_controller_files(spec, sil.raceline_table(spec.track, spec.vehicle), tmp_path, str(tmp_path))
    return json.loads(path.read_text())


def fixture_hash() -> str:
    text = (FIXTURE_NET / "ddyn_net_config.h").read_text()
    return re.search(r'DDYN_NET_CHECKPOINT_SHA256 "([0-9a-f]{64})"', text).group(1)


def check(bins: Path, cfg: dict, tmp_path: Path) -> subprocess.CompletedProcess:
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(cfg, indent=1))
    return subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True,
                          timeout=30)


def test_a_valid_config_is_printed_back_with_its_defaults(bins, good, tmp_path):
    r = check(bins, good, tmp_path)
    assert r.returncode == 0, r.stderr
    printed = json.loads(r.stdout)
    assert printed["raceline_points"] == len((tmp_path / "raceline.csv").read_text().splitlines()) - 1
    assert printed["control"]["period"] == good["control"]["period"]
    assert printed["nominal_coefficients"] == good["nominal_coefficients"]
    assert printed["realtime"]["lockstep_silence"] == 0.5
    # defaults of what the file leaves out: the MPC's own settings, no step cap, the timer pacing not chosen
    assert printed["mpc"]["horizon"] >= 1 and printed["control"]["max_steps"] == 0
    assert printed["coefficients"]["checkpoint_hash"] == ""
    # the printed configuration is itself a valid configuration that prints the same
    del printed["raceline_points"]
    printed["telemetry"]["log"] = str(tmp_path / "controller_log.csv")
    r2 = check(bins, printed, tmp_path)
    assert r2.returncode == 0, r2.stderr
    assert json.loads(r2.stdout) == json.loads(r.stdout)


def test_every_key_sil_writes_is_in_the_table(bins, good):
    keys = subprocess.run([str(bins / "ddyn_controller"), "--keys"], capture_output=True, text=True, check=True)
    listed = {ln.split()[0] for ln in keys.stdout.splitlines()}

    def paths(d: dict, prefix: str = ""):
        for k, v in d.items():
            p = f"{prefix}{k}"
            yield p
            if isinstance(v, dict) and p not in ("nominal_coefficients", "coefficients.fixed", "can.stale_periods",
                                                 "can.cycle_ms", "control.pid"):
                yield from paths(v, p + ".")
    assert set(paths(good)) <= listed
    assert "realtime.priority" in listed and "coefficients.checkpoint_hash" in listed


def _set(cfg: dict, dotted: str, value) -> dict:
    *parents, leaf = dotted.split(".")
    d = cfg
    for p in parents:
        d = d.setdefault(p, {})
    if value is DELETE:
        del d[leaf]
    else:
        d[leaf] = value
    return cfg


DELETE = object()

# (key to change, new value, the message's start: "controller.json: <key>: ...")
BAD = [
    ("vehicel", "orca_1_43", "vehicel: unknown key"),
    ("control.perod", 0.02, "control.perod: unknown key"),
    ("nominal_coefficients.Bx", 1.0, "nominal_coefficients.Bx: unknown key"),
    ("control.period", "0.02", "control.period: expected a number, got a string"),
    ("control.period", 0.0, "control.period: 0 is out of range"),
    ("control.period", DELETE, "control.period: missing (required)"),
    ("can.interface", DELETE, "can.interface: missing (required)"),
    ("can", DELETE, "can: missing (required)"),
    ("can.stale_periods.imu", 1.5, "can.stale_periods.imu: 1.5 is not an integer"),
    ("can.cycle_ms.imu", 20000, "can.cycle_ms.imu: 20000 is out of range"),
    ("can.cycle_ms.gnss_position", 40, "can.cycle_ms.gnss_position: 40 ms, but a position frame starts each period"),
    ("nominal_coefficients.Iz", DELETE, "nominal_coefficients.Iz: missing"),
    ("vehicle", "kart", "vehicle: no generated model 'kart'"),
    ("vehicle", 3, "vehicle: expected a string, got a number"),
    ("raceline", "no_such_raceline.csv", "raceline: cannot read"),
    ("control.throttle", "fast", "control.throttle: 'fast' is not one of mpc, pid"),
    ("control.prepare", 1, "control.prepare: expected true or false, got a number"),
    ("control.bank", 1, "control.bank: expected true or false, got a number"),
    ("control.bank", True, "control.bank: true, but "),
    ("filter.x0", [0.0] * 7, "filter.x0: expected an array of 8 numbers"),
    ("filter.sensor_std.heading", [-1.0], "filter.sensor_std.heading[0]: -1 is out of range"),
    ("filter.sensor_std.lidar", [1.0], "filter.sensor_std.lidar: unknown key"),
    ("realtime.priority", 150, "realtime.priority: 150 is out of range (0 .. 99)"),
    ("realtime.priority", 1.5, "realtime.priority: 1.5 is not an integer"),
    ("realtime.pacing", "sometimes", "realtime.pacing: 'sometimes' is not one of frame, timer"),
    ("realtime", [], "realtime: expected an object, got an array"),
    ("mpc.horizon", 0, "mpc.horizon: 0 is out of range"),
    ("coefficients.checkpoint_hash", "abc", "coefficients.checkpoint_hash: 'abc' is not a sha256"),
    ("coefficients.source", "fixed", "coefficients.fixed.Bf: missing (coefficients.source is fixed"),
    ("control.pid", {"kp": 1.0}, "control.pid: given, but control.throttle is not pid"),
    ("telemetry.metrics", "/no/such/dir/m.json", "telemetry.metrics: the directory of /no/such/dir/m.json does not"),
]


@pytest.mark.parametrize("key,value,said", BAD, ids=[f"{k}={v!r}"[:60] for k, v, _ in BAD])
def test_each_refusal_names_its_key(bins, good, tmp_path, key, value, said):
    r = check(bins, _set(good, key, value), tmp_path)
    assert r.returncode == 2, r.stdout
    assert f"controller.json: {said}" in r.stderr, r.stderr
    assert r.stdout == ""


def test_malformed_documents_and_rasterlines_are_refused(bins, good, tmp_path):
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(good, indent=1)[:-3])  # cut short
    r = subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True)
    assert r.returncode == 2 and "(document): not valid JSON (near line" in r.stderr
    text = json.dumps(good, indent=1)
    path.write_text(text.replace('"vehicle": "orca_1_43",', '"vehicle": "orca_1_43", "vehicle": "av21",'))
    r = subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True)
    assert r.returncode == 2 and "vehicle: given twice" in r.stderr
    lines = (tmp_path / "raceline.csv").read_text().splitlines()
    lines[3] = lines[3] + ",7"
    (tmp_path / "raceline.csv").write_text("\n".join(lines) + "\n")
    r = check(bins, good, tmp_path)
    # a 6th column is the road's bank, read with control.bank only (issue 34)
    assert r.returncode == 2 and "control.bank: false, but " in r.stderr and "line 4 has a 6th column" in r.stderr
    lines[3] = lines[3] + ",8"
    (tmp_path / "raceline.csv").write_text("\n".join(lines) + "\n")
    r = check(bins, good, tmp_path)
    assert r.returncode == 2 and "raceline: " in r.stderr and "line 4: more than 5 columns" in r.stderr
    (tmp_path / "raceline.csv").write_text("x,y,speed,width_left,width_right\n0,0,1,0.1,0.1\n1,0,1,0.1,0.1\n")
    r = check(bins, good, tmp_path)
    assert r.returncode == 2 and "2 points, at least 4 needed" in r.stderr


def test_the_built_network_identifies_itself(bins):
    r = subprocess.run([str(bins / "ddyn_controller"), "--checkpoint-hash"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == fixture_hash()


def test_a_network_of_another_checkpoint_is_refused(bins, good, tmp_path):
    """The configuration names the checkpoint (ddyn sil run --model passes its sha256): the controller
    and the in-process variant refuse a build for another one, before touching the bus."""
    mine = fixture_hash()
    other = "0" * 64
    good["coefficients"]["checkpoint_hash"] = mine
    assert check(bins, good, tmp_path).returncode == 0
    good["coefficients"]["checkpoint_hash"] = other
    good["can"]["interface"] = "no_such_can0"  # refused before it would fail on the interface
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(good))
    for cmd in ([bins / "ddyn_controller", "--check", path], [bins / "ddyn_controller", path]):
        r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=30)
        assert r.returncode == 2
        assert "refused: coefficients.checkpoint_hash" in r.stderr and "stale build" in r.stderr
        assert mine[:12] in r.stderr and other[:12] in r.stderr
        assert "CAN" not in r.stderr and "no_such_can0" not in r.stderr

def test_the_in_process_variant_refuses_it_too(bins, spec, good, tmp_path):
    plant = tmp_path / "plant.json"
    plant.write_text(json.dumps(sil.plant_config(spec, str(sil.plant_track_dir(spec.track, tmp_path)),
                                                 str(tmp_path))))
    good["coefficients"]["checkpoint_hash"] = "0" * 64
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(good))
    r = subprocess.run([str(bins / "ddyn_sil_inprocess"), str(plant), str(path)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "coefficients.checkpoint_hash" in r.stderr and "stale build" in r.stderr
    assert not (tmp_path / "controller_metrics.json").exists()


def test_sil_run_refuses_a_stale_build(spec, tmp_path):
    """`ddyn sil run --model X` names X's hash; a controller built for another network (here: the
    fixture's build, given the hash of a different checkpoint) is refused before the run starts."""
    stale = sil.SilSpec(**{**spec.__dict__, "checkpoint_hash": "1" * 64, "max_time": 1.0})
    with pytest.raises(DdynError, match="stale build"):
        sil.run_sil(stale, tmp_path, None, where="inprocess")
    ok = sil.SilSpec(**{**spec.__dict__, "coeffs_controller": spec.vehicle.true_vector(),
                        "checkpoint_hash": fixture_hash(), "max_time": 1.0})
    m = sil.run_sil(ok, tmp_path, None, where="inprocess")
    assert m["controller"] is not None
    cm = json.loads((tmp_path / "controller_metrics.json").read_text())
    assert cm["checkpoint_hash"] == fixture_hash()


def test_coefficient_names_match_the_model():
    """The configuration's coefficient names are the model's COEFF_NAMES, in order (controller_config.c)."""
    text = (REPO / "firmware_sim" / "controller" / "controller_config.c").read_text()
    block = re.search(r"COEFF_NAMES\[DDYN_NC\] = \{([^}]*)\}", text).group(1)
    assert tuple(re.findall(r'"(\w+)"', block)) == COEFF_NAMES


def test_a_missing_can_interface_is_named_after_the_config_passed(bins, good, tmp_path):
    good["can"]["interface"] = "no_such_can0"
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(good))
    r = subprocess.run([str(bins / "ddyn_controller"), str(path)], capture_output=True, text=True, timeout=30)
    # "no CAN interface 'no_such_can0'" where the kernel has CAN; on a host without it socket() itself fails
    assert r.returncode == 2 and "ddyn_controller: can.interface: " in r.stderr, r.stderr
    assert "no CAN interface 'no_such_can0'" in r.stderr or "socket()" in r.stderr


def test_the_bank_column_is_read_with_control_bank_and_refused_beyond_45_degrees(bins, good, tmp_path):
    """control.bank (issue 34): true reads the raceline's 6th column (rad) as the road's bank; each refusal is one
    line naming the key"""
    lines = (tmp_path / "raceline.csv").read_text().splitlines()
    rows = [ln + f",{0.1 + 0.001 * i!r}" for i, ln in enumerate(lines[1:])]
    (tmp_path / "raceline.csv").write_text("\n".join([lines[0] + ",bank"] + rows) + "\n")
    cfg = _set(good, "control.bank", True)
    r = check(bins, cfg, tmp_path)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["control"]["bank"] is True
    rows[2] = rows[2].rsplit(",", 1)[0] + ",0.8"       # 45.8 degrees
    (tmp_path / "raceline.csv").write_text("\n".join([lines[0]] + rows) + "\n")
    r = check(bins, cfg, tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "controller.json: control.bank: " in r.stderr and "line 4: bank 0.8 rad, beyond" in r.stderr
    rows[2] = rows[2].rsplit(",", 1)[0] + ",nan"
    (tmp_path / "raceline.csv").write_text("\n".join([lines[0]] + rows) + "\n")
    r = check(bins, cfg, tmp_path)
    assert r.returncode == 2 and "controller.json: control.bank: true, but " in r.stderr and "line 4 has no finite 6th" in r.stderr
