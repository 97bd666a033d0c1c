"""A road's grade along a track (issue 34): the world's, like the banked oval's bank (ddyn.model.track_oval), not a
drawn effect. `graded(track, amplitude)` gives a track hills: the grade (rad, + uphill in the direction of travel)
at arc length s is amplitude sin(2 pi waves s / L), so a closed lap climbs as much as it descends; `Track.grade`
holds it per centre-line point and `grade_at(track, s)` reads it anywhere. The SIL's plant drives it (plant.json
road_grade) and a grade-aware controller reads it along its raceline (controller.json control.grade).

The term is train/model/effects.py's grade: a longitudinal gravity -g sin(grade) on dvx."""
from __future__ import annotations

import copy
import math

import numpy as np

from ddyn.errors import DdynError
from ddyn.model.tracks import Track

WAVES = 2                 # hills per lap
MAX_AMPLITUDE = 0.3       # rad: within the controller's +-20 degrees (DDYN_MPC_MAX_GRADE)


def graded(track: Track, amplitude: float, waves: int = WAVES) -> Track:
    """A copy of track with its grade profile (Track.grade, rad per centre-line point); its name is kept (the
    same road, its lines the same)."""
    if not (isinstance(amplitude, (int, float)) and math.isfinite(amplitude) and 0.0 < amplitude <= MAX_AMPLITUDE):
        raise DdynError(f"road grade: amplitude {amplitude!r} rad; expected 0 < amplitude <= {MAX_AMPLITUDE:g}")
    if not (isinstance(waves, int) and waves >= 1):
        raise DdynError(f"road grade: waves {waves!r}; expected a whole number of hills per lap >= 1")
    out = copy.copy(track)
    out.grade = amplitude * np.sin(2.0 * np.pi * waves * np.asarray(track.s, float) / track.length)
    out.grade_source = f"ddyn.model.road_grade: {amplitude:g} rad amplitude, {waves} hills per lap"
    return out


def grade_at(track: Track, s) -> np.ndarray:
    """The track's own grade (rad) at arc lengths s; zero on a level track."""
    return track.road_profile_at("grade", s)
