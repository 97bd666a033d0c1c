"""ddyn's public Python API: the few calls a user scripts against (also importable as `ddyn.<name>`).

    import ddyn

    log = ddyn.load_log("run.csv", vehicle="orca_1_43")      # any accepted log format -> Dataset
    car = ddyn.load_vehicle("orca_1_43")                      # a vehicle file -> Vehicle
    ckpt = ddyn.load_checkpoint("model.ckpt")                 # a trained network and its vehicle
    d = ddyn.diagnose(log, car)                               # the sim-to-real gap diagnosis -> dict
    files = ddyn.generate_c("out/gen", vehicle=car)           # the model's C code in a folder you choose
    lap = ddyn.run_mpc_lap(track="ethzMobil")                 # a closed-loop lap of the C MPC on the host

and, for the examples' other steps, `simulate`, `save_log`, `train` and `evaluate`. Everything else in the
package is internal: it may change between versions. Every call raises `ddyn.DdynError` (one line naming the
file, key or argument) on bad input; the examples in examples/ show each call in a runnable script.

Heavy dependencies (torch, CasADi) are imported by the calls that need them, not by `import ddyn`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ddyn.errors import DdynError

if TYPE_CHECKING:   # names for the annotations only: importing them here would make `import ddyn.api` heavy
    import torch

    from ddyn.data.dataset import Dataset
    from ddyn.model.vehicle import Vehicle

__all__ = ["Checkpoint", "DdynError", "diagnose", "evaluate", "generate_c", "load_checkpoint", "load_log",
           "load_vehicle", "run_mpc_lap", "save_log", "simulate", "train"]


# ----------------------------------------------------------------------------------------------- logs, vehicles

def load_log(path: str | Path, vehicle: "str | Path | Vehicle | None" = None) -> "Dataset":
    """Read a log in any accepted format (canonical CSV, Deep Dynamics .npz, RACECAR CSV, LCM log; the format
    is detected from the file's first bytes) as a canonical `ddyn.data.dataset.Dataset`.

    path: the log file. vehicle: the car the log belongs to (a name in train/vehicles, a vehicle JSON file or
    a Vehicle); default: the one the file names, else the reader's default (orca_1_43 for .npz, av21 for
    RACECAR CSV). Returns the Dataset: `.time`, `.states` (N, 8: x, y, yaw, vx, vy, omega, throttle,
    steering), `.inputs` (N, 2: dthrottle, dsteering), `.column(name)`, `.extras` (e.g. the RACECAR log's
    `roll`), `.sample_time`, `.vehicle`, `.metadata`. Raises DdynError naming the file (and row and column
    where known) when it is missing, of no accepted format, or malformed.
    """
    from ddyn.data.importers import load_any

    return load_any(_path(path, "log"), vehicle=_vehicle_arg(vehicle))


def save_log(log: "Dataset", path: str | Path) -> Path:
    """Write a Dataset as a canonical CSV (every float64 round-trips exactly); returns the path written.
    Raises DdynError naming the path when it cannot be written."""
    from ddyn.data.dataset import Dataset, write_canonical

    if not isinstance(log, Dataset):
        raise DdynError(f"save_log: log must be a Dataset (from load_log or simulate), not {type(log).__name__}")
    try:
        return write_canonical(log, path)
    except OSError as e:
        raise DdynError(f"{path}: cannot write: {e.strerror or e}") from None


def load_vehicle(name_or_file: "str | Path | Vehicle") -> "Vehicle":
    """A vehicle: a name in train/vehicles (orca_1_43, av21, av21_powertrain) or a vehicle JSON file (today's
    schema, docs/model.md). Returns a `ddyn.model.vehicle.Vehicle` (frozen: `.name`, `.sample_time`,
    `.known` (mass, lf, lr, ...), `.ranges`, `.true_vector()`, `.input_limits`); a Vehicle given is returned
    as it is. Raises DdynError naming the file and the missing or malformed key, or listing the known names."""
    from ddyn.model import vehicle as vehicle_mod

    if isinstance(name_or_file, vehicle_mod.Vehicle):
        return name_or_file
    if not isinstance(name_or_file, (str, Path)) or not str(name_or_file):
        raise DdynError(f"load_vehicle: expected a vehicle name or a JSON file, not {name_or_file!r}")
    return vehicle_mod.load(name_or_file)


def simulate(vehicle: "str | Path | Vehicle", track: str = "ethzMobil", laps: float | None = None,
             duration: float | None = None, seed: int = 0, noise: float = 0.0, effects: str | None = None,
             method: str = "euler") -> "Dataset":
    """Drive a vehicle around a track in closed loop (pure pursuit and a speed profile, with random
    excitation) and record the log, as `ddyn simulate` does.

    vehicle: a name, JSON file or Vehicle. track: ethz, ethzMobil, putnam, random:SEED or a user's track files
    (docs/tracks.md). laps or duration (s): when to stop (default one lap). seed: the excitation's and the
    noise's seed. noise: measurement noise as a multiple of the vehicle's sensor_noise_std. effects:
    unmodelled effects of the plant, e.g. "throttle_delay=0.04" (ddyn.model.effects; recorded in
    `metadata["effects"]`). method: euler or rk4. Returns the Dataset. Raises DdynError on an unknown
    vehicle, track or effect, or when the car leaves the track.
    """
    from ddyn.data.simulate import simulate as _simulate

    return _simulate(load_vehicle(vehicle), track, duration=duration, laps=laps, method=method, seed=seed,
                     noise_scale=noise, effects=effects, progress=False)


# ----------------------------------------------------------------------------------------------- checkpoints

@dataclass(frozen=True)
class Checkpoint:
    """A trained network loaded from its checkpoint file (docs/checkpoint_format.md).

    model: the torch module in eval mode; `model.coefficients(history)` gives the 17 coefficients (DDM) from a
    (batch, tau, features) history; vehicle: the vehicle file embedded in the checkpoint; kind: "ddm" or
    "dpm"; tau: rows of history the network reads; path: the file; data: the checkpoint's whole dictionary
    (config, ranges, training record, metrics)."""
    model: "torch.nn.Module"
    vehicle: "Vehicle"
    kind: str
    tau: int
    path: Path
    data: dict

    @property
    def metrics(self) -> dict:
        """The evaluation results the checkpoint records (`ddyn train` adds "validation")."""
        return self.data.get("metrics", {})


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Load a checkpoint written by `ddyn train` (or `train` here): the network rebuilt from its recorded
    architecture with its weights, in eval mode, and the vehicle file it was trained for. Returns a
    Checkpoint. Raises DdynError naming the file when it is missing, not a ddyn checkpoint, of another
    version, or its weights do not fit the architecture."""
    from ddyn.learn import checkpoint

    p = _path(path, "checkpoint")
    if p.is_file() and p.read_bytes()[:2] != b"PK":   # torch.save writes a zip archive
        raise DdynError(f"{p}: not a ddyn checkpoint (not a torch.save archive)")
    try:
        model, ckpt = checkpoint.load(p)
    except DdynError as e:
        raise DdynError(str(e).splitlines()[0]) from None
    return Checkpoint(model, checkpoint.vehicle_of(ckpt), str(ckpt["kind"]), int(ckpt["config"]["tau"]), p, ckpt)


def train(log: str | Path, out: str | Path, vehicle: "str | Path | Vehicle | None" = None,
          **config: Any) -> Checkpoint:
    """Train a Deep Dynamics model (or, kind="dpm", the Deep Pacejka baseline) on a log file and write its
    checkpoint, as `ddyn train` does: the last `val_fraction` of the rows validate (by time), and the
    validation metrics are recorded in the checkpoint (`Checkpoint.metrics["validation"]`).

    log: a log file (any accepted format). out: the checkpoint file to write. vehicle: a name or JSON file
    (default: the log's). config: fields of ddyn.learn.training.TrainConfig, e.g. epochs=20, hidden=16,
    lbfgs_iterations=0, seed=0 (defaults: the project's). Returns the written checkpoint, loaded. Raises
    DdynError naming an unknown config key, a bad log or vehicle."""
    from dataclasses import fields

    from ddyn.learn.train_cmd import train_to_checkpoint
    from ddyn.learn.training import TrainConfig

    known = {f.name for f in fields(TrainConfig)}
    unknown = sorted(set(config) - known)
    if unknown:
        raise DdynError(f"train: unknown config key(s) {', '.join(unknown)}; expected {', '.join(sorted(known))}")
    if isinstance(vehicle, Path) or isinstance(vehicle, str) or vehicle is None:
        vehicle_arg = None if vehicle is None else str(vehicle)
    else:
        vehicle_arg = vehicle.source_path or vehicle.name
    train_to_checkpoint(str(_path(log, "log")), TrainConfig(**config), str(out), vehicle_arg, progress=False)
    return load_checkpoint(out)


def evaluate(checkpoint: "Checkpoint | str | Path", log: "str | Path | Dataset") -> dict:
    """A trained network on a log, as `ddyn evaluate` does: one-step RMSE and largest error of the next vx, vy,
    omega ("rmse", "max_error": {"vx", "vy", "omega"}), the multi-step "ade"/"fde" (m) over the vehicle's
    evaluation horizon, and per coefficient its mean, spread, error against the truth where the log or the
    vehicle knows it, and the share of samples at a guard bound ("coefficients"). checkpoint: a Checkpoint
    or its file; log: a Dataset or a log file (read for the checkpoint's vehicle). Returns that dict.
    Raises DdynError when the log belongs to another vehicle or sample time."""
    from ddyn.data.dataset import Dataset
    from ddyn.learn.evaluate import evaluate as _evaluate
    from ddyn.learn.evaluate import public

    ck = checkpoint if isinstance(checkpoint, Checkpoint) else load_checkpoint(checkpoint)
    ds = log if isinstance(log, Dataset) else load_log(log, vehicle=ck.vehicle)
    return public(_evaluate(ck.model, ck.data, ds))


# ----------------------------------------------------------------------------------------------- diagnosis

def diagnose(log: "str | Path | Dataset", nominal: Any, config: Any = None, out_dir: str | Path | None = None,
             track: Any = None, calibration: str | Path | None = None) -> dict:
    """The sim-to-real gap diagnosis of a log against a nominal model, as `ddyn gap diagnose` runs it (ddyn.gap):
    where the model's error lies, which unmodelled effect (delays, lags, bank, grade, mass offset, ...)
    explains it, its size and how much of the gap it closes.

    log: a Dataset or a log file. nominal: what the log is compared with: a vehicle (name, JSON file or
    Vehicle: its true coefficients), a Checkpoint or a checkpoint file (the network's coefficients, row by
    row), or a nominal already made with ddyn.gap.nominal_from_vehicle / nominal_from_checkpoint. config:
    None (the defaults of ddyn.gap.DiagnosisConfig), a DiagnosisConfig, or a TOML/JSON settings file (or the
    name of a shipped one, e.g. "dbw"). calibration: None (a shipped calibration that covers the log's length
    and sample time, if any: its margin and thresholds), a calibration's name or file, or "none"
    (uncalibrated); which one was used and why is recorded under "calibration". out_dir: also write the report
    there (diagnosis.json, diagnosis.md, figures). track: the track the log was driven on (a name or Track;
    default: the one the log names, if known). Returns the diagnosis.json dictionary: "selected" (the effects
    found, in order), "verdict", "model" ("effects" with their fitted parameters and uncertainty, held-out
    errors before and after, "gap_closed_pct"), "where", "calibration", ... Raises DdynError on a bad log,
    nominal, config or calibration (naming the file and key).
    """
    from ddyn import gap

    ck = None
    if isinstance(nominal, Checkpoint):
        ck = nominal
    elif isinstance(nominal, (str, Path)) and Path(nominal).is_file() and Path(nominal).suffix != ".json":
        ck = load_checkpoint(nominal)
    if ck is not None:
        vehicle = ck.vehicle            # the checkpoint's embedded vehicle file
    elif _is_nominal(nominal):
        vehicle = nominal.vehicle
    else:
        vehicle = load_vehicle(nominal)
    ds = load_log(log, vehicle=vehicle) if isinstance(log, (str, Path)) else log
    if ck is not None:
        nom = gap.nominal_from_checkpoint(ck.path, ds)
    elif _is_nominal(nominal):
        nom = nominal
    else:
        nom = gap.nominal_from_vehicle(vehicle, ds)
    if config is None:
        cfg = None      # the defaults, or a covering calibration's settings
    elif isinstance(config, (str, Path)):
        cfg = gap.DiagnosisConfig.from_file(_path(config, "config"))
    elif isinstance(config, gap.DiagnosisConfig):
        cfg = config
    else:
        raise DdynError(f"diagnose: config must be a DiagnosisConfig or a TOML/JSON file, not {type(config).__name__}")
    if track is None or isinstance(track, str):     # a name, a user's files, or the one the log names
        track = gap.track_for(track, ds)
    d = gap.diagnose_log(ds, nom, cfg, calibration=None if calibration is None else str(calibration), track=track)
    if out_dir is not None:
        gap.write_report(d, out_dir)
    return d


def _is_nominal(obj: Any) -> bool:
    """A nominal made by ddyn.gap (it carries its vehicle and per-row coefficients)."""
    return hasattr(obj, "vehicle") and hasattr(obj, "coeffs") and hasattr(obj, "valid")


# ----------------------------------------------------------------------------------------------- C code, MPC

def generate_c(out_dir: str | Path, vehicle: "str | Path | Vehicle" = "orca_1_43",
               reference_vectors: bool = False) -> list[Path]:
    """The vehicle model's C code, generated with CasADi from the one Python model, in a folder of your choice
    (as `ddyn codegen model --vehicle V --out DIR --no-vectors`): ddyn_<vehicle>_model.c/.h (continuous
    derivative, Euler and RK4 steps with their Jacobians, sensor models: CasADi functions f(arg, res, iw, w,
    mem) with caller-owned memory), the model table ddyn_models.c/.h and ddyn_model_dims.h (compile against
    c_src/include), and the MPC's prediction step ddyn_mpc_model.c/.h and input limits ddyn_mpc_limits.h.

    out_dir: the folder (made if missing); the committed c_src/generated is refused (it holds every vehicle:
    regenerate it with `ddyn codegen model`). vehicle: a name in train/vehicles (a Vehicle or JSON file must
    be one of those; the code names the vehicle). reference_vectors: also write ddyn_model_vectors.h and
    ddyn_test_vehicles.h (the Python model's answers for the C tests) into out_dir. Returns the files
    written. Raises DdynError on an unknown vehicle or an unusable folder."""
    from ddyn.codegen.generate import DEFAULT_OUT, generate

    out = Path(out_dir)
    if out.resolve() == DEFAULT_OUT.resolve():
        raise DdynError(f"generate_c: {out} is the committed generated code (every vehicle); regenerate it with "
                        "`ddyn codegen model`, or choose another folder")
    name = load_vehicle(vehicle).name
    from ddyn.model.vehicle import available

    if name not in available():
        raise DdynError(f"generate_c: vehicle {name!r} is not a file in train/vehicles "
                        f"(known: {', '.join(available())})")
    if out.exists() and not out.is_dir():
        raise DdynError(f"generate_c: {out} exists and is not a folder")
    return generate([name], out, out if reference_vectors else None)


def run_mpc_lap(vehicle: str = "orca_1_43", track: str = "ethzMobil", seconds: float = 7.0,
                reference: bool = False, out_dir: str | Path | None = None, tool: str | Path | None = None) -> dict:
    """A closed-loop lap of the C MPC on the host (as `ddyn mpc lap`): the host tool ddyn_mpc_lap drives the
    simulated car (the generated RK4 step, true coefficients) from near standstill along the vehicle's racing
    line with the MPC's real-time iteration (QP on DAQP).

    vehicle: a name in train/vehicles with an MPC set-up (orca_1_43, av21). track: ethz, ethzMobil, putnam,
    random:SEED or a user's files. seconds: simulated time. reference: also drive the lap with the CasADi +
    IPOPT MPC (slow: minutes) and compare. out_dir: also write mpc_lap.json and mpc_lap.png there. tool: the
    ddyn_mpc_lap binary (default: $DDYN_BUILD_DIR/c_src/ddyn_mpc_lap, DDYN_BUILD_DIR defaulting to build/;
    made by `bash scripts/build.sh`). Returns {"vehicle", "track", "settings", "c_mpc": {"lap_times_s",
    "lap_time_s" (the first, None if no lap was completed), "violation_steps" (steps with a footprint corner
    off the track), "min_boundary_distance_m", "qp_iterations_median"/"_max", "status_counts", "solve_us"},
    and with reference "ipopt_mpc"}. Raises DdynError when the tool is missing or fails."""
    from ddyn.control import mpc_lap
    from ddyn.paths import BUILD

    if not isinstance(seconds, (int, float)) or not seconds > 0:
        raise DdynError(f"run_mpc_lap: seconds must be positive, got {seconds!r}")
    name = load_vehicle(vehicle).name
    exe = Path(tool) if tool is not None else BUILD / "c_src" / "ddyn_mpc_lap"
    if not exe.is_file():
        raise DdynError(f"{exe}: the C MPC lap tool is not built; run `bash scripts/build.sh` "
                        "(or set DDYN_BUILD_DIR to a build folder that has it)")
    return mpc_lap.lap(name, track, float(seconds), reference=reference,
                       out=Path(out_dir) if out_dir is not None else None, tool=exe)


# ----------------------------------------------------------------------------------------------- helpers

def _path(p: Any, what: str) -> Path:
    if not isinstance(p, (str, Path)) or not str(p):
        raise DdynError(f"expected a {what} file path, not {p!r}")
    return Path(p)


def _vehicle_arg(vehicle: Any) -> Any:
    """None, or a Vehicle (a name or file is loaded first, so that an unknown one is named)."""
    return None if vehicle is None else load_vehicle(vehicle)
