"""A banked oval: two straights joined by two semicircular turns, with its banking along the lap.

Why: the issue's real oval (about 20 degrees in the turns, 9 on the front straight) is the case the
flat-track diagnosis got wrong; the independent plant (ddyn.plants.commonroad_st) drives this one so the
bank profile the diagnosis fits can be compared with the true one. The banking belongs to the track (the
world), not to a drawn effect: `Track.bank` holds it per centre-line point (rad, positive tilting the road
so that gravity pulls to the left of the direction of travel: into the turns of this counter-clockwise
oval), and `bank_at(track, s)` reads it anywhere.

Layout (counter-clockwise): the front straight runs along +x at y = -radius from x = 0 to x = straight,
turns 1-2 go round (straight, 0), the back straight returns along y = +radius, turns 3-4 round (0, 0).
The bank moves linearly between the turns' and the straights' values over `transition` metres centred
on each turn entry and exit.
"""
from __future__ import annotations

import math

import numpy as np

from ddyn.model.tracks import Track, bounds_from_widths

DEG = math.pi / 180.0
# defaults: the oval (20 deg turns, 9 deg front straight), sized for a saloon at 20-26 m/s
STRAIGHT = 300.0       # m
RADIUS = 100.0         # m
WIDTH = 15.0           # m
BANK_TURNS = 20.0      # deg
BANK_FRONT = 9.0       # deg
BANK_BACK = 5.0        # deg
TRANSITION = 60.0      # m
SPACING = 2.0          # m between centre-line points


def _centre(straight: float, radius: float) -> np.ndarray:
    """Centre-line points: front straight, turns 1-2, back straight, turns 3-4."""
    pts = []
    n_s = max(2, int(round(straight / SPACING)))
    n_t = max(8, int(round(math.pi * radius / SPACING)))
    for i in range(n_s):
        pts.append((straight * i / n_s, -radius))
    for i in range(n_t):
        a = -math.pi / 2 + math.pi * i / n_t
        pts.append((straight + radius * math.cos(a), radius * math.sin(a)))
    for i in range(n_s):
        pts.append((straight * (1 - i / n_s), radius))
    for i in range(n_t):
        a = math.pi / 2 + math.pi * i / n_t
        pts.append((radius * math.cos(a), radius * math.sin(a)))
    return np.array(pts)


def bank_along(s: np.ndarray, straight: float, radius: float, turns: float, front: float, back: float,
               transition: float) -> np.ndarray:
    """Bank (rad) at arc lengths s of the oval (s = 0 at the start of the front straight)."""
    turn = math.pi * radius
    # section boundaries along the lap and the bank of the section that starts there
    edges = np.array([0.0, straight, straight + turn, 2 * straight + turn])
    values = np.array([front, turns, back, turns])
    length = 2 * (straight + turn)
    s = np.mod(np.asarray(s, float), length)
    # knots: each section's value held between its edges, ramped over `transition` across each edge
    half = 0.5 * transition
    ks, kv = [], []
    for i, e in enumerate(edges):
        prev = values[i - 1]
        ks += [e - half, e + half]
        kv += [prev, values[i]]
    ks, kv = np.array(ks), np.array(kv)
    order = np.argsort(np.mod(ks, length))
    return np.interp(s, np.mod(ks, length)[order], kv[order], period=length)


def oval_track(straight: float = STRAIGHT, radius: float = RADIUS, bank_turns_deg: float = BANK_TURNS,
               bank_front_deg: float = BANK_FRONT, bank_back_deg: float = BANK_BACK,
               transition: float = TRANSITION, width: float = WIDTH, name: str = "oval") -> Track:
    """The oval with its banking (Track.bank, rad per centre-line point; Track.turns: a mask of the points in
    the turns' constant-bank part, where the issue's 3-degree target is scored)."""
    centre = _centre(straight, radius)
    half = np.full(len(centre), 0.5 * width)
    left, right = bounds_from_widths(centre, half, half)
    track = Track(name, centre, left, right, None,
                  source=f"ddyn.model.track_oval: straights {straight:g} m, turn radius {radius:g} m, bank "
                         f"{bank_turns_deg:g} deg turns / {bank_front_deg:g} front / {bank_back_deg:g} back")
    track.bank = bank_along(track.s, straight, radius, bank_turns_deg * DEG, bank_front_deg * DEG,
                            bank_back_deg * DEG, transition)
    turn = math.pi * radius
    s = np.asarray(track.s)
    inner = 0.5 * transition
    track.turns = (((s > straight + inner) & (s < straight + turn - inner))
                   | ((s > 2 * straight + turn + inner) & (s < 2 * (straight + turn) - inner)))
    return track


def bank_at(track: Track, s) -> np.ndarray:
    """The track's own bank (rad) at arc lengths s; zero on a track without banking."""
    return track.road_profile_at("bank", s)
