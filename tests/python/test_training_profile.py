"""A vehicle's training profile (train/vehicles/training/<vehicle>.json, ddyn.learn.training_profile): what
`ddyn train` uses when no flag gives a setting. Precedence flag > profile > built-in default; the line printed at
start; a bad profile is one line naming the file and the key; a vehicle without a profile trains as before.
No full training: the CLI runs stop at training (train_cmd.train replaced) or train one epoch of a tiny net."""
from __future__ import annotations

import contextlib
import io
import json
from dataclasses import fields
from pathlib import Path

import pytest

from ddyn import cli
from ddyn.errors import DdynError
from ddyn.learn import train_cmd
from ddyn.learn import training_profile as tp
from ddyn.learn.training import TrainConfig
from ddyn.model import vehicle

REPO = Path(__file__).resolve().parents[2]
TINY = ["--epochs", "1", "--lbfgs-iterations", "0", "--hidden", "4", "--layers", "1", "--quiet"]


class Stopped(Exception):
    """Raised in place of training: the config it would have trained with."""

    def __init__(self, cfg):
        super().__init__("stopped before training")
        self.cfg = cfg


def _stop(ds, v, cfg, progress=True):
    raise Stopped(cfg)


def run_cli(argv: list[str]) -> tuple[int, str, str, TrainConfig | None]:
    """cli.main in process, training replaced: (status, stdout, stderr, the config it would train with)."""
    out, err = io.StringIO(), io.StringIO()
    cfg = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = cli.main(argv)
        except SystemExit as e:
            rc = e.code
        except Stopped as s:
            rc, cfg = None, s.cfg
    return rc, out.getvalue(), err.getvalue(), cfg


@pytest.fixture(scope="module")
def orca_lap(tmp_path_factory) -> Path:
    """A short simulated log of the 1:43 car (a vehicle without a profile)."""
    from ddyn.data import simulate
    from ddyn.data.dataset import write_canonical
    from ddyn.model import tracks

    ds = simulate.simulate(vehicle.load("orca_1_43"), tracks.load_track("ethzMobil"), duration=2.0, seed=3,
                           progress=False)
    return write_canonical(ds, tmp_path_factory.mktemp("orca") / "lap.csv")


@pytest.fixture(scope="module")
def av21_lap(tmp_path_factory) -> Path:
    """A short simulated log of the AV-21 on Putnam (50 rows)."""
    from ddyn.data import simulate
    from ddyn.data.dataset import write_canonical
    from ddyn.model import tracks

    ds = simulate.simulate(vehicle.load("av21"), tracks.load_track("putnam"), duration=2.0, seed=3, progress=False)
    return write_canonical(ds, tmp_path_factory.mktemp("av21") / "lap.csv")


@pytest.fixture
def profiles(tmp_path, monkeypatch) -> Path:
    """An empty profile folder in place of train/vehicles/training."""
    folder = tmp_path / "training"
    folder.mkdir()
    monkeypatch.setattr(tp, "PROFILE_DIR", folder)
    return folder


def write_profile(folder: Path, vehicle_name: str, doc) -> Path:
    path = folder / f"{vehicle_name}.json"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def good(**settings) -> dict:
    return {"vehicle": "orca_1_43", "why": "a test", "settings": settings or {"tau": 3, "epochs": 7}}


# ------------------------------------------------------------------------------------------------ the av21 profile

def test_the_av21_profile_records_the_held_out_studys_settings():
    """The held-out study (results/ddm_real_heldout.json) kept the defaults (its run ddm_putnam: TrainConfig()):
    the profile records them, points at the study, and leaves the seed to the user."""
    p = tp.load("av21")
    assert p is not None and p.path == "train/vehicles/training/av21.json"
    assert "results/ddm_real_heldout.json" in p.why and (REPO / "results" / "ddm_real_heldout.json").is_file()
    defaults = TrainConfig()
    assert p.settings == {k: getattr(defaults, k) for k in p.settings}
    assert {"tau", "guard_prior", "epochs", "lbfgs_iterations", "lr", "kind"} <= set(p.settings)
    assert "seed" not in p.settings
    assert tp.resolve("av21", {}).config == TrainConfig()


def test_the_av21_profile_file_does_not_touch_the_hashed_vehicle_files():
    """The generated C headers carry the sha256 of train/vehicles/<name>.json: the profile lives elsewhere, and
    is not a vehicle file (vehicle.available lists only train/vehicles/*.json)."""
    assert tp.PROFILE_DIR == vehicle.VEHICLE_DIR / "training"
    assert "training" not in vehicle.available()
    assert not any("train" in json.loads(f.read_text()) for f in vehicle.VEHICLE_DIR.glob("*.json"))


@pytest.mark.parametrize("name", ["orca_1_43", "av21_powertrain"])
def test_a_vehicle_without_a_profile_gets_the_built_in_defaults(name):
    assert not tp.profile_path(name).exists() and tp.load(name) is None
    r = tp.resolve(name, {})
    assert r.profile is None and r.config == TrainConfig()
    assert set(r.origin.values()) == {"default"} and set(r.origin) == {f.name for f in fields(TrainConfig)}
    line = tp.describe(r)
    assert line.startswith(f"training profile: none for {name} (no train/vehicles/training/{name}.json)")
    assert "tau 1 [default]" in line and "[profile]" not in line


# ------------------------------------------------------------------------------------------------ precedence

def test_a_flag_overrides_the_profile_and_the_profile_the_default(profiles):
    write_profile(profiles, "orca_1_43", good(tau=3, epochs=7, guard_prior=0.05))
    r = tp.resolve("orca_1_43", {"epochs": 2})
    assert (r.config.tau, r.config.epochs, r.config.guard_prior, r.config.lr) == (3, 2, 0.05, TrainConfig().lr)
    assert r.origin["tau"] == "profile" and r.origin["guard_prior"] == "profile"
    assert r.origin["epochs"] == "--epochs" and r.origin["lr"] == "default"
    line = tp.describe(r)
    assert "\n" not in line
    assert line.startswith(f"training profile orca_1_43 ({profiles / 'orca_1_43.json'}): ")
    for part in ("tau 3 [profile]", "epochs 2 [--epochs]", "guard-prior 0.05 [profile]", "lr 0.003 [default]"):
        assert part in line, (part, line)
    # --no-profile: the defaults under the flags
    r = tp.resolve("orca_1_43", {"epochs": 2}, use_profile=False)
    assert r.config == TrainConfig(epochs=2) and r.origin["tau"] == "default"


def test_ddyn_train_prints_the_profile_line_first_and_trains_with_it(profiles, orca_lap, tmp_path, capsys):
    """End to end (a tiny net, one epoch): the printed line, and the checkpoint's recorded config."""
    write_profile(profiles, "orca_1_43", good(tau=2, lr=0.01, epochs=9))
    ck = tmp_path / "m.ckpt"
    assert cli.main(["train", "--data", str(orca_lap), "-o", str(ck), *TINY]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("training profile orca_1_43 (")
    for part in ("tau 2 [profile]", "lr 0.01 [profile]", "epochs 1 [--epochs]", "hidden 4 [--hidden]",
                 "guard-prior 0 [default]"):
        assert part in first, (part, first)
    from ddyn.learn import checkpoint

    _, c = checkpoint.load(ck)
    assert (c["config"]["tau"], c["config"]["lr"], c["config"]["epochs"], c["config"]["hidden"]) == (2, 0.01, 1, 4)


def test_ddyn_train_on_av21_applies_its_profile(av21_lap, monkeypatch):
    monkeypatch.setattr(train_cmd, "train", _stop)
    rc, out, err, cfg = run_cli(["train", "--data", str(av21_lap), "--vehicle", "av21", "-o", "/tmp/unused.ckpt",
                                 "--epochs", "40", "--quiet"])
    assert cfg is not None, (rc, err)
    assert cfg == TrainConfig(epochs=40)
    assert out.splitlines() == [out.splitlines()[0]]   # nothing else before training
    line = out.splitlines()[0]
    assert line.startswith("training profile av21 (train/vehicles/training/av21.json): ")
    assert "tau 1 [profile]" in line and "guard-prior 0 [profile]" in line and "epochs 40 [--epochs]" in line
    assert "seed 0 [default]" in line
    # the vehicle the log records is enough (no --vehicle)
    rc, out, err, cfg = run_cli(["train", "--data", str(av21_lap), "-o", "/tmp/unused.ckpt", "--no-profile",
                                 "--tau", "2", "--quiet"])
    assert cfg == TrainConfig(tau=2) and out.startswith("training profile: none for av21 (--no-profile)")
    assert "tau 2 [--tau]" in out and "epochs 100 [default]" in out


def test_a_vehicle_without_a_profile_trains_as_before_through_the_cli(orca_lap, monkeypatch):
    monkeypatch.setattr(train_cmd, "train", _stop)
    rc, out, err, cfg = run_cli(["train", "--data", str(orca_lap), "-o", "/tmp/unused.ckpt", "--quiet"])
    assert cfg == TrainConfig(), (rc, err)
    assert out.startswith("training profile: none for orca_1_43 (no train/vehicles/training/orca_1_43.json)")


# ------------------------------------------------------------------------------------------------ bad profiles

BAD = [
    ("not_json", "{", "not valid JSON"),
    ("a_list", [1, 2], "a training profile is a JSON object"),
    ("top_key", {**good(), "setings": {}}, "unknown key 'setings'"),
    ("flag_spelling", good(**{"guard-prior": 0.1}), "unknown key settings.'guard-prior' (did you mean 'guard_prior'?)"),
    ("unknown_setting", good(learning_rate=0.1), "settings.'learning_rate'"),
    ("tau_zero", good(tau=0), "settings.tau: tau must be at least 1"),
    ("tau_fraction", good(tau=1.5), "settings.tau must be a whole number"),
    ("epochs_string", good(epochs="100"), "settings.epochs must be a finite number"),
    ("epochs_bool", good(epochs=True), "settings.epochs must be a finite number"),
    ("lr_negative", good(lr=-1.0), "settings.lr: lr must be > 0"),
    ("guard_prior_negative", good(guard_prior=-0.1), "settings.guard_prior: guard_prior must be at least 0"),
    ("val_fraction_one", good(val_fraction=1.0), "settings.val_fraction"),
    ("kind_unknown", good(kind="xyz"), "settings.kind: model kind must be ddm or dpm"),
    ("kind_number", good(kind=3), "settings.kind must be a string"),
    ("prior_with_dpm", good(kind="dpm", guard_prior=0.1), "settings: guard_prior acts on the Physics Guard"),
    ("settings_list", {**good(), "settings": [1]}, "settings must be a JSON object"),
    ("no_why", {"vehicle": "orca_1_43", "settings": {}}, "missing key 'why'"),
    ("empty_why", {**good(), "why": " "}, "why must say what the settings rest on"),
    ("other_vehicle", {**good(), "vehicle": "av21"}, "vehicle is \"av21\", not 'orca_1_43'"),
    ("source_unset", {**good(), "sources": {"lr": "x"}}, "sources.lr notes a setting the profile does not set"),
    ("source_unknown", {**good(), "sources": {"foo": "x"}}, "unknown key sources.'foo'"),
]


@pytest.mark.parametrize("name,doc,expected", BAD, ids=[b[0] for b in BAD])
def test_a_bad_profile_is_one_line_naming_the_file_and_the_key(profiles, name, doc, expected):
    path = write_profile(profiles, "orca_1_43", doc)
    with pytest.raises(DdynError) as e:
        tp.load("orca_1_43")
    message = str(e.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    assert expected in message, (expected, message)


def test_ddyn_train_refuses_a_bad_profile_in_one_line_before_training(profiles, orca_lap, monkeypatch):
    monkeypatch.setattr(train_cmd, "train", _stop)
    path = write_profile(profiles, "orca_1_43", good(tau=0))
    rc, out, err, cfg = run_cli(["train", "--data", str(orca_lap), "-o", "/tmp/unused.ckpt", *TINY])
    assert cfg is None and rc == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, (rc, err)
    assert str(path) in err and "settings.tau" in err
    # --no-profile does not read it
    rc, out, err, cfg = run_cli(["train", "--data", str(orca_lap), "-o", "/tmp/unused.ckpt", *TINY, "--no-profile"])
    assert cfg is not None and cfg.tau == 1


def test_a_flag_at_odds_with_the_profile_names_the_profile(profiles, orca_lap, monkeypatch):
    """--kind dpm is a good flag alone; with the profile's guard prior it is not: the error says where that came
    from."""
    monkeypatch.setattr(train_cmd, "train", _stop)
    path = write_profile(profiles, "orca_1_43", good(guard_prior=0.1))
    rc, out, err, cfg = run_cli(["train", "--data", str(orca_lap), "-o", "/tmp/unused.ckpt", *TINY,
                                 "--kind", "dpm"])
    assert cfg is None and rc == 2 and len(err.splitlines()) == 1, (rc, err)
    assert "guard_prior acts on the Physics Guard" in err and str(path) in err and "guard-prior" in err
