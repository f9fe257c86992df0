"""Which shard of `serve --shards N` renders a viewer (pure Python: no Ray, no renderer).

A viewer is placed whole, its stereo pair included (one viewer, one job: the eyes stay one coupled CACRM pair). What
a shard renders per tick is its viewers' pixels plus the passes its render call shares between them: the light map,
the GI update, the fog shadow grid and the majorants of the part of the scene they look at. So the work a viewer adds
to a shard (`added_work`) is its pixels, plus SHARED_PASS_PX when no viewer there looks at what it looks at (its
frustum overlaps none of theirs: it brings a new rig, a new part of the scene, to that shard). A new viewer goes to
the shard where it adds the least work; ties go to the least loaded shard (fewest pixels), then the lowest index.

Frusta are compared by what they look at (`Footprint`): the ball about the camera's look-at point that its view cone
covers at the look-at distance (radius d tan(half the diagonal field of view)). Two viewers whose balls intersect see
the same part of the scene (an orbit about one volume, a group around one spot); balls apart are rigs far apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from volren.camera import Camera

SHARED_PASS_PX = 128 * 128
"""[px] the cost of a rig's shared passes in pixels of view work: the 64^3 smoke's light map at the interactive
preset took 31-99 ms on the CPU (2 busy cores) where one 320x180 view's passes took 150-250 ms, about a quarter"""


@dataclass(frozen=True)
class Footprint:
    """What a viewer costs (``pixels``, both eyes of a stereo pair) and looks at (a ball: ``centre``, ``radius``)."""

    pixels: int
    centre: tuple[float, float, float]
    radius: float


def footprint(camera: Camera, width: int, height: int) -> Footprint:
    """``camera``'s footprint for a viewer image of ``width`` x ``height`` pixels (both eyes when stereo)."""
    eye = camera.position
    d = math.dist(eye, camera.look_at)
    aspect = camera.width / camera.height
    half_y = math.tan(math.radians(camera.fov_y) / 2)
    return Footprint(width * height, tuple(float(x) for x in camera.look_at),  # type: ignore[arg-type]
                     d * half_y * math.hypot(1.0, aspect))


def overlaps(a: Footprint, b: Footprint) -> bool:
    return math.dist(a.centre, b.centre) < a.radius + b.radius


def added_work(shard: list[Footprint], new: Footprint) -> int:
    """[px] the work ``new`` adds to a shard holding ``shard``: its pixels, and the shared passes of its rig when no
    viewer there overlaps it."""
    return new.pixels + (0 if any(overlaps(new, f) for f in shard) else SHARED_PASS_PX)


def choose_shard(shards: list[list[Footprint] | None], new: Footprint) -> int:
    """The index of the shard ``new`` goes to: least added work, then least load, then lowest index. ``None`` marks
    a shard that is down (never chosen); at least one must be up."""
    live = [i for i, s in enumerate(shards) if s is not None]
    if not live:
        raise ValueError("no shard is up")
    return min(live, key=lambda i: (added_work(shards[i], new), sum(f.pixels for f in shards[i]), i))
