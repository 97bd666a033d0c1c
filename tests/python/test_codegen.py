"""Generated C is reproducible byte for byte and the committed copy is up to date."""
from __future__ import annotations

import filecmp
import re

import numpy as np

from ddyn.codegen import generate as gen


def test_regeneration_matches_committed_files(tmp_path):
    out, vec = tmp_path / "generated", tmp_path / "vectors"
    written = gen.generate(out=out, vectors_out=vec)
    assert written, "codegen wrote nothing"
    for f in written:
        committed = (gen.DEFAULT_VECTORS_OUT if f.parent == vec else gen.DEFAULT_OUT) / f.name
        assert committed.is_file(), f"{committed} is not committed: run `ddyn codegen model` and commit"
        if f.name == "ddyn_model_vectors.h":
            assert_same_reference_values(f, committed)
            continue
        assert filecmp.cmp(f, committed, shallow=False), (
            f"{committed.name} differs from a fresh generation: the model, a vehicle file or CasADi changed; "
            "run `ddyn codegen model` and commit the result")
    # nothing stale left behind in the committed folder either
    # (subfolders such as can/ belong to other generators, with their own tests)
    assert sorted(p.name for p in gen.DEFAULT_OUT.iterdir() if p.is_file()) == sorted(p.name for p in out.iterdir())


# The reference vectors are the Python model's answers (numpy steps, torch-autograd Jacobians), test data for the
# C tests (which compare at 1e-12 and 1e-9 relative to the value or a thousandth of its array's scale), not generated code: torch picks its float64 kernels by the
# CPU's vector extensions, so the Jacobians' last bits differ between machines (an AVX-512 AMD EPYC regenerates
# 1,667 of the 40,032 values up to 2.7e-13 away, relative to the scale below, from a copy committed on another
# machine). Everything but the numbers must be identical and every number equal to VECTOR_RTOL: a hundredth of the C
# tests' Jacobian tolerance, 40 times the largest change seen.
VECTOR_RTOL = 1e-11
_ARRAY_BODY = re.compile(r"(= \{)([^}]*)(\};)")


def _split_values(text: str) -> tuple[str, list[np.ndarray]]:
    """The header with every array's values replaced by their count, and the arrays."""
    arrays: list[np.ndarray] = []

    def take(m):
        arrays.append(np.array([float(v) for v in m.group(2).replace("\n", " ").split(",") if v.strip()]))
        return f"{m.group(1)}{len(arrays[-1])} values{m.group(3)}"

    return _ARRAY_BODY.sub(take, text), arrays


def assert_same_reference_values(fresh, committed):
    (a, x), (b, y) = _split_values(fresh.read_text()), _split_values(committed.read_text())
    assert a == b, (
        f"{committed.name}: its arrays differ from a fresh generation (names, sizes or cases): the model, a vehicle "
        "file or the cases changed; run `ddyn codegen model` and commit the result")
    for xa, ya in zip(x, y):
        # relative to the value, or to a thousandth of its array's largest where it is smaller (a Jacobian entry
        # that is the difference of two large terms keeps the absolute error of those terms), as the C tests do
        scale = np.maximum(np.abs(ya), 1e-3 * np.max(np.abs(ya), initial=0.0))
        worst = np.max(np.abs(xa - ya) / np.maximum(scale, 1e-300), initial=0.0)
        assert np.all(np.abs(xa - ya) <= VECTOR_RTOL * scale), (
            f"{committed.name}: a value differs from a fresh generation by {worst:.2g} relative (more than the "
            "last bits a CPU's kernels change): run `ddyn codegen model` and commit the result")


def test_reference_values_comparison_tolerates_last_bits_only(tmp_path):
    """The vectors' comparison passes a last-bit change and fails a real one or a changed array."""
    import pytest

    base = "static const double vec_x[3] = {\n    0.1, -2.5e-07, 3.0\n};\n"
    a, b = tmp_path / "a.h", tmp_path / "b.h"
    b.write_text(base)
    a.write_text(base.replace("0.1,", "0.10000000000000002,"))
    assert_same_reference_values(a, b)
    a.write_text(base.replace("0.1,", "0.100001,"))
    with pytest.raises(AssertionError, match="relative"):
        assert_same_reference_values(a, b)
    a.write_text(base.replace("vec_x[3]", "vec_y[3]"))
    with pytest.raises(AssertionError, match="arrays differ"):
        assert_same_reference_values(a, b)


def test_generated_files_say_what_generated_them():
    for f in (p for p in gen.DEFAULT_OUT.iterdir() if p.is_file()):
        head = f.read_text().splitlines()[:8]
        assert head[0] == "/* GENERATED FILE - DO NOT EDIT."
        assert any(gen.model_hash() in line for line in head), f"{f.name} lacks the current model hash"


def test_generated_jacobians_match_finite_differences():
    """The CasADi Jacobian functions (what the C gets) against central differences of the numpy model."""
    import numpy as np

    from ddyn.model import backends, vehicle
    from ddyn.model.sampling import random_cases

    v = vehicle.load("orca_1_43")
    jac = [f for f in gen.model_functions(v) if f.name().endswith("step_euler_jac")][0]
    x, u, c = random_cases(v, 5, np.random.default_rng(11))
    x[:, 3] = np.abs(x[:, 3]) + 0.5  # keep away from the v_min kink where differences are one-sided
    for i in range(5):
        A, B, P = (np.asarray(m) for m in jac(x[i], u[i], c[i]))
        for j in range(8):
            h = 1e-6 * max(1.0, abs(x[i, j]))
            xp, xm = x[i].copy(), x[i].copy()
            xp[j] += h
            xm[j] -= h
            fd = (backends.step_numpy(xp, u[i], c[i], v.known, v.sample_time)
                  - backends.step_numpy(xm, u[i], c[i], v.known, v.sample_time)) / (2 * h)
            assert np.allclose(A[:, j], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max() + 1e-9), (i, j)
