"""Math namespaces: the same few functions for numpy, torch and CasADi.

The vehicle model (ddyn.model.single_track.dynamics) is written once against one of these
namespaces, so a single definition evaluates with numpy (simulation and
analysis), torch (batched, differentiable training) and CasADi (symbolic, for
generated C). Only what the model needs is here; each function keeps the
semantics of the C math library so the three backends agree to rounding.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np


@dataclass(frozen=True)
class MathNamespace:
    name: str
    sin: Callable[[Any], Any]
    cos: Callable[[Any], Any]
    atan: Callable[[Any], Any]
    atan2: Callable[[Any, Any], Any]
    sqrt: Callable[[Any], Any]
    abs: Callable[[Any], Any]
    # fmax(a, b) with b a Python float: elementwise maximum
    fmax: Callable[[Any, float], Any]
    exp: Callable[[Any], Any]
    tanh: Callable[[Any], Any]


NUMPY = MathNamespace(
    name="numpy",
    sin=np.sin,
    cos=np.cos,
    atan=np.arctan,
    atan2=np.arctan2,
    sqrt=np.sqrt,
    abs=np.abs,
    fmax=np.maximum,
    exp=np.exp,
    tanh=np.tanh,
)


def _torch_namespace() -> MathNamespace:
    import torch

    def fmax(a, b: float):
        return torch.clamp(a, min=b)

    return MathNamespace(
        name="torch",
        sin=torch.sin,
        cos=torch.cos,
        atan=torch.atan,
        atan2=torch.atan2,
        sqrt=torch.sqrt,
        abs=torch.abs,
        fmax=fmax,
        exp=torch.exp,
        tanh=torch.tanh,
    )


def _casadi_namespace() -> MathNamespace:
    import casadi as ca

    return MathNamespace(
        name="casadi",
        sin=ca.sin,
        cos=ca.cos,
        atan=ca.atan,
        atan2=ca.atan2,
        sqrt=ca.sqrt,
        abs=ca.fabs,
        fmax=ca.fmax,
        exp=ca.exp,
        tanh=ca.tanh,
    )


_LAZY = {"torch": _torch_namespace, "casadi": _casadi_namespace}
_CACHE: dict[str, MathNamespace] = {"numpy": NUMPY}


def get(name: str) -> MathNamespace:
    """Namespace by backend name ("numpy", "torch", "casadi"); torch and CasADi load on first use."""
    if name not in _CACHE:
        if name not in _LAZY:
            raise ValueError(f"unknown math backend {name!r}; expected one of numpy, torch, casadi")
        _CACHE[name] = _LAZY[name]()
    return _CACHE[name]


# math is used by scalar helpers elsewhere; re-exported so callers need one import
pi = math.pi
