"""`ddyn bench make-net` and `ddyn bench large-net`: the cost of a large guard network.

* `make_net`: a random-initialised DDM of a chosen size (about 100k parameters by default),
  saved as a normal checkpoint whose input normalisation comes from a dataset, so that
  `ddyn export` turns it into C tables and `ddyn bench runtime` times it against PyTorch. The
  weights are random: the point is the cost of inference at that size, not its accuracy.
* `large_net_bench`: make, export, build and time such a network, alone and inside the
  closed-loop controller step.
"""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import torch

from ddyn.bench.controller import format_controller, run_controller
from ddyn.bench.runtime import format_table
from ddyn.bench.runtime import run as run_runtime_bench
from ddyn.data.importers import load_any
from ddyn.data.windows import features
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn.training import TrainConfig, TrainResult, build_model
from ddyn.model import vehicle as vehicle_mod
from ddyn.paths import REPO


def parameter_count(tau: int, hidden: int, layers: int, gru_layers: int, n_out: int = 17, n_feat: int = 7) -> int:
    """Trainable parameters of a DDM of this shape (what export.json reports)."""
    n, width = 0, tau * n_feat
    for layer in range(gru_layers):
        inp = n_feat if layer == 0 else hidden
        n += 3 * hidden * (inp + hidden) + 6 * hidden
        width = hidden
    for _ in range(layers):
        n += hidden * width + hidden
        width = hidden
    return n + n_out * width + n_out


def make_net(out: str | Path, data: str | Path, tau: int, hidden: int, layers: int, gru_layers: int,
             seed: int = 0, vehicle: str = "orca_1_43") -> tuple[Path, int]:
    """Write a random-initialised DDM checkpoint; returns its path and parameter count."""
    torch.manual_seed(seed)
    v = vehicle_mod.load(vehicle)
    ds = load_any(data, vehicle=vehicle)
    f = features(ds)
    mean, std = f.mean(axis=0), np.maximum(f.std(axis=0), 1e-6)
    cfg = TrainConfig(tau=tau, hidden=hidden, layers=layers, gru_layers=gru_layers, seed=seed, dtype="float32")
    model = build_model(cfg, v, mean, std)
    n = int(sum(p.numel() for p in model.parameters()))
    ckpt = checkpoint.make(TrainResult(model, cfg, np.ones(3), [], 0.0, 0.0), v, "random-init",
                           f"ddyn bench make-net (random weights, seed {seed}; normalisation of {data})",
                           len(ds))
    return checkpoint.save(ckpt, out), n


def build_for(ckpt: str | Path, directory: str | Path) -> Path:
    """`ddyn export` the checkpoint into directory/export and build the C side against it in
    directory/build (one build per network: the shapes are compile-time constants)."""
    from ddyn.learn.export import export

    directory = Path(directory).resolve()
    export(ckpt, directory / "export", torch_export=False)
    build = directory / "build"
    for cmd in (["cmake", "-S", str(REPO), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release", "-DDDYN_BUILD_TESTS=OFF",
                 f"-DDDYN_NET_EXPORT_DIR={directory / 'export'}"],
                ["cmake", "--build", str(build), "-j2", "--target", "ddyn_bench", "ddyn_controller_bench"]):
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise DdynError(f"{' '.join(cmd[:2])} failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    return build / "c_src"


def large_net_bench(directory: str | Path, data: str | Path | None, tau: int, hidden: int, layers: int,
                    gru_layers: int, n: int, n_python: int, steps: int) -> dict:
    """A random DDM of the given shape: C inference against PyTorch (`ddyn bench runtime`), and the whole
    controller step in closed loop with that network."""
    from ddyn.data.dataset import write_canonical
    from ddyn.data.simulate import simulate

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if data is None:  # the histories and the normalisation come from a simulated run on ETHZ
        data = write_canonical(simulate("orca_1_43", "ethz", laps=2, seed=1, noise_scale=1.0, progress=False), directory / "data.csv")
    ckpt, count = make_net(directory / "net.ckpt", data, tau, hidden, layers, gru_layers)
    tools = build_for(ckpt, directory)
    torch.set_num_threads(1)
    r = run_runtime_bench(str(ckpt), str(data), n, n_python, tools / "ddyn_bench")
    r["controller"] = run_controller(tools / "ddyn_controller_bench", steps)
    r["shape"] = {"tau": tau, "hidden": hidden, "layers": layers, "gru_layers": gru_layers, "parameters": count}
    return r


def _make_net(args) -> int:
    path, n = make_net(args.out, args.data, args.tau, args.hidden, args.layers, args.gru_layers, args.seed)
    print(f"wrote {path}: {n} parameters")
    return 0


def _large_net(args) -> int:
    r = large_net_bench(args.dir, args.data, args.tau, args.hidden, args.layers, args.gru_layers, args.n,
                        args.n_python, args.steps)
    print(f"network: {r['shape']}")
    print(format_table(r))
    print(format_controller(r["controller"]))
    if args.out:
        Path(args.out).write_text(json.dumps(r, indent=2) + "\n")
    return 0


def register(subparsers) -> None:
    m = subparsers.add_parser("make-net", help="write a random-initialised DDM checkpoint of a chosen size")
    m.add_argument("--data", required=True, help="dataset whose feature mean/std become the normalisation")
    m.add_argument("-o", "--out", required=True)
    m.add_argument("--tau", type=int, default=5)
    m.add_argument("--hidden", type=int, default=137)
    m.add_argument("--layers", type=int, default=2)
    m.add_argument("--gru-layers", type=int, default=1)
    m.add_argument("--seed", type=int, default=0)
    m.set_defaults(func=_make_net)
    b = subparsers.add_parser("large-net", help="make, export, build and time a ~100k-parameter guard network")
    b.add_argument("--dir", default=str(REPO / "build-net100k"), help="working folder (default %(default)s)")
    b.add_argument("--data", help="dataset for histories and normalisation (default: a simulated ETHZ run)")
    b.add_argument("--tau", type=int, default=5)
    b.add_argument("--hidden", type=int, default=210)
    b.add_argument("--layers", type=int, default=3)
    b.add_argument("--gru-layers", type=int, default=0)
    b.add_argument("-n", type=int, default=10000, help="C inference calls")
    b.add_argument("--n-python", type=int, default=2000, help="PyTorch inference calls")
    b.add_argument("--steps", type=int, default=10000, help="closed-loop controller periods")
    b.add_argument("--out", help="write the results as JSON here")
    b.set_defaults(func=_large_net)
