"""Fuzzing the importers: whatever the bytes, only a DdynError (normally DataError) comes out,
and a Dataset that does come out is finite with strictly increasing time.

numpy warnings are errors here: an overflow the importers did not expect would otherwise
pass silently as inf."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ddyn.data.dataset import COLUMNS, Dataset, write_canonical
from ddyn.data.importers import load_any, read_canonical, read_ddm_npz, read_racecar_csv
from ddyn.errors import DdynError
from ddyn.paths import shared_data_dir

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

RACECAR_HEADER = ("# time(s),x(m),y(m),vx(m/s),vy(m/s),phi(rad),delta(rad),omega(rad/s),ax(m/s^2),"
                  "deltadelta(rad/s),wheel_fl(kmph),wheel_fr(kmph),wheel_rl(kmph),wheel_rr(kmph),roll(rad),"
                  "throttle_ped_cmd(%),brake_ped_cmd(kPa)")
PUTNAM = shared_data_dir() / "real" / "Putnam_park2023_run4_2.csv"

# cells that have broken parsers: empty, non-finite, overflowing, Python-float-only spellings, separators
TOKENS = ["", " ", "nan", "NaN", "-nan", "inf", "-inf", "Infinity", "1e999", "-1e999", "1e308", "-1e308",
          "5e-324", "0", "-0", "1", "0.02", "0.04", "abc", "#", "1,2", "0x10", "1_0", "\u0663", "1e", ".", "--1",
          "\x00", "\t1", "\u00a0"]
cells = st.one_of(st.sampled_from(TOKENS), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.integers(-10, 10).map(str), st.text(max_size=6))


def check_outcome(read) -> Dataset | None:
    """Run read(); a Dataset must be sane, a failure must be a DdynError."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            ds = read()
        except DdynError:
            return None
    for name, values in [("time", ds.time), ("states", ds.states), ("inputs", ds.inputs), *ds.extras.items()]:
        assert np.all(np.isfinite(values)), name
    assert len(ds) >= 1 and np.all(np.diff(ds.time) > 0)
    assert np.all(np.diff(ds.segment) >= 0)
    assert np.isfinite(ds.sample_time) and ds.sample_time > 0
    return ds


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.fixture(scope="module")
def valid_canonical(workdir) -> str:
    rng = np.random.default_rng(7)
    n = 8
    ds = Dataset(time=np.r_[np.arange(4) * 0.02, 1 + np.arange(4) * 0.02], segment=np.r_[[0] * 4, [1] * 4],
                 states=rng.normal(size=(n, 8)), inputs=rng.normal(size=(n, 2)), sample_time=0.02,
                 vehicle="orca_1_43", source="fuzz", extras={"true_vx": rng.normal(size=n)})
    return write_canonical(ds, workdir / "valid.csv").read_text()


@st.composite
def mutated_lines(draw, text: str) -> str:
    """A few line- and cell-level edits of text: what a truncated copy or a bad hand edit does."""
    lines = text.split("\n")
    # mostly cell edits, which often leave a readable file, so the accepting path is exercised too
    ops = ["cell"] * 6 + ["del", "dup", "swap", "insert", "chars", "cut"]
    for op in draw(st.lists(st.sampled_from(ops), min_size=1, max_size=3)):
        i = draw(st.integers(0, len(lines) - 1)) if lines else 0
        if op == "cell" and lines:
            row = lines[i].split(",")
            row[draw(st.integers(0, len(row) - 1))] = draw(cells)
            lines[i] = ",".join(row)
        elif op == "del" and lines:
            del lines[i]
        elif op == "dup" and lines:
            lines.insert(i, lines[i])
        elif op == "swap" and len(lines) > 1:
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "insert":
            lines.insert(i, draw(st.text(max_size=30)))
        elif op == "chars" and lines:
            k = draw(st.integers(0, len(lines[i])))
            lines[i] = lines[i][:k] + draw(st.text(max_size=4)) + lines[i][k + draw(st.integers(0, 3)):]
        elif op == "cut":
            lines = lines[:i]
    return "\n".join(lines)


@st.composite
def csv_like(draw, header: str) -> str:
    """header (sometimes damaged), random metadata for canonical files, rows of random cells and lengths."""
    width = len(header.split(","))
    lines = [header if draw(st.booleans()) else draw(mutated_lines(header))]
    if header.startswith("time,segment"):   # a canonical body: magic and metadata come first
        meta = draw(st.lists(st.tuples(st.sampled_from(["sample_time", "vehicle", "source", "units", "note", ""]),
                                       st.one_of(st.sampled_from(["0.02", "0.04", "", "nan", "-1", "orca_1_43"]),
                                                 st.text(max_size=8))), max_size=4))
        lines = ["# ddyn-dataset 1", *[f"# {k}: {v}" for k, v in meta]] + lines
    lengths = st.one_of(st.just(width), st.integers(0, width + 2))
    for _ in range(draw(st.integers(0, 6))):
        lines.append(",".join(draw(st.lists(cells, min_size=1, max_size=width + 2))
                              if draw(st.booleans()) else [draw(cells) for _ in range(draw(lengths))]))
    return "\n".join(lines) + draw(st.sampled_from(["", "\n", "\r\n", "\n\n"]))


MAGICS = [b"", b"PK\x03\x04", b"PK\x05\x06", b"# ddyn-dataset 1\n", b"# time(s),", b"\x93NUMPY", b"\xef\xbb\xbf"]


@FUZZ
@given(prefix=st.sampled_from(MAGICS), body=st.binary(max_size=400))
def test_random_bytes(workdir, prefix, body):
    path = workdir / "random.bin"
    path.write_bytes(prefix + body)
    for read in (load_any, read_canonical, read_ddm_npz, read_racecar_csv):
        check_outcome(lambda: read(path))


@FUZZ
@given(text=csv_like(",".join(COLUMNS) + ",extra"))
def test_random_canonical_like_text(workdir, text):
    path = workdir / "random_canonical.csv"
    path.write_text(text)
    check_outcome(lambda: read_canonical(path))
    check_outcome(lambda: load_any(path))


@FUZZ
@given(text=csv_like(RACECAR_HEADER), min_vx=st.sampled_from([-1e300, 0.0, 5.0]))
def test_random_racecar_like_text(workdir, text, min_vx):
    path = workdir / "random_racecar.csv"
    path.write_text(text)
    check_outcome(lambda: read_racecar_csv(path, min_vx=min_vx))
    check_outcome(lambda: load_any(path, min_vx=min_vx))


finite = st.floats(allow_nan=False, allow_infinity=False)


@FUZZ
@given(n=st.integers(1, 8), data=st.data())
def test_round_trip_of_arbitrary_finite_values(workdir, n, data):
    """Any finite values, extreme ones included, survive write_canonical -> read_canonical bit for bit."""
    ts = data.draw(st.sampled_from([0.02, 0.04, 1e-3, 0.1]))
    segment = np.cumsum(data.draw(st.lists(st.integers(0, 1), min_size=n, max_size=n)))
    time = data.draw(st.floats(-1e6, 1e6)) + np.arange(n) * ts + segment * 10 * ts   # a gap starts a segment
    ds = Dataset(time=time, segment=segment, sample_time=ts,
                 states=np.array(data.draw(st.lists(finite, min_size=8 * n, max_size=8 * n))),
                 inputs=np.array(data.draw(st.lists(finite, min_size=2 * n, max_size=2 * n))),
                 extras={"e": np.array(data.draw(st.lists(finite, min_size=n, max_size=n)))})
    back = check_outcome(lambda: read_canonical(write_canonical(ds, workdir / "rt.csv")))
    assert back is not None and back.content_hash() == ds.content_hash()


@FUZZ
@given(n=st.integers(2, 8), data=st.data())
def test_random_values_in_a_valid_racecar_layout(workdir, n, data):
    """Regular time stamps, anything finite elsewhere: the derived rates and pedals may overflow."""
    rows = [[1692117187.5 + k * 0.04] + data.draw(st.lists(finite | st.sampled_from([0.0, 10.0]),
                                                           min_size=16, max_size=16)) for k in range(n)]
    path = workdir / "values.csv"
    path.write_text(RACECAR_HEADER + "\n" + "".join(",".join(map(repr, r)) + "\n" for r in rows))
    check_outcome(lambda: read_racecar_csv(path, min_vx=data.draw(st.sampled_from([-1e300, 5.0]))))


@FUZZ
@given(data=st.data())
def test_mutated_canonical_file(workdir, valid_canonical, data):
    text = data.draw(mutated_lines(valid_canonical))
    path = workdir / "mutated.csv"
    path.write_text(text)
    ds = check_outcome(lambda: read_canonical(path))
    if ds is not None:   # what was accepted writes and reads back identically
        again = check_outcome(lambda: read_canonical(write_canonical(ds, workdir / "again.csv")))
        assert again is not None and again.content_hash() == ds.content_hash()


@pytest.fixture(scope="module")
def putnam_head() -> str:
    if not PUTNAM.is_file():
        pytest.skip(f"SHARED DATA MISSING: {PUTNAM} (set DDYN_SHARED_DATA)")
    with PUTNAM.open() as f:
        return "".join(next(f) for _ in range(50))


@FUZZ
@given(data=st.data(), min_vx=st.sampled_from([-1.0, 0.001, 5.0]))
def test_mutated_putnam_head(workdir, putnam_head, data, min_vx):
    text = data.draw(mutated_lines(putnam_head))
    path = workdir / "putnam_head.csv"
    path.write_text(text)
    check_outcome(lambda: read_racecar_csv(path, min_vx=min_vx))


def test_fuzz_bases_are_valid(workdir, valid_canonical):
    """The mutations start from files that are accepted, so the accepting path is exercised."""
    path = workdir / "base.csv"
    path.write_text(valid_canonical)
    assert check_outcome(lambda: read_canonical(path)) is not None


def test_putnam_head_is_valid(workdir, putnam_head):
    path = workdir / "base.csv"
    path.write_text(putnam_head)
    assert len(check_outcome(lambda: read_racecar_csv(path, min_vx=-1.0))) == 49
