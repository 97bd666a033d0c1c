"""`ddyn study fidelity`: measured agreement of the model's implementations and with the papers' data.

Two checks, each a function the tests assert on and the command prints:
  * backend_agreement: the one model through numpy, torch and CasADi on random
    points of each vehicle's envelope (ddyn.model.sampling), largest relative difference;
  * reproduce_reference: the Euler chain of the 1:43 car fed DYN-PP-ETHZ.npz's first
    state and inputs, largest error against its dstates (vx, vy, omega).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.model import backends
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.sampling import random_cases
from ddyn.paths import shared_data_dir


def _relative_difference(a: np.ndarray, ref: np.ndarray) -> float:
    # relative to each channel's magnitude across the batch: near-zero elements are
    # judged on their channel's scale, not their own
    scale = np.maximum(np.abs(ref).max(axis=0), 1e-300)
    return float((np.abs(a - ref) / scale).max())


def backend_agreement(vehicle_name: str, method: str, n: int = 4000, seed: int = 7) -> dict[str, float]:
    """Largest relative difference of torch and CasADi against numpy over n random cases."""
    import torch

    v = vehicle_mod.load(vehicle_name)
    x, u, c = random_cases(v, n, np.random.default_rng(seed))
    substeps = v.rk4_substeps if method == "rk4" else 1
    ref = backends.step_numpy(x, u, c, v.known, v.sample_time, method, substeps)
    if not np.all(np.isfinite(ref)):
        raise DdynError(f"numpy model returned non-finite values for {vehicle_name}")
    t = backends.step_torch(*(torch.tensor(a, dtype=torch.float64) for a in (x, u, c)),
                            v.known, v.sample_time, method, substeps).numpy()
    f = backends.casadi_step_function(v.known, v.sample_time, method, substeps).map(n)
    cas = np.asarray(f(x.T, u.T, c.T)).T
    return {"torch": _relative_difference(t, ref), "casadi": _relative_difference(cas, ref)}


def euler_chain_from_reference(npz, coeffs: np.ndarray, v) -> np.ndarray:
    """(8, N+1) Euler chain from states[:, 0], using the command inputs[:, k] during step k."""
    states, inputs = npz["states"], npz["inputs"]
    x = np.concatenate([states[:, 0], inputs[:, 0]])
    out = [x]
    for k in range(inputs.shape[1]):
        x = x.copy()
        x[6:] = inputs[:, k]
        x = backends.step_numpy(x, np.zeros(2), coeffs, v.known, v.sample_time, "euler")
        out.append(x)
    return np.array(out).T


def reproduce_reference(coeff_set: str = "reference_dataset", path: Path | None = None) -> dict[str, float]:
    """Largest |error| of vx, vy, omega (and of x, y, yaw) against DYN-PP-ETHZ.npz's dstates."""
    path = path or shared_data_dir() / "reference" / "DYN-PP-ETHZ.npz"
    if not path.is_file():
        raise DdynError(f"reference dataset not found: {path}")
    v = vehicle_mod.load("orca_1_43")
    npz = np.load(path)
    sim = euler_chain_from_reference(npz, v.coefficient_vector(coeff_set), v)
    ds = npz["dstates"]
    # column 0 of dstates stores x, y, yaw as zeros (an artefact): compare from column 1
    err = np.abs(sim[:, 1:] - ds[:, 1:]).max(axis=1)
    return {"vx": err[3], "vy": err[4], "omega": err[5], "pose": float(err[:3].max()), "steps": ds.shape[1] - 1}


def _run(args) -> int:
    print(f"backend agreement, largest relative difference to numpy over {args.cases} random cases:")
    for name in vehicle_mod.available():
        for method in ("euler", "rk4"):
            a = backend_agreement(name, method, args.cases)
            print(f"  {name:10s} {method:5s}  torch {a['torch']:.1e}   casadi {a['casadi']:.1e}")
    print("DYN-PP-ETHZ.npz reproduction (Euler chain, largest |error| over all steps):")
    for coeff_set in ("reference_dataset", "true"):
        r = reproduce_reference(coeff_set)
        print(f"  {coeff_set + ' coefficients':32s} vx {r['vx']:.1e}  vy {r['vy']:.1e}  omega {r['omega']:.1e}"
              f"  pose {r['pose']:.1e}  ({r['steps']} steps)")
    from ddyn.analysis.track2_file import format_report, track2_provenance

    print(format_report(track2_provenance()))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("fidelity", help="measure backend agreement, the DYN-PP-ETHZ reproduction and how DYN-PP-ETHZMobil was made")
    p.add_argument("--cases", type=int, default=4000, help="random cases per vehicle and method")
    p.set_defaults(func=_run)
