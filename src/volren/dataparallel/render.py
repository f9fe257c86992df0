"""Sort-last rendering of a volume split into regions (issue 43 items 2 and 3), one renderer per region, in this
process (`RegionSet`, what the tests compare and `volren.distributed.regions` runs one per Ray actor).

A frame is two passes over the regions:

1. **Light.** Each region's renderer runs its light-map pass on its own region (`LightMapRenderer.region_light_map`):
   every light-map node's march towards each light takes the steps of the one-process march (the whole box's t0, t1
   and step count) whose cell the region owns, so its map holds the optical depth of the region's part of each
   node's path. Optical depth adds along a path, so the regions' maps summed are the one-process map (to float
   rounding of the sum): the regions exchange their maps once (a reduction, not a sweep in light order: no region
   waits on the ones before it along the light; what travels is each map's non-zero box and, back, the sum over the
   nodes each region reads, `volren.dataparallel.light`), and only when the map's inputs change (an orbit keeps
   it). This departs from the issue's "boundary optical depth in light order": a boundary map is exact only for the
   nodes on a region's face; the sum is exact at every node and costs one exchange (bytes in the stats).
2. **Views.** Each region marches the steps of the one-process march whose cell it owns
   (`volren.kernels.common.owns_sample`), shaded from the summed map, into premultiplied RGBA and depth; the partial
   images composite in each view's visibility order (`volren.dataparallel.order`): ``over`` for DVR, ``max`` for MIP
   (bit-exact: the same samples read the same voxels), the nearest hit for iso (exact: its depth is the hit's). A
   DVR pixel's depth (where the transmittance fell to 1/2) is the nearest region's: regions do not know the
   transmittance in front of them.

What runs: DSSRM in modes dvr (with shadows), mip and iso, one volume (dense, bricked, .vdb or a streamed pyramid's
finest level) or a multi-channel file's channels (each split alike, composited over its regions, then tinted and
added as `volren.render.compositing.channels.AdditiveChannels` adds them), directional, point and spot lights.
Refused in one line: other methods (CMSRM's and CACRM's cube maps and LOD levels, VPT's paths and GI's SH grids
cross regions and are not split), MIDA (its running maximum weighs what lies in front, across regions), several
volumes, meshes and fog. Early ray termination does not cross regions: each region marches to its own end, so DVR
differs from the one-process image by at most the termination threshold in alpha (and a dense front region makes
the back ones' work wasted, not wrong).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from volren.camera import Camera
from volren.dataparallel.composite import composite_max, composite_nearest, composite_over
from volren.dataparallel.light import light_map_of, light_part, light_patch, light_sum
from volren.dataparallel.order import visibility_order
from volren.dataparallel.regions import RegionTree, split_regions
from volren.dataparallel.volume import brick_weights, region_volume
from volren.errors import VolrenError
from volren.render.compositing.channels import add_channel_images, channel_color, tint_mip
from volren.render.frame import Frame, Stats
from volren.scene import Scene
from volren.sparse.grid import BRICK

METHODS = ("dssrm",)
"""the methods that render data-parallel"""
MODES = ("dvr", "mip", "iso")


def check_data_parallel(method: str, config: Any, scene: Scene | None = None, flag: str = "--data-parallel",
                        channels: bool = False) -> None:
    """Refuse in one line what does not split into regions (module docstring). ``channels``: the scene's volumes are
    a multi-channel file's (`volren.render.compositing.channels`), one grid at one placement, split alike."""
    if method not in METHODS:
        raise VolrenError(f"{flag} renders with {', '.join(METHODS)} only: method {method} has cube maps, paths or "
                          "grids that cross the regions")
    mode = getattr(config, "mode", "dvr")
    if mode not in MODES:
        raise VolrenError(f"{flag} renders modes {', '.join(MODES)}: mode {mode}'s running maximum weighs what lies in "
                          "front, in other regions")
    if getattr(config, "gi", None) is not None and config.gi.on:
        raise VolrenError(f"{flag} does not split ambient GI's SH grid across regions: leave --gi off")
    if scene is None:
        return
    volumes = scene.volumes
    if not channels and len(volumes) != 1:
        raise VolrenError(f"{flag} splits one volume into regions; scene '{scene.name}' has {len(volumes)}")
    if any(v.density.shape != volumes[0].density.shape or not np.array_equal(v.to_world, volumes[0].to_world)
           for v in volumes):
        raise VolrenError(f"{flag} splits channels of one grid at one placement; scene '{scene.name}'s differ")
    if scene.opaque or scene.fog is not None:
        raise VolrenError(f"{flag} renders a volume alone: scene '{scene.name}' has meshes or fog")


def split_volume(scene: Scene, n: int, brick: int = BRICK) -> RegionTree:
    """The k-d tree of ``n`` regions of the scene's volume (its channels': one grid), balanced by the bricks active
    in any of them (`brick_weights`)."""
    density = scene.volumes[0].density
    weights = np.sum([brick_weights(v.density, brick) for v in scene.volumes], axis=0) > 0
    if not weights.any():
        weights[...] = True  # nothing active: halve geometrically
    return split_regions(weights.astype(np.float64), n, shape=tuple(int(s) for s in density.shape), brick=brick)


def region_scenes(scene: Scene, tree: RegionTree, index: int, mode: str, channels: bool = False) -> list[Scene]:
    """The scenes region ``index`` renders: the scene with its volume cut to the region (`region_volume`; iso holds
    one brick around it for the crossing search and the gradient), or with ``channels`` one scene per channel, as
    `volren.render.compositing.channels.AdditiveChannels` renders them."""
    halo = 1 if mode == "iso" else 0
    cut = [region_volume(v, tree.regions[index], tree, halo) for v in scene.volumes]
    if not channels:
        return [replace(scene, volumes=(cut[0],))]
    return [replace(scene, volumes=(v,), name=f"{scene.name}[c{c}]") for c, v in enumerate(cut)]


def view_orders(tree: RegionTree, to_local: np.ndarray, views: Sequence[Camera]) -> list[list[int]]:
    """Per view, the regions front to back for its eye (`visibility_order` in the volume's local coordinates, which
    ``to_local`` maps the world into)."""
    return [visibility_order(tree, (to_local @ np.append(np.asarray(c.position, np.float64), 1.0))[:3])
            for c in views]


def composite_views(images: Sequence[Sequence[np.ndarray]], depths: Sequence[Sequence[np.ndarray]],
                    orders: Sequence[Sequence[int]], mode: str) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per view the composited image and depth of the regions' partial ones (``images[r][v]``: region r, view v)."""
    out_images, out_depths = [], []
    for v, order in enumerate(orders):
        rgba = [im[v] for im in images]
        z = [d[v] for d in depths]
        if mode == "iso":
            image, depth = composite_nearest(rgba, z, order)
            out_images.append(image)
            out_depths.append(depth)
            continue
        out_images.append(composite_max(rgba) if mode == "mip" else composite_over(rgba, order))
        out_depths.append(np.minimum.reduce(z))  # the nearest region's (module docstring), whatever the order
    return out_images, out_depths


def composite_channels(images: Sequence[Sequence[Sequence[np.ndarray]]],
                       depths: Sequence[Sequence[Sequence[np.ndarray]]], orders: Sequence[Sequence[int]], mode: str,
                       colors: Sequence[np.ndarray] | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per view the composited image and depth of the regions' partial ones per channel (``images[r][c][v]``):
    each channel composited over its regions (`composite_views`), then, with ``colors`` (a multi-channel scene's),
    MIP tinted and the channels added as `AdditiveChannels` adds them."""
    per_channel = [composite_views([im[c] for im in images], [d[c] for d in depths], orders, mode)
                   for c in range(len(images[0]))]
    if colors is None:
        return per_channel[0]
    out_images, out_depths = [], []
    for v in range(len(orders)):
        rgba = [tint_mip(ims[v], colors[c]) if mode == "mip" else ims[v] for c, (ims, _) in enumerate(per_channel)]
        image, depth = add_channel_images(rgba, [ds[v] for _, ds in per_channel])
        out_images.append(image)
        out_depths.append(depth)
    return out_images, out_depths


def channel_colors(scene: Scene, channels: bool) -> list[np.ndarray] | None:
    """The channels' colours (`channel_color`) for `composite_channels`; None for one volume."""
    return [channel_color(v) for v in scene.volumes] if channels else None


def region_report(tree: RegionTree, index: int, scenes: Sequence[Scene], stats: Stats | None = None,
                  load_seconds: float | None = None) -> dict[str, Any]:
    """stats.json's entry of one region: its box, bricks held (every channel's) and bytes, its load time and its
    render's pass times."""
    region, grids = tree.regions[index], [s.volumes[0].density for s in scenes]
    out: dict[str, Any] = {"index": index, "lo": list(region.lo), "hi": list(region.hi), "bricks": region.bricks,
                           "active_bricks": int(region.weight), "resident_bricks": sum(len(g.pool) for g in grids),
                           "bytes": sum(int(g.nbytes) for g in grids)}
    if stats is not None:
        out["times_ms"] = {k: round(v, 3) for k, v in stats.times_ms.items()}
    if load_seconds is not None:
        out["load_seconds"] = round(load_seconds, 4)
    return out


def merged_stats(parts: Sequence[Stats], reports: list[dict[str, Any]], times: dict[str, float],
                 extra: dict[str, Any], light: Sequence[tuple[dict[str, float], dict[str, int]]] = ()) -> Stats:
    """One frame's stats from its regions': counters summed (the work of every region, with their light-map passes'
    ``light``: (times, counters) per region), pass times the slowest region's (they run side by side) plus the
    exchange and compositing, ``regions`` and per region its report."""
    first = parts[0]
    counters = {k: sum(p.counters.get(k, 0) for p in parts) + sum(c.get(k, 0) for _, c in light)
                for k in first.counters}
    passes = [p.times_ms for p in parts] + [t for t, _ in light]
    slowest = {k: max(t.get(k, 0.0) for t in passes) for k in {k for t in passes for k in t}}
    info = {**first.info, "regions": len(reports), "region_stats": reports, **extra}
    return Stats(first.device, first.method, {**first.settings, "data_parallel": len(reports)},
                 {**slowest, **times}, counters, info)


@dataclass
class RegionSet:
    """N regions of one scene's volume rendered in this process, one renderer each (per channel with ``channels``),
    composited sort-last (module docstring). ``make_renderer()`` builds one region's renderer (a
    `volren.render.DSSRM`)."""

    scene: Scene
    n: int
    make_renderer: Callable[[], Any]
    channels: bool = False

    def __post_init__(self) -> None:
        count = len(self.scene.volumes) if self.channels else 1
        self.renderers = [[self.make_renderer() for _ in range(count)] for _ in range(self.n)]
        first = self.renderers[0][0]
        check_data_parallel(first.name, first.config, self.scene, channels=self.channels)
        self.mode = first.config.mode
        self.tree = split_volume(self.scene, self.n)
        self.scenes = [region_scenes(self.scene, self.tree, i, self.mode, self.channels) for i in range(self.n)]

    def render(self, views: Sequence[Camera], frame: int = 0) -> Frame:
        views = list(views)
        start = time.perf_counter()
        pairs = [list(zip(rs, ss, strict=True)) for rs, ss in zip(self.renderers, self.scenes, strict=True)]
        maps = [[r.region_light_map(s, frame) for r, s in region] for region in pairs]
        light_bytes = 0
        for c in range(len(pairs[0])):  # the exchange of `volren.dataparallel.light`, as the Ray actors make it
            if any(region[c] is not None for region in maps):
                parts = [light_part(m[c], region[c][1].volumes[0], region[c][0].config.light_grid)
                         for m, region in zip(maps, pairs, strict=True)]
                total = light_sum(parts)
                for region, part in zip(pairs, parts, strict=True):
                    patch = light_patch(total, part)
                    region[c][0].light_map_total = light_map_of(patch, part)
                    light_bytes += part.nbytes + patch.nbytes
        frames = [[r.render(s, views, frame) for r, s in region] for region in pairs]
        t = time.perf_counter()
        orders = view_orders(self.tree, self.scene.volumes[0].to_local, views)
        images, depths = composite_channels([[f.images for f in fs] for fs in frames],
                                            [[f.depths for f in fs] for fs in frames], orders, self.mode,
                                            channel_colors(self.scene, self.channels))
        composite_ms = (time.perf_counter() - t) * 1e3
        reports = [region_report(self.tree, i, ss, fs[0].stats) for i, (ss, fs) in enumerate(zip(self.scenes, frames,
                                                                                                strict=True))]
        stats = merged_stats([f.stats for fs in frames for f in fs], reports, {"composite": composite_ms},
                             {"light_exchange_bytes": light_bytes, "orders": orders,
                              "wall_ms": (time.perf_counter() - start) * 1e3},
                             [r.region_light_stats for rs in self.renderers for r in rs])
        return Frame(images, depths, stats, frame, background=self.scene.background, scene_name=self.scene.name)
