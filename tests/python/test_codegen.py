"""Generated C is reproducible byte for byte and the committed copy is up to date."""
from __future__ import annotations

import filecmp

from ddyn.codegen import generate as gen


def test_regeneration_matches_committed_files(tmp_path):
    out, vec = tmp_path / "generated", tmp_path / "vectors"
    written = gen.generate(out=out, vectors_out=vec)
    assert written, "codegen wrote nothing"
    for f in written:
        committed = (gen.DEFAULT_VECTORS_OUT if f.parent == vec else gen.DEFAULT_OUT) / f.name
        assert committed.is_file(), f"{committed} is not committed: run `ddyn codegen model` and commit"
        assert filecmp.cmp(f, committed, shallow=False), (
            f"{committed.name} differs from a fresh generation: the model, a vehicle file or CasADi changed; "
            "run `ddyn codegen model` and commit the result")
    # nothing stale left behind in the committed folder either
    # (subfolders such as can/ belong to other generators, with their own tests)
    assert sorted(p.name for p in gen.DEFAULT_OUT.iterdir() if p.is_file()) == sorted(p.name for p in out.iterdir())


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
