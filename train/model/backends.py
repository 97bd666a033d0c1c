"""Array adapters around the one model: numpy and torch batches, CasADi functions.

The model works on tuples of components; these helpers split arrays of shape
(..., 8), (..., 2), (..., 17) into components, call the model with the right math
namespace, and stack the result back, so callers deal in ordinary arrays.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ddyn.model import integrators, mathns
from ddyn.model.single_track import N_COEFF, N_INPUT, N_STATE, KnownParams, derivatives


def _split(a, n: int, what: str) -> tuple:
    if a.shape[-1] != n:
        raise ValueError(f"{what}: last dimension must be {n}, got shape {tuple(a.shape)}")
    return tuple(a[..., i] for i in range(n))


def _discrete(ns, state, inputs, coeffs, p: KnownParams, dt: float, method: str, substeps: int) -> tuple:
    def f(s):
        return derivatives(ns, s, inputs, coeffs, p)

    return integrators.step(f, state, dt, method, substeps)


def step_numpy(state: np.ndarray, inputs: np.ndarray, coeffs: np.ndarray, p: KnownParams, dt: float,
               method: str = "euler", substeps: int = 1) -> np.ndarray:
    """Next state for a batch (broadcasting over leading dimensions), float64 numpy."""
    out = _discrete(mathns.NUMPY, _split(np.asarray(state, float), N_STATE, "state"),
                    _split(np.asarray(inputs, float), N_INPUT, "inputs"),
                    _split(np.asarray(coeffs, float), N_COEFF, "coeffs"), p, dt, method, substeps)
    return np.stack(np.broadcast_arrays(*out), axis=-1)


def derivatives_numpy(state: np.ndarray, inputs: np.ndarray, coeffs: np.ndarray, p: KnownParams) -> np.ndarray:
    out = derivatives(mathns.NUMPY, _split(np.asarray(state, float), N_STATE, "state"),
                      _split(np.asarray(inputs, float), N_INPUT, "inputs"),
                      _split(np.asarray(coeffs, float), N_COEFF, "coeffs"), p)
    return np.stack(np.broadcast_arrays(*out), axis=-1)


def step_torch(state, inputs, coeffs, p: KnownParams, dt: float, method: str = "euler", substeps: int = 1):
    """Next state for a batch of torch tensors; differentiable in all arguments."""
    import torch

    out = _discrete(mathns.get("torch"), _split(state, N_STATE, "state"), _split(inputs, N_INPUT, "inputs"),
                    _split(coeffs, N_COEFF, "coeffs"), p, dt, method, substeps)
    return torch.stack(torch.broadcast_tensors(*out), dim=-1)


def casadi_symbols() -> tuple[Any, Any, Any]:
    import casadi as ca

    return ca.SX.sym("x", N_STATE), ca.SX.sym("u", N_INPUT), ca.SX.sym("c", N_COEFF)


def casadi_derivatives_expr(x, u, c, p: KnownParams):
    """Symbolic continuous-time derivative (CasADi SX column)."""
    import casadi as ca

    split = lambda v, n: tuple(v[i] for i in range(n))  # noqa: E731
    return ca.vertcat(*derivatives(mathns.get("casadi"), split(x, N_STATE), split(u, N_INPUT), split(c, N_COEFF), p))


def casadi_step_expr(x, u, c, p: KnownParams, dt: float, method: str, substeps: int):
    """Symbolic next state (CasADi SX column) from symbols x (8), u (2), c (17)."""
    import casadi as ca

    ns = mathns.get("casadi")
    split = lambda v, n: tuple(v[i] for i in range(n))  # noqa: E731
    out = _discrete(ns, split(x, N_STATE), split(u, N_INPUT), split(c, N_COEFF), p, dt, method, substeps)
    return ca.vertcat(*out)


def casadi_step_function(p: KnownParams, dt: float, method: str = "euler", substeps: int = 1, name: str = "step"):
    """CasADi Function name(x[8], u[2], c[17]) -> x_next[8]."""
    import casadi as ca

    x, u, c = casadi_symbols()
    return ca.Function(name, [x, u, c], [casadi_step_expr(x, u, c, p, dt, method, substeps)],
                       ["x", "u", "c"], ["x_next"])
