"""The telemetry's LCM message types in Python, generated from lcmtypes/*.lcm when first used.

The .lcm files are the one definition of the wire format. CMake runs lcm-gen for the
C side (and writes Python beside it in the build tree); the Python side runs the same
lcm-gen of the pinned `lcm` package into a temporary directory on first use, imports
the package from there, and keeps the modules in memory. Nothing generated is
committed, and the types can never be older than the .lcm files.
"""
from __future__ import annotations

import functools
import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path
from types import ModuleType

from ddyn.errors import DdynError
from ddyn.paths import REPO

LCM_TYPES_DIR = REPO / "lcmtypes"
PACKAGE = "ddyn_lcm"
# channel suffix (after the prefix, default DDYN_) -> message type, as c_src/linux/telemetry_lcm.c publishes
CHANNEL_TYPES = {"STATE": "state_estimate_t", "COEFFS": "guard_coeffs_t", "PLAN": "mpc_plan_t",
                 "TIMING": "loop_timing_t", "FAULTS": "faults_t"}
DEFAULT_PREFIX = "DDYN_"


def lcm_module() -> ModuleType:
    """The `lcm` Python package; a clear error when it is not installed."""
    try:
        import lcm
    except ImportError as e:
        raise DdynError(f"the `lcm` Python package is missing ({e}); run scripts/setup.sh, "
                        "which installs it from requirements.lock") from None
    return lcm


def lcm_gen() -> Path:
    """The lcm-gen executable shipped with the `lcm` package."""
    exe = Path(lcm_module().LCM_BIN_DIR).resolve() / "lcm-gen"
    if not exe.is_file():
        raise DdynError(f"lcm-gen not found at {exe}; reinstall the pinned `lcm` package (scripts/setup.sh)")
    return exe


@functools.lru_cache(maxsize=1)
def types() -> ModuleType:
    """The generated `ddyn_lcm` package (attributes state_estimate_t, guard_coeffs_t, ...)."""
    lcm_files = sorted(LCM_TYPES_DIR.glob("*.lcm"))
    if not lcm_files:
        raise DdynError(f"no message definitions in {LCM_TYPES_DIR}")
    with tempfile.TemporaryDirectory(prefix="ddyn-lcmtypes-") as out:
        cmd = [str(lcm_gen()), "--python", "--ppath", out, *map(str, lcm_files)]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            raise DdynError(f"lcm-gen failed on {LCM_TYPES_DIR}: {done.stderr.strip() or done.stdout.strip()}")
        init = Path(out) / PACKAGE / "__init__.py"
        spec = importlib.util.spec_from_file_location(PACKAGE, init, submodule_search_locations=[str(init.parent)])
        module = importlib.util.module_from_spec(spec)
        sys.modules[PACKAGE] = module
        try:
            spec.loader.exec_module(module)   # imports every type module while the files exist
        except Exception:
            del sys.modules[PACKAGE]
            raise
    return module


def channel_types(prefix: str = DEFAULT_PREFIX) -> dict[str, type]:
    """{channel name: message class} for a channel prefix."""
    t = types()
    return {prefix + suffix: getattr(t, name) for suffix, name in CHANNEL_TYPES.items()}
