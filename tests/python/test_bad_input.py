"""Issue 35, item 1: one error path for bad input. Every file or value a user gives is checked where it enters,
and the CLI turns every expected failure into one line `ddyn COMMAND: error: ...` naming the file, key or row,
exit status 2, never a traceback.

The explicit examples are the failures found by hand and by the generation below (each failed before its fix);
`test_commands_refuse_generated_bad_input` runs simulate, train, export and gap diagnose in process over a corpus
of malformed inputs made by hypothesis (truncated, empty, wrong type, wrong kind, NaN, negative, unwritable
output), derandomised so that it is the same corpus on every run.
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ddyn import cli
from ddyn.errors import DdynError
from ddyn.model import vehicle
from ddyn.model.single_track import COEFF_NAMES

ORCA = json.loads(vehicle.load("orca_1_43").raw_json)


def run_cli(argv: list[str]) -> tuple[int, str]:
    """cli.main in process: (exit status, stderr). SystemExit (argparse) counts as its status."""
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            rc = cli.main(argv)
        except SystemExit as e:
            rc = e.code
    return rc, err.getvalue()


def assert_one_line_error(argv: list[str], *expected: str) -> str:
    rc, err = run_cli(argv)
    lines = err.splitlines()
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, (argv, rc, err)
    for text in expected:
        assert text in lines[0], (text, lines[0])
    return lines[0]


def write_vehicle(path: Path, doc) -> str:
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return str(path)


def mutated(path: tuple, value):
    """ORCA with the key at path set to value (a _DELETE value removes it)."""
    doc = json.loads(json.dumps(ORCA))
    node = doc
    for key in path[:-1]:
        node = node[key]
    if value is _DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return doc


_DELETE = object()


@pytest.fixture(scope="module")
def lap(tmp_path_factory, shared_data) -> Path:
    """A short simulated log of the 1:43 car (100 rows)."""
    from ddyn.data import simulate
    from ddyn.data.dataset import write_canonical
    from ddyn.model import tracks

    ds = simulate.simulate(vehicle.load("orca_1_43"), tracks.load_track("ethzMobil"), duration=2.0, seed=3,
                           progress=False)
    return write_canonical(ds, tmp_path_factory.mktemp("lap") / "lap.csv")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory, lap) -> Path:
    """A tiny trained DDM checkpoint."""
    from ddyn.learn.train_cmd import train_to_checkpoint
    from ddyn.learn.training import TrainConfig

    out = tmp_path_factory.mktemp("ckpt") / "m.ckpt"
    train_to_checkpoint(str(lap), TrainConfig(epochs=1, lbfgs_iterations=0, hidden=4, layers=1), str(out),
                        progress=False)
    return out


def ckpt_variant(ckpt: Path, out: Path, change) -> str:
    c = torch.load(ckpt, weights_only=True)
    c = {**c, "config": dict(c["config"]), "vehicle": dict(c["vehicle"]), "architecture": dict(c["architecture"])}
    change(c)
    torch.save(c, out)
    return str(out)


# ----------------------------------------------------------------------------------------------- vehicle files

@pytest.mark.parametrize("name,doc,expected", [
    ("top_list", [1, 2], "a vehicle file is a JSON object"),
    ("known_list", mutated(("known",), [0.041, 0.029]), "known must be a JSON object"),
    ("limits_list", mutated(("input_limits",), [[-1, 1]]), "input_limits must be a JSON object"),
    ("noise_list", mutated(("sensor_noise_std",), [0.1]), "sensor_noise_std must be a JSON object"),
    ("ranges_list", mutated(("ranges",), [[0, 1]]), "ranges must be a JSON object"),
    ("dt_negative", mutated(("sample_time",), -0.02), "sample_time must be > 0"),
    ("dt_nan", json.dumps(mutated(("sample_time",), 0.02)).replace("0.02,", "NaN,", 1), "sample_time must be finite"),
    ("dt_string", mutated(("sample_time",), "0.02"), "sample_time must be a number"),
    ("mass_zero", mutated(("known", "mass"), 0), "known.mass must be > 0"),
    ("range_word", mutated(("ranges", "Bf"), ["a", 1]), "ranges.Bf[0] must be a number"),
    ("limits_short", mutated(("input_limits", "throttle"), [1]), "input_limits.throttle must be [lo, hi]"),
    ("noise_negative", mutated(("sensor_noise_std", "vx"), -0.1), "sensor_noise_std.vx must be >= 0"),
    ("substeps_zero", mutated(("rk4_substeps",), 0), "rk4_substeps must be a whole number"),
    ("true_list", mutated(("true_coefficients",), [1.0] * 17), "true_coefficients must be a JSON object"),
])
def test_bad_vehicle_file_is_one_line(tmp_path, name, doc, expected):
    """Before: AttributeError ('list' object has no attribute 'get' / 'items') and a negative or NaN sample
    time accepted."""
    path = write_vehicle(tmp_path / f"{name}.json", doc)
    line = assert_one_line_error(["simulate", "--vehicle", path, "--track", "ethz", "-o", str(tmp_path / "o.csv")],
                                 expected)
    assert path in line


@pytest.mark.parametrize("argv", [
    ["sil", "run", "--where", "inprocess", "--track", "ethzMobil", "--coeffs", "true", "--laps", "1"],
    ["mpc", "raceline", "--track", "ethzMobil"],
])
def test_a_vehicle_file_of_another_car_is_one_line_where_its_body_is_needed(tmp_path, argv):
    """A user's own vehicle file (another name, valid) has no body size for the track-bound checks. Before: a
    KeyError traceback from the MPC's setup (`ddyn sil run`)."""
    path = write_vehicle(tmp_path / "my_car.json", {**ORCA, "name": "my_car"})
    line = assert_one_line_error([*argv, "--vehicle", path, "--out", str(tmp_path / "o")], "'my_car'",
                                 "no body size known")
    assert "orca_1_43" in line


def test_todays_vehicle_files_keep_loading():
    folder = vehicle.VEHICLE_DIR
    files = sorted(folder.glob("*.json")) + sorted((folder / "plants").glob("*.json"))
    assert len(files) >= 10
    for f in files:
        v = vehicle.load(f)
        assert v.sample_time > 0 and math.isfinite(v.sample_time) and set(v.ranges) == set(COEFF_NAMES)


# ----------------------------------------------------------------------------------------------- train

TRAIN_TINY = ["--epochs", "1", "--lbfgs-iterations", "0", "--hidden", "4", "--layers", "1", "--quiet"]


def test_train_refuses_an_unwritable_output_before_any_work(tmp_path, lap, monkeypatch):
    """Before: the checkpoint's write failed (torch RuntimeError, FileExistsError) after the whole training."""
    from ddyn.learn import train_cmd

    monkeypatch.setattr(train_cmd, "train", lambda *a, **k: pytest.fail("trained before checking the output"))
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out in (tmp_path, a_file / "m.ckpt"):
        assert_one_line_error(["train", "--data", str(lap), "-o", str(out), *TRAIN_TINY], str(out))
    assert_one_line_error(["train", "--data", str(lap), "-o", str(tmp_path / "m.ckpt"), "--metrics-json",
                           str(tmp_path), *TRAIN_TINY], "--metrics-json")


@pytest.mark.parametrize("option,value", [("--method", "rk5"), ("--dtype", "foo"), ("--kind", "xyz")])
def test_train_refuses_unknown_names_at_parse_time(tmp_path, option, value):
    """Before: --method rk5 and --dtype foo failed only once training started."""
    line = assert_one_line_error(["train", "--data", "nowhere.csv", "-o", str(tmp_path / "m.ckpt"), option, value],
                                 "invalid choice", value)
    assert line.startswith("ddyn train: error:")


@pytest.mark.parametrize("option,value,expected", [
    ("--lr", "nan", "lr must be a finite number"), ("--lr", "-1", "lr must be > 0"),
    ("--val-fraction", "1.5", "val_fraction"), ("--weight-decay", "-1", "weight_decay"),
])
def test_train_refuses_bad_numbers(tmp_path, lap, option, value, expected):
    assert_one_line_error(["train", "--data", str(lap), "-o", str(tmp_path / "m.ckpt"), option, value], expected)


def test_ranges_file_with_a_word_for_a_bound(tmp_path, lap):
    """Before: ValueError: could not convert string to float."""
    rf = tmp_path / "r.json"
    rf.write_text('{"Cm1": ["a", 1]}')
    assert_one_line_error(["train", "--data", str(lap), "-o", str(tmp_path / "m.ckpt"), "--ranges", str(rf),
                           *TRAIN_TINY], str(rf), "Cm1", "numbers")


# ----------------------------------------------------------------------------------------------- checkpoints

@pytest.mark.parametrize("name,change,expected", [
    ("unknown_key", lambda c: c["config"].update(bogus=1), "unknown config key(s) 'bogus'"),
    ("mistyped", lambda c: c["config"].update(tau="3"), "config: tau must be a finite number"),
    ("no_vehicle_json", lambda c: c["vehicle"].pop("json"), "vehicle.json missing"),
    ("no_architecture", lambda c: c.pop("architecture"), "checkpoint lacks 'architecture'"),
    ("config_list", lambda c: c.update(config=[1]), "config must be a mapping"),
    ("bad_embedded_vehicle", lambda c: c["vehicle"].update(json="[1]"), "a vehicle file is a JSON object"),
])
def test_bad_checkpoint_is_one_line(tmp_path, ckpt, name, change, expected):
    """Before: TypeError (unknown or mistyped config key), KeyError (no vehicle.json, no architecture)."""
    path = ckpt_variant(ckpt, tmp_path / f"{name}.ckpt", change)
    assert_one_line_error(["export", path, "--out", str(tmp_path / "exp"), "--no-torch-export"], expected)


def test_corrupt_checkpoint_is_one_line(tmp_path, ckpt):
    """Before: torch's paragraph about weights_only (several lines) and a pickle-protocol warning."""
    import pickle

    cut = tmp_path / "cut.ckpt"
    cut.write_bytes(ckpt.read_bytes()[:500])
    pickled = tmp_path / "pickled.ckpt"
    pickled.write_bytes(pickle.dumps(object))
    for path in (cut, pickled):
        line = assert_one_line_error(["export", str(path), "--out", str(tmp_path / "exp")],
                                     "not a readable checkpoint")
        assert "weights_only" not in line


def test_export_refuses_a_file_as_its_output_folder(tmp_path, ckpt):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert_one_line_error(["export", str(ckpt), "--out", str(a_file)], "is a file, expected a directory")


# ----------------------------------------------------------------------------------------------- the parser

def test_usage_errors_are_one_line():
    line = assert_one_line_error(["simulate", "--vehicle"], "ddyn simulate: error:")
    assert "--help" in line
    assert_one_line_error(["no_such_command"], "invalid choice")


def test_a_command_whose_module_cannot_be_imported_fails_alone(monkeypatch, tmp_path):
    """One missing dependency broke every command: the parser imported every command's module. Now main()
    imports only the module of the command it runs, and a command whose module fails to import is one line."""
    monkeypatch.setattr(cli, "COMMANDS", cli.COMMANDS + (cli.Command("needs_x", ("ddyn.no_such_module_x",)),))
    assert_one_line_error(["needs_x", "--anything", "1"], "ddyn needs_x: error:", "ddyn.no_such_module_x")
    # the listing still builds with the stand-in
    assert "needs_x" in cli.build_parser().format_help()


def test_a_missing_optional_dependency_breaks_only_its_commands(tmp_path):
    """With casadi unimportable, simulate (which does not need it) runs, and `codegen c` fails in one line
    naming what is missing (subprocess: casadi may already be imported here)."""
    code = ("import sys; sys.modules['casadi'] = None\n"
            "from ddyn.cli import main\n"
            f"rc = main(['simulate', '--vehicle', 'orca_1_43', '--track', 'ethz', '--duration', '0.2', '-q', "
            f"'-o', {str(tmp_path / 'o.csv')!r}])\n"
            "assert rc == 0, rc\n"
            "assert 'casadi' not in sys.modules or sys.modules['casadi'] is None\n"
            "main(['codegen', 'c'])\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and "casadi" in lines[0] and "Traceback" not in r.stderr, r.stderr


# ----------------------------------------------------------------------------------------------- generated corpus

NUMBER_FIELDS = [("sample_time",), ("max_speed",), ("evaluation_horizon",), ("known", "mass"), ("known", "lf"),
                 ("known", "lr")]
OBJECT_FIELDS = [("known",), ("ranges",), ("input_limits",), ("sensor_noise_std",), ("true_coefficients",)]
PAIR_FIELDS = [("ranges", k) for k in COEFF_NAMES[:4]] + [("input_limits", "throttle"), ("input_limits", "steering")]
WRONG_TYPES = [[1, 2], {"a": 1}, "0.5", None, True]

bad_numbers = st.sampled_from([float("nan"), float("inf"), -float("inf"), -1.0, -0.02, 0.0] + WRONG_TYPES)
bad_vehicle_docs = st.one_of(
    st.tuples(st.sampled_from(NUMBER_FIELDS), bad_numbers),
    st.tuples(st.sampled_from(OBJECT_FIELDS), st.sampled_from([[1, 2], [], "x", 3, True])),
    st.tuples(st.sampled_from(PAIR_FIELDS), st.sampled_from([[1], [1, 2, 3], ["a", 1], [float("nan"), 1], [2, 1],
                                                             "x", None, {"lo": 1}])),
    st.tuples(st.sampled_from([("known", "v_min"), ("sensor_noise_std", "vx")]),
              st.sampled_from([-1.0, float("nan"), "x", None, [1]])),
    st.tuples(st.sampled_from([("rk4_substeps",)]), st.sampled_from([0, -1, 1.5, "2", None, [2]])),
    st.tuples(st.sampled_from([("name",), ("sample_time",), ("known",), ("ranges",), ("input_limits",),
                               ("known", "mass")]), st.just(_DELETE)),
).map(lambda pv: json.dumps(mutated(*pv)))

ORCA_TEXT = json.dumps(ORCA, indent=2)
bad_files = st.one_of(
    bad_vehicle_docs,
    st.integers(0, len(ORCA_TEXT) - 1).map(lambda n: ORCA_TEXT[:n]),            # truncated (or empty)
    st.sampled_from(["", "[]", "[1, 2]", "3", '"orca"', "null", "\x00\xff", "{"]),  # empty, wrong kind
)

# a file argument, or an output that cannot be written
UNWRITABLE = ["dir", "under_a_file"]


def _case_paths(tmp: Path) -> dict:
    tmp.mkdir(parents=True, exist_ok=True)
    (tmp / "a_file").write_text("x")
    return {"dir": str(tmp), "under_a_file": str(tmp / "a_file" / "out")}


def _commands(bad: str, lap: Path, ckpt: Path, tmp: Path) -> list[list[str]]:
    """The commands that take the bad vehicle file `bad`: each must refuse it."""
    ok_out = str(tmp / "out.csv")
    return [
        ["simulate", "--vehicle", bad, "--track", "ethz", "--duration", "0.2", "-q", "-o", ok_out],
        ["train", "--data", str(lap), "--vehicle", bad, "-o", str(tmp / "m.ckpt"), *TRAIN_TINY],
        ["gap", "diagnose", "--vehicle", bad, "--data", str(lap), "--out", str(tmp / "diag"), "--no-plots"],
    ]


@pytest.fixture(scope="module")
def corpus_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("corpus")


@settings(derandomize=True, max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(text=bad_files, which=st.integers(0, 2))
def test_commands_refuse_generated_bad_vehicle_files(text, which, lap, ckpt, corpus_dir):
    bad = corpus_dir / "vehicle.json"
    bad.write_text(text, encoding="utf-8", errors="surrogateescape")
    argv = _commands(str(bad), lap, ckpt, corpus_dir)[which]
    assert_one_line_error(argv, str(bad))


def _checkpoint_cases():
    """(name, change of the checkpoint dict) pairs: every one makes it unusable."""
    cfg_bad = [("tau", v) for v in ("1", 0, -1, 1.5, None, float("nan"), [1])] + \
              [("lr", v) for v in (float("nan"), -1.0, "x")] + [("method", "rk5"), ("dtype", "foo"), ("kind", "xyz"),
                                                              ("bogus", 1)]
    cases = [(f"config.{k}={v!r}", lambda c, k=k, v=v: c["config"].__setitem__(k, v)) for k, v in cfg_bad]
    for key in ("kind", "config", "architecture", "state_dict", "vehicle", "normalisation", "format", "version"):
        cases.append((f"no {key}", lambda c, key=key: c.pop(key)))
        cases.append((f"{key}=[]", lambda c, key=key: c.__setitem__(key, [])))
    for key in ("tau", "hidden", "layers", "gru_layers", "n_features", "outputs"):
        cases.append((f"architecture.{key}='x'", lambda c, key=key: c["architecture"].__setitem__(key, "x")))
    cases.append(("vehicle.json truncated", lambda c: c["vehicle"].__setitem__("json", c["vehicle"]["json"][:40])))
    cases.append(("vehicle.json NaN dt", lambda c: c["vehicle"].__setitem__(
        "json", json.dumps(mutated(("sample_time",), -1.0)))))
    cases.append(("state_dict lacks a tensor", lambda c: c.__setitem__(
        "state_dict", {k: v for i, (k, v) in enumerate(c["state_dict"].items()) if i})))
    cases.append(("state_dict wrong shape", lambda c: c.__setitem__(
        "state_dict", {k: v[..., :1] if v.ndim else v for k, v in c["state_dict"].items()})))
    cases.append(("normalisation short", lambda c: c.__setitem__("normalisation", {"mean": [0.0], "std": [1.0]})))
    return cases


CHECKPOINT_CASES = _checkpoint_cases()


@settings(derandomize=True, max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(case=st.one_of(st.sampled_from(range(len(CHECKPOINT_CASES))).map(lambda i: ("change", i)),
                      st.integers(0, 4000).map(lambda n: ("truncate", n)),
                      st.sampled_from(["", "garbage", "list", "unwritable_dir", "unwritable_file"]).map(
                          lambda k: ("kind", k))))
def test_export_refuses_generated_bad_checkpoints(case, ckpt, corpus_dir):
    how, what = case
    path, out = corpus_dir / "bad.ckpt", corpus_dir / "exp"
    paths = _case_paths(corpus_dir / "outs")
    if how == "change":
        ckpt_variant(ckpt, path, CHECKPOINT_CASES[what][1])
    elif how == "truncate":
        path.write_bytes(ckpt.read_bytes()[:what])
    elif what in ("", "garbage"):
        path.write_bytes(b"\x00\x01garbage" if what else b"")
    elif what == "list":
        torch.save([1, 2, 3], path)
    else:
        path, out = ckpt, Path(paths["under_a_file"] if what == "unwritable_dir" else Path(paths["dir"]) / "a_file")
    assert_one_line_error(["export", str(path), "--out", str(out), "--no-torch-export"])


@settings(derandomize=True, max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(option=st.sampled_from(["--lr", "--val-fraction", "--epochs", "--hidden", "--tau", "--weight-decay",
                               "--dpm-iz-scale", "--batch-size", "--restarts", "--out", "--metrics-json",
                               "--ranges", "--data"]),
       value=st.sampled_from(["nan", "-1", "0", "inf", "-0.5", "x", "", "unwritable_dir", "under_a_file",
                              "truncated", "[1, 2]", '{"Cm1": [1]}']))
def test_train_refuses_generated_bad_options(option, value, lap, corpus_dir):
    """Each case must fail before training: the tiny training itself is never reached here."""
    paths = _case_paths(corpus_dir / "train_outs")
    data, extra = str(lap), []
    if option in ("--out", "--metrics-json"):
        extra = [option, paths.get(value, paths["dir"])]
    elif option in ("--ranges", "--data"):
        f = corpus_dir / ("r.json" if option == "--ranges" else "d.csv")
        text = {"truncated": '{"Cm1": [0.1, ', "nan": '{"Cm1": [NaN, 1]}', "-1": '{"Cm1": [1, -1]}',
                "0": '{"Cm1": [0, 0]}', "x": "time,x\n1,a\n", "unwritable_dir": "", "under_a_file": ""}.get(value, value)
        f.write_text(text)
        if option == "--data":
            data = str(f)
        else:
            extra = [option, str(f)]
    else:
        if value in ("unwritable_dir", "under_a_file", "truncated", "[1, 2]", '{"Cm1": [1]}'):
            value = "x"
        if value == "0" and option == "--weight-decay":
            value = "-1"
        extra = [option, value]
    argv = ["train", "--data", data, "-o", str(corpus_dir / "t.ckpt"), *TRAIN_TINY, *extra]
    from ddyn.learn import train_cmd

    real_train = train_cmd.train
    train_cmd.train = lambda *a, **k: pytest.fail(f"trained: {argv}")
    try:
        assert_one_line_error(argv)
    finally:
        train_cmd.train = real_train


@pytest.mark.parametrize("command", ["simulate", "train", "export", "diagnose"])
@pytest.mark.parametrize("where", UNWRITABLE)
def test_unwritable_output_is_one_line(command, where, tmp_path, lap, ckpt):
    """Found by the generation: `gap diagnose --out` under a file ended in NotADirectoryError (from the report
    writer, after the diagnosis); now one line (cli.main: an OSError naming a file). simulate, train and export
    check their output before any work."""
    out = _case_paths(tmp_path)[where]
    if command == "export" and where == "dir":
        out = str(tmp_path / "a_file")   # export writes a folder: a file there is what cannot be written
    argv = {"simulate": ["simulate", "--vehicle", "orca_1_43", "--track", "ethz", "--duration", "0.2", "-q",
                         "-o", out],
            "train": ["train", "--data", str(lap), "-o", out, *TRAIN_TINY],
            "export": ["export", str(ckpt), "--out", out, "--no-torch-export"],
            "diagnose": ["gap", "diagnose", "--vehicle", "orca_1_43", "--data", str(lap), "--out", out,
                         "--no-plots"]}[command]
    if command == "diagnose" and where == "dir":
        argv[-2] = str(tmp_path / "a_file")   # a folder is what diagnose writes: a file there cannot be used
    assert_one_line_error(argv, "a_file" if where == "under_a_file" or command in ("export", "diagnose")
                          else str(tmp_path))


def _data_text(lap: Path, how: str, n: int) -> str:
    """The log made unusable: cut inside its header, a cell spoilt, its embedded vehicle file broken."""
    import base64

    text = lap.read_text()
    lines = text.splitlines(keepends=True)
    header_end = next(i for i, line in enumerate(lines) if not line.startswith("#")) + 1
    if how == "cut":
        return text[:n % len("".join(lines[:header_end]))]
    if how == "cell":
        row = header_end + n % (len(lines) - header_end)
        cells = lines[row].rstrip("\n").split(",")
        cells[n % len(cells)] = ["nan", "abc", "", "inf", "1e999"][n % 5]
        lines[row] = ",".join(cells) + "\n"
        return "".join(lines)
    # the embedded vehicle file: a list, a NaN sample time, a non-object known, truncated
    bad = ["[1, 2]", json.dumps(mutated(("sample_time",), -0.04)), json.dumps(mutated(("known",), [1])),
           ORCA_TEXT[:50]][n % 4]
    b64 = base64.b64encode(bad.encode()).decode()
    return "".join(f"# vehicle_json_b64: {b64}\n" if line.startswith("# vehicle_json_b64:") else line
                   for line in lines)


@settings(derandomize=True, max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(how=st.sampled_from(["cut", "cell", "vehicle"]), n=st.integers(0, 10_000), command=st.sampled_from(
    ["train", "diagnose"]))
def test_commands_refuse_generated_bad_logs(how, n, command, lap, corpus_dir):
    """train reads the vehicle embedded in the log (no --vehicle); gap diagnose needs --vehicle or --model, so it
    gets the spoilt cells and the cut header only."""
    if command == "diagnose" and how == "vehicle":
        how = "cell"
    bad = corpus_dir / "log.csv"
    bad.write_text(_data_text(lap, how, n))
    argv = (["train", "--data", str(bad), "-o", str(corpus_dir / "t.ckpt"), *TRAIN_TINY] if command == "train" else
            ["gap", "diagnose", "--data", str(bad), "--out", str(corpus_dir / "diag"), "--no-plots",
             "--vehicle", "orca_1_43"])
    from ddyn.learn import train_cmd

    real_train = train_cmd.train
    train_cmd.train = lambda *a, **k: pytest.fail(f"trained: {how} {n}")
    try:
        assert_one_line_error(argv)
    finally:
        train_cmd.train = real_train
