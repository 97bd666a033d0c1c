"""`ddyn tune`: hyper-parameter search for DDM/DPM training with Optuna.

Each trial trains with `training.train` on the given dataset and reports the best
validation loss (lower is better). The search space: learning rate (log 1e-4..1e-2),
batch size (64, 128, 256, 512), dense layers (1..4), width (16..256, log), GRU layers
(0..2) and history length tau (1..10); the epochs, L-BFGS iterations and model kind
come from the command line and are the same for every trial of a study.

Storage: by default a SQLite file `<out>/<study>.db`, for one machine. With
`--storage postgresql://user@host:port/db` any number of workers, on any number of
machines, share one study: each runs `--trials` trials of its own, the TPE sampler of
each worker is seeded from `--seed` and the worker's identity (`--worker-id`, default
hostname:pid) so that workers do not propose identical trials, and every trial records
the worker that ran it in its user attributes. A study remembers the dataset (content
hash), kind, epochs and L-BFGS iterations it was created with; a worker that joins
with different ones is refused, since its losses would not be comparable.

Trials whose training fails or diverges (DdynError) are recorded as failed, with the
message in the trial's `error` user attribute; the study goes on.
"""
from __future__ import annotations

import hashlib
import json
import os
import random
import socket
import sys
import time
import warnings
from pathlib import Path

from ddyn.errors import DdynError

DEFAULT_OUT = "out/tune"
BATCH_SIZES = (64, 128, 256, 512)
# study attributes that must agree between all workers of one study
_STUDY_KEYS = ("data_hash", "kind", "vehicle", "epochs", "lbfgs_iterations")
_LOCK_KEY = 0x6464796E74756E65  # PostgreSQL advisory lock held while a worker sets up the study ("ddyntune")


def _optuna():
    try:
        import optuna
    except ImportError:  # pragma: no cover - the lock file pins it
        raise DdynError("optuna is not installed; run scripts/setup.sh") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    return optuna


def default_worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def sampler_seed(seed: int, worker_id: str) -> int:
    """The TPE seed of one worker: stable for a given (seed, worker id), different between workers."""
    digest = hashlib.sha256(f"{seed}\0{worker_id}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


def default_storage(out: str | Path, study_name: str) -> str:
    folder = Path(out).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{folder / (study_name + '.db')}"


def safe_url(url: str) -> str:
    """The storage URL with any password hidden, for messages."""
    try:
        from sqlalchemy.engine import make_url
        return make_url(url).render_as_string(hide_password=True)
    except Exception:
        return url.split("@")[-1] if "@" in url else url


def normalize_storage_url(url: str) -> str:
    """Pin a bare postgresql:// URL to the psycopg2 driver the lock file installs.

    SQLAlchemy 2.1 maps postgresql:// to psycopg 3, 2.0 to psycopg2; an explicit driver
    (postgresql+psycopg://...) is left alone.
    """
    for bare in ("postgresql://", "postgres://"):
        if url.startswith(bare):
            return "postgresql+psycopg2://" + url[len(bare):]
    return url


def _make_storage(url: str):
    optuna = _optuna()
    if url.startswith("sqlite"):
        # trials of one worker are sequential; the timeout only matters for a shared file
        return optuna.storages.RDBStorage(url, engine_kwargs={"connect_args": {"timeout": 60}})
    # a server: recover from dropped connections, and let a worker that dies mid-trial
    # have that trial marked failed by the others (heartbeat) instead of running forever
    return optuna.storages.RDBStorage(url, engine_kwargs={"pool_pre_ping": True},
                                      heartbeat_interval=60, grace_period=180)


def _open_study(url: str, study_name: str, sampler=None, create: bool = True, attempts: int = 8):
    """Create or load a study; safe when many workers start at once on an empty database.

    Creating Optuna's tables, its schema-version rows and the study itself are
    check-then-insert steps; workers starting together can collide in them. On
    PostgreSQL the set-up runs under an advisory lock; on any backend a collision is
    retried after a short random wait.
    """
    optuna = _optuna()
    import sqlalchemy
    from sqlalchemy import exc as sa_exc

    url = normalize_storage_url(url)
    last: Exception | None = None
    for attempt in range(attempts):
        lock_engine = lock = None
        try:
            if url.startswith("postgresql"):
                # a session-level lock, released when its (unpooled) connection closes below
                lock_engine = sqlalchemy.create_engine(url, poolclass=sqlalchemy.pool.NullPool)
                lock = lock_engine.connect()
                lock.execute(sqlalchemy.text("SELECT pg_advisory_lock(:k)"), {"k": _LOCK_KEY})
            storage = _make_storage(url)
            if create:
                return optuna.create_study(storage=storage, study_name=study_name, sampler=sampler,
                                           direction="minimize", load_if_exists=True)
            return optuna.load_study(storage=storage, study_name=study_name, sampler=sampler)
        except KeyError:
            raise DdynError(f"no study {study_name!r} in {safe_url(url)}") from None
        except ImportError as e:
            raise DdynError(f"storage {safe_url(url)}: database driver missing ({e}); run scripts/setup.sh") from None
        except sa_exc.ArgumentError as e:
            raise DdynError(f"bad storage URL {safe_url(url)}: {e}") from None
        except sa_exc.OperationalError as e:
            last = e
            if attempt >= 2:  # a server that is down or refuses us: give up soon
                break
        except sa_exc.SQLAlchemyError as e:
            last = e
        finally:
            if lock is not None:
                lock.close()
            if lock_engine is not None:
                lock_engine.dispose()
        time.sleep(random.uniform(0.2, 1.0) * (attempt + 1))
    reason = str(getattr(last, "orig", None) or last).strip().splitlines()[0] if last else "unknown error"
    raise DdynError(f"cannot open study {study_name!r} in {safe_url(url)}: {reason}")


def _check_study_attrs(study, expected: dict) -> None:
    have = study.user_attrs
    clash = {k: (have[k], v) for k, v in expected.items() if k in have and have[k] != v}
    if clash:
        detail = ", ".join(f"{k} is {a!r} in the study, {b!r} here" for k, (a, b) in clash.items())
        raise DdynError(f"study {study.study_name!r} was made with other settings: {detail}; "
                        f"use another --study-name")
    for k, v in expected.items():
        if k not in have:
            study.set_user_attr(k, v)


def suggest_config(trial, kind: str, epochs: int, lbfgs_iterations: int, seed: int):
    """The TrainConfig a trial proposes."""
    from ddyn.learn.training import TrainConfig

    return TrainConfig(
        kind=kind,
        lr=trial.suggest_float("lr", 1e-4, 1e-2, log=True),
        batch_size=trial.suggest_categorical("batch_size", list(BATCH_SIZES)),
        layers=trial.suggest_int("layers", 1, 4),
        hidden=trial.suggest_int("hidden", 16, 256, log=True),
        gru_layers=trial.suggest_int("gru_layers", 0, 2),
        tau=trial.suggest_int("tau", 1, 10),
        epochs=epochs,
        lbfgs_iterations=lbfgs_iterations,
        seed=seed,
    )


def run_study(data_path: str | Path, storage: str | None, study_name: str | None, n_trials: int, *,
              kind: str = "ddm", vehicle: str | None = None, epochs: int | None = None,
              lbfgs_iterations: int | None = None, seed: int = 0, timeout: float | None = None,
              worker_id: str | None = None, out: str | Path = DEFAULT_OUT, progress: bool = True):
    """Run n_trials trials of this worker in the study (created when new); returns the Study.

    storage None: SQLite file <out>/<study_name>.db. study_name None: "<kind>-<data file stem>".
    epochs, lbfgs_iterations None: TrainConfig's defaults (what `ddyn train` does). Writes
    <out>/best_params.json for the study's best trial so far (all workers') when any trial
    has completed.
    """
    optuna = _optuna()
    from ddyn.data.importers import load_with_vehicle
    from ddyn.learn.training import TrainConfig, train

    if n_trials < 1:
        raise DdynError(f"--trials must be at least 1, got {n_trials}")
    if timeout is not None and not timeout > 0:
        raise DdynError(f"--timeout must be positive, got {timeout}")
    defaults = TrainConfig()
    epochs = defaults.epochs if epochs is None else epochs
    lbfgs_iterations = defaults.lbfgs_iterations if lbfgs_iterations is None else lbfgs_iterations
    if lbfgs_iterations < 0:
        raise DdynError(f"--lbfgs-iterations must not be negative, got {lbfgs_iterations}")
    TrainConfig(kind=kind, epochs=epochs, lbfgs_iterations=lbfgs_iterations)  # validates kind and epochs
    ds, veh = load_with_vehicle(data_path, vehicle)

    study_name = study_name or f"{kind}-{Path(data_path).stem}"
    url = storage or default_storage(out, study_name)
    worker = worker_id or default_worker_id()
    sampler = optuna.samplers.TPESampler(seed=sampler_seed(seed, worker))
    study = _open_study(url, study_name, sampler=sampler)
    _check_study_attrs(study, {"data_hash": ds.content_hash(), "kind": kind, "vehicle": veh.name,
                               "epochs": int(epochs), "lbfgs_iterations": int(lbfgs_iterations)})

    def objective(trial) -> float:
        trial.set_user_attr("worker", worker)
        trial.set_user_attr("host", socket.gethostname())
        trial.set_user_attr("pid", os.getpid())
        trial.set_user_attr("train_seed", seed)
        cfg = suggest_config(trial, kind, epochs, lbfgs_iterations, seed)
        try:
            result = train(ds, veh, cfg, progress=False)
        except DdynError as e:
            trial.set_user_attr("error", str(e))
            raise
        trial.set_user_attr("seconds", round(result.seconds, 3))
        return float(result.best_val_loss)  # NaN or inf: Optuna records the trial as failed

    study.optimize(objective, n_trials=n_trials, timeout=timeout, catch=(DdynError,), show_progress_bar=progress)
    write_best(study, out, url)
    return study


def _complete(study) -> list:
    optuna = _optuna()
    return study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))


def best_trial(storage: str, study_name: str):
    """The best completed trial of a stored study (a fresh connection), as an optuna FrozenTrial."""
    study = _open_study(storage, study_name, create=False)
    if not _complete(study):
        raise DdynError(f"study {study_name!r} has no completed trial yet")
    return study.best_trial


def best_summary(study, storage_url: str | None = None) -> dict | None:
    """What best_params.json holds; None when no trial has completed."""
    from ddyn.learn.training import TrainConfig, config_dict

    done = _complete(study)
    if not done:
        return None
    best = study.best_trial
    a = study.user_attrs
    cfg = TrainConfig(kind=a.get("kind", "ddm"), epochs=a.get("epochs", TrainConfig().epochs),
                      lbfgs_iterations=a.get("lbfgs_iterations", 0), seed=best.user_attrs.get("train_seed", 0),
                      **best.params)
    states = [t.state.name for t in study.get_trials(deepcopy=False)]
    return {
        "study_name": study.study_name,
        "storage": safe_url(storage_url) if storage_url else None,
        "value": best.value,
        "params": best.params,
        "trial": best.number,
        "worker": best.user_attrs.get("worker"),
        "train_config": config_dict(cfg),
        "trials": {s: states.count(s) for s in sorted(set(states))},
        "study": {k: a[k] for k in _STUDY_KEYS if k in a},
    }


def write_best(study, out: str | Path, storage_url: str | None = None) -> Path | None:
    summary = best_summary(study, storage_url)
    if summary is None:
        return None
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "best_params.json"
    tmp = path.with_suffix(f".json.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    tmp.replace(path)
    return path


def _train_flags(params: dict) -> str:
    return " ".join(f"--{k.replace('_', '-')} {v:.4g}" if isinstance(v, float) else f"--{k.replace('_', '-')} {v}"
                    for k, v in params.items())


def _run(args) -> int:
    study = run_study(args.data, args.storage, args.study_name, args.trials, kind=args.kind,
                      vehicle=args.vehicle, epochs=args.epochs, lbfgs_iterations=args.lbfgs_iterations,
                      seed=args.seed, timeout=args.timeout, worker_id=args.worker_id, out=args.out,
                      progress=not args.quiet)
    summary = best_summary(study)
    if summary is None:
        states = sorted({t.state.name.lower() for t in study.trials})
        raise DdynError(f"no trial of study {study.study_name!r} completed "
                        f"({', '.join(states) or 'no trials'}); see the messages above")
    counts = ", ".join(f"{n} {s.lower()}" for s, n in summary["trials"].items())
    print(f"study {study.study_name}: {counts}")
    print(f"best trial #{summary['trial']} (worker {summary['worker']}): validation loss {summary['value']:.4e}")
    print("params: " + json.dumps(summary["params"]))
    budget = summary["study"]
    vehicle = f" --vehicle {args.vehicle}" if args.vehicle else ""
    print(f"train with: ddyn train --data {args.data}{vehicle} --kind {budget['kind']} "
          f"{_train_flags(summary['params'])} --epochs {budget['epochs']} "
          f"--lbfgs-iterations {budget['lbfgs_iterations']} -o MODEL")
    print(f"wrote {Path(args.out) / 'best_params.json'}")
    return 0


def register(subparsers) -> None:
    from ddyn.learn.training import TrainConfig

    defaults = TrainConfig()
    p = subparsers.add_parser("tune", help="search training hyper-parameters with Optuna (one machine or many)")
    p.add_argument("--data", required=True, help="training dataset (any supported format)")
    p.add_argument("--vehicle", help="vehicle name or JSON file (default: the one the dataset records)")
    p.add_argument("--kind", choices=("ddm", "dpm"), default="ddm", help="model to tune (default ddm)")
    p.add_argument("--trials", type=int, default=20, help="trials this worker runs (default 20)")
    p.add_argument("--epochs", type=int, default=None,
                   help=f"Adam epochs per trial (default: ddyn train's, {defaults.epochs})")
    p.add_argument("--lbfgs-iterations", type=int, default=None,
                   help=f"L-BFGS polish iterations per trial (default: ddyn train's, {defaults.lbfgs_iterations}); "
                   "0 tunes the Adam phase alone, much faster")
    p.add_argument("--storage", help="Optuna storage URL, e.g. postgresql://user@host:5432/db to share a study "
                   "between workers (default: SQLite file <out>/<study>.db)")
    p.add_argument("--study-name", help="study name (default <kind>-<data file stem>)")
    p.add_argument("--seed", type=int, default=0,
                   help="training seed of every trial; with the worker id, seeds this worker's sampler (default 0)")
    p.add_argument("--worker-id", help="this worker's name in the study (default hostname:pid); "
                   "a fixed id makes the worker's sampler reproducible")
    p.add_argument("--timeout", type=float, help="stop starting trials after this many seconds")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"folder for best_params.json (default {DEFAULT_OUT})")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


if __name__ == "__main__":  # pragma: no cover
    from ddyn.cli import main
    sys.exit(main(["tune"] + sys.argv[1:]))
