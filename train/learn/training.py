"""Training of DDM and DPM on one-step prediction of vx, vy, omega.

Loss: mean squared error of the next velocities, each channel divided by the
standard deviation of its one-step change on the training set (so vx, vy and
omega, which differ by orders of magnitude, weigh alike; the scales are stored
in the checkpoint). Adam with a cosine learning-rate decay; the weights with the
lowest validation loss are kept. float64 by default: the simulated targets are
exact to rounding, and float32 would floor the error above the papers' figures.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np
import torch
from tqdm import tqdm

from ddyn.data.dataset import Dataset
from ddyn.data.windows import Windows, split_train_validation
from ddyn.errors import DdynError
from ddyn.learn.networks import DPM_OUTPUTS, DeepDynamics, DeepPacejka, bound_shares, set_feature_range
from ddyn.model.integrators import DISCRETISATIONS
from ddyn.model.single_track import COEFF_NAMES
from ddyn.model.vehicle import Vehicle

DTYPES = ("float32", "float64")   # torch dtypes a model trains in


@dataclass
class TrainConfig:
    kind: str = "ddm"              # "ddm" or "dpm"
    tau: int = 1                   # history length (rows)
    hidden: int = 32               # width of GRU and dense layers
    layers: int = 2                # dense layers (Mish) before the head
    gru_layers: int = 0            # GRU layers before the dense ones (0: flattened history)
    lr: float = 3e-3
    batch_size: int = 256
    epochs: int = 100
    val_fraction: float = 0.2
    seed: int = 0
    method: str = "euler"          # discretisation of the physics step
    weight_decay: float = 1e-7     # L2 penalty on weights (not biases): favours coefficients that vary
                                   # only as much as the data demand
    lbfgs_iterations: int = 4000     # full-batch L-BFGS iterations after Adam (polishes a near-exact fit)
    dpm_iz_scale: float = 1.0      # DPM only: Iz given as truth times this (1.2, 0.8 for the +-20 % variants)
    dtype: str = "float64"
    restarts: int = 1              # trainings from seeds seed, seed+1, ...: the lowest validation loss is kept
                                   # (a bad initialisation's local minimum is caught on the validation part)
    guard_prior: float = 0.0       # DDM only: weight of the mean squared guard logit (a prior toward each range's
                                   # middle): near a bound the sigmoid's slope, and with it the data's pull, vanishes,
                                   # so a coefficient the data do not pin can drift onto a bound and stay there

    def __post_init__(self):
        if self.kind not in ("ddm", "dpm"):
            raise DdynError(f"model kind must be ddm or dpm, got {self.kind!r}")
        if self.method not in DISCRETISATIONS:
            raise DdynError(f"method must be one of {', '.join(DISCRETISATIONS)}, got {self.method!r}")
        if self.dtype not in DTYPES:
            raise DdynError(f"dtype must be one of {', '.join(DTYPES)}, got {self.dtype!r}")
        for f in fields(self):   # a checkpoint's config or a caller may give a string where a number belongs
            value, want = getattr(self, f.name), type(getattr(TrainConfig, f.name, None))
            if want not in (int, float):
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise DdynError(f"{f.name} must be a finite number, got {value!r}")
            if want is int:
                if value != int(value):
                    raise DdynError(f"{f.name} must be a whole number, got {value!r}")
                setattr(self, f.name, int(value))
        if not self.lr > 0:
            raise DdynError(f"lr must be > 0, got {self.lr}")
        if not 0 < self.val_fraction < 1:
            raise DdynError(f"val_fraction must lie between 0 and 1, got {self.val_fraction}")
        for name in ("gru_layers", "lbfgs_iterations", "weight_decay"):
            if getattr(self, name) < 0:
                raise DdynError(f"{name} must be at least 0, got {getattr(self, name)}")
        if not self.dpm_iz_scale > 0:
            raise DdynError(f"dpm_iz_scale must be > 0, got {self.dpm_iz_scale}")
        for name in ("tau", "hidden", "layers", "batch_size", "epochs", "restarts"):
            if getattr(self, name) < 1:
                raise DdynError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.guard_prior < 0:
            raise DdynError(f"guard_prior must be at least 0, got {self.guard_prior}")
        if self.guard_prior > 0 and self.kind != "ddm":
            raise DdynError("guard_prior acts on the Physics Guard: DDM only (the DPM has no guard)")


@dataclass
class TrainResult:
    model: torch.nn.Module
    config: TrainConfig
    loss_scale: np.ndarray
    history: list[dict]
    best_val_loss: float
    seconds: float
    restarts: list = field(default_factory=list)   # [{"seed", "best_val_loss", "seconds", ...}] of every restart
    seed: int | None = None                         # the seed of the model kept (config.seed without restarts)
    # DDM: the coefficient most often at a guard bound on the validation windows {"coefficient", "share"}
    validation_saturation: dict | None = None


def _tensor(a, dtype):
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def build_model(cfg: TrainConfig, vehicle: Vehicle, mean: np.ndarray, std: np.ndarray) -> torch.nn.Module:
    dtype = getattr(torch, cfg.dtype)
    substeps = vehicle.rk4_substeps if cfg.method == "rk4" else 1
    common = dict(tau=cfg.tau, hidden=cfg.hidden, layers=cfg.layers, gru_layers=cfg.gru_layers,
                  mean=_tensor(mean, dtype), std=_tensor(std, dtype), known=vehicle.known,
                  sample_time=vehicle.sample_time, method=cfg.method, substeps=substeps)
    if cfg.kind == "ddm":
        lo, hi = vehicle.range_arrays()
        model = DeepDynamics(lo=_tensor(lo, dtype), hi=_tensor(hi, dtype), **common)
    else:
        if vehicle.true_coefficients is None:
            raise DdynError(f"DPM needs Iz; vehicle {vehicle.name} has no true coefficients")
        mid = {k: 0.5 * (a + b) for k, (a, b) in vehicle.ranges.items()}
        init = _tensor([mid[k] if k != "Frx" else 0.0 for k in DPM_OUTPUTS], dtype)
        model = DeepPacejka(init=init, iz=vehicle.true_coefficients["Iz"] * cfg.dpm_iz_scale, **common)
    return model.to(dtype)


def loss_fn(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return (((pred[:, 3:6] - target) / scale) ** 2).mean()


def objective(model: torch.nn.Module, cfg: "TrainConfig", h, s, u, t, scale) -> torch.Tensor:
    """The training loss of one batch: the scaled next-state MSE, the weights' L2 penalty and, with
    cfg.guard_prior, the mean squared guard logit."""
    if cfg.guard_prior > 0:
        pred, _, z = model.forward_with_logits(h, s, u)
        prior = cfg.guard_prior * (z ** 2).mean()
    else:
        pred, _ = model(h, s, u)
        prior = 0.0
    return loss_fn(pred, t, scale) + weight_penalty(model, cfg.weight_decay) + prior


def weight_penalty(model: torch.nn.Module, weight_decay: float) -> torch.Tensor | float:
    if weight_decay <= 0:
        return 0.0
    return weight_decay * sum((p ** 2).sum() for name, p in model.named_parameters() if "weight" in name)


def _batch_tensors(w: Windows, dtype):
    return tuple(_tensor(a, dtype) for a in (w.history, w.state, w.inputs, w.target))


def evaluate_loss(model, w: Windows, scale: torch.Tensor, batch: int = 4096) -> float:
    dtype = scale.dtype
    total, n = 0.0, len(w)
    with torch.no_grad():
        for i in range(0, n, batch):
            h, s, u, t = _batch_tensors(w.subset(slice(i, i + batch)), dtype)
            pred, _ = model(h, s, u)
            total += float(loss_fn(pred, t, scale)) * len(t)
    return total / n


def train(ds: Dataset, vehicle: Vehicle, cfg: TrainConfig, progress: bool = True,
          validation: Windows | None = None) -> TrainResult:
    """Train on ds (split by time into train and validation unless `validation` is given); with cfg.restarts > 1,
    once per seed cfg.seed, cfg.seed + 1, ..., keeping the model with the lowest validation loss (only the
    validation part, inside the training data, decides: a held-out test part plays no role). Each restart's
    guard saturation on the validation part is recorded beside its loss; it is not a selection criterion: on the
    real Putnam log every restart measured had Gf or Kf at a bound in 20-29 % of the validation samples whatever
    its held-out saturation (0.2-35 %; docs/learning.md). The result's seconds are the total over the restarts."""
    if cfg.restarts == 1:
        return _train_once(ds, vehicle, cfg, progress, validation)
    runs = [_train_once(ds, vehicle, replace(cfg, seed=cfg.seed + k, restarts=1), progress, validation)
            for k in range(cfg.restarts)]
    best = min(runs, key=lambda r: r.best_val_loss)
    record = [{"seed": r.config.seed, "best_val_loss": r.best_val_loss, "seconds": r.seconds,
               "validation_saturation": r.validation_saturation} for r in runs]
    return TrainResult(best.model, cfg, best.loss_scale, best.history, best.best_val_loss,
                       sum(r.seconds for r in runs), record, best.config.seed, best.validation_saturation)


def validation_saturation(model: torch.nn.Module, va: Windows) -> dict | None:
    """The coefficient most often within 1 % of the range width of a guard bound on the validation windows (the
    saturation figure of ddyn evaluate), and that share; None for a model without a guard (DPM)."""
    if not hasattr(model, "lo"):
        return None
    with torch.no_grad():
        c = model.coefficients(_tensor(va.history, model.lo.dtype)).numpy()
    lower, upper = bound_shares(c, model.lo.numpy(), model.hi.numpy())
    share = lower + upper     # a range is wider than twice the tolerance: no sample is at both bounds
    i = int(np.argmax(share))
    return {"coefficient": COEFF_NAMES[i], "share": float(share[i])}


def _train_once(ds: Dataset, vehicle: Vehicle, cfg: TrainConfig, progress: bool,
                validation: Windows | None) -> TrainResult:
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    dtype = getattr(torch, cfg.dtype)
    if validation is None:
        tr, va = split_train_validation(ds, cfg.tau, cfg.val_fraction)
    else:
        from ddyn.data.windows import make_windows
        tr, va = make_windows(ds, cfg.tau), validation
    flat = tr.history.reshape(-1, tr.history.shape[-1])
    mean, std = flat.mean(axis=0), np.maximum(flat.std(axis=0), 1e-12)
    scale_np = np.maximum((tr.target - tr.state[:, 3:6]).std(axis=0), 1e-12)
    scale = _tensor(scale_np, dtype)
    model = build_model(cfg, vehicle, mean, std)
    # the inputs it is trained and selected on: the identity on every window used here (training unchanged)
    set_feature_range(model, tr.history, va.history)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs, eta_min=cfg.lr * 1e-3)
    h_all, s_all, u_all, t_all = _batch_tensors(tr, dtype)
    best = (float("inf"), None)
    log: list[dict] = []
    start = time.perf_counter()
    bar = tqdm(range(cfg.epochs), desc=f"train {cfg.kind}", disable=not progress, leave=False)
    for epoch in bar:
        model.train()
        order = torch.as_tensor(rng.permutation(len(tr)))
        for i in range(0, len(tr), cfg.batch_size):
            b = order[i:i + cfg.batch_size]
            loss = objective(model, cfg, h_all[b], s_all[b], u_all[b], t_all[b], scale)
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
        model.eval()
        val = evaluate_loss(model, va, scale)
        if not np.isfinite(val):
            raise DdynError(f"training diverged at epoch {epoch} (validation loss {val}); lower the learning rate")
        log.append({"epoch": epoch, "val_loss": val})
        if val < best[0]:
            best = (val, {k: v.clone() for k, v in model.state_dict().items()})
        bar.set_postfix(val=f"{val:.3e}", best=f"{best[0]:.3e}")
    model.load_state_dict(best[1])
    if cfg.lbfgs_iterations > 0:
        best = _polish_lbfgs(model, cfg, (h_all, s_all, u_all, t_all), va, scale, best, log, progress)
    model.eval()
    return TrainResult(model, cfg, scale_np, log, best[0], time.perf_counter() - start,
                       validation_saturation=validation_saturation(model, va))


def _polish_lbfgs(model, cfg: TrainConfig, batch, va: Windows, scale, best, log, progress: bool):
    """Full-batch L-BFGS from the best Adam weights; keeps whichever validates best."""
    h, s, u, t = batch
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=20, history_size=50,
                            tolerance_grad=1e-14, tolerance_change=1e-18, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = objective(model, cfg, h, s, u, t, scale)
        loss.backward()
        return loss

    rounds = max(1, cfg.lbfgs_iterations // 20)
    for r in tqdm(range(rounds), desc="polish (L-BFGS)", disable=not progress, leave=False):
        opt.step(closure)
        val = evaluate_loss(model, va, scale)
        log.append({"epoch": cfg.epochs + r, "val_loss": val, "phase": "lbfgs"})
        if not np.isfinite(val):
            break
        if val < best[0]:
            best = (val, {k: v.clone() for k, v in model.state_dict().items()})
    model.load_state_dict(best[1])
    return best


def config_dict(cfg: TrainConfig) -> dict:
    return asdict(cfg)


def config_from_dict(raw, origin: str) -> TrainConfig:
    """A TrainConfig from a recorded or given dict (a checkpoint's "config", an API call's config): unknown keys
    and bad values are a DdynError naming origin and the key, not a TypeError."""
    if not isinstance(raw, dict):
        raise DdynError(f"{origin}: config must be a mapping of TrainConfig fields, got {type(raw).__name__}")
    known = {f.name for f in fields(TrainConfig)}
    unknown = sorted(str(k) for k in raw if k not in known)
    if unknown:
        raise DdynError(f"{origin}: unknown config key(s) {', '.join(map(repr, unknown))} "
                        f"(known: {', '.join(sorted(known))})")
    try:
        return TrainConfig(**raw)
    except DdynError as e:
        raise DdynError(f"{origin}: config: {e}") from None
