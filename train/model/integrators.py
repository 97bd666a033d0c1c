"""Discretisations of a continuous model: explicit Euler (what the papers trained with) and RK4.

Both work on tuples of components (numpy arrays, torch tensors or CasADi SX), so the
discrete step is as backend-independent as the model. Inputs are held constant over
the step (zero-order hold, as the controller applies them).
"""
from __future__ import annotations

from typing import Callable, Sequence

Derivative = Callable[[Sequence], tuple]

DISCRETISATIONS = ("euler", "rk4")


def euler(f: Derivative, state: Sequence, dt: float) -> tuple:
    k = f(state)
    return tuple(s + dt * ki for s, ki in zip(state, k))


def rk4(f: Derivative, state: Sequence, dt: float, substeps: int = 1) -> tuple:
    if substeps < 1:
        raise ValueError(f"rk4 needs at least one sub-step, got {substeps}")
    h = dt / substeps
    s = tuple(state)
    for _ in range(substeps):
        k1 = f(s)
        k2 = f(tuple(si + 0.5 * h * ki for si, ki in zip(s, k1)))
        k3 = f(tuple(si + 0.5 * h * ki for si, ki in zip(s, k2)))
        k4 = f(tuple(si + h * ki for si, ki in zip(s, k3)))
        s = tuple(si + (h / 6.0) * (a + 2.0 * b + 2.0 * c + d)
                  for si, a, b, c, d in zip(s, k1, k2, k3, k4))
    return s


def step(f: Derivative, state: Sequence, dt: float, method: str = "euler", substeps: int = 1) -> tuple:
    """One discrete step of length dt with the named method ("euler" or "rk4")."""
    if method == "euler":
        return euler(f, state, dt)
    if method == "rk4":
        return rk4(f, state, dt, substeps)
    raise ValueError(f"unknown discretisation {method!r}; expected one of {', '.join(DISCRETISATIONS)}")
