"""Viewer sets for many-viewer rendering (paper 003 §4): the camera rigs of its evaluation.

- ``wander``: viewers walking a shared area (the paper's realistic movement): each on its own smooth closed path
  through the area's walkable space (`WalkArea`: its floor minus the footprints of walls, columns, buildings) at eye
  height, looking along its path;
- ``overlap``: one camera duplicated and yawed so that neighbouring frusta share a given fraction of their horizontal
  field of view (the paper's fixed-overlap rigs, 10% ... 100%);
- ``arc``: `volren.camera.orbit_views` (viewers on an arc about the look-at point), each viewer that would leave the
  walkable space moved towards the look-at point until it stands in it (`arc_viewers`);
- ``stereo`` comes from `volren.camera.make_views`.
Every rig is a function of time [s], so a sequence of frames moves the viewers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from volren.camera import MAX_VIEWS, Camera, orbit_views
from volren.errors import VolrenError

EYE_HEIGHT = 1.7
"""[m] above the area's floor"""
WALK_SPEED = 1.2
"""[m/s]"""


def check_count(count: int) -> None:
    if not 1 <= count <= MAX_VIEWS:
        raise VolrenError(f"viewer count must lie in [1, {MAX_VIEWS}], got {count}")


@dataclass(frozen=True)
class WalkArea:
    """Where viewers may stand: the floor rectangle [lo, hi] (x, z) [m] at height ``floor``, minus the footprints
    (x0, z0, x1, z1) of everything standing on it, with ``clearance`` [m] kept from the rectangle's edges and every
    footprint (more than a camera's near plane, so no viewer looks through a wall)."""

    lo: tuple[float, float]
    hi: tuple[float, float]
    floor: float = 0.0
    obstacles: tuple[tuple[float, float, float, float], ...] = ()
    clearance: float = 0.3

    def __post_init__(self) -> None:
        if not all(h - lo > 2 * self.clearance for lo, h in zip(self.lo, self.hi, strict=True)):
            raise VolrenError(f"walk area {self.lo} - {self.hi} leaves no room inside a clearance of "
                              f"{self.clearance} m")

    def walkable(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Whether each point (x, z) keeps the clearance from the area's edges and from every obstacle."""
        x, z, c = np.asarray(x, float), np.asarray(z, float), self.clearance
        ok = (x >= self.lo[0] + c) & (x <= self.hi[0] - c) & (z >= self.lo[1] + c) & (z <= self.hi[1] - c)
        for x0, z0, x1, z1 in self.obstacles:
            ok &= ~((x > x0 - c) & (x < x1 + c) & (z > z0 - c) & (z < z1 + c))
        return ok


MAX_PATH_TRIES = 1000
PATH_CHECKS = 96
"""points per walk checked against the walk area"""


def wandering_viewers(base: Camera, count: int, area: WalkArea, time: float = 0.0, seed: int = 0) -> list[Camera]:
    """``count`` viewers (``base``'s image size and lens) on seeded elliptic walks that stay in ``area``'s walkable
    space, eyes at area.floor + EYE_HEIGHT, each looking ahead along its walk. Each walk is drawn (centre anywhere
    in the area, radii up to the area's edges) until all of it is walkable."""
    check_count(count)
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(area.lo, float), np.asarray(area.hi, float)
    around = np.linspace(0.0, 2 * math.pi, PATH_CHECKS, endpoint=False)
    views = []
    for _ in range(count):
        for _ in range(MAX_PATH_TRIES):
            c = lo + rng.random(2) * (hi - lo)
            room = np.minimum(c - lo, hi - c) - area.clearance
            radii = 0.5 + rng.random(2) * np.maximum(room - 0.5, 0.0)
            if area.walkable(c[0] + radii[0] * np.cos(around), c[1] + radii[1] * np.sin(around)).all():
                break
        else:
            raise VolrenError(f"found no walk of at least 0.5 m radius in the walk area {area.lo} - {area.hi}")
        phase = rng.random() * 2 * math.pi
        omega = WALK_SPEED / float(np.mean(radii)) * rng.choice([-1.0, 1.0])
        a = phase + omega * time
        pos = np.array([c[0] + radii[0] * math.cos(a), area.floor + EYE_HEIGHT, c[1] + radii[1] * math.sin(a)])
        ahead = np.array([-radii[0] * math.sin(a), 0.0, radii[1] * math.cos(a)]) * np.sign(omega)
        ahead /= max(np.linalg.norm(ahead), 1e-9)
        views.append(replace(base, position=tuple(pos), look_at=tuple(pos + ahead)))
    return views


ARC_STEPS = 64
"""candidate positions between a viewer and its look-at point"""


def arc_viewers(base: Camera, count: int, area: WalkArea | None = None, spread_deg: float = 10.0) -> list[Camera]:
    """``count`` viewers on `orbit_views`' arc about ``base``'s look-at point; with an ``area`` (used only when
    ``base`` itself stands in it), each viewer outside the walkable space moves along its line of sight towards the
    look-at point to the first walkable spot, so the arc keeps its directions and stays in the scene."""
    check_count(count)
    views = orbit_views(base, count, spread_deg)
    if area is None or not area.walkable(base.position[0], base.position[2]):
        return views
    target = np.asarray(base.look_at, float)
    out = []
    for v in views:
        p = np.asarray(v.position, float)
        points = target + np.linspace(1.0, 0.0, ARC_STEPS, endpoint=False)[:, None] * (p - target)
        ok = np.flatnonzero(area.walkable(points[:, 0], points[:, 2]))
        if not len(ok):
            raise VolrenError(f"no walkable point between viewer {tuple(p.round(2))} and its look-at point")
        out.append(replace(v, position=tuple(points[ok[0]])))
    return out


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
