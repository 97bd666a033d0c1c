"""The networks: Deep Dynamics (DDM) with its Physics Guard, and the Deep Pacejka baseline (DPM).

Both read a history (batch, tau, 7), held inside the feature range of the windows they were trained and
selected on and then normalised (HistoryEncoder), produce coefficients, and take
one step of the shared single-track model (ddyn.model.single_track via ddyn.model.backends) to
predict the next state. Only the coefficient heads differ:

* DDM: all 17 coefficients through the Physics Guard,
      c = lo + (hi - lo) * sigmoid(z),   ranges [lo, hi] from the vehicle file,
  so every coefficient is physical by construction (a coefficient pinned at a
  bound is reported by evaluation, not hidden).
* DPM (Kim et al., 2022): unbounded Pacejka B, C, D, E per axle and the rear
  longitudinal force Frx estimated directly; Iz given (truth or off by +-20 %);
  no shifts G, K. Its raw outputs start at the middle of the DDM ranges (and Frx
  at 0) so training starts from a sane car; nothing bounds them afterwards.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ddyn.data.windows import FEATURE_NAMES
from ddyn.model import integrators, mathns
from ddyn.model.backends import step_torch
from ddyn.model.single_track import KnownParams, pacejka, rigid_body, slip_angles

# a coefficient within this share of its range's width from a guard bound counts as at the bound (saturated)
SATURATION_TOL = 0.01


def bound_shares(coeffs, lo, hi):
    """Shares of the rows of `coeffs` (numpy, samples x coefficients, or one coefficient's column) at the lower
    and at the upper guard bound: within SATURATION_TOL of the range's width (ddyn evaluate, training restarts)."""
    tol = SATURATION_TOL * (hi - lo)
    return (coeffs <= lo + tol).mean(axis=0), (coeffs >= hi - tol).mean(axis=0)

DPM_OUTPUTS = ("Bf", "Cf", "Df", "Ef", "Br", "Cr", "Dr", "Er", "Frx")


class HistoryEncoder(nn.Module):
    """Hold the history inside its feature range, normalise it, optionally run GRU layers, then Mish-activated
    dense layers.

    The feature range (feature_lo, feature_hi: per feature, the smallest and largest value in the windows the
    network was trained and selected on; set_feature_range) is why a DDM's coefficients do not run away where its
    inputs leave what it has seen: a row beyond it (a faster, more sideways car than in training) gets the
    coefficients of the nearest row it knows, and the physics step, not the network, carries the state past it.
    Measured (issue 36; docs/learning.md "Inputs held to the trained range"): trained below 20 m/s on the real
    Putnam log and scored above, and trained on one track of an independent plant and scored on another. Inside
    the range it is the identity, so it changes no training; an old checkpoint without a range is not held
    (+-inf)."""

    def __init__(self, tau: int, n_features: int, hidden: int, layers: int, gru_layers: int,
                 mean: torch.Tensor, std: torch.Tensor):
        super().__init__()
        self.register_buffer("mean", mean.clone())
        self.register_buffer("std", std.clone())
        self.register_buffer("feature_lo", torch.full_like(mean, -float("inf")))
        self.register_buffer("feature_hi", torch.full_like(mean, float("inf")))
        self.gru = nn.GRU(n_features, hidden, gru_layers, batch_first=True) if gru_layers > 0 else None
        width = hidden if gru_layers > 0 else tau * n_features
        dense: list[nn.Module] = []
        for _ in range(layers):
            dense += [nn.Linear(width, hidden), nn.Mish()]
            width = hidden
        self.dense = nn.Sequential(*dense)
        self.out_width = width

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        h = (torch.clamp(history, self.feature_lo, self.feature_hi) - self.mean) / self.std
        if self.gru is not None:
            h, _ = self.gru(h)
            h = h[:, -1]
        else:
            h = h.flatten(1)
        return self.dense(h)


def set_feature_range(model: nn.Module, *histories, join: bool = False) -> None:
    """model's feature range: per feature, the extremes over every row of the given histories (numpy
    (n, tau, 7) arrays: the training and the validation windows). join: widened to them from the range the
    model holds (a fine-tuned model keeps what its base was trained on; a base without a range, +-inf, stays
    without one) instead of replaced."""
    flat = torch.cat([torch.as_tensor(h).reshape(-1, h.shape[-1]) for h in histories if len(h)])
    enc = model.encoder
    lo, hi = flat.amin(dim=0).to(enc.feature_lo), flat.amax(dim=0).to(enc.feature_hi)
    if join:
        lo, hi = torch.minimum(enc.feature_lo, lo), torch.maximum(enc.feature_hi, hi)
    enc.feature_lo.copy_(lo)
    enc.feature_hi.copy_(hi)


def outside_range_shares(model: nn.Module, history) -> dict | None:
    """Where a history leaves the model's feature range: the share of samples with any feature outside it, and per
    feature (numpy (n, tau, 7) raw histories); None for a model without a range (a checkpoint from before it)."""
    enc = model.encoder
    lo, hi = enc.feature_lo.detach().cpu().numpy(), enc.feature_hi.detach().cpu().numpy()
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or len(history) == 0:
        return None
    out = (history < lo) | (history > hi)            # (n, tau, 7)
    per_feature = out.any(axis=1).mean(axis=0)
    return {"any": float(out.any(axis=(1, 2)).mean()), "features": dict(zip(FEATURE_NAMES, map(float, per_feature)))}


class DeepDynamics(nn.Module):
    kind = "ddm"

    def __init__(self, tau: int, hidden: int, layers: int, gru_layers: int, mean, std, lo, hi,
                 known: KnownParams, sample_time: float, method: str = "euler", substeps: int = 1):
        super().__init__()
        self.encoder = HistoryEncoder(tau, mean.shape[-1], hidden, layers, gru_layers, mean, std)
        self.head = nn.Linear(self.encoder.out_width, lo.shape[-1])
        self.register_buffer("lo", lo.clone())
        self.register_buffer("hi", hi.clone())
        self.known, self.sample_time, self.method, self.substeps = known, sample_time, method, substeps

    def logits(self, history: torch.Tensor) -> torch.Tensor:
        """The guard's inputs z (0: the middle of a range; |z| >= 4.6: within 1 % of a bound)."""
        return self.head(self.encoder(history))

    def coefficients(self, history: torch.Tensor) -> torch.Tensor:
        """The Physics Guard: every coefficient inside its nominal range."""
        return self.guard(self.logits(history))

    def guard(self, z: torch.Tensor) -> torch.Tensor:
        return self.lo + (self.hi - self.lo) * torch.sigmoid(z)

    def step(self, state: torch.Tensor, inputs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        return step_torch(state, inputs, coeffs, self.known, self.sample_time, self.method, self.substeps)

    def forward(self, history, state, inputs):
        c = self.coefficients(history)
        return self.step(state, inputs, c), c

    def forward_with_logits(self, history, state, inputs):
        """forward's prediction and coefficients, and the guard's logits (for TrainConfig.guard_prior)."""
        z = self.logits(history)
        c = self.guard(z)
        return self.step(state, inputs, c), c, z


class DeepPacejka(nn.Module):
    kind = "dpm"

    def __init__(self, tau: int, hidden: int, layers: int, gru_layers: int, mean, std, init: torch.Tensor,
                 iz: float, known: KnownParams, sample_time: float, method: str = "euler", substeps: int = 1):
        super().__init__()
        self.encoder = HistoryEncoder(tau, mean.shape[-1], hidden, layers, gru_layers, mean, std)
        self.head = nn.Linear(self.encoder.out_width, len(DPM_OUTPUTS))
        with torch.no_grad():
            self.head.bias.copy_(init)
        self.iz = float(iz)
        self.known, self.sample_time, self.method, self.substeps = known, sample_time, method, substeps

    def coefficients(self, history: torch.Tensor) -> torch.Tensor:
        return self.head(self.encoder(history))

    def step(self, state: torch.Tensor, inputs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        ns = mathns.get("torch")
        Bf, Cf, Df, Ef, Br, Cr, Dr, Er, Frx = coeffs.unbind(-1)
        zero = torch.zeros_like(Bf)
        u = inputs.unbind(-1)

        def f(s):
            _, _, _, vx, vy, omega, _, delta = s
            alpha_f, alpha_r = slip_angles(ns, vx, vy, omega, delta, zero, zero, self.known)
            Ffy = pacejka(ns, alpha_f, Bf, Cf, Df, Ef, zero)
            Fry = pacejka(ns, alpha_r, Br, Cr, Dr, Er, zero)
            return rigid_body(ns, s, u, Ffy, Fry, Frx, self.iz, self.known)

        out = integrators.step(f, state.unbind(-1), self.sample_time, self.method, self.substeps)
        return torch.stack(out, dim=-1)

    def forward(self, history, state, inputs):
        c = self.coefficients(history)
        return self.step(state, inputs, c), c
