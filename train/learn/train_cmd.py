"""`ddyn train`: train a DDM or DPM on a dataset and write a checkpoint."""
from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import fields

from ddyn.data.windows import split_train_validation
from ddyn.errors import DdynError
from ddyn.learn import checkpoint, training_profile
from ddyn.learn.evaluate import evaluate, format_summary, public
from ddyn.learn.guard_ranges import describe, read_ranges, with_ranges
from ddyn.learn.training import DTYPES, TrainConfig, train
from ddyn.model.integrators import DISCRETISATIONS
from ddyn.model.vehicle import Vehicle
from ddyn.paths import check_writable

# the TrainConfig fields that take one of a few names: refused by the parser, before any work
CHOICES = {"kind": ("ddm", "dpm"), "method": DISCRETISATIONS, "dtype": DTYPES}


def _ranges_need_ddm(cfg: TrainConfig) -> None:
    if cfg.kind != "ddm":
        raise DdynError("--ranges sets the Physics Guard's ranges: DDM only (the DPM has no guard)")


def train_to_checkpoint(data_path: str, cfg: "TrainConfig | Callable[[Vehicle], TrainConfig]", out: str,
                        vehicle_name: str | None = None, progress: bool = True,
                        ranges_file: str | None = None) -> dict:
    """vehicle_name: a name in train/vehicles or a JSON path (default: the dataset's, see vehicle_ref).
    ranges_file: guard ranges in place of the vehicle file's (ddyn.learn.guard_ranges).
    cfg: the config, or a function giving it from the vehicle once that is known (`ddyn train`: the vehicle's
    training profile under the flags), called before any training."""
    from ddyn.data.importers import load_with_vehicle

    # every input checked before any work: the output writable, the ranges file readable
    check_writable(out, "checkpoint")
    if ranges_file:
        if isinstance(cfg, TrainConfig):
            _ranges_need_ddm(cfg)
        read_ranges(ranges_file)
    ds, v = load_with_vehicle(data_path, vehicle_name)
    if not isinstance(cfg, TrainConfig):
        cfg = cfg(v)
        if ranges_file:
            _ranges_need_ddm(cfg)
    ranges_record = None
    if ranges_file:
        v, ranges_record = with_ranges(v, ranges_file)
    result = train(ds, v, cfg, progress=progress)
    ckpt = checkpoint.make(result, v, ds.content_hash(), str(data_path), len(ds))
    if ckpt["ranges"] is not None:
        ckpt["ranges"]["source"] = ranges_record
    # validation metrics on the held-out block, recorded in the checkpoint
    _, va = split_train_validation(ds, cfg.tau, cfg.val_fraction)
    val_ds = ds.subset(slice(int(va.end_row.min()) - cfg.tau + 1, int(va.end_row.max()) + 2))
    ckpt["metrics"]["validation"] = public(evaluate(result.model, ckpt, val_ds))
    checkpoint.save(ckpt, out)
    return ckpt


def flags_given(args) -> dict:
    """{TrainConfig field: value} of the setting flags given on the command line (None: not given)."""
    return {f.name: getattr(args, f.name) for f in fields(TrainConfig) if getattr(args, f.name, None) is not None}


def settings_for(args, vehicle: Vehicle) -> training_profile.ResolvedSettings:
    """The settings `ddyn train` trains `vehicle` with: the flags, over its training profile, over the defaults."""
    return training_profile.resolve(vehicle.name, flags_given(args),
                                    use_profile=not getattr(args, "no_profile", False))


def _run(args) -> int:
    TrainConfig(**flags_given(args))   # the flags' own values checked before any work
    check_writable(args.out, "-o/--out")
    if args.metrics_json:
        check_writable(args.metrics_json, "--metrics-json")
    resolved = []

    def configure(vehicle: Vehicle) -> TrainConfig:
        r = settings_for(args, vehicle)
        print(training_profile.describe(r, no_profile=getattr(args, "no_profile", False)), flush=True)
        resolved.append(r)
        return r.config

    ckpt = train_to_checkpoint(args.data, configure, args.out, args.vehicle, progress=not args.quiet,
                               ranges_file=args.ranges)
    cfg = resolved[0].config
    t = ckpt["training"]
    print(f"trained {cfg.kind} in {t['seconds']:.1f} s, best validation loss {t['best_val_loss']:.4e}")
    if t.get("restarts"):
        print(f"restarts: kept seed {t['seed']} of " + ", ".join(
            f"{r['seed']} ({r['best_val_loss']:.4e})" for r in t["restarts"]))
    if ckpt["ranges"] is not None:
        print(describe(ckpt["ranges"].get("source")))
    print("validation: " + format_summary(ckpt["metrics"]["validation"]))
    print(f"wrote {args.out}")
    if args.metrics_json:
        with open(args.metrics_json, "w") as f:
            json.dump(ckpt["metrics"], f, indent=2)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("train", help="train a Deep Dynamics (ddm) or Deep Pacejka (dpm) model",
                              description="Each training setting comes from its flag if given, else from the "
                              "vehicle's training profile (train/vehicles/training/VEHICLE.json, docs/learning.md), "
                              "else the built-in default; the first line printed says which.")
    p.add_argument("--data", required=True, help="training dataset (any supported format)")
    p.add_argument("-o", "--out", required=True, help="checkpoint file to write")
    p.add_argument("--vehicle", help="vehicle name or JSON file (default: the one the dataset records)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--ranges", help="guard ranges file in place of the vehicle file's: `ddyn denoise --model` "
                                    "writes one (OUT.ranges.json), or {\"Cm1\": [lo, hi], ...}")
    p.add_argument("--metrics-json", help="also write the checkpoint's metrics to this JSON file")
    p.add_argument("--no-profile", action="store_true",
                   help="ignore the vehicle's training profile (train/vehicles/training/VEHICLE.json): the "
                        "built-in defaults under the flags given")
    defaults = TrainConfig()
    for f in fields(TrainConfig):
        flag = "--" + f.name.replace("_", "-")
        p.add_argument(flag, dest=f.name, type=type(getattr(defaults, f.name)), default=None,
                       choices=CHOICES.get(f.name),
                       help=f"(default: the vehicle's profile, else {getattr(defaults, f.name)})")
    p.set_defaults(func=_run)
