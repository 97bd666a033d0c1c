"""Checkpoints: everything needed to rebuild, evaluate and export a trained network.

A checkpoint is a `torch.save` file of plain containers (loadable with
`torch.load(weights_only=True)`), documented in docs/checkpoint_format.md:

  format, version        "ddyn-checkpoint", 1
  kind                   "ddm" | "dpm"
  config                 the TrainConfig fields (tau, hidden, layers, gru_layers, ...)
  architecture           features (input order), outputs (coefficient order), activation,
                         n_features, tau, hidden, layers, gru_layers, method, substeps
  state_dict             the network's tensors (encoder.mean/std hold the input normalisation, encoder.feature_lo/hi
                         the feature range its inputs are held in; absent in older checkpoints: not held)
  normalisation          {"mean": [7], "std": [7]}   (same values as in state_dict, for readers without torch)
  ranges                 {"names", "lo", "hi"}  the Physics Guard's ranges (ddm), or None
  dpm_iz                 the yaw inertia given to a DPM, or None
  loss_scale             per-channel divisors of the loss (vx, vy, omega)
  vehicle                {"name", "sha256", "json"}: the whole vehicle file
  data                   {"train_sha256", "source", "rows", "split"}
  training               {"seconds", "best_val_loss", "epochs_run", "val_loss_curve", "seed", "restarts",
                          "validation_saturation"}
  metrics                evaluation results added by `ddyn train` (validation) or later tools
  software               versions of ddyn and torch
"""
from __future__ import annotations

import hashlib
import io
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from ddyn.data.windows import FEATURE_NAMES
from ddyn.errors import DdynError
from ddyn.learn.networks import DPM_OUTPUTS
from ddyn.learn.training import TrainResult, build_model, config_dict, config_from_dict
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import COEFF_NAMES

FORMAT, VERSION = "ddyn-checkpoint", 1


def make(result: TrainResult, vehicle: vehicle_mod.Vehicle, data_hash: str, data_source: str, rows: int,
         metrics: dict | None = None) -> dict:
    cfg, model = result.config, result.model
    ddm = cfg.kind == "ddm"
    return {
        "format": FORMAT, "version": VERSION, "kind": cfg.kind,
        "config": config_dict(cfg),
        "architecture": {
            "features": list(FEATURE_NAMES), "outputs": list(COEFF_NAMES if ddm else DPM_OUTPUTS),
            "activation": "mish", "n_features": len(FEATURE_NAMES), "tau": cfg.tau, "hidden": cfg.hidden,
            "layers": cfg.layers, "gru_layers": cfg.gru_layers, "method": cfg.method, "substeps": model.substeps,
            "dtype": cfg.dtype,
        },
        "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
        "normalisation": {"mean": model.encoder.mean.tolist(), "std": model.encoder.std.tolist()},
        "ranges": ({"names": list(COEFF_NAMES), "lo": model.lo.tolist(), "hi": model.hi.tolist()} if ddm else None),
        "dpm_iz": None if ddm else model.iz,
        "loss_scale": [float(x) for x in result.loss_scale],
        # the drivetrain form is in the embedded vehicle file too; named here so a reader sees which
        # longitudinal model the coefficients belong to without parsing it
        "vehicle": {"name": vehicle.name, "sha256": vehicle.digest, "json": vehicle.raw_json,
                    "drivetrain": vehicle.known.drivetrain, "brake_gain": vehicle.known.brake_gain},
        "data": {"train_sha256": data_hash, "source": data_source, "rows": rows,
                 "split": f"by time: last {cfg.val_fraction:.0%} of rows validate, windows never cross the cut"},
        "training": {"seconds": result.seconds, "best_val_loss": result.best_val_loss,
                     "epochs_run": len(result.history),
                     "val_loss_curve": [h["val_loss"] for h in result.history],
                     # TrainConfig.restarts: every restart's seed and validation loss, the kept model's seed
                     "seed": cfg.seed if result.seed is None else result.seed, "restarts": result.restarts,
                     "validation_saturation": result.validation_saturation},
        "metrics": metrics or {},
        "software": {"torch": str(torch.__version__), "ddyn": _ddyn_version()},
    }


def _ddyn_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ddyn")
    except PackageNotFoundError:
        return "unknown"


def save(ckpt: dict, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, path)
    return path


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def read(path: str | Path) -> dict:
    """The checkpoint's dictionary, validated by kind and keys; DdynError names the file and what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise DdynError(f"checkpoint not found: {path}")
    try:
        with warnings.catch_warnings():   # torch warns about pickle protocols of foreign files
            warnings.simplefilter("ignore")
            ckpt = torch.load(io.BytesIO(path.read_bytes()), map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for corrupt files; all mean the same to a user
        # torch's messages run to a paragraph (the weights_only advice): its first sentence is the cause
        first = re.split(r"(?<=\.)\s", " ".join(str(e).split()), maxsplit=1)[0]
        raise DdynError(f"{path}: not a readable checkpoint, not a file `ddyn train` writes ({type(e).__name__}"
                        f"{': ' + first[:200] if first else ''})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise DdynError(f"{path}: not a ddyn checkpoint (no format field {FORMAT!r})")
    if ckpt.get("version") != VERSION:
        raise DdynError(f"{path}: checkpoint version {ckpt.get('version')} is not supported (expected {VERSION})")
    for key in ("kind", "config", "architecture", "state_dict", "vehicle", "normalisation"):
        if key not in ckpt:
            raise DdynError(f"{path}: checkpoint lacks {key!r}")
    if ckpt["kind"] not in ("ddm", "dpm"):
        raise DdynError(f"{path}: checkpoint kind {ckpt['kind']!r} is not ddm or dpm")
    cfg = config_from_dict(ckpt["config"], str(path))
    if cfg.kind != ckpt["kind"]:
        raise DdynError(f"{path}: checkpoint kind {ckpt['kind']!r} differs from its config's {cfg.kind!r}")
    arch = ckpt["architecture"]
    if not isinstance(arch, dict):
        raise DdynError(f"{path}: architecture must be a mapping, got {type(arch).__name__}")
    for key in ("tau", "hidden", "layers", "gru_layers", "n_features"):
        if key not in arch:
            raise DdynError(f"{path}: architecture lacks {key!r}")
        if isinstance(arch[key], bool) or not isinstance(arch[key], int) or arch[key] < 0:
            raise DdynError(f"{path}: architecture.{key} must be a whole number >= 0, got {arch[key]!r}")
    for key in ("features", "outputs"):
        if not (isinstance(arch.get(key), list) and all(isinstance(x, str) for x in arch[key])):
            raise DdynError(f"{path}: architecture.{key} must be a list of names, got {arch.get(key)!r}")
    veh = ckpt["vehicle"]
    if not isinstance(veh, dict):
        raise DdynError(f"{path}: vehicle must be a mapping, got {type(veh).__name__}")
    for key in ("name", "json"):
        if not isinstance(veh.get(key), str):
            raise DdynError(f"{path}: vehicle.{key} missing or not a string: the checkpoint must embed its vehicle file")
    norm = ckpt["normalisation"]
    for key in ("mean", "std"):
        if not (isinstance(norm, dict) and isinstance(norm.get(key), list) and len(norm[key]) == len(FEATURE_NAMES)
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in norm[key])):
            raise DdynError(f"{path}: normalisation.{key} must be a list of {len(FEATURE_NAMES)} numbers")
    sd = ckpt["state_dict"]
    if not (isinstance(sd, dict) and all(isinstance(v, torch.Tensor) for v in sd.values())):
        raise DdynError(f"{path}: state_dict must map parameter names to tensors")
    return ckpt


def vehicle_of(ckpt: dict) -> vehicle_mod.Vehicle:
    v = ckpt["vehicle"]
    return vehicle_mod.parse(v["json"].encode(), f"vehicle {v['name']} embedded in checkpoint")


def load(path: str | Path) -> tuple[torch.nn.Module, dict]:
    """Rebuild the network of a checkpoint (in eval mode) and return it with the checkpoint."""
    ckpt = read(path)
    cfg = config_from_dict(ckpt["config"], str(path))
    v = vehicle_of(ckpt)
    norm = ckpt["normalisation"]
    model = build_model(cfg, v, np.array(norm["mean"]), np.array(norm["std"]))
    state = dict(ckpt["state_dict"])
    for key in ("encoder.feature_lo", "encoder.feature_hi"):
        # a checkpoint from before the feature range was recorded: its inputs are not held (build_model's +-inf)
        state.setdefault(key, model.state_dict()[key])
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        detail = " ".join(str(e).split())   # torch lists the keys over several lines
        raise DdynError(f"{path}: weights do not fit the recorded architecture: {detail[:300]}") from None
    model.eval()
    return model, ckpt
