"""EKF-FTHD's filter as a network layer: an extended Kalman filter and RTS smoother over the logged
velocities, with process and measurement noise learned through bounded guards.

State. The filter's state is s = (vx, vy, omega). Throttle T, steering delta and their rates
(dT, ddelta) are known inputs (the logged commands; they carry no measurement noise in the
simulator and are the actuator commands on the car). Position and yaw are *excluded*: the
velocity dynamics of the single-track model do not depend on x, y or yaw (the model is
invariant to translation and rotation; x, y, yaw are integrals of the velocities), so the
3-state filter is the exact velocity sub-system and the 5 extra states would only matter with
position/heading measurements, which add no useful velocity information here (1:43 car:
position noise 2 mm over a 20 ms step is 0.14 m/s of velocity noise against a 0.01 m/s vx
sensor; AV-21 log: the position carries 0.4 m GNSS correction jumps). Position and yaw are
carried through unchanged by `ddyn denoise`.

Model. s_{k+1} = f(s_k; T_k, delta_k, dT_k, ddelta_k, c_k) + w_k is one step of the shared
single-track model (ddyn.model.backends.step_torch, the discretisation of the checkpoint or of the
caller's choice), velocities taken from the full 8-state step. Coefficients c_k (17 per
sample) come from a DDM checkpoint (its Physics Guard's estimate per sample) or from a vehicle
file's true coefficients. The measurement is the identity: z_k = s_k + v_k.

Jacobian. F_k = df/ds is computed by torch autograd of step_torch, batched over all time steps
at once: rows are independent, so the gradient of sum_k f_i(s_k) with respect to the stacked
states is row k's i-th Jacobian row (three backward passes for the 3x3 Jacobians of a whole
log; `create_graph` when the coefficients are being learned, so gradients flow through F).
`jacobian_torchfunc` (torch.func.vmap(jacfwd)) gives the same values and is used by the tests.

Linearisation. Two modes share one recursion:
  "filtered"  the textbook EKF: f and F evaluated at the filtered estimate s_{k|k}, step by step
              (sequential model evaluations, batched over independent chunks only);
  "nominal"   f and F evaluated once, batched over time, along a nominal trajectory sbar
              (s_{k+1|k} = f(sbar_k) + F_k (s_{k|k} - sbar_k)); with sbar = the previous
              smoother pass this is the iterated extended Kalman smoother (a Gauss-Newton step
              on the MAP trajectory per iteration), and with sbar_k = s_{k|k} it is the EKF.
`ddyn denoise` uses "nominal", starting from a Savitzky-Golay pre-smoothed trajectory and
relinearising about the smoothed estimate. The recursion itself is sequential over time
and batched over independent chunks (segments, or pieces of segments while learning).

Noise guards. Q = diag(q), R = diag(r) (variances per sample, (m/s)^2 and (rad/s)^2), each
component  q_i = exp(log lo_i + (log hi_i - log lo_i) sigmoid(z_i))  ("log" scaling, the default:
the ranges span decades and a linear sigmoid could barely reach their lower end) or
q_i = lo_i + (hi_i - lo_i) sigmoid(z_i) ("linear", the paper's form). Either way the value lies
inside [lo, hi] for every z. `default_ranges(vehicle)` scales the ranges to the vehicle's
sensor noise sigma (vehicle file `sensor_noise_std`):
    R in [(sigma / 10)^2, (10 sigma)^2]         (a decade either side of the nominal sensor noise)
    Q in [(sigma / 1000)^2, (10 sigma)^2]       (from "the model is near exact" to "a random walk
                                                 as noisy as the sensor")
1:43 car (sigma = 0.01 m/s, 0.005 m/s, 0.05 rad/s): R vx 1e-6..1e-2, vy 2.5e-7..2.5e-3,
omega 2.5e-5..0.25; Q vx 1e-10..1e-2, vy 2.5e-11..2.5e-3, omega 2.5e-9..0.25. AV-21 (sigma =
0.05 m/s, 0.02 m/s, 0.005 rad/s): R vx 2.5e-5..0.25, vy 4e-6..0.04, omega 2.5e-7..2.5e-3; Q from
2.5e-9, 4e-10, 2.5e-11 to the same upper ends. The paper's real-car ranges (Q 0.1-1, R 0.01-1,
linear) are `PAPER_REAL_RANGES` (`ddyn denoise --q-range 0.1 1 --r-range 0.01 1 --range-scale
linear`); for the Putnam log's velocities, which come out of the car's own 100 Hz EKF, they
would force a measurement noise of at least 0.1 m/s and 0.1 rad/s, far above its apparent noise.

Objective. The negative log-likelihood of the innovations (prediction-error decomposition of
the linearised state-space model):
    NLL = 1/N sum_k [ 1/2 log det S_k + 1/2 nu_k' S_k^-1 nu_k + 3/2 log 2 pi ],
    nu_k = z_k - s_{k|k-1},   S_k = P_{k|k-1} + R,
over every sample but the first of each chunk (a diffuse prior: s_{0|0} = z_0, P_{0|0} = R, the
exact limit of an infinitely wide prior, whose first innovation carries no information).
Minimising it over the guards' logits (and optionally the DDM head or all its weights) is
maximum likelihood for Q and R (and the model): too small a Q makes the innovations larger than
S predicts, too large a Q or R inflates log det S. While learning, segments are cut into chunks
filtered in parallel (each with its own diffuse start, so the objective is the sum of the
chunks' exact likelihoods); chunks are padded at the end, and padded samples neither step,
update nor count.

Coloured noise (option). EKFLayer(coloured=True) adds an AR(1) noise state per channel (see
the class); the measurement is then z = s + c + v, and the physical part is s alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ddyn.errors import DdynError
from ddyn.model.backends import step_torch
from ddyn.model.single_track import KnownParams

CHANNELS = ("vx", "vy", "omega")
EXOGENOUS = ("throttle", "steering", "dthrottle", "dsteering")
LINEARISATIONS = ("nominal", "filtered")
LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class NoiseRanges:
    """Ranges of the diagonal process (q) and measurement (r) variances, per channel vx, vy, omega."""

    q_lo: tuple[float, float, float]
    q_hi: tuple[float, float, float]
    r_lo: tuple[float, float, float]
    r_hi: tuple[float, float, float]
    scale: str = "log"                 # "log" or "linear" sigmoid scaling inside the range

    def __post_init__(self):
        if self.scale not in ("log", "linear"):
            raise DdynError(f"noise range scale must be log or linear, got {self.scale!r}")
        for name in ("q", "r"):
            lo, hi = getattr(self, f"{name}_lo"), getattr(self, f"{name}_hi")
            if len(lo) != 3 or len(hi) != 3:
                raise DdynError(f"{name.upper()} range needs 3 values per bound (vx, vy, omega)")
            for c, a, b in zip(CHANNELS, lo, hi):
                if not (0 < a < b and math.isfinite(b)):
                    raise DdynError(f"{name.upper()} range of {c} must satisfy 0 < lo < hi, got [{a}, {b}]")

    def as_dict(self) -> dict:
        return {"q_lo": list(self.q_lo), "q_hi": list(self.q_hi), "r_lo": list(self.r_lo),
                "r_hi": list(self.r_hi), "scale": self.scale, "channels": list(CHANNELS)}

    @staticmethod
    def uniform(q: tuple[float, float], r: tuple[float, float], scale: str = "log") -> "NoiseRanges":
        """The same range for all three channels."""
        return NoiseRanges((q[0],) * 3, (q[1],) * 3, (r[0],) * 3, (r[1],) * 3, scale)


# Xiao et al. (EKF-FTHD) on the real full-scale car
PAPER_REAL_RANGES = NoiseRanges.uniform((0.1, 1.0), (0.01, 1.0), scale="linear")
R_DECADES = 1.0     # R within a factor 10**R_DECADES of the sensor's std either way
Q_DECADES_BELOW = 3.0
Q_DECADES_ABOVE = 1.0


def default_ranges(vehicle) -> NoiseRanges:
    """Q and R ranges scaled to the vehicle's sensor noise (see the module docstring for the rule)."""
    try:
        sigma = np.array([vehicle.sensor_noise_std[c] for c in CHANNELS], dtype=float)
    except KeyError as e:
        raise DdynError(f"vehicle {vehicle.name!r} has no sensor_noise_std for {e.args[0]}; "
                        "give the Q and R ranges explicitly") from None
    var = sigma ** 2
    return NoiseRanges(tuple(var * 10 ** (-2 * Q_DECADES_BELOW)), tuple(var * 10 ** (2 * Q_DECADES_ABOVE)),
                       tuple(var * 10 ** (-2 * R_DECADES)), tuple(var * 10 ** (2 * R_DECADES)))


class BoundedDiagonal(nn.Module):
    """A positive diagonal kept inside [lo, hi] by a sigmoid guard (in log or linear scale)."""

    def __init__(self, lo, hi, scale: str = "log", init=None, dtype=torch.float64):
        super().__init__()
        lo = torch.as_tensor(np.asarray(lo, dtype=float), dtype=dtype)
        hi = torch.as_tensor(np.asarray(hi, dtype=float), dtype=dtype)
        if scale not in ("log", "linear"):
            raise DdynError(f"scale must be log or linear, got {scale!r}")
        self.scale = scale
        self.register_buffer("lo", lo)
        self.register_buffer("hi", hi)
        self.logit = nn.Parameter(torch.zeros_like(lo))
        if init is not None:
            self.set(init)

    def _bounds(self):
        return (self.lo.log(), self.hi.log()) if self.scale == "log" else (self.lo, self.hi)

    def forward(self) -> torch.Tensor:
        a, b = self._bounds()
        v = a + (b - a) * torch.sigmoid(self.logit)
        return v.exp() if self.scale == "log" else v

    @torch.no_grad()
    def set(self, value) -> None:
        """Set the logits so that forward() returns `value` (clipped just inside the range)."""
        value = torch.as_tensor(np.asarray(value, dtype=float), dtype=self.lo.dtype).expand_as(self.lo)
        a, b = self._bounds()
        v = value.log() if self.scale == "log" else value
        frac = ((v - a) / (b - a)).clamp(1e-6, 1 - 1e-6)
        self.logit.copy_(torch.log(frac) - torch.log1p(-frac))


def velocity_step(s: torch.Tensor, exo: torch.Tensor, coeffs: torch.Tensor, known: KnownParams, dt: float,
                  method: str = "euler", substeps: int = 1) -> torch.Tensor:
    """Next (vx, vy, omega) from (..., 3) velocities, (..., 4) known inputs T, delta, dT, ddelta and
    (..., 17) coefficients: one step of the shared model (position and yaw set to zero: they do
    not enter the velocity dynamics)."""
    zeros = torch.zeros(s.shape[:-1] + (3,), dtype=s.dtype)
    state = torch.cat([zeros, s, exo[..., :2]], dim=-1)
    return step_torch(state, exo[..., 2:], coeffs, known, dt, method, substeps)[..., 3:6]


def linearise(s: torch.Tensor, exo: torch.Tensor, coeffs: torch.Tensor, known: KnownParams, dt: float,
              method: str = "euler", substeps: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """f(s) (..., 3) and its Jacobian df/ds (..., 3, 3), batched over all leading dimensions.

    Torch autograd of step_torch: samples are independent, so d(sum_k f_i(s_k))/ds_k is row i
    of sample k's Jacobian. When gradients are enabled (learning), the graph is kept so that
    F differentiates with respect to the coefficients and everything upstream of s.
    """
    grad_mode = torch.is_grad_enabled() and any(t.requires_grad for t in (s, exo, coeffs))
    with torch.enable_grad():
        x = s if (s.requires_grad and grad_mode) else s.detach().requires_grad_(True)
        f = velocity_step(x, exo, coeffs, known, dt, method, substeps)
        rows = [torch.autograd.grad(f[..., i].sum(), x, retain_graph=True, create_graph=grad_mode)[0]
                for i in range(3)]
    F = torch.stack(rows, dim=-2)
    if not grad_mode:
        f, F = f.detach(), F.detach()
    return f, F


def jacobian_torchfunc(s, exo, coeffs, known: KnownParams, dt: float, method: str = "euler", substeps: int = 1):
    """The same Jacobians with torch.func.vmap(jacfwd) over a flat batch (a cross-check)."""
    from torch.func import jacfwd, vmap

    def one(a, b, c):
        return velocity_step(a, b, c, known, dt, method, substeps)

    return vmap(jacfwd(one))(s, exo, coeffs)


@dataclass
class FilterResult:
    filtered: torch.Tensor        # (B, L, n) x_{k|k}  (n = 3: vx, vy, omega; 6 with coloured-noise states)
    P_filtered: torch.Tensor      # (B, L, n, n)
    predicted: torch.Tensor       # (B, L, n) x_{k|k-1} (row 0: the initial estimate)
    P_predicted: torch.Tensor     # (B, L, n, n)
    innovations: torch.Tensor     # (B, L, 3) z_k - H x_{k|k-1} (row 0: zero)
    S: torch.Tensor               # (B, L, 3, 3) innovation covariance
    F: torch.Tensor               # (B, L, n, n) transition Jacobian used for the step k -> k+1
    nll_terms: torch.Tensor       # (B, L) per-sample NLL (0 where masked and at row 0)
    counted: torch.Tensor         # (B, L) 1 where the sample enters the NLL
    smoothed: torch.Tensor | None = None     # (B, L, 3) RTS estimate
    P_smoothed: torch.Tensor | None = None

    @property
    def physical(self) -> torch.Tensor:
        """The smoothed (filtered if not smoothed) vx, vy, omega (B, L, 3)."""
        return (self.smoothed if self.smoothed is not None else self.filtered)[..., :3]

    @property
    def nll(self) -> torch.Tensor:
        return self.nll_terms.sum() / self.counted.sum().clamp(min=1)


class EKFLayer(nn.Module):
    """EKF + RTS smoother over (vx, vy, omega) with guarded, learnable diagonal Q and R.

    coloured=True augments the state with one first-order Gauss-Markov (AR(1)) measurement-noise
    state per channel, c_{k+1} = phi c_k + e_k, measured as z = s + c + v (H = [I I]); phi and the
    stationary variance of c are learned through guards too (phi in phi_range, linear; the
    variance in the R range). Off by default: the plain filter has identity measurement.
    """

    def __init__(self, known: KnownParams, sample_time: float, ranges: NoiseRanges, method: str = "euler",
                 substeps: int = 1, q_init=None, r_init=None, dtype=torch.float64, coloured: bool = False,
                 phi_range: tuple[float, float] = (0.0, 0.98)):
        super().__init__()
        self.known, self.sample_time, self.method, self.substeps = known, float(sample_time), method, substeps
        self.ranges = ranges
        self.q = BoundedDiagonal(ranges.q_lo, ranges.q_hi, ranges.scale, q_init, dtype)
        self.r = BoundedDiagonal(ranges.r_lo, ranges.r_hi, ranges.scale, r_init, dtype)
        self.coloured = bool(coloured)
        if self.coloured:
            self.phi = BoundedDiagonal((phi_range[0],) * 3, (phi_range[1],) * 3, "linear", dtype=dtype)
            self.c = BoundedDiagonal(ranges.r_lo, ranges.r_hi, ranges.scale, r_init, dtype)
        self.n = 6 if self.coloured else 3

    def Q(self) -> torch.Tensor:
        return torch.diag(self.q())

    def R(self) -> torch.Tensor:
        return torch.diag(self.r())

    def linearise(self, s, exo, coeffs):
        return linearise(s, exo, coeffs, self.known, self.sample_time, self.method, self.substeps)

    def forward(self, z: torch.Tensor, exo: torch.Tensor, coeffs: torch.Tensor, nominal: torch.Tensor | None = None,
                mask: torch.Tensor | None = None, linearisation: str = "nominal", smooth: bool = True,
                joseph: bool = True) -> FilterResult:
        """Filter (and smooth) measurements z (B, L, 3) with known inputs exo (B, L, 4) and
        coefficients (B, L, 17). mask (B, L): 1 for real samples, 0 for padding at the end of a
        chunk (no update, no likelihood). nominal (B, L, 3): the linearisation trajectory for
        "nominal" (default: the measurements)."""
        if linearisation not in LINEARISATIONS:
            raise DdynError(f"linearisation must be one of {', '.join(LINEARISATIONS)}, got {linearisation!r}")
        B, L, _ = z.shape
        dtype = z.dtype
        n = self.n
        if mask is None:
            mask = torch.ones(B, L, dtype=dtype)
        mask = mask.to(dtype)
        Q, R = self.Q(), self.R()
        eye_n = torch.eye(n, dtype=dtype)
        if self.coloured:
            phi, cvar = self.phi(), self.c()
            H = torch.cat([torch.eye(3, dtype=dtype)] * 2, dim=1)
            Qa = torch.block_diag(Q, torch.diag(cvar * (1 - phi ** 2)))
            C = torch.diag(cvar)
            P = torch.cat([torch.cat([R + C, -C], 1), torch.cat([-C, C], 1)], 0).expand(B, n, n)
            x = torch.cat([z[:, 0], torch.zeros_like(z[:, 0])], dim=1)
        else:
            H, Qa = torch.eye(3, dtype=dtype), Q
            P = R.expand(B, 3, 3)
            x = z[:, 0]
        # diffuse start: s_{0|0} = z_0 (white: P_{0|0} = R; coloured: c_0 ~ N(0, C) stationary)
        if linearisation == "nominal":
            xbar = z if nominal is None else nominal
            fbar, Fbar = self.linearise(xbar, exo, coeffs)
        Ht = H.transpose(0, 1)
        xf, Pf, xp, Pp, nus, Ss, Fs, terms = [x], [P], [x], [P], [torch.zeros_like(z[:, 0])], \
            [H @ P @ Ht + R], [], [torch.zeros(B, dtype=dtype)]
        for k in range(L - 1):
            s = x[:, :3]
            if linearisation == "nominal":
                F = Fbar[:, k]
                s_pred = fbar[:, k] + (F @ (s - xbar[:, k]).unsqueeze(-1)).squeeze(-1)
            else:
                s_pred, F = self.linearise(s, exo[:, k], coeffs[:, k])
            if self.coloured:
                A = torch.zeros(B, n, n, dtype=dtype)
                A[:, :3, :3] = F
                A[:, 3:, 3:] = torch.diag(phi)
                x_pred = torch.cat([s_pred, x[:, 3:] * phi], dim=1)
            else:
                A, x_pred = F, s_pred
            # padding (mask 0) holds the last estimate: no step, no process noise, no update
            m = mask[:, k + 1]
            live = m[:, None] > 0
            x_pred = torch.where(live, x_pred, x)
            A = torch.where(live[:, :, None], A, eye_n)
            z_pred = x_pred[:, :3] + x_pred[:, 3:] if self.coloured else x_pred
            Fs.append(A)
            P_pred = A @ P @ A.transpose(-1, -2) + m[:, None, None] * Qa
            P_pred = 0.5 * (P_pred + P_pred.transpose(-1, -2))
            nu = (z[:, k + 1] - z_pred) * m[:, None]
            PHt = P_pred @ Ht
            S = H @ PHt + R
            S_chol, _ = torch.linalg.cholesky_ex(S)
            Sinv_nu = torch.cholesky_solve(nu.unsqueeze(-1), S_chol).squeeze(-1)
            logdet = 2.0 * torch.log(torch.diagonal(S_chol, dim1=-2, dim2=-1)).sum(-1)
            terms.append(m * 0.5 * (logdet + (nu * Sinv_nu).sum(-1) + 3 * LOG_2PI))
            # K = P H' S^-1  ->  K' = S^-1 H P  (S, P symmetric)
            K = torch.cholesky_solve(PHt.transpose(-1, -2), S_chol).transpose(-1, -2) * m[:, None, None]
            x = x_pred + (K @ nu.unsqueeze(-1)).squeeze(-1)
            IKH = eye_n - K @ H
            if joseph:
                P = IKH @ P_pred @ IKH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)
            else:
                P = IKH @ P_pred
            P = 0.5 * (P + P.transpose(-1, -2))
            xf.append(x), Pf.append(P), xp.append(x_pred), Pp.append(P_pred), nus.append(nu)
            Ss.append(S)
        Fs.append(eye_n.expand(B, n, n))   # no step after the last sample
        counted = mask.clone()
        counted[:, 0] = 0
        res = FilterResult(torch.stack(xf, 1), torch.stack(Pf, 1), torch.stack(xp, 1), torch.stack(Pp, 1),
                           torch.stack(nus, 1), torch.stack(Ss, 1), torch.stack(Fs, 1), torch.stack(terms, 1),
                           counted)
        if smooth:
            res.smoothed, res.P_smoothed = rts_smooth(res)
        return res


def rts_smooth(res: FilterResult) -> tuple[torch.Tensor, torch.Tensor]:
    """Rauch-Tung-Striebel backward pass over a FilterResult (padding at the end is harmless: padded
    samples have no update, so their smoothing correction is zero)."""
    L = res.filtered.shape[1]
    xs, Ps = res.filtered[:, -1], res.P_filtered[:, -1]
    out_x, out_P = [xs], [Ps]
    for k in range(L - 2, -1, -1):
        Pf, F = res.P_filtered[:, k], res.F[:, k]
        Pp_next = res.P_predicted[:, k + 1]
        chol, _ = torch.linalg.cholesky_ex(Pp_next)
        # G = Pf F' Pp^-1  ->  G' = Pp^-1 F Pf
        G = torch.cholesky_solve(F @ Pf, chol).transpose(-1, -2)
        xs = res.filtered[:, k] + (G @ (xs - res.predicted[:, k + 1]).unsqueeze(-1)).squeeze(-1)
        Ps = Pf + G @ (Ps - Pp_next) @ G.transpose(-1, -2)
        Ps = 0.5 * (Ps + Ps.transpose(-1, -2))
        out_x.append(xs)
        out_P.append(Ps)
    return torch.stack(out_x[::-1], 1), torch.stack(out_P[::-1], 1)


# ----------------------------------------------------------------------------- chunking

def chunk_index(segment: np.ndarray, length: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Index (B, L) of rows and mask (B, L) that cut every segment into chunks of `length` rows
    (None: whole segments; a 1-row remainder joins the chunk before it, a 1-row segment is left
    out: it holds no transition), padded at the end by repeating the chunk's last row."""
    segment = np.asarray(segment)
    bounds = np.flatnonzero(np.diff(segment) != 0) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [len(segment)]])
    pieces = []
    for a, b in zip(starts, ends):
        step = (b - a) if length is None else max(2, int(length))
        for c in range(a, b, step):
            d = min(c + step, b)
            if d - c >= 2:
                pieces.append((c, d))
            elif c > a:                      # a 1-row remainder joins the chunk before it
                pieces[-1] = (pieces[-1][0], d)
    if not pieces:
        raise DdynError("no chunk of at least 2 rows to filter")
    L = max(d - c for c, d in pieces)
    idx = np.empty((len(pieces), L), dtype=np.int64)
    mask = np.zeros((len(pieces), L))
    for i, (c, d) in enumerate(pieces):
        idx[i, :d - c] = np.arange(c, d)
        idx[i, d - c:] = d - 1
        mask[i, :d - c] = 1.0
    return idx, mask


def scatter_back(values: np.ndarray, idx: np.ndarray, mask: np.ndarray, n: int) -> np.ndarray:
    """Rows (B, L, ...) back to (n, ...) in dataset order (padding dropped)."""
    out = np.zeros((n,) + values.shape[2:])
    keep = mask > 0
    out[idx[keep]] = values[keep]
    return out


@dataclass
class FitResult:
    nll_history: list[float]
    q: np.ndarray
    r: np.ndarray
    iterations: int


def fit_noise(layer: EKFLayer, z, exo, coeff_fn, nominal, mask, iterations: int = 40, lr: float = 0.05,
              extra_params=(), extra_lr: float = 1e-3, linearisation: str = "nominal",
              tol: float = 1e-9) -> FitResult:
    """Minimise the innovation NLL over the guards' logits (and `extra_params`, e.g. a DDM head).

    Q and R alone (6 logits): full-batch L-BFGS (strong Wolfe line search), `iterations` outer
    steps of at most 5 evaluations each. With extra parameters: Adam for `iterations` steps (lr
    for the logits, extra_lr for the rest). coeff_fn() returns the coefficients (B, L, 17); it is
    called at every evaluation, so a DDM head being fine-tuned is re-evaluated. The parameters
    with the lowest NLL seen are kept. The NLL history holds the objective at the start, after
    every step, and (last) the value kept.
    """
    extra = [p for p in extra_params if p.requires_grad]

    def objective():
        res = layer(z, exo, coeff_fn(), nominal=nominal, mask=mask, linearisation=linearisation, smooth=False)
        if not torch.isfinite(res.nll):
            raise DdynError("innovation NLL became non-finite")
        return res.nll

    params = list(layer.parameters()) + extra
    best = [float("inf"), None]

    def remember(value: float):
        if value < best[0]:
            best[0], best[1] = value, [p.detach().clone() for p in params]

    hist: list[float] = []
    with torch.no_grad():
        hist.append(float(objective()))
    remember(hist[0])
    if extra:
        opt = torch.optim.Adam([{"params": list(layer.parameters()), "lr": lr}, {"params": extra, "lr": extra_lr}])
        for it in range(iterations):
            opt.zero_grad()
            loss = objective()
            if it > 0:
                hist.append(float(loss.detach()))
                remember(hist[-1])
            loss.backward()
            opt.step()
        with torch.no_grad():
            hist.append(float(objective()))
        remember(hist[-1])
    else:
        opt = torch.optim.LBFGS(list(layer.parameters()), lr=1.0, max_iter=5, history_size=20,
                                tolerance_grad=1e-12, tolerance_change=tol, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = objective()
            loss.backward()
            return loss

        for _ in range(iterations):
            opt.step(closure)
            with torch.no_grad():
                hist.append(float(objective()))
            remember(hist[-1])
            if abs(hist[-2] - hist[-1]) < tol * max(1.0, abs(hist[-1])):
                break
    # keep the best parameters seen (a fresh optimiser may overshoot a point that is already good)
    with torch.no_grad():
        for p, v in zip(params, best[1]):
            p.copy_(v)
    hist.append(best[0])
    return FitResult(hist, layer.q().detach().numpy().copy(), layer.r().detach().numpy().copy(), len(hist) - 1)
