"""Multi-volume order-independent transparency: per pixel, the boxes its ray meets in the order it meets them, and
the joint march where boxes overlap along the ray (paper 001 §3.4, paper 000 §3.4; issue 14).

Layer finding (`pixel_layers`) keeps, per pixel, the K = ``oit_k`` boxes with the nearest entry distances, sorted
front to back (ties by volume index), each clipped to the near/far planes and the opaque surface; boxes beyond the
K-th on a ray are dropped (the k-buffer's behaviour; K = 16 by default and at most). Three schemes find them:

- ``pixel-sort``: every instance box tested per pixel and the K nearest kept in a sorted register k-buffer (paper 000
  Table 3's per-pixel k-buffer baseline); ``box_tests`` = instances per pixel.
- ``pixel-rt``: per pixel one ray query against the instance BVH (`DeviceScene.volume_bvh`, `wp.bvh_query_ray`, paper
  001 §3.4's "following layers found by ray queries"). Warp's query reports every box whose world AABB the ray
  line meets, unordered and without a closest-hit mode, so one traversal tests each reported box exactly and keeps
  the K nearest (the paper repeats a closest-hit query per layer); ``bvh_queries`` = pixels, ``box_tests`` = boxes
  reported. Warp does not report nodes visited, so none are counted.
- ``tiled`` (paper 000 §3.4): phase 1 (`tile_layers_kernel`, timed as "oit") traces one ray per tile of a fixed
  240 x 135 layout (tiles of ceil(W / 240) x ceil(H / 135) pixels, 8 x 8 at 1080p) through the tile centre against a
  per-view BVH over conservatively enlarged boxes and stores the K nearest instance IDs per tile (the tiled
  k-buffer); phase 2 tests per pixel only its tile's instances. The enlargement (`conservative_view_boxes`) is the
  paper's "scale the instance in projection space to cover the tile centre", made exact: a box whose projection
  spans [a0, a1] x [b0, b1] on the image plane (x / z, y / z, from its corners) and depths [z0, z1] becomes the view
  -space AABB of {z in [z0, z1], x / z in [a0 - h_x, a1 + h_x], y / z in [b0 - h_y, b1 + h_y]} with (h_x, h_y) half a
  tile: any pixel ray of the tile that meets the box puts the tile-centre ray through that AABB at the same depth.
  That AABB only feeds the BVH; each box it reports is then tested exactly, the tile centre's (x / z, y / z) against
  the grown rectangle (the AABB is loose where z0 is small: its x range at depth z0 is that of depth z1). A box
  crossing the near plane is first clipped to it (corners and edge crossings at depth >= near): pixel rays keep
  only that part (their intervals start at the near plane), so a box beside the eye covers just the tiles its part
  in front projects to, not every tile (issue 19 item 5: with the eye among 36 instances every tile listed the six
  boxes of the eye's row). The per-pixel result equals the other schemes' whenever at most K boxes touch a tile;
  with more, the tile keeps the K whose parts in front begin nearest (by z0).

Compositing: a run of layers whose intervals overlap (a cluster) is marched jointly (`march_joint`): the run is cut
at every box entry and exit, each piece takes the step count of the smallest diagonal among the boxes covering it
(the reference's rule at the method's V), extinctions add, and the source is each volume's own light-map-shaded
scattering plus emission weighted by its own density, as `volren.render.reference` does. A layer alone is left to
the method (DSSRM marches it, the cube methods read its cube map), which is exact for disjoint boxes in any
arrangement, the eye inside a box included. ``joint_rays`` counts the pixels with a cluster.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.kernels.common import (
    INF,
    CameraGPU,
    MarchState,
    Medium,
    VolumeGPU,
    box_hit,
    composite_step,
    count,
    counter_row,
    emitted_radiance,
    half_depth,
    march_step_count,
    sample_density,
    state_accumulator,
    with_accumulator,
)
from volren.render.base import MAX_OIT_K
from volren.render.frame import BOX_TESTS, BVH_QUERIES, TILE_BOX_TESTS, PassClock
from volren.render.marching.march import MarchParams, shade_light_map
from volren.upload import DeviceScene, camera_struct

OIT_TILED = 0
OIT_PIXEL_RT = 1
OIT_PIXEL_SORT = 2
OIT_CODES = {"tiled": OIT_TILED, "pixel-rt": OIT_PIXEL_RT, "pixel-sort": OIT_PIXEL_SORT}
TILE_LAYOUT = (240, 135)
"""paper 000 §3.4: tiles across and down at every viewport size (8 x 8 pixels at 1080p)"""

LayerInts = wp.types.vector(length=MAX_OIT_K, dtype=int)
LayerFloats = wp.types.vector(length=MAX_OIT_K, dtype=float)


@wp.struct
class Layers:
    """A pixel's k-buffer: the boxes its ray meets, front to back, with entry and exit ray distances."""

    volume: LayerInts
    t_in: LayerFloats
    t_out: LayerFloats
    count: int


@wp.struct
class OITParams:
    scheme: int
    k: int
    bvh: wp.uint64
    """pixel-rt: the instance BVH over world boxes"""
    tile_ids: wp.array2d(dtype=int)
    """tiled: the tiled k-buffer, K instance IDs per tile, front to back"""
    tile_count: wp.array(dtype=int)
    tile_w: int
    tile_h: int
    tiles_x: int


@wp.func
def insert_layer(layers: Layers, v: int, t0: float, t1: float, k: int) -> Layers:
    """Insert box v's interval into the sorted k-buffer (by entry, then index); the farthest drops out when full."""
    out = layers
    j = out.count
    if j == k:
        last = k - 1
        if t0 > out.t_in[last] or (t0 == out.t_in[last] and v > out.volume[last]):
            return out
        j = last
    else:
        out.count = j + 1
    while j > 0 and (out.t_in[j - 1] > t0 or (out.t_in[j - 1] == t0 and out.volume[j - 1] > v)):
        out.volume[j] = out.volume[j - 1]
        out.t_in[j] = out.t_in[j - 1]
        out.t_out[j] = out.t_out[j - 1]
        j -= 1
    out.volume[j] = v
    out.t_in[j] = t0
    out.t_out[j] = t1
    return out


@wp.func
def test_box(layers: Layers, volumes: wp.array(dtype=VolumeGPU), v: int, origin: wp.vec3, d: wp.vec3,
             planes: wp.vec2, k: int) -> Layers:
    """The exact ray/box test of instance v, its interval clipped to ``planes``, inserted when not empty."""
    vol = volumes[v]
    h = box_hit(wp.transform_point(vol.to_local, origin), wp.transform_vector(vol.to_local, d))
    t0 = wp.max(h[0], planes[0])
    t1 = wp.min(h[1], planes[1])
    if t1 > t0:
        return insert_layer(layers, v, t0, t1, k)
    return layers


@wp.func
def pixel_tile(oit: OITParams, row: int, col: int) -> int:
    """The tiled k-buffer's tile holding pixel (row, col)."""
    return (row / oit.tile_h) * oit.tiles_x + col / oit.tile_w


@wp.func
def lone_candidate(oit: OITParams, volumes: wp.array(dtype=VolumeGPU), row: int, col: int) -> wp.vec2i:
    """(n, v): the n boxes `pixel_layers` tests for pixel (row, col) without a ray query, and when n = 1 that box's
    instance v (the cube resampling pass's one-box case); n = -1 for pixel-rt, whose boxes only its query reports."""
    if oit.scheme == OIT_PIXEL_SORT:
        return wp.vec2i(volumes.shape[0], 0)
    if oit.scheme == OIT_PIXEL_RT:
        return wp.vec2i(-1, 0)
    tile = pixel_tile(oit, row, col)
    n = oit.tile_count[tile]
    if n == 1:
        return wp.vec2i(1, oit.tile_ids[tile, 0])
    return wp.vec2i(n, 0)


@wp.func
def pixel_layers(oit: OITParams, volumes: wp.array(dtype=VolumeGPU), origin: wp.vec3, d: wp.vec3, planes: wp.vec2,
                 row: int, col: int, counters: wp.array(dtype=wp.int64)) -> Layers:
    """The pixel's k-buffer by the configured scheme (module docstring), counting its box tests and BVH queries."""
    layers = Layers()
    layers.count = 0
    tested = int(0)
    if oit.scheme == OIT_PIXEL_SORT:
        for v in range(volumes.shape[0]):
            layers = test_box(layers, volumes, v, origin, d, planes, oit.k)
        tested = volumes.shape[0]
    elif oit.scheme == OIT_PIXEL_RT:
        query = wp.bvh_query_ray(oit.bvh, origin, d)
        v = int(0)
        while wp.bvh_query_next(query, v):
            layers = test_box(layers, volumes, v, origin, d, planes, oit.k)
            tested += 1
        count(counters, BVH_QUERIES, 1)
    else:
        tile = pixel_tile(oit, row, col)
        tested = oit.tile_count[tile]
        for i in range(tested):
            layers = test_box(layers, volumes, oit.tile_ids[tile, i], origin, d, planes, oit.k)
    count(counters, BOX_TESTS, tested)
    return layers


@wp.func
def cluster_end(layers: Layers, first: int) -> int:
    """One past the last layer of the run starting at ``first`` whose intervals overlap (chain) along the ray."""
    end = layers.t_out[first]
    j = first + 1
    while j < layers.count and layers.t_in[j] < end:
        end = wp.max(end, layers.t_out[j])
        j += 1
    return j


@wp.func
def next_boundary(layers: Layers, first: int, last: int, t: float) -> float:
    """The nearest entry or exit of layers [first, last) beyond t (INF if none)."""
    best = float(INF)
    for i in range(first, last):
        if layers.t_in[i] > t:
            best = wp.min(best, layers.t_in[i])
        if layers.t_out[i] > t:
            best = wp.min(best, layers.t_out[i])
    return best


@wp.func
def march_joint(
    state: MarchState,
    layers: Layers,
    first: int,
    last: int,
    volumes: wp.array(dtype=VolumeGPU),
    origin: wp.vec3,
    d: wp.vec3,
    offset: float,
    medium: Medium,
    params: MarchParams,
    span: wp.vec2,
) -> MarchState:
    """March the overlapping layers [first, last) together from the first entry to the last exit, clipped to the ray
    distances ``span`` (so that a translucent mesh layer inside the run is blended where it lies, between two calls):
    pieces between box boundaries, each with the step count of its smallest covering diagonal; per sample the
    extinctions of the covering volumes add and each contributes its own shaded scattering and emission
    (reference.py's sum)."""
    acc = state_accumulator(state)
    depth_t = state.depth_t
    taken = int(0)
    shaded = int(0)
    t = wp.max(layers.t_in[first], span[0])
    t_end = layers.t_out[first]
    for i in range(first + 1, last):
        t_end = wp.max(t_end, layers.t_out[i])
    t_end = wp.min(t_end, span[1])
    while t < t_end and acc[3] >= params.min_transmittance:
        t_next = wp.min(next_boundary(layers, first, last, t), t_end)
        mid = 0.5 * (t + t_next)
        diag = float(INF)
        for i in range(first, last):
            if layers.t_in[i] <= mid and mid < layers.t_out[i]:
                diag = wp.min(diag, volumes[layers.volume[i]].diagonal)
        if diag < INF:
            n = march_step_count(t_next - t, diag, params.samples)
            dt = (t_next - t) / float(n)
            for j in range(n):
                ts = t + (float(j) + offset) * dt
                x = origin + ts * d
                sigma_t = float(0.0)
                source = wp.vec3(0.0)
                for i in range(first, last):
                    if layers.t_in[i] <= mid and mid < layers.t_out[i]:
                        vol = volumes[layers.volume[i]]
                        p = wp.transform_point(vol.to_local, x)
                        rho = sample_density(medium.density, vol, p)
                        taken += 1
                        if rho > 0.0:
                            shaded += 1
                            sigma_v = vol.density_scale * rho
                            light = shade_light_map(vol, medium, p, x, d, params.ambient)
                            source += wp.cw_mul(vol.albedo, light) * sigma_v + emitted_radiance(
                                vol, medium.density, p, rho)
                            sigma_t += sigma_v
                if sigma_t > 0.0:
                    before = acc[3]
                    acc = composite_step(acc, source, sigma_t, dt)
                    depth_t = half_depth(depth_t, before, acc[3], ts)
                    if acc[3] < params.min_transmittance:
                        break
        t = t_next
    s = with_accumulator(state, acc)
    s.depth_t = depth_t
    s.samples = s.samples + taken
    s.shaded = s.shaded + shaded
    return s


@wp.kernel
def tile_layers_kernel(
    cam: CameraGPU,
    bvh: wp.uint64,
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
    slopes: wp.array(dtype=wp.vec4),
    tile_w: int,
    tile_h: int,
    tiles_x: int,
    k: int,
    tile_ids: wp.array2d(dtype=int),
    tile_count: wp.array(dtype=int),
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """Phase 1 of the tiled k-buffer: one view-space ray through each tile's centre against the BVH over the
    conservative boxes, each reported box tested exactly against its grown image-plane rectangle ``slopes``; the
    tile keeps the K nearest instance IDs (by the nearest depth of the box's part beyond the near plane) in order."""
    r, tx = wp.tid()
    counters = counter_row(counter_rows, r, tx)
    ty = r + row0
    x = ((float(tx) + 0.5) * float(tile_w) / float(cam.width) * 2.0 - 1.0) * cam.tan_half_fov * cam.aspect
    y = (1.0 - (float(ty) + 0.5) * float(tile_h) / float(cam.height) * 2.0) * cam.tan_half_fov
    d = wp.vec3(x, y, 1.0)
    layers = Layers()
    layers.count = 0
    tested = int(0)
    query = wp.bvh_query_ray(bvh, wp.vec3(0.0), d)
    v = int(0)
    while wp.bvh_query_next(query, v):
        tested += 1
        s = slopes[v]
        if s[0] <= x and x <= s[1] and s[2] <= y and y <= s[3]:
            layers = insert_layer(layers, v, lo[v][2], hi[v][2], k)
    tile = ty * tiles_x + tx
    for i in range(layers.count):
        tile_ids[tile, i] = layers.volume[i]
    tile_count[tile] = layers.count
    count(counters, TILE_BOX_TESTS, tested)
    count(counters, BVH_QUERIES, 1)


@dataclass(frozen=True)
class TileLayout:
    """The tiled k-buffer's tiles for one viewport: ``tiles_x`` x ``tiles_y`` tiles of ``tile_w`` x ``tile_h``
    pixels (the last row and column may stick out of the viewport)."""

    tile_w: int
    tile_h: int
    tiles_x: int
    tiles_y: int


def tile_layout(width: int, height: int, layout: tuple[int, int]) -> TileLayout:
    """Paper 000 §3.4's fixed layout: the tile size grows with the viewport, the tile count stays at ``layout``."""
    tw, th = max(1, math.ceil(width / layout[0])), max(1, math.ceil(height / layout[1]))
    return TileLayout(tw, th, math.ceil(width / tw), math.ceil(height / th))


BOX_EDGES = np.array([(i, i ^ (1 << b)) for i in range(8) for b in range(3) if i < i ^ (1 << b)])
"""the 12 edges of a box as pairs of corner indices (x fastest, the order of `Volume.corners_world`)"""


def clip_to_near(c: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of boxes (n, 8, 3) in view space clipped to depth >= ``near``: (n, 20, 3) points (the 8 corners
    and the 12 edges' crossings of the near plane) and (n, 20) which of them are vertices of the clipped box."""
    a, b = c[:, BOX_EDGES[:, 0]], c[:, BOX_EDGES[:, 1]]
    za, zb = a[..., 2] - near, b[..., 2] - near
    crossing = za * zb < 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crossing, za / (za - zb), 0.0)
    points = np.concatenate([c, a + s[..., None] * (b - a)], axis=1)
    points[:, 8:, 2] = np.where(crossing, near, points[:, 8:, 2])  # exactly on the plane, whatever the rounding
    return points, np.concatenate([c[..., 2] >= near, crossing], axis=1)


def conservative_view_boxes(scene_corners: list[np.ndarray], cam: Camera, tiles: TileLayout
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per instance the image-plane rectangle (x / z from a0 to a1, y / z from b0 to b1) of the box's part at depth
    >= near grown by half a tile, which holds the tile centre whenever a pixel ray of that tile meets the box
    (module docstring), and the view-space (right, up, forward) AABB (lo, hi) of that rectangle's frustum between
    the part's depths, which the tile-centre ray then meets (the phase-1 BVH's boxes). Returns (lo, hi, (a0, a1,
    b0, b1)); a box wholly nearer than the near plane gets an empty box behind the eye and an empty rectangle."""
    right, up, forward = cam.basis()
    axes = np.stack([right, up, forward])
    pixel = 2.0 * cam.tan_half_fov / cam.height
    half = np.array([tiles.tile_w, tiles.tile_h]) * 0.5 * pixel * (1 + 1e-4)
    # all instances at once: a per-instance Python loop cost ~1 ms per view at 36 instances (CPU)
    points, kept = clip_to_near((np.stack(scene_corners) - np.asarray(cam.position)) @ axes.T, cam.near)
    z = points[..., 2]
    z0 = np.where(kept, z, np.inf).min(axis=1)
    z1 = np.where(kept, z, -np.inf).max(axis=1)
    slope = points[..., :2] / np.where(kept, z, 1.0)[..., None]
    a0 = np.where(kept[..., None], slope, np.inf).min(axis=1) - half
    a1 = np.where(kept[..., None], slope, -np.inf).max(axis=1) + half
    with np.errstate(invalid="ignore"):
        lo = np.column_stack([np.minimum(z0[:, None] * a0, z1[:, None] * a0), z0])
        hi = np.column_stack([np.maximum(z0[:, None] * a1, z1[:, None] * a1), z1])
    slopes = np.column_stack([a0[:, 0], a1[:, 0], a0[:, 1], a1[:, 1]])
    behind = ~kept.any(axis=1)
    lo[behind] = hi[behind] = (0.0, 0.0, -1.0)
    slopes[behind] = (1.0, -1.0, 1.0, -1.0)
    return lo.astype(np.float32), hi.astype(np.float32), slopes.astype(np.float32)


class LayerFinder:
    """Builds one view's `OITParams`: for ``tiled`` it runs phase 1 (timed as "oit") into the tiled k-buffer."""

    def __init__(self, scheme: str, k: int, device: str) -> None:
        self.scheme, self.k, self.device = scheme, k, device
        self._keep: list = []
        """every view's phase-1 BVH and boxes (a finder lives one frame): `OITParams` holds only the BVH's id, and
        on CUDA the view's kernels may still run after the next view's phase 1"""

    def params(self, ds: DeviceScene, cam: Camera, clock: PassClock) -> OITParams:
        p = OITParams()
        p.scheme, p.k, p.bvh = OIT_CODES[self.scheme], self.k, ds.volume_bvh.id
        tiles = tile_layout(cam.width, cam.height, TILE_LAYOUT)
        p.tile_w, p.tile_h, p.tiles_x = tiles.tile_w, tiles.tile_h, tiles.tiles_x
        if self.scheme != "tiled":
            p.tile_ids = wp.zeros((1, 1), dtype=int, device=self.device)
            p.tile_count = wp.zeros(1, dtype=int, device=self.device)
            return p
        with clock.measure("oit"):
            lo, hi, slopes = conservative_view_boxes([v.corners_world for v in ds.scene.volumes], cam, tiles)
            lo_d = wp.array(lo, dtype=wp.vec3, device=self.device)
            hi_d = wp.array(hi, dtype=wp.vec3, device=self.device)
            slopes_d = wp.array(slopes, dtype=wp.vec4, device=self.device)
            bvh = wp.Bvh(lo_d, hi_d)
            p.tile_ids = wp.zeros((tiles.tiles_x * tiles.tiles_y, self.k), dtype=int, device=self.device)
            p.tile_count = wp.zeros(tiles.tiles_x * tiles.tiles_y, dtype=int, device=self.device)
            launch_rows(tile_layers_kernel, tiles.tiles_y, tiles.tiles_x,
                        [camera_struct(cam), bvh.id, lo_d, hi_d, slopes_d, tiles.tile_w, tiles.tile_h, tiles.tiles_x,
                         self.k, p.tile_ids, p.tile_count], self.device, clock.counters)
        self._keep.append((bvh, lo_d, hi_d, slopes_d))
        return p
