"""`ddyn finetune`: FTHD, fine-tuning a pre-trained Deep Dynamics model with a hybrid loss.

FTHD (Fine Tuning Hybrid Dynamics) starts from a trained DDM checkpoint, freezes its
first layers and trains the rest on a (small) dataset of the target car with

    L = lambda1 * L_sup + lambda2 * L_der,     lambda1, lambda2 >= 0,  lambda1 + lambda2 = 1,

where L_sup is the DDM's supervised one-step loss (ddyn.learn.training.loss_fn) and L_der an
unsupervised derivative-consistency term, derived here.

Freezing. The trainable layers, in forward order, are the GRU layers (if any; layer i
holds the GRU's *_l{i} tensors), the dense Linear layers of the encoder, and the head.
A fraction f freezes the first floor(f * n_layers) of them. At least one hidden
(non-head) layer must stay trainable and the head always is; a fraction that would
freeze more is refused. The input normalisation (encoder.mean/std) is the base's:
the frozen layers were trained on it; its feature range (networks.set_feature_range) is the
base's widened to the fine-tuning and selection rows.

The derivative term
-------------------
Notation: row k of a segment holds the state x_k (velocities v_k = x_k[3:6]) and the
input u_k; Ts is the sample time; f(x, u, c) = ddyn.model.single_track.derivatives (continuous
time); S(x, u, c) the model's discrete step (Euler: S = x + Ts f). The window ending at
row k yields coefficients c_k = net(history_k) and the predicted next velocities
vhat_{k+1} = S(x_k, u_k, c_k)[3:6]. Its label is v_{k+1}; L_sup compares the two.

The velocity trajectory around t_k as window k sees it is v_{k-1}, v_k (measured; the
rows the window is given, not its label) followed by its own prediction vhat_{k+1}.
Its central-difference time derivative over [t_{k-1}, t_{k+1}] is
(vhat_{k+1} - v_{k-1}) / (2 Ts). What the model's own equations imply over the same
interval, with the coefficients c_k and the inputs held over each sample (as the data
are recorded), is the trapezoidal mean of the acceleration at the two sample starts,
(f(x_{k-1}, u_{k-1}, c_k) + f(x_k, u_k, c_k)) / 2. The term asks the two to agree:

    r_k = (vhat_{k+1} - v_{k-1}) / (2 Ts) - (f(x_{k-1}, u_{k-1}, c_k) + f(x_k, u_k, c_k))[3:6] / 2.

For the Euler step, vhat_{k+1} = v_k + Ts f(x_k, u_k, c_k)[3:6], the f(x_k) parts cancel:

    r_k = ( (v_k - v_{k-1}) / Ts - f(x_{k-1}, u_{k-1}, c_k)[3:6] ) / 2,

so the coefficients that window k estimates must also explain the transition *into*
row k, the one before its label. The label v_{k+1} never enters r_k (only c_k's own
prediction of it does): the term needs no target and could be evaluated online on the
car at time t_k. On noise-free Euler data the rows obey v_k = v_{k-1} + Ts f(x_{k-1},
u_{k-1}, c_true), so r_k = 0 to rounding for the true coefficients, and r_k != 0 for
coefficients that do not describe the car. (For an RK4 step r_k is the same up to
O(Ts) terms and does not vanish exactly.)

Why it carries information although it reads nothing new. L_sup gives three
equations per window for seventeen coefficients: a DDM can meet them with per-window
estimates that wander along a many-dimensional family of coefficient vectors that all
fit that one transition, and with few rows it does, so its coefficients are poorly
identified. r_k makes the same c_k satisfy three more equations at another operating
point (x_{k-1}, u_{k-1}). Because the true coefficients are constants of the car, both
sets hold for them; a spurious solution rarely fits both. It also ties consecutive
estimates together: the transition k-1 -> k must be explained by c_{k-1} (through
L_sup) and by c_k (through r_k), i.e. consecutive coefficient estimates must imply
consistent dynamics on the transition they share. It is a physics prior on how the
coefficients may vary, not a second copy of the labels.

Scaling: 2 Ts r_k is a velocity change over the central-difference interval; each
channel is divided by the supervised loss's scale s (the std of the one-step change
on the training windows), L_der = mean_k,ch (2 Ts r_k,ch / s_ch)^2. For the Euler step
this is exactly the normalised one-step residual of the previous transition under
c_k, so the two terms weigh alike and lambda1, lambda2 mean what they say. Windows
whose row k-1 lies outside their segment (or outside the data) get no term.

A pitfall of the reference implementation, avoided here. It fills an acceleration
tensor `dxdt`, keeps `ax = dxdt` as "the derivative", then scales `dxdt *= Ts` in place
to form the Euler increment. `ax` is a second name for the same storage, not a copy,
so the derivative it returns is the acceleration times Ts (off by 1/Ts: 50 for the
1:43 car, 25 for the AV-21) and its derivative loss compares mismatched units. Here
the accelerations come from ddyn.model.single_track.derivatives, which builds new tensors (no
in-place arithmetic anywhere in the term), the step is formed out of place by
ddyn.model.integrators, and the residual divides by 2 Ts explicitly; the tests check the
term against a numpy hand computation and its vanishing for the true coefficients.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ddyn.data.dataset import Dataset
from ddyn.data.windows import Windows, make_windows, valid_end_rows
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn.networks import set_feature_range
from ddyn.learn.training import TrainConfig, TrainResult, build_model, loss_fn
from ddyn.model import mathns
from ddyn.model.single_track import N_COEFF, N_INPUT, N_STATE, derivatives
from ddyn.model.vehicle import Vehicle

LAMBDA_TOL = 1e-9


# ---------------------------------------------------------------------------------------------
# layers and freezing

def trainable_layers(model: torch.nn.Module) -> list[tuple[str, list[torch.nn.Parameter]]]:
    """The network's layers in forward order: GRU layers, dense Linear layers, head."""
    enc = model.encoder
    layers: list[tuple[str, list[torch.nn.Parameter]]] = []
    if enc.gru is not None:
        for i in range(enc.gru.num_layers):
            params = [p for n, p in enc.gru.named_parameters() if n.endswith(f"_l{i}")]
            layers.append((f"encoder.gru.l{i}", params))
    for name, module in enc.dense.named_children():
        if isinstance(module, torch.nn.Linear):
            layers.append((f"encoder.dense.{name}", list(module.parameters())))
    layers.append(("head", list(model.head.parameters())))
    return layers


def freeze_count(n_layers: int, fraction: float) -> int:
    """Number of leading layers that `fraction` freezes; refuses leaving no hidden layer trainable."""
    if not 0.0 <= fraction <= 1.0 or not math.isfinite(fraction):
        raise DdynError(f"freeze fraction must lie in [0, 1], got {fraction}")
    n = int(math.floor(fraction * n_layers + 1e-9))
    n_hidden = n_layers - 1
    if n > n_hidden - 1:
        most = max(n_hidden - 1, 0)
        raise DdynError(f"freeze fraction {fraction} freezes {n} of {n_layers} layers ({n_hidden} hidden + head); "
                        f"at least one hidden layer and the head must stay trainable, so at most {most} "
                        f"may be frozen (fraction below {most + 1} / {n_layers})")
    return n


def freeze(model: torch.nn.Module, fraction: float) -> tuple[list[str], list[str]]:
    """Freeze the first layers (requires_grad False); returns (frozen, trainable) layer names."""
    layers = trainable_layers(model)
    n = freeze_count(len(layers), fraction)
    for i, (_, params) in enumerate(layers):
        for p in params:
            p.requires_grad_(i >= n)
    return [name for name, _ in layers[:n]], [name for name, _ in layers[n:]]


def check_lambdas(lambda1: float, lambda2: float) -> tuple[float, float]:
    """The hybrid loss weights: both in [0, 1] and summing to 1."""
    l1, l2 = float(lambda1), float(lambda2)
    if not (math.isfinite(l1) and math.isfinite(l2)) or l1 < 0 or l2 < 0:
        raise DdynError(f"lambda1 and lambda2 must be finite and non-negative, got {lambda1}, {lambda2}")
    if abs(l1 + l2 - 1.0) > LAMBDA_TOL:
        raise DdynError(f"lambda1 + lambda2 must equal 1, got {l1} + {l2} = {l1 + l2}")
    return l1, l2


# ---------------------------------------------------------------------------------------------
# data: windows plus the row before each window's last row

@dataclass
class Batch:
    """Tensors of a set of windows: what both loss terms read."""

    history: torch.Tensor      # (n, tau, 7)
    state: torch.Tensor        # (n, 8)   row k
    inputs: torch.Tensor       # (n, 2)   row k
    target: torch.Tensor       # (n, 3)   v_{k+1} (L_sup only)
    prev_state: torch.Tensor   # (n, 8)   row k-1 (zeros where absent)
    prev_inputs: torch.Tensor  # (n, 2)
    has_prev: torch.Tensor     # (n,) bool: row k-1 lies in k's segment

    def __len__(self) -> int:
        return len(self.state)

    def index(self, idx) -> "Batch":
        return Batch(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))


def batch_of(ds: Dataset, w: Windows, dtype=torch.float64) -> Batch:
    """A Batch for windows w of ds (w.end_row index ds's rows)."""
    k = np.asarray(w.end_row)
    has = (k >= 1) & (ds.segment[np.maximum(k - 1, 0)] == ds.segment[k])
    prev = np.maximum(k - 1, 0)
    ps = np.where(has[:, None], ds.states[prev], 0.0)
    pu = np.where(has[:, None], ds.inputs[prev], 0.0)

    def t(a):
        return torch.as_tensor(np.asarray(a), dtype=dtype)

    return Batch(t(w.history), t(w.state), t(w.inputs), t(w.target), t(ps), t(pu), torch.as_tensor(has))


# ---------------------------------------------------------------------------------------------
# the loss terms

def derivatives_torch(state: torch.Tensor, inputs: torch.Tensor, coeffs: torch.Tensor, known) -> torch.Tensor:
    """Continuous-time state derivative (n, 8) of the one model, for torch batches (no in-place ops)."""
    for a, n, what in ((state, N_STATE, "state"), (inputs, N_INPUT, "inputs"), (coeffs, N_COEFF, "coeffs")):
        if a.shape[-1] != n:
            raise ValueError(f"{what}: last dimension must be {n}, got shape {tuple(a.shape)}")
    out = derivatives(mathns.get("torch"), state.unbind(-1), inputs.unbind(-1), coeffs.unbind(-1), known)
    return torch.stack(torch.broadcast_tensors(*out), dim=-1)


def derivative_residual(model, coeffs: torch.Tensor, b: Batch, pred: torch.Tensor | None = None) -> torch.Tensor:
    """r_k (n, 3) of the module docstring, in m/s^2 (rad/s^2 for omega)."""
    Ts = float(model.sample_time)
    if pred is None:
        pred = model.step(b.state, b.inputs, coeffs)
    f_prev = derivatives_torch(b.prev_state, b.prev_inputs, coeffs, model.known)[:, 3:6]
    f_now = derivatives_torch(b.state, b.inputs, coeffs, model.known)[:, 3:6]
    return (pred[:, 3:6] - b.prev_state[:, 3:6]) / (2.0 * Ts) - 0.5 * (f_prev + f_now)


def derivative_loss_from(model, coeffs, b: Batch, scale: torch.Tensor, pred=None) -> torch.Tensor:
    """L_der: mean over windows with a previous row and over channels of (2 Ts r / s)^2."""
    r = derivative_residual(model, coeffs, b, pred)
    z = (2.0 * float(model.sample_time)) * r / scale
    m = b.has_prev
    if not bool(m.any()):
        return z.sum() * 0.0
    return (z[m] ** 2).mean()


def derivative_loss(model, b: Batch, scale: torch.Tensor) -> torch.Tensor:
    return derivative_loss_from(model, model.coefficients(b.history), b, scale)


def hybrid_loss(model, b: Batch, scale: torch.Tensor, lambda1: float, lambda2: float) -> tuple:
    """(lambda1 L_sup + lambda2 L_der, L_sup, L_der); L_der is skipped (zero) when lambda2 is 0."""
    c = model.coefficients(b.history)
    pred = model.step(b.state, b.inputs, c)
    sup = loss_fn(pred, b.target, scale)
    if lambda2 == 0.0:
        return lambda1 * sup, sup, torch.zeros((), dtype=sup.dtype)
    der = derivative_loss_from(model, c, b, scale, pred)
    return lambda1 * sup + lambda2 * der, sup, der


def supervised_loss(model, b: Batch, scale: torch.Tensor, chunk: int = 8192) -> float:
    """L_sup of a whole set (no gradient), as ddyn.learn.training.evaluate_loss."""
    total = 0.0
    with torch.no_grad():
        for i in range(0, len(b), chunk):
            s = b.index(slice(i, i + chunk))
            total += float(loss_fn(model(s.history, s.state, s.inputs)[0], s.target, scale)) * len(s)
    return total / len(b)


def trainable_weight_penalty(model, weight_decay: float):
    if weight_decay <= 0:
        return 0.0
    return weight_decay * sum((p ** 2).sum() for n, p in model.named_parameters() if "weight" in n and p.requires_grad)


# ---------------------------------------------------------------------------------------------
# optimisation with a counted step budget (the same loop for FTHD and the from-scratch DDM)

@dataclass
class FitConfig:
    adam_steps: int = 1500         # Adam optimiser steps (mini-batches), cosine-decayed learning rate
    lbfgs_iterations: int = 300    # full-batch L-BFGS iterations afterwards
    lr: float = 1e-3
    batch_size: int = 256
    weight_decay: float = 1e-7
    seed: int = 0
    eval_every: int = 25           # Adam steps between validation evaluations

    def __post_init__(self):
        if self.adam_steps < 0 or self.lbfgs_iterations < 0 or self.adam_steps + self.lbfgs_iterations < 1:
            raise DdynError("the step budget must be non-negative and at least one step in all")
        if self.batch_size < 1 or self.eval_every < 1 or not self.lr > 0:
            raise DdynError("batch size and eval_every must be at least 1 and lr positive")


@dataclass
class FitResult:
    history: list[dict]
    best_val_loss: float
    steps: dict                    # {"adam": n, "lbfgs": m}: optimiser steps actually taken
    seconds: float
    final_train: dict = field(default_factory=dict)


def fit(model, train: Batch, val: Batch, train_scale: torch.Tensor, val_scale: torch.Tensor,
        lambdas: tuple[float, float], cfg: FitConfig, progress: bool = False, desc: str = "fit") -> FitResult:
    """Adam then L-BFGS on the trainable parameters; keeps the weights with the lowest validation L_sup."""
    l1, l2 = check_lambdas(*lambdas)
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise DdynError("nothing to train: every parameter is frozen")
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    start = time.perf_counter()
    log: list[dict] = []
    best = [float("inf"), None]

    def validate(step: int, phase: str):
        model.eval()
        v = supervised_loss(model, val, val_scale)
        log.append({"step": step, "phase": phase, "val_loss": v})
        if not np.isfinite(v):
            raise DdynError(f"{desc}: diverged at {phase} step {step} (validation loss {v}); lower the learning rate")
        if v < best[0]:
            best[0], best[1] = v, {k: t.clone() for k, t in model.state_dict().items()}

    validate(0, "start")
    n_adam = 0
    if cfg.adam_steps > 0:
        opt = torch.optim.Adam(params, lr=cfg.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.adam_steps, eta_min=cfg.lr * 1e-3)
        bs = min(cfg.batch_size, len(train))
        order, pos = rng.permutation(len(train)), 0
        for _ in tqdm(range(cfg.adam_steps), desc=f"{desc} (Adam)", disable=not progress, leave=False):
            if pos >= len(order):
                order, pos = rng.permutation(len(train)), 0
            idx = torch.as_tensor(order[pos:pos + bs])
            pos += bs
            model.train()
            loss = hybrid_loss(model, train.index(idx), train_scale, l1, l2)[0] \
                + trainable_weight_penalty(model, cfg.weight_decay)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            n_adam += 1
            if n_adam % cfg.eval_every == 0 or n_adam == cfg.adam_steps:
                validate(n_adam, "adam")
        model.load_state_dict(best[1])
    n_lbfgs = _lbfgs(model, params, train, train_scale, (l1, l2), cfg, validate, progress, desc) \
        if cfg.lbfgs_iterations > 0 else 0
    model.load_state_dict(best[1])
    model.eval()
    with torch.no_grad():
        total, sup, der = hybrid_loss(model, train, train_scale, l1, l2)
    return FitResult(log, best[0], {"adam": n_adam, "lbfgs": n_lbfgs}, time.perf_counter() - start,
                     {"hybrid": float(total), "supervised": float(sup), "derivative": float(der)})


def _lbfgs(model, params, train: Batch, scale, lambdas, cfg: FitConfig, validate, progress, desc) -> int:
    """Full-batch L-BFGS for exactly cfg.lbfgs_iterations iterations (fewer only if it stalls)."""
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=20, history_size=50, tolerance_grad=1e-14,
                            tolerance_change=1e-18, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = hybrid_loss(model, train, scale, *lambdas)[0] + trainable_weight_penalty(model, cfg.weight_decay)
        loss.backward()
        return loss

    done = 0
    bar = tqdm(total=cfg.lbfgs_iterations, desc=f"{desc} (L-BFGS)", disable=not progress, leave=False)
    while done < cfg.lbfgs_iterations:
        opt.param_groups[0]["max_iter"] = min(20, cfg.lbfgs_iterations - done)
        opt.param_groups[0]["max_eval"] = int(opt.param_groups[0]["max_iter"] * 1.25) + 1
        model.train()
        opt.step(closure)
        n = int(opt.state[params[0]].get("n_iter", 0))
        stalled = n == done
        bar.update(n - done)
        done = n
        validate(done, "lbfgs")  # raises if the loss went non-finite
        if stalled:
            break
    bar.close()
    return done


# ---------------------------------------------------------------------------------------------
# the two arms and their checkpoints

def one_step_scale(w: Windows) -> np.ndarray:
    """Per-channel loss scale: std of the one-step change of vx, vy, omega (as ddyn.learn.training)."""
    return np.maximum((w.target - w.state[:, 3:6]).std(axis=0), 1e-12)


def windows_of(ds: Dataset, tau: int) -> Windows:
    k = valid_end_rows(ds, tau)
    if len(k) == 0:
        raise DdynError(f"dataset ({len(ds)} rows) has no window of {tau} rows plus a successor in one segment")
    return make_windows(ds, tau, k)


def fraction_of(ds: Dataset, fraction: float) -> Dataset:
    """The first `fraction` of the rows (by time): a smaller dataset of the same driving."""
    if not 0 < fraction <= 1:
        raise DdynError(f"data fraction must lie in (0, 1], got {fraction}")
    return ds.subset(slice(0, max(2, int(round(len(ds) * fraction)))))


def split_by_time(ds: Dataset, val_fraction: float) -> tuple[Dataset, Dataset]:
    """(pool, validation): the last val_fraction of the rows validate (no window reads both sides)."""
    if not 0 < val_fraction < 1:
        raise DdynError(f"validation fraction must lie in (0, 1), got {val_fraction}")
    cut = int(round(len(ds) * (1 - val_fraction)))
    return ds.subset(slice(0, cut)), ds.subset(slice(cut, None))


@dataclass
class FinetuneConfig:
    freeze_fraction: float = 0.5   # of the trainable layers (GRU, dense, head), counted from the input
    lambda1: float = 0.5           # weight of the supervised term
    lambda2: float = 0.5           # weight of the derivative term
    data_fraction: float = 1.0     # share of the training pool used (its first rows)
    fit: FitConfig = field(default_factory=FitConfig)

    def __post_init__(self):
        check_lambdas(self.lambda1, self.lambda2)
        if not 0 < self.data_fraction <= 1:
            raise DdynError(f"data fraction must lie in (0, 1], got {self.data_fraction}")


def _result_config(base: TrainConfig, fc: FitConfig, n_train: int) -> TrainConfig:
    per_epoch = max(1, math.ceil(n_train / max(1, min(fc.batch_size, n_train))))
    return replace(base, lr=fc.lr, batch_size=fc.batch_size, seed=fc.seed, weight_decay=fc.weight_decay,
                   epochs=max(1, math.ceil(fc.adam_steps / per_epoch)), lbfgs_iterations=fc.lbfgs_iterations)


def _checkpoint(model, cfg: TrainConfig, vehicle: Vehicle, scale: np.ndarray, fr: FitResult, train_ds: Dataset,
                source: str, split: str) -> dict:
    history = [{"epoch": i, "val_loss": h["val_loss"]} for i, h in enumerate(fr.history)]
    result = TrainResult(model, cfg, scale, history, fr.best_val_loss, fr.seconds)
    ckpt = checkpoint.make(result, vehicle, train_ds.content_hash(), source, len(train_ds))
    ckpt["data"]["split"] = split
    ckpt["training"]["optimizer_steps"] = dict(fr.steps)
    ckpt["training"]["curve_steps"] = [[h["phase"], h["step"]] for h in fr.history]
    return ckpt


def finetune(base_path: str | Path, train_ds: Dataset, val_ds: Dataset, cfg: FinetuneConfig,
             val_scale: np.ndarray | None = None, source: str = "", progress: bool = False,
             split: str = "") -> tuple[torch.nn.Module, dict]:
    """FTHD: load the base DDM, freeze, fine-tune on the first cfg.data_fraction of train_ds.

    Returns the model (eval mode, best validation weights) and its checkpoint dictionary
    (not yet saved). val_scale: per-channel divisors of the validation loss (default:
    those of the training windows, as ddyn train).
    """
    base_path = Path(base_path)
    model, base = checkpoint.load(base_path)
    if base["kind"] != "ddm":
        raise DdynError(f"{base_path}: FTHD fine-tunes a DDM checkpoint, this one is {base['kind']!r}")
    v = checkpoint.vehicle_of(base)
    for what, ds in (("training", train_ds), ("validation", val_ds)):
        if ds.vehicle and ds.vehicle != v.name:
            raise DdynError(f"{what} data are for vehicle {ds.vehicle!r}, the base checkpoint for {v.name!r}")
        if abs(ds.sample_time - v.sample_time) > 1e-6 * v.sample_time:
            raise DdynError(f"{what} data sample time {ds.sample_time} s differs from the model's {v.sample_time} s")
    base_cfg = TrainConfig(**base["config"])
    dtype = getattr(torch, base_cfg.dtype)
    part = fraction_of(train_ds, cfg.data_fraction)
    tw, vw = windows_of(part, base_cfg.tau), windows_of(val_ds, base_cfg.tau)
    scale = one_step_scale(tw)
    vscale = scale if val_scale is None else np.asarray(val_scale, float)
    frozen, trainable = freeze(model, cfg.freeze_fraction)
    # the base's input range widened to the rows it is fine-tuned and selected on
    set_feature_range(model, tw.history, vw.history, join=True)
    fr = fit(model, batch_of(part, tw, dtype), batch_of(val_ds, vw, dtype), torch.as_tensor(scale, dtype=dtype),
             torch.as_tensor(vscale, dtype=dtype), (cfg.lambda1, cfg.lambda2), cfg.fit, progress, "finetune")
    for p in model.parameters():
        p.requires_grad_(True)
    ckpt = _checkpoint(model, _result_config(base_cfg, cfg.fit, len(tw)), v, scale, fr, part, source,
                       split or "validation: a separate, fixed block (see finetune.validation)")
    ckpt["finetune"] = {
        "method": "FTHD",
        "base_sha256": checkpoint.file_sha256(base_path),
        "base_source": str(base_path),
        "base_data": base.get("data", {}),
        "frozen_layers": frozen,
        "trainable_layers": trainable,
        "freeze_fraction": cfg.freeze_fraction,
        "lambdas": {"lambda1": cfg.lambda1, "lambda2": cfg.lambda2},
        "data_fraction": cfg.data_fraction,
        "train_rows": len(part),
        "pool_rows": len(train_ds),
        "validation": {"rows": len(val_ds), "sha256": val_ds.content_hash(), "source": val_ds.source},
        "optimizer_steps": dict(fr.steps),
        "fit": asdict(cfg.fit),
        "final_train_loss": fr.final_train,
        "derivative_term": "r_k = (vhat_{k+1} - v_{k-1})/(2 Ts) - (f(x_{k-1},u_{k-1},c_k) + f(x_k,u_k,c_k))[3:6]/2, "
                           "loss mean (2 Ts r / loss_scale)^2 (train/learn/finetune.py)",
    }
    return model, ckpt


def train_scratch(vehicle: Vehicle, train_ds: Dataset, val_ds: Dataset, tcfg: TrainConfig, fcfg: FitConfig,
                  val_scale: np.ndarray | None = None, source: str = "", progress: bool = False,
                  split: str = "") -> tuple[torch.nn.Module, dict, FitResult]:
    """A DDM from scratch with the same optimisation loop and step budget as FTHD (supervised loss only)."""
    dtype = getattr(torch, tcfg.dtype)
    tw, vw = windows_of(train_ds, tcfg.tau), windows_of(val_ds, tcfg.tau)
    flat = tw.history.reshape(-1, tw.history.shape[-1])
    torch.manual_seed(fcfg.seed)
    model = build_model(tcfg, vehicle, flat.mean(axis=0), np.maximum(flat.std(axis=0), 1e-12))
    set_feature_range(model, tw.history, vw.history)
    scale = one_step_scale(tw)
    vscale = scale if val_scale is None else np.asarray(val_scale, float)
    fr = fit(model, batch_of(train_ds, tw, dtype), batch_of(val_ds, vw, dtype), torch.as_tensor(scale, dtype=dtype),
             torch.as_tensor(vscale, dtype=dtype), (1.0, 0.0), fcfg, progress, "ddm")
    ckpt = _checkpoint(model, _result_config(tcfg, fcfg, len(tw)), vehicle, scale, fr, train_ds, source,
                       split or "validation: a separate, fixed block")
    return model, ckpt, fr


# ---------------------------------------------------------------------------------------------
# `ddyn finetune`

def _run(args) -> int:
    from ddyn.data.importers import load_any
    from ddyn.learn.evaluate import evaluate, format_summary, public

    base = checkpoint.read(args.base)
    vname = base["vehicle"]["name"]
    ds = load_any(args.data, vehicle=vname)
    if args.validation:
        pool, val = ds, load_any(args.validation, vehicle=vname)
        split = f"validation: all of {args.validation}; training: first {args.fraction:.0%} of {args.data}"
    else:
        pool, val = split_by_time(ds, args.val_fraction)
        split = (f"by time: last {args.val_fraction:.0%} of rows validate; training: first {args.fraction:.0%} "
                 f"of the rows before the cut")
    fc = FitConfig(adam_steps=args.adam_steps, lbfgs_iterations=args.lbfgs_iterations, lr=args.lr,
                   batch_size=args.batch_size, weight_decay=args.weight_decay, seed=args.seed)
    cfg = FinetuneConfig(freeze_fraction=args.freeze_fraction, lambda1=args.lambda1, lambda2=args.lambda2,
                         data_fraction=args.fraction, fit=fc)
    model, ckpt = finetune(args.base, pool, val, cfg, source=str(args.data), progress=not args.quiet, split=split)
    ckpt["metrics"]["validation"] = public(evaluate(model, ckpt, val))
    checkpoint.save(ckpt, args.out)
    ft = ckpt["finetune"]
    print(f"fine-tuned in {ckpt['training']['seconds']:.1f} s ({ft['optimizer_steps']['adam']} Adam + "
          f"{ft['optimizer_steps']['lbfgs']} L-BFGS steps), frozen: {', '.join(ft['frozen_layers']) or 'nothing'}; "
          f"best validation loss {ckpt['training']['best_val_loss']:.4e}")
    print("validation: " + format_summary(ckpt["metrics"]["validation"]))
    print(f"wrote {args.out}")
    if args.metrics_json:
        import json

        Path(args.metrics_json).write_text(json.dumps(ckpt["metrics"], indent=2))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("finetune", help="FTHD: fine-tune a pre-trained DDM (frozen first layers, hybrid loss)")
    p.add_argument("--base", required=True, help="pre-trained DDM checkpoint (ddyn train)")
    p.add_argument("--data", required=True, help="fine-tuning dataset of the target car (any supported format)")
    p.add_argument("-o", "--out", required=True, help="checkpoint file to write (kind ddm, with a finetune record)")
    p.add_argument("--validation", help="separate validation dataset (default: the last --val-fraction of --data)")
    p.add_argument("--val-fraction", type=float, default=0.2, help="(default %(default)s)")
    p.add_argument("--fraction", type=float, default=1.0,
                   help="share of the training rows used, from their start (default %(default)s)")
    p.add_argument("--freeze-fraction", type=float, default=0.5,
                   help="share of the layers (GRU, dense, head) frozen from the input side; at least one hidden "
                        "layer and the head stay trainable (default %(default)s)")
    p.add_argument("--lambda1", type=float, default=0.5, help="weight of the supervised loss (default %(default)s)")
    p.add_argument("--lambda2", type=float, default=0.5,
                   help="weight of the derivative term; lambda1 + lambda2 must be 1 (default %(default)s)")
    d = FitConfig()
    p.add_argument("--adam-steps", type=int, default=d.adam_steps, help="(default %(default)s)")
    p.add_argument("--lbfgs-iterations", type=int, default=d.lbfgs_iterations, help="(default %(default)s)")
    p.add_argument("--lr", type=float, default=d.lr, help="(default %(default)s)")
    p.add_argument("--batch-size", type=int, default=d.batch_size, help="(default %(default)s)")
    p.add_argument("--weight-decay", type=float, default=d.weight_decay, help="(default %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="(default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--metrics-json", help="also write the checkpoint's metrics to this JSON file")
    p.set_defaults(func=_run)
