"""Built-in triangle-mesh scenes for the froxel volumetric fog (paper 003, Stojanovic et al. 2023).

The paper evaluates on Sponza and Bistro; these procedural stand-ins exercise the same light paths without asset
files (world: y up, metres, right-handed):

- ``hall``: a Sponza-like colonnade hall, closed except for a row of tall windows on its +z wall. A low sun shines
  through them, so the fog shows sharp light shafts broken by the wall piers and the columns; dust boxes near the
  floor add heterogeneous density.
- ``courtyard``: a Bistro-like night square among building blocks, lit only by warm point lights on lamp poles and
  spot lights on the facades pointing down: local lights, inverse-square falloff and cone edges in thin height fog.
- ``dynamic``: a small windowed room whose box, sphere and fan move with ``time``, so their shadows sweep through
  the sunlit fog: the case for temporal reprojection and per-frame shadow updates.

Every wall, floor and ceiling is a closed box (never a single-sided plane), so shadow rays cannot leak through.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import cache

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from volren.errors import VolrenError
from volren.scene import (
    DirectionalLight,
    Environment,
    Fog,
    FogBox,
    Light,
    PointLight,
    Scene,
    SpotLight,
    TriangleMesh,
)
from volren.viewers import EYE_HEIGHT, WalkArea

Part = tuple[np.ndarray, np.ndarray]
"""(vertices (N, 3) float64, faces (M, 3) int64) of one closed primitive."""

FOG_SCENES: dict[str, str] = {
    "hall": "Sponza-like colonnade hall, sun shafts through one row of windows, dusty floor (24 x 10 x 7 m)",
    "courtyard": "Bistro-like night square, 4 warm lamp-post point lights and 3 facade spot lights (30 x 30 m)",
    "dynamic": "small windowed room with a moving box, sphere and fan casting moving shadows in sunlit fog (12 m)",
}
ANIMATED_FOG_SCENES = frozenset({"dynamic"})
"""scenes whose geometry moves with time (re-built per frame)"""


# ---- geometry helpers -------------------------------------------------------------------------------------------


def box_mesh(lo: Sequence[float], hi: Sequence[float]) -> Part:
    """A closed axis-aligned box from corner ``lo`` to corner ``hi`` (12 triangles)."""
    b = trimesh.creation.box(bounds=np.array([lo, hi], dtype=np.float64))
    return np.asarray(b.vertices, dtype=np.float64), np.asarray(b.faces, dtype=np.int64)


def cylinder_mesh(base: Sequence[float], radius: float, height: float, sections: int = 24) -> Part:
    """A closed vertical (y-axis) cylinder standing on the point ``base``."""
    c = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    v = np.asarray(c.vertices, dtype=np.float64)
    # trimesh builds it along z about the origin; (x, y, z) -> (x, z, -y) is a rotation, so windings stay outward
    v = np.stack([v[:, 0], v[:, 2] + height / 2, -v[:, 1]], axis=1) + np.asarray(base, dtype=np.float64)
    return v, np.asarray(c.faces, dtype=np.int64)


def sphere_mesh(center: Sequence[float], radius: float) -> Part:
    s = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    return np.asarray(s.vertices, dtype=np.float64) + np.asarray(center, dtype=np.float64), np.asarray(s.faces)


def rotate_y(part: Part, angle: float, pivot: Sequence[float]) -> Part:
    """Rotate a part by ``angle`` [rad] about the vertical axis through ``pivot`` (counter-clockwise seen from +y)."""
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    p = np.asarray(pivot, dtype=np.float64)
    return (part[0] - p) @ rot.T + p, part[1]


def merge(parts: Sequence[Part], name: str, albedo: Sequence[float]) -> TriangleMesh:
    """One logical object (one BVH in the renderer) from several parts."""
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)])
    return TriangleMesh(vertices, faces.astype(np.int64), albedo=tuple(albedo), name=name)


def sun_direction(elevation_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    """Travel direction of sunlight coming from +z (azimuth 0), tilted towards +x by ``azimuth_deg``, descending at
    ``elevation_deg`` above the horizon; it travels towards -z, -x and -y."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return (-math.cos(e) * math.sin(a), -math.sin(e), -math.cos(e) * math.cos(a))


def windowed_wall(x0: float, x1: float, z0: float, z1: float, height: float, sill: float, top: float,
                  windows: Sequence[tuple[float, float]]) -> list[Part]:
    """A wall along x between ``z0`` and ``z1`` with rectangular openings ``(x_from, x_to)`` from ``sill`` up to
    ``top``: a sill strip, a lintel strip and the piers between the openings."""
    parts = [box_mesh((x0, 0.0, z0), (x1, sill, z1)), box_mesh((x0, top, z0), (x1, height, z1))]
    edges = [x0, *[x for w in windows for x in w], x1]
    parts += [box_mesh((a, sill, z0), (b, top, z1)) for a, b in zip(edges[::2], edges[1::2], strict=True) if b > a]
    return parts


def room_shell(half_x: float, half_z: float, height: float, wall: float, slab: float, sill: float, top: float,
               windows: Sequence[tuple[float, float]]) -> list[TriangleMesh]:
    """Floor, ceiling and four walls of a closed room over [-half_x, half_x] x [-half_z, half_z]; the +z wall has
    the window openings. The walls stand outside the interior, the slabs cover the walls."""
    ox, oz = half_x + wall, half_z + wall
    floor = merge([box_mesh((-ox, -slab, -oz), (ox, 0.0, oz))], "floor", (0.55, 0.5, 0.45))
    ceiling = merge([box_mesh((-ox, height, -oz), (ox, height + slab, oz))], "ceiling", (0.6, 0.58, 0.55))
    walls = [
        box_mesh((-ox, 0.0, -oz), (-half_x, height, oz)),
        box_mesh((half_x, 0.0, -oz), (ox, height, oz)),
        box_mesh((-half_x, 0.0, -oz), (half_x, height, -half_z)),
        *windowed_wall(-half_x, half_x, half_z, oz, height, sill, top, windows),
    ]
    return [floor, ceiling, merge(walls, "walls", (0.7, 0.62, 0.5))]


# ---- scenes -----------------------------------------------------------------------------------------------------

HALL_SUN = sun_direction(40.0, 20.0)
HALL_WINDOW_X = (-9.0, -6.0, -3.0, 0.0, 3.0, 6.0, 9.0)
"""[m] window centres on the +z wall (z in [5, 5.5]); openings are 1.6 m wide, from y = 1.5 to 5.5 m."""


def _hall(time: float) -> Scene:
    shell = room_shell(12.0, 5.0, 7.0, 0.5, 0.4, 1.5, 5.5, [(x - 0.8, x + 0.8) for x in HALL_WINDOW_X])
    column_x = [-10.5 + 3.0 * i for i in range(8)]
    columns = [cylinder_mesh((x, 0.0, z), 0.35, 6.0) for z in (-2.5, 2.5) for x in column_x]
    # an architrave on each row of columns, up to the ceiling: the arcade of Sponza without its arches
    beams = [box_mesh((-12.0, 6.0, z - 0.3), (12.0, 7.0, z + 0.3)) for z in (-2.5, 2.5)]
    opaque = (*shell, merge(columns, "columns", (0.75, 0.72, 0.66)), merge(beams, "beams", (0.7, 0.66, 0.6)))
    fog = Fog(extinction=0.08, albedo=(0.9, 0.9, 0.9), g=0.5, density=1.0, height_density=0.5, height_falloff=0.4,
              height_base=0.0, boxes=(
                  FogBox((0.0, 0.6, 0.0), (12.0, 0.6, 5.0), density=2.0, noise_amount=0.6, noise_frequency=0.6,
                         seed=1),
                  FogBox((-4.0, 2.0, 1.5), (3.0, 2.0, 2.0), density=3.0, noise_amount=0.7, noise_frequency=0.8,
                         seed=2),
              ))
    lights: tuple[Light, ...] = (DirectionalLight(HALL_SUN, (8.0, 7.5, 6.5)),)
    return Scene((), lights, Environment((0.02, 0.022, 0.026)), name="hall", opaque=opaque, fog=fog)


COURTYARD_SKY = (0.01, 0.016, 0.04)
"""the courtyard's night sky: dark blue, the ambient of everything the lamps do not reach"""


def _courtyard(time: float) -> Scene:
    ground = merge([box_mesh((-15.0, -0.3, -15.0), (15.0, 0.0, 15.0))], "ground", (0.35, 0.33, 0.3))
    # (x0, x1, z0, z1, height): blocks along the four sides, with alleys between them
    blocks = [
        (-15.0, -6.0, -15.0, -10.0, 8.0), (-4.0, 5.0, -15.0, -10.0, 10.0), (7.0, 15.0, -15.0, -10.0, 6.0),
        (-15.0, -3.0, 10.0, 15.0, 5.0), (-1.0, 15.0, 10.0, 15.0, 7.0),
        (-15.0, -10.0, -8.0, 3.0, 4.0), (-15.0, -10.0, 5.0, 8.0, 9.0),
        (10.0, 15.0, -8.0, -2.0, 8.0), (10.0, 15.0, 0.0, 8.0, 5.0),
    ]
    buildings = merge([box_mesh((x0, 0.0, z0), (x1, h, z1)) for x0, x1, z0, z1, h in blocks], "buildings",
                      (0.62, 0.55, 0.48))
    fountain = merge([cylinder_mesh((0.0, 0.0, 0.0), 2.5, 0.5, 48), cylinder_mesh((0.0, 0.5, 0.0), 0.3, 1.5),
                      cylinder_mesh((0.0, 2.0, 0.0), 1.0, 0.2, 32)], "fountain", (0.7, 0.7, 0.68))
    lamp_xz = [(-6.0, -6.0), (6.0, -6.0), (6.0, 6.0), (-6.0, 6.0)]
    props = [cylinder_mesh((x, 0.0, z), 0.08, 3.4, 12) for x, z in lamp_xz]
    props += [box_mesh((-8.0, 0.0, -1.0), (-6.5, 0.45, 1.0)), box_mesh((4.0, 0.0, 3.0), (5.0, 0.9, 4.0)),
              box_mesh((4.6, 0.0, 4.3), (5.4, 0.6, 5.1))]  # a bench and two crates
    # A night picture (issue 22.10): lamps and spots dim enough that the square between their pools stays dark under
    # a blue night sky (4.5 W/sr lamps, not 45, which lit every facade beige through the fog)
    lamps = [PointLight((x, 3.6, z), e) for (x, z), e in zip(lamp_xz, [(4.5, 3.0, 1.4), (4.0, 2.8, 1.2),
                                                                       (3.5, 2.6, 1.4), (5.0, 3.4, 1.6)],
                                                             strict=True)]
    # (position on a facade, aim point on the ground)
    spots = [((0.0, 7.0, -9.6), (0.0, 0.0, -4.0)), ((9.6, 4.5, 3.0), (5.0, 0.0, 3.0)),
             ((-6.0, 4.5, 9.6), (-6.0, 0.0, 5.0))]
    spot_lights = [SpotLight(p, tuple(np.subtract(a, p)), (11.0, 11.5, 12.5), inner_angle=20.0, outer_angle=35.0)
                   for p, a in spots]
    fog = Fog(extinction=0.012, albedo=(0.9, 0.9, 0.9), g=0.3, density=1.0, height_density=1.0, height_falloff=0.3,
              height_base=0.0, boxes=(FogBox((0.0, 1.0, 0.0), (3.5, 1.0, 3.5), density=3.0, noise_amount=0.5,
                                             noise_frequency=0.7, seed=3),))
    opaque = (ground, buildings, fountain, merge(props, "props", (0.4, 0.36, 0.3)))
    return Scene((), (*lamps, *spot_lights), Environment(COURTYARD_SKY), name="courtyard", opaque=opaque,
                 fog=fog)


DYNAMIC_SUN = sun_direction(40.0, 20.0)


def _dynamic(time: float) -> Scene:
    shell = room_shell(6.0, 6.0, 5.0, 0.4, 0.3, 1.0, 4.0, [(-4.5, -2.5), (-1.0, 1.0), (2.5, 4.5)])
    # the movers stay in the sunlit wedge near the window wall (z ~ 4-6, y < 3), periods 8 s, 6 s / 3 s and 4 s
    w = 2.0 * math.pi / 8.0
    c = (2.0 * math.cos(w * time), 1.5 + 0.4 * math.sin(2.0 * w * time), 4.6 + 0.6 * math.sin(w * time))
    box = rotate_y(box_mesh(np.subtract(c, 0.35), np.add(c, 0.35)), w * time, c)
    sphere = sphere_mesh((-4.2 + 0.6 * math.sin(2.0 * math.pi * time / 6.0),
                          1.2 + 0.5 * math.sin(2.0 * math.pi * time / 3.0), 5.0), 0.45)
    hub = (4.0, 2.4, 5.0)
    blades = [box_mesh((3.2, 2.37, 4.875), (4.8, 2.43, 5.125)), box_mesh((3.875, 2.37, 4.2), (4.125, 2.43, 5.8))]
    fan = [rotate_y(b, 2.0 * math.pi * time / 4.0, hub) for b in blades]
    fan.append(cylinder_mesh((4.0, 2.43, 5.0), 0.03, 2.57, 8))  # the rod up to the ceiling
    opaque = (*shell, merge([box], "box", (0.8, 0.3, 0.2)), merge([sphere], "sphere", (0.25, 0.45, 0.8)),
              merge(fan, "fan", (0.3, 0.3, 0.3)))
    fog = Fog(extinction=0.1, albedo=(0.9, 0.9, 0.9), g=0.5, density=1.0, height_density=0.5, height_falloff=0.5,
              height_base=0.0, boxes=(FogBox((0.0, 0.5, 0.0), (6.0, 0.5, 6.0), density=2.0, noise_amount=0.6,
                                             noise_frequency=0.8, seed=4),))
    lights: tuple[Light, ...] = (DirectionalLight(DYNAMIC_SUN, (8.0, 7.5, 6.5)),)
    return Scene((), lights, Environment((0.02, 0.022, 0.026)), name="dynamic", opaque=opaque, fog=fog)


_BUILDERS: dict[str, Callable[[float], Scene]] = {"hall": _hall, "courtyard": _courtyard, "dynamic": _dynamic}

_CAMERAS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "hall": ((-11.0, 1.7, -1.5), (4.0, 2.6, 1.5)),
    "courtyard": ((-10.0, 2.0, 8.5), (3.0, 2.5, -4.0)),
    "dynamic": ((-5.0, 1.7, -5.0), (0.5, 1.8, 4.0)),
}


def _check_name(name: str) -> None:
    if name not in FOG_SCENES:
        raise VolrenError(f"unknown fog scene {name!r}; choose one of: {', '.join(FOG_SCENES)}")


def fog_scene(name: str, time: float = 0.0) -> Scene:
    """The built-in fog scene ``name`` at ``time`` [s] (only ``dynamic`` moves; the others ignore it)."""
    _check_name(name)
    if not math.isfinite(time):
        raise VolrenError(f"fog scene time must be a finite number of seconds, got {time}")
    return _BUILDERS[name](float(time))


def fog_scene_camera(name: str) -> dict:
    """A default viewpoint inside the scene: ``position`` and ``look_at`` (3-tuples [m]), and ``extent`` = (lo, hi),
    the world-space bounds of the scene's meshes (the moving objects of ``dynamic`` stay inside its room)."""
    _check_name(name)
    vertices = np.concatenate([m.vertices for m in fog_scene(name).opaque])
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    position, look_at = _CAMERAS[name]
    return {"position": position, "look_at": look_at,
            "extent": (tuple(round(float(v), 6) for v in lo), tuple(round(float(v), 6) for v in hi))}


_WALK_BOUNDS: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "hall": ((-12.0, -5.0), (12.0, 5.0)),
    "courtyard": ((-15.0, -15.0), (15.0, 15.0)),
    "dynamic": ((-6.0, -6.0), (6.0, 6.0)),
}
"""[m] (x, z) of each scene's floor: the hall's and the room's interiors, the courtyard's ground"""
STEP_HEIGHT = 0.05
"""[m] parts lower than this above the floor (the floor slab) can be walked over"""
HEADROOM = 0.3
"""[m] above the eyes: parts higher than EYE_HEIGHT + this (beams, ceilings, the fan) pass overhead"""
WALK_PERIOD = 24.0
"""[s] the common period of the dynamic scene's movers: their footprints are swept over it"""


def part_footprints(mesh: TriangleMesh, floor: float) -> list[tuple[float, float, float, float] | None]:
    """(x0, z0, x1, z1) bounds of each closed part (connected component) of ``mesh``, None for a part a walker does
    not bump into (no higher than STEP_HEIGHT above the floor, or starting above the head)."""
    n = len(mesh.vertices)
    edges = np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    parts, label = connected_components(graph, directed=False)
    out = []
    for c in range(parts):
        v = mesh.vertices[label == c]
        lo, hi = v.min(0), v.max(0)
        bump = hi[1] > floor + STEP_HEIGHT and lo[1] < floor + EYE_HEIGHT + HEADROOM
        out.append((float(lo[0]), float(lo[2]), float(hi[0]), float(hi[2])) if bump else None)
    return out


@cache
def fog_scene_walk_area(name: str) -> WalkArea:
    """Where viewers may stand in fog scene ``name``: its floor (`_WALK_BOUNDS`) minus the footprints of every part
    in the way (walls, columns, buildings, the fountain, lamp posts, props; the dynamic scene's movers swept over
    their period)."""
    _check_name(name)
    times = np.linspace(0.0, WALK_PERIOD, 97) if name in ANIMATED_FOG_SCENES else [0.0]
    swept: dict[tuple[int, int], np.ndarray] = {}  # (mesh, part) -> footprint bounds over time
    for t in times:
        for m, mesh in enumerate(fog_scene(name, float(t)).opaque):
            for p, f in enumerate(part_footprints(mesh, 0.0)):
                if f is not None:
                    b = swept.setdefault((m, p), np.array(f))
                    b[:2], b[2:] = np.minimum(b[:2], f[:2]), np.maximum(b[2:], f[2:])
    lo, hi = _WALK_BOUNDS[name]
    return WalkArea(lo, hi, floor=0.0, obstacles=tuple(tuple(float(v) for v in b) for b in swept.values()))
