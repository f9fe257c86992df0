"""Which level each brick wants this frame, whether it is in view, and in which order the bricks load (issue 41
item 3).

**Placement.** Every level of a pyramid fills the same local cube [-1, 1]^3 (DESIGN.md: voxel i of n sits at local
-1 + (i + 0.5) 2 / n), placed in the world by the volume's ``to_world`` matrix; so level k's voxel index (x, y, z)
maps to the world by ``to_world @ index_to_local(shape_k)`` (`level_index_to_world`), and its voxel size is
``voxel_size(to_world, shape_k)`` [m], the longest of its three world edges.

**Level rule.** For a brick whose world box (the box around the voxel centres it spans, grown by half a voxel at
the volume's border, transformed to the world and boxed again) is at distance d from the camera (Euclidean distance
from the eye to the nearest point of the box, 0 inside it), the pixel footprint is

    footprint(d) = 2 d tan(fov_y / 2) / H          (H: image height in pixels)

the width a pixel covers at distance d on the view axis. The wanted level is the **coarsest level k whose voxel size
v_k <= max(footprint(d), step)** (``step``: the ray march's step [m]); where no level's voxel is that small, level 0.
A level's voxel is its longest world edge, so an anisotropic level is taken only where all its edges are small
enough. Finer detail than a pixel or than the step cannot show, so a finer level would cost I/O and memory for
nothing.

**Descent.** The frame's needs start at the coarsest level's bricks: a brick that is out of every view, or wants its
own level or a coarser one, is needed as it is; a visible brick that wants a finer level is replaced by its children
(`PyramidLayout.children`), each judged again. A child lies inside its parent's box, so it is no nearer and wants
no finer level than its parent: the descent stops at the wanted level.

**Visibility** is the brick's world box against each camera's frustum (near, far and the four side planes): a box
wholly outside one plane is out of view (conservative: a box that only crosses a frustum's corner region counts as
visible).

**Priority** (smallest first): ``(not visible, -level, distance)``. Visible before not; among the visible, coarse
before fine, so that every brick of the view reaches level k + 1 before any reaches level k (the whole picture
sharpens evenly, no region waits at the coarsest while another is already fine); within a level, near before far
(the nearest bricks cover the most pixels and draw the eye).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from volren.stream.layout import Brick, BrickKey, PyramidLayout

if TYPE_CHECKING:
    from volren.camera import Camera


def pixel_footprint(distance: float, fov_y: float, height: int) -> float:
    """[m] the width one pixel covers at ``distance`` [m] on the view axis: 2 d tan(fov_y / 2) / H (fov_y in
    degrees)."""
    return 2.0 * distance * math.tan(math.radians(fov_y) / 2.0) / height


def wanted_level(voxel_sizes: Sequence[float], footprint: float, step: float = 0.0) -> int:
    """The coarsest level whose voxel size [m] is at most max(footprint, step); 0 where none is (module docstring).
    ``voxel_sizes`` finest first."""
    limit = max(footprint, step)
    fitting = [k for k, v in enumerate(voxel_sizes) if v <= limit * (1 + 1e-9)]
    return max(fitting) if fitting else 0


def index_to_local(shape: Sequence[int]) -> np.ndarray:
    """4x4: voxel index (x, y, z, 1) of a level of ``shape`` voxels (z, y, x) -> local [-1, 1]^3 (DESIGN.md)."""
    n = np.array(shape[::-1], dtype=np.float64)
    m = np.eye(4)
    m[[0, 1, 2], [0, 1, 2]] = 2.0 / n
    m[:3, 3] = -1.0 + 1.0 / n
    return m


def level_index_to_world(to_world: np.ndarray, shape: Sequence[int]) -> np.ndarray:
    """4x4: voxel index (x, y, z, 1) of a level of ``shape`` voxels -> world [m]."""
    return np.asarray(to_world, dtype=np.float64) @ index_to_local(shape)


def voxel_size(to_world: np.ndarray, shape: Sequence[int]) -> float:
    """[m] the longest world edge of a voxel of a level of ``shape`` voxels placed by ``to_world``."""
    return float(np.max(np.linalg.norm(level_index_to_world(to_world, shape)[:3, :3], axis=0)))


def brick_box(to_world: np.ndarray, layout: PyramidLayout, level: int, brick: Brick) -> tuple[np.ndarray, np.ndarray]:
    """The world box (lo, hi) [m] of ``brick`` of ``level`` (module docstring)."""
    lo, hi = _boxes(to_world, layout, level, np.array([brick], dtype=np.int64))
    return lo[0], hi[0]


def box_distance(eye: Sequence[float], lo: np.ndarray, hi: np.ndarray) -> float:
    """[m] from ``eye`` to the nearest point of the box [lo, hi]; 0 inside it."""
    return float(_distances(np.asarray(eye, dtype=np.float64), np.atleast_2d(lo), np.atleast_2d(hi))[0])


def in_frustum(camera: Camera, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether the box [lo, hi] may be seen by ``camera``: not wholly outside one of its six frustum planes."""
    eye = np.asarray(camera.position, dtype=np.float64)
    return bool(_seen(eye, _planes(camera), np.atleast_2d(lo), np.atleast_2d(hi))[0])


@dataclass(frozen=True, order=True)
class BrickNeed:
    """One brick a frame needs, sortable by priority (module docstring)."""

    priority: tuple[int, int, float]
    """(not visible, -level, distance [m])"""
    key: BrickKey
    """(level, bz, by, bx)"""

    @property
    def level(self) -> int:
        return self.key[0]

    @property
    def brick(self) -> Brick:
        return self.key[1:]  # type: ignore[return-value]

    @property
    def visible(self) -> bool:
        return self.priority[0] == 0


def need(key: BrickKey, visible: bool, distance: float) -> BrickNeed:
    return BrickNeed((0 if visible else 1, -key[0], float(distance)), key)


def need_keys(needs: Sequence[BrickNeed]) -> np.ndarray:
    """(M, 4) int64: the keys (level, bz, by, bx) of ``needs``, in their order."""
    return np.array([n.key for n in needs], np.int64).reshape(-1, 4)


def _within(refine: np.ndarray, distance: np.ndarray, room: int, growth: int) -> np.ndarray:
    """``refine`` cut to its nearest bricks where refining them all would add more than ``room`` bricks, each
    refined brick adding at most ``growth`` (its children; it stays wanted, as their ancestor)."""
    chosen = np.flatnonzero(refine)
    most = max(room, 0) // max(growth, 1)
    if len(chosen) <= most:
        return refine
    out = np.zeros_like(refine)
    out[chosen[np.argsort(distance[chosen], kind="stable")[:most]]] = True
    return out


def _order(n: BrickNeed) -> tuple[tuple[int, int, float], BrickKey]:
    return n.priority, n.key


def _boxes(to_world: np.ndarray, layout: PyramidLayout, level: int, bricks: np.ndarray) -> tuple[np.ndarray, ...]:
    """`brick_box` of many bricks (M, 3) (z, y, x) of ``level`` at once: their world boxes (lo, hi), (M, 3) each."""
    shape, counts, b = np.array(layout.shapes[level]), np.array(layout.bricks(level)), layout.brick
    first = bricks * b
    lo_i = np.where(bricks == 0, first - 0.5, first)
    last = np.minimum(first + b, shape - 1)
    hi_i = np.where(bricks == counts - 1, last + 0.5, last).astype(float)
    m = level_index_to_world(to_world, layout.shapes[level])
    corners = []
    for cx in (lo_i[:, 2], hi_i[:, 2]):  # index (x, y, z) of the 8 corners
        for cy in (lo_i[:, 1], hi_i[:, 1]):
            for cz in (lo_i[:, 0], hi_i[:, 0]):
                corners.append(np.stack([cx, cy, cz], 1) @ m[:3, :3].T + m[:3, 3])
    corners = np.stack(corners)
    return corners.min(axis=0), corners.max(axis=0)


def _distances(eye: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """`box_distance` of one eye to many boxes."""
    return np.sqrt(np.sum((eye - np.clip(eye, lo, hi)) ** 2, axis=1))


def _planes(camera: Camera) -> list[tuple[np.ndarray, float]]:
    """The inward normals n and offsets o of ``camera``'s six frustum planes (`in_frustum`)."""
    right, up, forward = (np.asarray(v, dtype=np.float64) for v in camera.basis())
    t = camera.tan_half_fov
    tx = t * camera.width / camera.height
    return [(forward, camera.near), (-forward, -camera.far), (tx * forward - right, 0.0),
            (tx * forward + right, 0.0), (t * forward - up, 0.0), (t * forward + up, 0.0)]


def _seen(eye: np.ndarray, planes: list[tuple[np.ndarray, float]], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """`in_frustum` of many boxes for one camera (its planes computed once a frame: per brick, `Camera.basis` was
    1 s of a 2 s frame of 9,168 bricks)."""
    inside = np.ones(len(lo), bool)
    for n, o in planes:
        farthest = np.where(n >= 0, hi, lo)
        inside &= (farthest - eye) @ n >= o
    return inside


def _children(layout: PyramidLayout, level: int, bricks: np.ndarray) -> np.ndarray:
    """`PyramidLayout.children` of many bricks of ``level`` (M, 3): the bricks of level - 1 under them."""
    counts, own = np.array(layout.bricks(level - 1)), np.array(layout.bricks(level))
    f = np.array(layout.factors[level - 1])
    first = bricks * f
    stop = np.where(bricks == own - 1, counts, np.minimum(first + f, counts))  # the last takes a clamped overflow
    span = stop - first
    out = []
    for extent in np.unique(span, axis=0):
        group = first[np.all(span == extent, axis=1)]
        offsets = np.stack(np.meshgrid(*[np.arange(e) for e in extent], indexing="ij"), -1).reshape(-1, 3)
        out.append((group[:, None, :] + offsets[None]).reshape(-1, 3))
    return np.concatenate(out) if out else np.zeros((0, 3), np.int64)


def frame_needs(views: Sequence[Camera], to_world: np.ndarray, layout: PyramidLayout, *, step: float = 0.0,
                marched: int | None = None, ancestors: bool = False, limit: int | None = None) -> list[BrickNeed]:
    """The bricks a frame seen by ``views`` needs, by the level rule and the descent of the module docstring, in
    priority order. Each brick is judged for every view: visible where any view sees it, at the finest level a view
    that sees it wants, its distance the nearest such view's (the nearest view's where none sees it). A level's
    bricks are judged at once (numpy), the views' frustum planes computed once.

    For a renderer that reads a level of its own besides (the cube-map methods march level l of the pyramid into
    their cube maps, and the pixels they march directly at the footprint's level): the visible bricks are refined to
    level ``marched`` at least, and with ``ancestors`` a refined brick is needed too, so that every level a sample
    may be read at is on the device.

    ``limit``: the most bricks the memory budget holds beside the coarsest level (`BrickStreamer.room`). Where
    refining every brick that wants it would need more (the needs and their ancestors below the coarsest level,
    which the streamer holds too), the nearest are refined and the rest stay needs at their level (coarse before
    fine, near before far: the rule the streamer admits by), so what is wanted never outgrows what can be held. A
    1080p close-up of a 4096^3 pyramid wants 2.5 M bricks of levels 0 and 1 where a 2 GiB budget holds 55 K: judged
    brick by brick they took a minute a frame, and what came was drawn from level 2 everywhere."""
    if not views:
        raise ValueError("frame_needs needs at least one view")
    sizes = np.array([voxel_size(to_world, s) for s in layout.shapes])
    cams = [(np.asarray(v.position, dtype=np.float64), _planes(v), math.tan(math.radians(v.fov_y) / 2.0) / v.height)
            for v in views]
    out: list[BrickNeed] = []
    held = 0  # bricks below the coarsest level the streamer will hold: the needs and their ancestors (refined ones)
    level = layout.coarsest
    bricks = np.array(list(np.ndindex(*layout.bricks(level))), dtype=np.int64).reshape(-1, 3)
    while len(bricks):
        lo, hi = _boxes(to_world, layout, level, bricks)
        seen = np.stack([_seen(eye, planes, lo, hi) for eye, planes, _ in cams])
        dist = np.stack([_distances(eye, lo, hi) for eye, _, _ in cams])
        visible = seen.any(axis=0)
        distance = np.where(visible, np.where(seen, dist, np.inf).min(axis=0), dist.min(axis=0))
        # the coarsest level whose voxel is at most max(footprint, step) per view (wanted_level), the finest over
        # the views that see the brick
        footprint = np.maximum(2.0 * dist * np.array([c[2] for c in cams])[:, None], step) * (1 + 1e-9)
        wanted = np.maximum(np.searchsorted(sizes, footprint, side="right") - 1, 0)
        want = np.where(seen, wanted, level).min(axis=0)
        refine = visible & ((want < level) | (marched is not None and level > marched))
        held += len(bricks) if level < layout.coarsest else 0
        if limit is not None and refine.any():
            refine = _within(refine, distance, limit - held, int(np.prod(layout.factors[level - 1])))
        keep = np.arange(len(bricks)) if ancestors else np.flatnonzero(~refine)
        out += [need((level, *(int(v) for v in bricks[i])), bool(visible[i]), float(distance[i])) for i in keep]
        if level == 0 or not refine.any():
            break
        bricks = _children(layout, level, bricks[refine])
        level -= 1
    return sorted(out, key=_order)  # BrickNeed's order, compared as tuples: its generated __lt__ took 0.1 s of 8 K
