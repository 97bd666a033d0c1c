"""05: generate the model's C code into a folder, compile it and check it against the Python model.

Shows: ddyn.generate_c (CasADi C of the one Python model: derivative, Euler/RK4 steps, Jacobians, sensors, the
MPC's prediction step) written to a folder you choose (here a temporary one; the committed c_src/generated is
regenerated with `ddyn codegen model` only), that it is byte for byte the committed code, that it compiles
warning-free as C99, and a small C program calling the RK4 step with caller-owned work memory, whose answer
is compared with numpy's.
Run:   .venv/bin/python examples/05_generate_c.py [--vehicle orca_1_43] [--keep DIR]
Takes about ten seconds; needs a C compiler (cc).
"""
import argparse
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

import ddyn
from ddyn.model import backends
from ddyn.paths import REPO

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--vehicle", default="orca_1_43")
parser.add_argument("--keep", help="generate into this folder (kept) instead of a temporary one")
args = parser.parse_args()

car = ddyn.load_vehicle(args.vehicle)
tmp = tempfile.TemporaryDirectory()
out = Path(args.keep or tmp.name)
files = ddyn.generate_c(out, vehicle=car)
print(f"generated {len(files)} files in {out}: {', '.join(sorted(f.name for f in files))}")

model_c = out / f"ddyn_{car.name}_model.c"
committed = REPO / "c_src" / "generated" / model_c.name
print(f"{model_c.name} identical to the committed {committed.relative_to(REPO)}: "
      f"{model_c.read_bytes() == committed.read_bytes()}")   # same inputs, same bytes

cc = shutil.which("cc") or shutil.which("gcc")
# the project's flags; CasADi's fixed f(arg, res, iw, w, mem) leaves parameters unused in simple functions,
# so that one warning is off for generated files (as in c_src/CMakeLists.txt)
flags = ["-std=c99", "-O1", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-Wno-unused-parameter", "-I", str(out),
         "-I", str(REPO / "c_src" / "include")]
for src in sorted(out.glob("*.c")):
    subprocess.run([cc, *flags, "-c", str(src), "-o", str(src.with_suffix(".o"))], check=True)
print(f"compiled {len(list(out.glob('*.c')))} C files with {' '.join(flags[:7])}: no warnings")

# a C program: one RK4 step through the generated function, work memory owned by the caller
p = f"ddyn_{car.name}_step_rk4"
main_c = out / "step_main.c"
main_c.write_text(f"""#include <stdio.h>
#include "ddyn_{car.name}_model.h"
int main(void) {{
    static casadi_real w[4096];
    static casadi_int iw[256];
    casadi_int n_arg, n_res, n_iw, n_w;
    const casadi_real *arg[3];
    casadi_real *res[1];
    double x[8], u[2], c[17], x_next[8];
    int i;
    {p}_work(&n_arg, &n_res, &n_iw, &n_w);
    if (n_w > 4096 || n_iw > 256) return 2;
    for (i = 0; i < 8; i++) if (scanf("%lf", &x[i]) != 1) return 3;
    for (i = 0; i < 2; i++) if (scanf("%lf", &u[i]) != 1) return 3;
    for (i = 0; i < 17; i++) if (scanf("%lf", &c[i]) != 1) return 3;
    arg[0] = x; arg[1] = u; arg[2] = c; res[0] = x_next;
    if ({p}(arg, res, iw, w, 0) != 0) return 4;
    printf("work %d doubles:", (int)n_w);
    for (i = 0; i < 8; i++) printf(" %.17g", x_next[i]);
    printf("\\n");
    return 0;
}}
""")
exe = out / "step_main"
subprocess.run([cc, *flags, str(main_c), str(model_c.with_suffix(".o")), "-lm", "-o", str(exe)], check=True)

x = np.array([0.1, -0.2, 0.3, 0.6 * car.max_speed, 0.05, 0.5, 0.3, 0.1])
u = np.array([0.5, -0.2])
c = car.true_vector()
stdin = " ".join(repr(float(v)) for v in np.concatenate([x, u, c]))
line = subprocess.run([str(exe)], input=stdin, capture_output=True, text=True, check=True).stdout
c_next = np.array([float(t) for t in line.split(":")[1].split()])
py_next = backends.step_numpy(x, u, c, car.known, car.sample_time, "rk4", car.rk4_substeps)
print(f"C RK4 step ({line.split(':')[0]}): next vx {c_next[3]:.12f} vy {c_next[4]:.12f} omega {c_next[5]:.12f}")
print(f"largest relative difference C vs numpy: {np.max(np.abs(c_next - py_next) / (np.abs(py_next) + 1.0)):.2e}")
