"""The drive-by-wire C generated from the DBC is reproducible byte for byte and up to date."""
from __future__ import annotations

import filecmp

from ddyn.codegen import can as cangen


def test_can_regeneration_matches_committed_files(tmp_path):
    written = cangen.generate(out=tmp_path)
    assert sorted(f.name for f in written) == ["ddyn_can.c", "ddyn_can.h"]
    for f in written:
        committed = cangen.DEFAULT_OUT / f.name
        assert committed.is_file(), f"{committed} is not committed: run `ddyn can codegen` and commit"
        assert filecmp.cmp(f, committed, shallow=False), (
            f"{committed.name} differs from a fresh generation: the DBC or cantools changed; "
            "run `ddyn can codegen` and commit the result")
    assert sorted(p.name for p in cangen.DEFAULT_OUT.iterdir()) == sorted(f.name for f in written)


def test_can_generation_is_deterministic(tmp_path):
    a, b = cangen.generate(out=tmp_path / "a"), cangen.generate(out=tmp_path / "b")
    for fa, fb in zip(a, b):
        assert fa.read_bytes() == fb.read_bytes()


def test_generated_can_files_name_their_recipe():
    for f in cangen.DEFAULT_OUT.iterdir():
        head = f.read_text().splitlines()[:6]
        assert head[0] == "/* GENERATED FILE - DO NOT EDIT."
        assert any(cangen.dbc_hash() in line for line in head), f"{f.name} lacks the current DBC hash"
        assert "ddyn can codegen" in "\n".join(head)
