"""Viewer sets for many-viewer rendering (paper 003 §4): the camera rigs of its evaluation.

- ``wander``: viewers walking a shared area (the paper's realistic movement): each on its own smooth closed path
  inside the area's horizontal extent at eye height, looking along its path with a slow head turn;
- ``overlap``: one camera duplicated and yawed so that neighbouring frusta share a given fraction of their horizontal
  field of view (the paper's fixed-overlap rigs, 10% ... 100%);
- ``stereo`` and ``arc`` come from `volren.camera.make_views`.
Every rig is a function of time [s], so a sequence of frames moves the viewers.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from volren.camera import MAX_VIEWS, Camera
from volren.errors import VolrenError

EYE_HEIGHT = 1.7
"""[m] above the area's floor"""
WALK_SPEED = 1.2
"""[m/s]"""


def check_count(count: int) -> None:
    if not 1 <= count <= MAX_VIEWS:
        raise VolrenError(f"viewer count must lie in [1, {MAX_VIEWS}], got {count}")


def wandering_viewers(base: Camera, count: int, lo: tuple[float, float, float], hi: tuple[float, float, float],
                      time: float = 0.0, seed: int = 0) -> list[Camera]:
    """``count`` viewers (``base``'s image size and lens) on seeded elliptic walks inside [lo, hi] (x, z), eyes at
    lo[1] + EYE_HEIGHT, each looking ahead along its walk."""
    check_count(count)
    rng = np.random.default_rng(seed)
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    centre = 0.5 * (lo_a + hi_a)
    half = 0.5 * (hi_a - lo_a) * 0.8  # keep clear of the walls
    views = []
    for _ in range(count):
        c = centre + (rng.random(3) - 0.5) * half
        radii = np.maximum(half - np.abs(c - centre), 0.5) * (0.3 + 0.7 * rng.random(3))
        phase = rng.random() * 2 * math.pi
        omega = WALK_SPEED / max(float(np.mean(radii[[0, 2]])), 0.5) * rng.choice([-1.0, 1.0])
        a = phase + omega * time
        y = lo_a[1] + EYE_HEIGHT
        pos = np.array([c[0] + radii[0] * math.cos(a), y, c[2] + radii[2] * math.sin(a)])
        ahead = np.array([-radii[0] * math.sin(a), 0.0, radii[2] * math.cos(a)]) * np.sign(omega)
        ahead /= max(np.linalg.norm(ahead), 1e-9)
        views.append(replace(base, position=tuple(pos), look_at=tuple(pos + ahead)))
    return views


def overlap_viewers(base: Camera, count: int, overlap: float) -> list[Camera]:
    """``count`` copies of ``base`` yawed about its position so that neighbours share ``overlap`` of the horizontal
    field of view (1 = all looking the same way), fanned symmetrically about ``base``'s direction."""
    check_count(count)
    if not 0 <= overlap <= 1:
        raise VolrenError(f"viewer overlap must lie in [0, 1], got {overlap}")
    h_fov = 2 * math.atan(base.tan_half_fov * base.width / base.height)
    step = (1 - overlap) * h_fov
    origin = np.asarray(base.position, float)
    ahead = np.asarray(base.look_at, float) - origin
    views = []
    for i in range(count):
        a = (i - (count - 1) / 2) * step
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        views.append(replace(base, look_at=tuple(origin + rot @ ahead)))
    return views
