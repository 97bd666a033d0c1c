"""`ddyn codegen`, MPC part: each vehicle's input limits as a C table for the MPC's defaults.

The MPC (c_src/src/mpc.c) bounds the input rates dthrottle, dsteering and the states throttle,
steering by the vehicle file's input_limits. They are generated rather than typed into C so the
one vehicle file stays the only place they are written. Output: c_src/generated/ddyn_mpc_limits.h
(byte-reproducible, banner with the vehicle files' hashes like the model code).
"""
from __future__ import annotations

from pathlib import Path

from train.vehicle import Vehicle

# order of the four limits in each table row (lo, hi each)
LIMIT_ORDER = ("dthrottle", "dsteering", "throttle", "steering")


def generate_limits(vehicles: list[Vehicle], out: Path, banner) -> list[Path]:
    from .generate import _c_double

    lines = [banner("Input limits of each vehicle (vehicle files' input_limits) for the MPC defaults.", vehicles),
             "#ifndef DDYN_MPC_LIMITS_H", "#define DDYN_MPC_LIMITS_H", "",
             "/* one row per vehicle: name, then lo, hi of " + ", ".join(LIMIT_ORDER) + " */",
             "typedef struct {", "    const char *name;", "    double lo_hi[4][2];", "} ddyn_mpc_vehicle_limits;", "",
             f"#define DDYN_MPC_LIMITS_COUNT {len(vehicles)}",
             "static const ddyn_mpc_vehicle_limits ddyn_mpc_limits[DDYN_MPC_LIMITS_COUNT] = {"]
    for v in vehicles:
        rows = ", ".join("{" + f"{_c_double(v.input_limits[k][0])}, {_c_double(v.input_limits[k][1])}" + "}"
                         for k in LIMIT_ORDER)
        lines.append(f'    {{"{v.name}", {{{rows}}}}},')
    lines += ["};", "", "#endif", ""]
    path = Path(out) / "ddyn_mpc_limits.h"
    path.write_text("\n".join(lines))
    return [path]
