"""`ddyn sil tracks`: the SIL's first lap on a random track with noisy sensors, scored against the track's
optimum (the held-out study over 20 tracks x 3 noise seeds is a documented command, docs/tracks.md)."""
from __future__ import annotations

import json

from ddyn.cli import main


def test_sil_tracks_drives_a_random_track_over_two_noise_seeds(tmp_path):
    out = tmp_path / "st"
    assert main(["sil", "tracks", "--seeds", "210", "--noise-seeds", "1-2", "--out", str(out)]) == 0
    d = json.loads((out / "sil_tracks.json").read_text())
    rows = d["rows"]
    assert [r["noise_seed"] for r in rows] == [1, 2]
    # the noise seed reaches the plant: two seeds, two different laps
    assert rows[0]["lap_s"] != rows[1]["lap_s"]
    plant = json.loads((out / "random210_noise2" / "plant.json").read_text())
    assert plant["seed"] == 2 and plant["track"] == "random210"
    assert d["summary"]["clean"] == 2 and d["summary"]["within_5pct"] == 2, rows
