"""CMSRM: cube-map-space ray marching on the interior faces of each volume's box (paper 001; paper 000 §3.1.1).

Per volume and view: (1) the cube ray-marching pass casts a ray from the eye through the centre of every texel of
the visible faces (Eq. 1) of a cube map over the box and marches it from the box entry (or the near plane, with the
eye inside) to the texel, storing premultiplied colour and transmittance; (2) the cube resampling pass casts each
pixel's ray, finds where it leaves the box and samples the cube map there bilinearly (seamless across face edges).
The march is DSSRM's (`march_volume_light_map`), lit by the same light map. Cost follows the cube-map size, not the
viewport: S x S texels per visible face.

The resampling pass is the paper's "simple cube mapping" per pixel (§3, §3.2's 2x2 bilateral gather) where that is all
a pixel needs: `cube_resample_kernel` finishes each pixel whose ray meets no box, or one cube-scheme box with no
translucent mesh layer and no rim to march, with one box test and one 2x2 lookup, and defers the others (several boxes
along the ray, mesh layers, a direct-scheme box, a rim, pixel-rt's ray queries) to `layered_resample_kernel`, which runs
over the list of deferred pixels only. On the CPU each thread takes a span of pixels (`RESAMPLE_SPAN`), since Warp
copies a kernel's arguments per thread. Measured (cloud 128^3, 960x540, one core, thread time): 126 ms for the former
single per-pixel kernel, 46 ms now, against a cube march of 45 ms; the images are the same to the bit.

Adaptive LOD (§3.3) picks per volume and view the cube-map/density mip level and the sample count N from the box's
projected size, and (without a given S0) raises the face size to what the screen needs where the box is near,
elongated, coarse-gridded or around the eye (`cubemap.screen_texels`, at most `cubemap.face_size_cap` = max(S0, 64):
bounded and, past the cap, independent of the viewport); pixels whose lookup falls within half a texel of a face
edge (the box's silhouettes and path-length kinks, sharper than any texel) are marched directly (``rim_direct``);
the hybrid choice (§3.4, first paragraph) marches a volume directly in screen space when its
projected pixels are fewer than its visible texels. ``cube_faces="exterior"`` casts rays to the exterior faces the eye
sees instead (paper 001 Fig. 2 (a)); it exists to show the texel aliasing that the interior scheme avoids.

Mesh occlusion (§3.2): each texel ray stops at the opaque surface of the z-buffer pixel its texel projects to
(nearest), its end depth is kept in a cube depth map, and resampling weights the 2x2 texels by the bilateral
edge-stopping w_z = max(1 - k_z |z_buffer - z_cube|, 0) (k_z = 0.5) so that texels cut at a different depth than
the pixel's own ray do not bleed across occlusion edges (the halo of plain bilinear).

Frustum culling (§3.4's culling pass, per volume and view, on the device with the LOD, scheme and face mask in
`volren.render.marching.culling`; `frustum_visible` is its host reference): a box that a frustum plane or a box face
plane separates from the view frustum gets no cube map, no tiles and no rays, and no pixel ray meets it; without it a
box behind the eye counted as covering the viewport, and with the hybrid off a cloud 30 m to the side cost 8,192
texel rays for no visible pixel.

Several volumes (§3.4's ray-traced multi-volume pass, issue 14): each pixel takes the boxes its ray meets in ray
order from `volren.render.compositing.oit` (tiled k-buffer, per-pixel BVH queries or per-pixel sorting); a
cube-scheme box alone on its stretch of the ray is read from its cube map, a run of boxes overlapping along the ray is
marched jointly at N_max (``joint_rays``), since a texel holds only its own volume's march.

Empty-tile culling (paper 000 §3's coarse phase, shared with CACRM): faces are marched in 32x32-texel tiles, and a
coarse pass drops the tiles whose rays can only meet zero density according to the conservative max-density pyramid
(`tile_occupancy_kernel`). Culled texels keep the transparent fill, which is what marching them would have given.
Interior rays end at their texel, exterior rays start there and run on to the box exit, and the bound follows.

Tile LOD (paper 000 §3.1.3, ``tile_lod``): the same coarse pass gives each tile a level l in {0, 1, 2} from its texels'
screen footprint (`tile_lod_kernel`: coarse texels stay within k_u pixels, like the per-volume LOD); a level-l tile
is marched as (32 / 2^l + 2)^2 level-l texels (a one-texel apron makes it self-contained) against the density mip
raised by l, then `cube_compose_kernel` fills its level-0 texels with the bilateral filter, so resampling reads one
level. Measured on the cloud 5 m away: half the samples, 10 dB lower PSNR (46.9 -> 36.3 dB; 4 dB of it from the
coarser density). The per-volume LOD picks S from the box's nearest edge, so the far faces are oversampled and that
headroom is what the tile levels spend: a coarse texel of ~1 pixel resampled bilinearly blurs silhouettes the
reference resolves. Hence off by default, and for CACRM too.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.errors import VolrenError
from volren.kernels.common import (
    INF,
    CameraGPU,
    Medium,
    ViewBuffers,
    VolumeGPU,
    box_hit,
    count,
    counter_row,
    new_march_state,
    occluded_end,
    pixel_ray,
    state_accumulator,
    with_accumulator,
    write_pixel,
)
from volren.render.base import LightMapMarchConfig, LightMapRenderer
from volren.render.compositing.mesh_layers import (
    MeshLayers,
    blend_cube_segments,
    blend_layers_before,
    has_translucent,
    layer_before,
    layer_stats,
    march_between_layers,
    march_texel_segments,
    mesh_layers_pass,
)
from volren.render.compositing.oit import LayerFinder, OITParams, cluster_end, lone_candidate, pixel_layers
from volren.render.frame import (
    BOX_TESTS,
    DENSITY_SAMPLES,
    JOINT_RAYS,
    LIGHTMAP_LOOKUPS,
    RAYS,
    SKIPPED_STEPS,
    PassClock,
)
from volren.render.marching.cubemap import (
    FACE_COUNT,
    MAX_TILE_LEVEL,
    TILE,
    CubeLOD,
    CubeTarget,
    coarse_tiles,
    cube_face_point,
    cube_lod,
    cube_quad,
    cube_sample,
    face_size_cap,
    face_tiles,
    max_tile_level,
    point_face,
    ray_face_point,
    rim_needs_march,
    store_texel,
    texel_index,
    texel_point,
    tile_lod_kernel,
    tile_occupancy_kernel,
    tile_texel,
    visible_faces,
)
from volren.render.marching.culling import (
    SCHEME_CUBE,
    SCHEME_CULLED,
    SCHEME_DIRECT,
    CullParams,
    cull_instances,
    unpack,
)
from volren.render.marching.march import MarchParams
from volren.render.marching.modes import combine_segment
from volren.scene import Volume
from volren.upload import DeviceScene, camera_struct

SCHEME_NAMES = {SCHEME_CULLED: "culled", SCHEME_DIRECT: "direct", SCHEME_CUBE: "cube"}
CUBE_TEXEL_BYTES = 24
"""a cube-map texel: premultiplied RGB and transmittance, t_half, z_end (float32 each)"""
SEGMENT_BYTES = 20
"""a cube k-buffer segment: premultiplied RGB and transmittance, end depth (float32 each)"""
RESAMPLE_SPAN = 32
"""pixels per thread of `cube_resample_kernel` on the CPU: Warp's CPU backend copies every kernel argument for each
thread, which at one pixel per thread cost more than the lookups (cloud 128^3, 960x540, one core: 48 ms a pass at
1 pixel, 35 at 8, 31.5 at 32, 33 at 128)"""


@dataclass
class CubeMaps:
    """One view's cube maps of all its cube-scheme volumes, packed: volume v's 6 faces start at ``offsets[v]``."""

    color: wp.array
    """premultiplied rgb and transmittance per texel"""
    t_half: wp.array
    """ray distance where the texel's transmittance reached 1/2 (INF if never)"""
    z_end: wp.array
    """linear depth where the texel's ray ends (its texel, or an opaque surface in front of it)"""
    offsets: list[int]
    sizes: list[int]
    texels: int
    seg: wp.array
    """the cube k-buffer (paper 000 §3.3): ``segments`` (premultiplied colour, transmittance) per texel"""
    seg_z: wp.array
    """linear depth where each segment ends"""
    segments: int
    """K + 1 with translucent meshes (K: the mesh k-buffer's layers), else 0 (no cube k-buffer)"""

    def target(self, v: int) -> CubeTarget:
        """Volume v's cube map, as the march kernels write it."""
        t = CubeTarget()
        t.color, t.t_half, t.z_end, t.offset = self.color, self.t_half, self.z_end, self.offsets[v]
        t.seg, t.seg_z, t.segments = self.seg, self.seg_z, self.segments
        return t


@wp.struct
class CubeLookup:
    """What the resampling kernels read of one view's cube maps (`CubeMaps`) and of the config: per volume its scheme
    and where its faces start and their size, the texels, the cube k-buffer and the bilateral filter's settings."""

    scheme: wp.array(dtype=int)
    offset: wp.array(dtype=int)
    size: wp.array(dtype=int)
    color: wp.array(dtype=wp.vec4)
    t_half: wp.array(dtype=float)
    z_end: wp.array(dtype=float)
    seg: wp.array(dtype=wp.vec4)
    seg_z: wp.array(dtype=float)
    segments: int
    exterior: int
    """1: the exterior faces (`CMSRMConfig.cube_faces`)"""
    rim_direct: int
    k_z: float
    k_z_layers: float


@dataclass(frozen=True)
class TileGroup:
    """The live tiles of one tile level, as the fine pass launches them."""

    level: int
    """tile LOD l: 2^l x 2^l fine texels per texel marched"""
    origins: wp.array
    """(face, i0, j0) per tile in level-l texels, less the apron"""
    fine: wp.array
    """(face, i0, j0) per tile in level-0 texels"""
    rows: int
    """texels per tile side marched, apron included"""
    apron: int
    size: int
    """face size at level l"""
    fine_rows: int
    """level-0 texels per tile side"""
    eyes: wp.array
    """per tile, the views of the group that march it: bit e for the group's view e (`tile_occupancy_kernel`)"""


@dataclass(frozen=True)
class CMSRMConfig(LightMapMarchConfig):
    cube_size: int | None = None
    """S0: level-0 face size [texels], fixed (the LOD only lowers it); None = S0 the density grid's longest axis,
    and with the adaptive LOD each face raised to what the screen needs (`cubemap.cube_lod`'s screen sizing, at most
    `cubemap.face_size_cap`)"""
    cube_faces: str = "interior"
    """interior (the method) or exterior (only to show its texel aliasing)"""
    adaptive_lod: bool = True
    """choose the mip level and N from the projected size (§3.3); off = level 0 and N_max"""
    k_u: float = 1.0
    """screen up-scaling coefficient of S_ideal = max projected edge / k_u"""
    k_c: float = 3.0
    """sampling coefficient of N_ideal = k_c S_ideal / sqrt 3; 3 gives one sample per texel along a diagonal"""
    hybrid: bool = True
    """march a volume directly when its projected pixels are fewer than its visible texels"""
    cull_tiles: bool = True
    """skip 32x32-texel tiles whose rays can only meet zero density (coarse pass on the max-density pyramid)"""
    k_z: float = 0.5
    """[1/m] edge-stopping coefficient of the 2x2 bilateral resampling filter (§3.2); 0 = plain bilinear"""
    k_z_layers: float = 2.0
    """[1/m] Eq. 13's edge-stopping coefficient across the cube k-buffer's segment depths (translucent meshes, paper
    000 §3.3); steeper than k_z: at 33 x 33 with a sheet inside a slab and 8^2 texels per face, 42.1 / 49.5 / 43.4 dB
    against DSSRM at 0.5 / 2 / 4 (16^2 texels: 44.1 / 61.6 / 57.2 dB), 36.6 dB with the filter off"""
    rim_direct: bool = True
    """march directly the pixels whose cube-map lookup falls within half a texel of a face edge across texels that
    differ (`rim_needs_march`: a silhouette or steep edge of the box)"""
    tile_lod: bool = False
    """per-tile LOD l in {0, 1, 2} (paper 000 §3.1.3); off by default: it halves the samples of a distant volume
    but costs 5-10 dB there (see the module docstring)"""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.tile_lod and self.cube_faces != "interior":
            raise VolrenError("tile LOD needs interior cube faces")
        if self.cube_faces not in ("interior", "exterior"):
            raise VolrenError(f"cube faces must be interior or exterior, got '{self.cube_faces}'")
        if self.cube_size is not None and not 2 <= self.cube_size <= 4096:
            raise VolrenError(f"cube size must lie in [2, 4096] texels, got {self.cube_size}")
        for name in ("k_z", "k_z_layers"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise VolrenError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not (self.k_u > 0 and self.k_c > 0):
            raise VolrenError(f"k_u and k_c must be > 0, got {self.k_u} and {self.k_c}")


@wp.kernel
def cube_march_kernel(
    cam: CameraGPU,
    vol: VolumeGPU,
    tiles: wp.array(dtype=wp.vec3i),
    tile: int,
    apron: int,
    size: int,
    exterior: int,
    medium: Medium,
    params: MarchParams,
    buffers: ViewBuffers,
    mesh: MeshLayers,
    target: CubeTarget,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """One ray per texel of the visible faces: from the eye through the texel centre, marched from the box entry
    (or near plane) to the texel (interior), or from the texel to the box exit (exterior), and cut at the opaque
    surface of the z-buffer pixel the texel projects to (nearest, the paper's blit into a cube depth map); with
    translucent meshes split at that pixel's mesh layers into the cube k-buffer (`march_texel_segments`)."""
    r, c = wp.tid()
    counters = counter_row(counter_rows, r, c)
    q = tile_texel(tiles, tile, apron, size, r + row0, c)
    if q[0] < 0:
        return
    x = wp.transform_point(vol.to_world, texel_point(q, size))
    dist = wp.length(x - cam.origin)
    d = (x - cam.origin) / dist
    s = new_march_state()
    facing = wp.dot(d, cam.forward)
    t1 = dist
    if facing > 0.0:
        hb = box_hit(wp.transform_point(vol.to_local, cam.origin), wp.transform_vector(vol.to_local, d))
        t0 = wp.max(hb[0], cam.near / facing)
        if exterior != 0:
            t0 = wp.max(dist, cam.near / facing)
            t1 = hb[1]
        t1 = occluded_end(cam, buffers, x, t1, facing)
        if t1 > t0:
            count(counters, RAYS, 1)
            s = march_texel_segments(mesh, cam, x, target.seg, target.seg_z, target.segments,
                                     target.offset + texel_index(q[0], q[1], q[2], size), vol, d, t0, t1, medium,
                                     params)
    store_texel(target, texel_index(q[0], q[1], q[2], size),
                wp.vec4(s.color[0], s.color[1], s.color[2], s.transmittance), s.depth_t, t1 * facing)
    count(counters, DENSITY_SAMPLES, s.samples)
    count(counters, SKIPPED_STEPS, s.skipped)
    count(counters, LIGHTMAP_LOOKUPS, s.shaded * medium.lights.shape[0])


@wp.func
def cube_nearest_t(cube_t: wp.array(dtype=float), offset: int, size: int, p: wp.vec3) -> float:
    """The texel ray's half-transmittance distance stored nearest to the box-surface point p."""
    f = point_face(p)
    a = f / 2
    i = wp.clamp(int((p[(a + 1) % 3] + 1.0) * 0.5 * float(size)), 0, size - 1)
    j = wp.clamp(int((p[(a + 2) % 3] + 1.0) * 0.5 * float(size)), 0, size - 1)
    return cube_t[offset + texel_index(f, i, j, size)]


@wp.kernel
def cube_compose_kernel(
    cam: CameraGPU,
    vol: VolumeGPU,
    tiles: wp.array(dtype=wp.vec3i),
    tile: int,
    size: int,
    coarse: CubeTarget,
    coarse_size: int,
    k_z: float,
    buffers: ViewBuffers,
    target: CubeTarget,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """Combine tile levels (paper 000 §3.1.3, last paragraph): each level-0 texel of a level-l tile takes the 2x2
    bilateral filter of `cube_sample` over the level-l cube map at its centre, edge-stopped against the depth where
    its own ray would end (eye to texel, cut by the z-buffer). Texels of level-0 tiles are marched directly, so the
    cube resampling pass then reads one level everywhere."""
    r, c = wp.tid()
    q = tile_texel(tiles, tile, 0, size, r + row0, c)
    if q[0] < 0:
        return
    p = texel_point(q, size)
    x = wp.transform_point(vol.to_world, p)
    dist = wp.length(x - cam.origin)
    facing = wp.dot(x - cam.origin, cam.forward) / dist
    z = dist * facing
    if facing > 0.0:
        z = occluded_end(cam, buffers, x, dist, facing) * facing
    idx, b, _rim = cube_quad(coarse.offset, coarse_size, p)
    store_texel(target, texel_index(q[0], q[1], q[2], size), cube_sample(coarse.color, coarse.z_end, idx, b, z, k_z),
                cube_nearest_t(coarse.t_half, coarse.offset, coarse_size, p), z)


@wp.func
def resample_lone_box(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    oit: OITParams,
    cubes: CubeLookup,
    mode: int,
    mesh_count: wp.array2d(dtype=int),
    buffers: ViewBuffers,
    counters: wp.array(dtype=wp.int64),
    row: int,
    col: int,
) -> int:
    """Pixel (row, col) of the cube resampling pass when its ray meets no box, or one cube-scheme box with no
    translucent mesh layer and no rim to march (`rim_needs_march`): one 2x2 lookup where the ray leaves the box
    (paper 001 §3.2's bilateral filter), written; returns 0 and writes nothing for any other pixel, which
    `layered_resample_kernel` then takes. The same operations as that kernel's one-layer case, so the same bits."""
    if mesh_count[row, col] != 0:
        return 0
    n = lone_candidate(oit, volumes, row, col)
    if n[0] < 0 or n[0] > 1:
        return 0
    s = new_march_state()
    d = cam.forward  # what `write_pixel` does with an untouched state does not depend on the ray
    if n[0] == 1:
        d, planes = pixel_ray(cam, buffers, row, col)
        v = n[1]
        o_l = wp.transform_point(volumes[v].to_local, cam.origin)
        d_l = wp.transform_vector(volumes[v].to_local, d)
        h = box_hit(o_l, d_l)
        t_out = wp.min(h[1], planes[1])
        if t_out > wp.max(h[0], planes[0]):
            if cubes.scheme[v] != SCHEME_CUBE:
                return 0
            offset = cubes.offset[v]
            size = cubes.size[v]
            p = ray_face_point(o_l, d_l, h, cubes.exterior)
            idx, b, rim = cube_quad(offset, size, p)
            if cubes.rim_direct != 0 and rim_needs_march(cubes.color, idx, rim) != 0:
                return 0
            acc = combine_segment(mode, state_accumulator(s),
                                  cube_sample(cubes.color, cubes.z_end, idx, b, t_out * wp.dot(d, cam.forward),
                                              cubes.k_z))
            if acc[3] <= 0.5:
                s.depth_t = cube_nearest_t(cubes.t_half, offset, size, p)
            s = with_accumulator(s, acc)
        count(counters, BOX_TESTS, 1)
    write_pixel(s, cam, d, row, col, buffers, counters, DENSITY_SAMPLES)
    return 1


@wp.kernel
def cube_resample_kernel(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    oit: OITParams,
    cubes: CubeLookup,
    mode: int,
    mesh_count: wp.array2d(dtype=int),
    span: int,
    buffers: ViewBuffers,
    deferred: wp.array2d(dtype=int),
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """The cube resampling pass (paper 001 §3): thread (r, c) resamples the ``span`` pixels of row r from column
    c span (`resample_lone_box`) and flags in ``deferred`` those it leaves to `layered_resample_kernel`."""
    r, c = wp.tid()
    counters = counter_row(counter_rows, r, c)
    row = r + row0
    for col in range(c * span, wp.min(c * span + span, cam.width)):
        if resample_lone_box(cam, volumes, oit, cubes, mode, mesh_count, buffers, counters, row, col) == 0:
            deferred[row, col] = 1


@wp.kernel
def layered_resample_kernel(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    oit: OITParams,
    cubes: CubeLookup,
    medium: Medium,
    params: MarchParams,
    mesh: MeshLayers,
    buffers: ViewBuffers,
    pixels: wp.array(dtype=int),
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """Per pixel of the list ``pixels`` (row-major indices; thread r takes entry r), front to back over the boxes its
    ray meets (`pixel_layers`): a cube-scheme volume alone on its
    stretch of the ray is looked up bilinearly where the ray leaves its box (enters, for exterior faces); a
    direct-scheme volume is marched here, as in DSSRM; boxes overlapping along the ray are marched jointly (a texel
    holds one volume's march only, wrong where another box shares that stretch). Translucent mesh layers (paper 000
    §3.3) are blended between the boxes; with layers inside a cube-scheme box the pixel blends the cube k-buffer's
    segments and its layers in turn (`blend_cube_segments`), and marches the box directly, split at its layers
    (`march_between_layers`, flagged in ``mesh.direct``), only where Eq. 13 leaves a segment without weight or there
    is no cube k-buffer (tile LOD on)."""
    r, lane = wp.tid()
    counters = counter_row(counter_rows, r, lane)
    row = pixels[r + row0] / cam.width
    col = pixels[r + row0] % cam.width
    d, planes = pixel_ray(cam, buffers, row, col)
    layers = pixel_layers(oit, volumes, cam.origin, d, planes, row, col, counters)
    s = new_march_state()
    facing = wp.dot(d, cam.forward)
    next_mesh = int(0)
    direct = int(0)
    joint = int(0)
    i = int(0)
    while i < layers.count:
        end = cluster_end(layers, i)
        v = layers.volume[i]
        s, next_mesh = blend_layers_before(s, next_mesh, mesh, row, col, facing, layers.t_in[i])
        if end - i > 1:
            direct = 1
            joint = 1
            s, next_mesh = march_between_layers(s, next_mesh, mesh, row, col, facing, layers, i, end, volumes,
                                                cam.origin, d, 0.5, medium, params)
        else:
            # A cube-scheme box: its cube map, or with layers inside it the cube k-buffer's segments between them;
            # marched directly where neither applies (a direct-scheme box, a segment without Eq. 13 weight).
            done = int(0)
            p = cube_face_point(volumes[v], cam.origin, d, cubes.exterior)
            offset = cubes.offset[v]
            size = cubes.size[v]
            # only a cube-scheme box has texels to read (a direct or culled box's cube size may be 0)
            march = int(0)
            idx = wp.vec4i(0)
            b = wp.vec4(0.0)
            if cubes.scheme[v] == SCHEME_CUBE:
                idx, b, rim = cube_quad(offset, size, p)
                if cubes.rim_direct != 0:
                    march = rim_needs_march(cubes.color, idx, rim)
            if cubes.scheme[v] == SCHEME_CUBE and march == 0:
                if not layer_before(mesh, row, col, next_mesh, facing, layers.t_out[i]):
                    c = cube_sample(cubes.color, cubes.z_end, idx, b, layers.t_out[i] * facing, cubes.k_z)
                    acc = combine_segment(params.mode, state_accumulator(s), c)
                    if s.transmittance > 0.5 and acc[3] <= 0.5:
                        s.depth_t = cube_nearest_t(cubes.t_half, offset, size, p)
                    s = with_accumulator(s, acc)
                    done = 1
                else:
                    s, next_mesh, done = blend_cube_segments(s, next_mesh, mesh, row, col, facing, cubes.seg,
                                                             cubes.seg_z, cubes.segments, offset, size, p,
                                                             layers.t_in[i], layers.t_out[i], cubes.k_z_layers)
                    if done == 0:
                        mesh.direct[row, col] = 1
            if done == 0:
                direct = 1
                s, next_mesh = march_between_layers(s, next_mesh, mesh, row, col, facing, layers, i, end, volumes,
                                                    cam.origin, d, 0.5, medium, params)
        if s.transmittance < params.min_transmittance:
            break
        i = end
    s, next_mesh = blend_layers_before(s, next_mesh, mesh, row, col, facing, INF)
    count(counters, RAYS, direct)
    count(counters, JOINT_RAYS, joint)
    count(counters, SKIPPED_STEPS, s.skipped)
    count(counters, LIGHTMAP_LOOKUPS, s.shaded * medium.lights.shape[0])
    write_pixel(s, cam, d, row, col, buffers, counters, DENSITY_SAMPLES)


def frustum_visible(vol: Volume, cam: Camera) -> bool:
    """Viewport-visibility culling of a whole volume (paper 001 §3.4's culling pass): False when one of the 12
    candidate separating planes has the box and the view frustum (near to far plane, through the viewport's edges)
    on opposite sides, i.e. all 8 box corners lie outside one frustum plane or all 8 frustum corners lie outside one
    face plane of the box. Conservative: a box kept may still miss the frustum near a frustum edge (the planes
    tested are not every separating axis), but a culled box meets no ray of the view, so culling never changes the
    image. Points on a plane (within 1e-6 relative) count as inside."""
    tx = cam.tan_half_fov * cam.width / cam.height
    ty = cam.tan_half_fov
    c = np.c_[vol.corners_world, np.ones(8)] @ cam.view_matrix().T
    x, y, depth = c[:, 0], c[:, 1], -c[:, 2]
    tol = 1e-6 * max(1.0, float(np.abs(c[:, :3]).max()))
    outside = (cam.near - depth, depth - cam.far, x - tx * depth, -x - tx * depth, y - ty * depth, -y - ty * depth)
    if any(np.all(o > tol) for o in outside):
        return False
    right, up, forward = cam.basis()
    corners = np.array([np.asarray(cam.position) + z * (forward + sx * tx * right + sy * ty * up)
                        for z in (cam.near, cam.far) for sx in (-1, 1) for sy in (-1, 1)])
    local = (np.c_[corners, np.ones(8)] @ vol.to_local.T)[:, :3]
    tol = 1e-6 * max(1.0, float(np.abs(local).max()))
    return not any(np.all(local[:, a] > 1 + tol) or np.all(local[:, a] < -1 - tol) for a in range(3))


def host_plan(vol: Volume, cam: Camera, c: CMSRMConfig) -> dict:
    """The culling pass for one volume on the host in float64 (how `CMSRM._plan` did it before the kernel): the
    reference that tests hold `culling.culling_kernel` to."""
    visible = frustum_visible(vol, cam)
    eye = (vol.to_local @ np.r_[cam.position, 1.0])[:3]
    faces = visible_faces(eye, c.cube_faces) if visible else []
    lod = cube_lod(vol, cam, c.cube_size or max(vol.resolution), c.samples, c.k_u, c.k_c, c.adaptive_lod,
                   screen_sizing=c.cube_size is None)
    texels = len(faces) * lod.size**2
    pixels = projected_pixels(vol.corners_world, cam) if visible else 0.0
    if not visible:
        scheme = SCHEME_CULLED
    elif (c.hybrid and pixels < texels) or not faces:
        scheme = SCHEME_DIRECT
    else:
        scheme = SCHEME_CUBE
    return {"faces": faces, "lod": lod, "texels": texels, "pixels": pixels, "scheme": scheme}


def projected_pixels(vol_corners: np.ndarray, cam: Camera) -> float:
    """Viewport pixels covered by the box's projection, estimated by the bounding rectangle of its projected corners
    clipped to the viewport; the whole viewport when a corner is behind the near plane."""
    view = cam.view_matrix()
    c = np.c_[vol_corners, np.ones(len(vol_corners))] @ view.T
    depth = -c[:, 2]
    if np.any(depth <= cam.near):
        return float(cam.width * cam.height)
    focal = cam.height / (2 * cam.tan_half_fov)
    x = c[:, 0] / depth * focal + cam.width / 2
    y = c[:, 1] / depth * focal + cam.height / 2
    w = np.clip(x.max(), 0, cam.width) - np.clip(x.min(), 0, cam.width)
    h = np.clip(y.max(), 0, cam.height) - np.clip(y.min(), 0, cam.height)
    return float(w * h)


class CMSRM(LightMapRenderer):
    """Cube-map-space ray marching; ``config`` is a `CMSRMConfig`."""

    name = "cmsrm"
    translucent_meshes = True
    cube_kbuffer = True
    """whether the texel march writes the cube k-buffer (paper 000 §3.3); without it a pixel with a translucent layer
    inside a cube-scheme box marches that box directly"""

    def __init__(self, config: CMSRMConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or CMSRMConfig(), device)

    def release_views(self) -> None:
        super().release_views()
        self._layers = LayerFinder(self.config.oit, self.config.oit_k, self.device)  # the views' OIT tiles gone
        self._meshes = []  # and their mesh k-buffers

    def _prepare(self, scene, clock: PassClock, frame: int) -> DeviceScene:
        self._layers = LayerFinder(self.config.oit, self.config.oit_k, self.device)
        ds = self._upload(scene, clock, self.config.light_grid, mip_levels=True)
        self._lighting(ds, clock)
        self._frame_info["volumes"] = []
        return ds

    def _stream_levels(self, ds: DeviceScene) -> tuple[list[int] | None, bool]:
        """A cube-mapped volume is marched at its LOD level l (`cube_lod`, the finest over the views), its coarse
        tiles at l + 1, ... and its direct pixels at level 0: a streamed volume's bricks are needed at level l and at
        the footprint's level, with their ancestors."""
        c = self.config
        marched = [min(cube_lod(vol, cam, c.cube_size or max(vol.resolution), c.samples, c.k_u, c.k_c,
                                c.adaptive_lod, screen_sizing=c.cube_size is None).level for cam in self._views)
                   for vol in ds.scene.volumes]
        return marched, True

    def _params(self, ds: DeviceScene, view: int, samples: int) -> MarchParams:
        params = MarchParams()
        params.samples = samples
        params.jitter = 0
        params.seed = 0
        params.view = view
        params.min_transmittance = self.config.min_transmittance
        params.ambient = ds.ambient
        return self._mode_params(params, ds)

    def _plan(self, ds: DeviceScene, cam: Camera) -> list[dict]:
        """Per volume, the culling pass of §3.4 on the device (`culling.culling_kernel`, one thread per instance):
        frustum culling, LOD (§3.3), scheme (hybrid) and visible faces (Eq. 1), read back as packed descriptors.
        A culled volume has no visible faces, texels or pixels. Measured on 36 instances (CPU): 0.55 ms for the
        kernel and its readback against 52 ms for `host_plan` on each."""
        c = self.config
        params = CullParams()
        params.samples, params.k_u, params.k_c = c.samples, c.k_u, c.k_c
        params.adaptive, params.hybrid = int(c.adaptive_lod), int(c.hybrid)
        params.exterior = int(c.cube_faces == "exterior")
        # Screen sizing of the faces (`cube_lod`) unless S0 is given, up to `face_size_cap` (the kernel adds the base).
        params.max_size = 0 if c.cube_size else face_size_cap(0)
        bases = [c.cube_size or max(v.resolution) for v in ds.scene.volumes]
        descriptors, footprints = cull_instances(ds, cam, bases, params)
        plans = []
        for descriptor, (pixels, edge) in zip(descriptors, footprints, strict=True):
            d = unpack(descriptor)
            lod = CubeLOD(d["level"], d["size"], d["samples"], float(edge) if edge < INF else math.inf)
            plans.append({"faces": d["faces"], "lod": lod, "texels": len(d["faces"]) * d["size"] ** 2,
                          "pixels": float(pixels), "scheme": d["scheme"]})
        return plans

    def _plan_views(self, ds: DeviceScene, views: list[Camera]) -> list[list[dict]]:
        return [self._plan(ds, cam) for cam in views]

    def _cube_arrays(self, texels: int, offsets: list[int], sizes: list[int], segments: int = 0) -> CubeMaps:
        """Cube maps of ``texels`` texels, transparent until marched, with a cube k-buffer of ``segments`` per
        texel (none when 0)."""
        n = max(texels, 1)
        m = max(texels * segments, 1)
        return CubeMaps(
            color=wp.full(n, wp.vec4(0.0, 0.0, 0.0, 1.0), dtype=wp.vec4, device=self.device),
            t_half=wp.full(n, INF, dtype=float, device=self.device),
            z_end=wp.full(n, INF, dtype=float, device=self.device),
            offsets=offsets,
            sizes=sizes,
            texels=texels,
            seg=wp.full(m, wp.vec4(0.0, 0.0, 0.0, 1.0), dtype=wp.vec4, device=self.device),
            seg_z=wp.full(m, INF, dtype=float, device=self.device),
            segments=segments,
        )

    def _segments(self, ds: DeviceScene) -> int:
        """Segments per texel of the cube k-buffer: K + 1 where the scene has translucent meshes and this method's
        texel march writes them (CMSRM's, at tile level 0 only: the tile-LOD composition does not filter segments),
        else 0 and a pixel with a layer inside a cube-scheme box is marched directly."""
        if not (self.cube_kbuffer and has_translucent(ds)) or self.config.tile_lod:
            return 0
        return self.config.mesh_layers + 1

    def _allocate(self, plans: list[dict], segments: int) -> CubeMaps:
        """One view's cube maps: colour + transmittance, half-transmittance distance and end depth per texel, and
        the cube k-buffer of ``segments`` per texel."""
        offsets, sizes, total = [], [], 0
        for plan in plans:
            offsets.append(total)
            sizes.append(plan["lod"].size)
            if plan["scheme"] == SCHEME_CUBE:
                total += FACE_COUNT * plan["lod"].size ** 2
        return self._cube_arrays(total, offsets, sizes, segments)

    def _tile_groups(self, ds: DeviceScene, v: int, plan: dict, cams: list[Camera], clock: PassClock
                     ) -> list[TileGroup]:
        """The coarse phase: the plan's face tiles, their tile LOD (when on) and the empty-tile culling (when on),
        grouped by level for the fine pass. Records the counts in the plan."""
        c = self.config
        lod = plan["lod"]
        tiles = face_tiles(plan["faces"], lod.size)
        tile = min(TILE, lod.size)
        plan["tiles"] = len(tiles)
        device_tiles = wp.array(tiles, dtype=wp.vec3i, device=self.device)
        levels = wp.zeros(len(tiles), dtype=int, device=self.device)
        top = max_tile_level(tile) if c.tile_lod else 0
        if top and len(tiles):
            with clock.measure("tile_lod"):
                wp.launch(tile_lod_kernel, dim=len(tiles),
                          inputs=[device_tiles, tile, lod.size, ds.levels[v][0], camera_struct(cams[0]),
                                  camera_struct(cams[-1]), c.k_u, top, levels], device=self.device)
        marchers = np.full(len(tiles), 3, dtype=np.int32)
        if c.cull_tiles and len(tiles):
            vol = ds.scene.volumes[v]
            eyes = [(vol.to_local @ np.r_[cam.position, 1.0])[:3] for cam in cams]
            offset, res = ds.max_grids[v]
            # A coarser density level reads voxels up to 2^level base voxels away (its trilinear support).
            margin = (2**lod.level) * 2.0 / min(vol.resolution)
            occupied = wp.zeros(len(tiles), dtype=int, device=self.device)
            with clock.measure("tile_cull"):
                wp.launch(tile_occupancy_kernel, dim=len(tiles),
                          inputs=[device_tiles, tile, lod.size, wp.vec3(*eyes[0]), wp.vec3(*eyes[-1]),
                                  int(c.cube_faces == "exterior"), margin, levels,
                                  ds.max_density, offset, wp.vec3i(*res), occupied], device=self.device)
            marchers = occupied.numpy()
        live = marchers > 0
        plan["live_tiles"] = int(live.sum())
        tile_levels = levels.numpy()
        plan["tile_levels"] = [int(np.sum(live & (tile_levels == level))) for level in range(MAX_TILE_LEVEL + 1)]
        groups = []
        for level in range(top + 1):
            kept = live & (tile_levels == level)
            chosen = tiles[kept]
            if not len(chosen):
                continue
            fine = wp.array(chosen, dtype=wp.vec3i, device=self.device)
            views = wp.array(marchers[kept], dtype=int, device=self.device)
            if level == 0:
                groups.append(TileGroup(0, fine, fine, tile, 0, lod.size, tile, views))
            else:
                origins, width, size = coarse_tiles(chosen, tile, lod.size, level)
                groups.append(TileGroup(level, wp.array(origins, dtype=wp.vec3i, device=self.device), fine, width, 1,
                                        size, tile, views))
        return groups

    def _compose(self, ds: DeviceScene, v: int, cam: Camera, tiles: TileGroup, size: int, coarse: CubeTarget,
                 target: CubeTarget, buffers: ViewBuffers, clock: PassClock) -> None:
        """Fill the level-0 texels of level-l tiles from the level-l cube map (`cube_compose_kernel`)."""
        launch_rows(
            cube_compose_kernel,
            len(tiles.fine) * tiles.fine_rows,
            tiles.fine_rows,
            [camera_struct(cam), ds.levels[v][0], tiles.fine, tiles.fine_rows, size, coarse, tiles.size,
             self.config.k_z, buffers, target],
            self.device,
            clock.counters,
        )

    def _view_groups(self, n: int) -> list[tuple[int, ...]]:
        """The views whose cube maps one march launch fills: each view alone."""
        return [(v,) for v in range(n)]

    def _launch_march(self, ds: DeviceScene, views: list[Camera], group: tuple[int, ...], v: int, level: VolumeGPU,
                      tiles: TileGroup, samples: int, dest: list[CubeTarget], targets: list[ViewBuffers],
                      clock: PassClock) -> None:
        """March the tiles of one level of volume v for the views of a group into ``dest`` (a cube map per view)."""
        (view,) = group
        launch_rows(
            cube_march_kernel,
            len(tiles.origins) * tiles.rows,
            tiles.rows,
            [camera_struct(views[view]), level, tiles.origins, tiles.rows, tiles.apron, tiles.size,
             int(self.config.cube_faces == "exterior"), ds.medium(), self._params(ds, view, samples), targets[view],
             self._meshes[view], dest[0]],
            self.device,
            clock.counters,
        )

    def _march_cubes(
        self,
        ds: DeviceScene,
        views: list[Camera],
        plans: list[list[dict]],
        cubes: list[CubeMaps],
        targets: list[ViewBuffers],
        clock: PassClock,
    ) -> None:
        """The cube ray-marching pass (with its coarse phase) of every view group. Tiles at level l > 0 are marched
        into a level-l cube map, with the density level raised by l too (paper 000 §3.1.3), and composed into the
        view's cube map by the bilateral filter (`cube_compose_kernel`)."""
        for group in self._view_groups(len(views)):
            for v, plan in enumerate(plans[group[0]]):
                if plan["scheme"] != SCHEME_CUBE:
                    continue
                lod = plan["lod"]
                for tiles in self._tile_groups(ds, v, plan, [views[i] for i in group], clock):
                    density = ds.levels[v][min(lod.level + tiles.level, len(ds.levels[v]) - 1)]
                    if tiles.level == 0:
                        dest = [cubes[i].target(v) for i in group]
                    else:
                        texels = FACE_COUNT * tiles.size**2
                        dest = [self._cube_arrays(texels, [0], [tiles.size]).target(0) for _ in group]
                    self._launch_march(ds, views, group, v, density, tiles, lod.samples, dest, targets, clock)
                    if tiles.level:
                        for i, coarse in zip(group, dest, strict=True):
                            self._compose(ds, v, views[i], tiles, lod.size, coarse, cubes[i].target(v), targets[i],
                                          clock)
                for i in group[1:]:
                    plans[i][v].update({k: plan[k] for k in ("tiles", "live_tiles", "tile_levels")})

    def _lookup(self, plans: list[dict], cubes: CubeMaps) -> CubeLookup:
        """One view's cube maps and the filter's settings as the resampling kernels read them."""
        c = self.config
        look = CubeLookup()
        look.scheme, look.offset, look.size = (wp.array(a, dtype=int, device=self.device)
                                               for a in ([p["scheme"] for p in plans], cubes.offsets, cubes.sizes))
        look.color, look.t_half, look.z_end = cubes.color, cubes.t_half, cubes.z_end
        look.seg, look.seg_z, look.segments = cubes.seg, cubes.seg_z, cubes.segments
        look.exterior, look.rim_direct = int(c.cube_faces == "exterior"), int(c.rim_direct)
        look.k_z, look.k_z_layers = c.k_z, c.k_z_layers
        return look

    def _resample(self, ds: DeviceScene, cam: Camera, view: int, plans: list[dict], cubes: CubeMaps, oit: OITParams,
                  mesh: MeshLayers, target: ViewBuffers, clock: PassClock) -> None:
        """The cube resampling pass of one view: `cube_resample_kernel` in spans of `RESAMPLE_SPAN` pixels (one on a
        GPU) where a cube-scheme volume gives it something to read and the layer finder needs no ray query, then
        `layered_resample_kernel` over the pixels it deferred (over every pixel without it)."""
        c = self.config
        shared = [camera_struct(cam), ds.volumes, oit, self._lookup(plans, cubes)]
        params = self._params(ds, view, c.samples)
        if c.oit != "pixel-rt" and any(p["scheme"] == SCHEME_CUBE for p in plans):
            span = RESAMPLE_SPAN if self.device.startswith("cpu") else 1
            deferred = wp.zeros((cam.height, cam.width), dtype=int, device=self.device)
            launch_rows(cube_resample_kernel, cam.height, -(-cam.width // span),
                        [*shared, params.mode, mesh.count, span, target, deferred], self.device, clock.counters)
            pixels = np.flatnonzero(deferred.numpy()).astype(np.int32)
        else:
            pixels = np.arange(cam.height * cam.width, dtype=np.int32)
        # stats info: per view, the pixels the layered kernel took (the rest took one lookup each)
        self._frame_info.setdefault("deferred_pixels", []).append(len(pixels))
        launch_rows(
            layered_resample_kernel,
            len(pixels),
            1,
            [*shared, ds.medium(), params, mesh, target, wp.array(pixels, dtype=int, device=self.device)],
            self.device,
            clock.counters,
            self._pixel_progress(cam.height, len(pixels)),
        )

    def _pixel_progress(self, rows: int, pixels: int) -> Callable[[int], None] | None:
        """`on_rows` for the launch over a view's ``pixels`` deferred pixels, the last of its ``rows`` image rows to
        finish: each launch reports its share of the rows (bands call this from their threads); with none deferred
        the rows are reported at once."""
        on_rows = self.on_rows
        if on_rows is None:
            return None
        if pixels == 0:
            on_rows(rows)
            return None
        lock = threading.Lock()
        launched = [0, 0]  # pixels launched, rows reported

        def advance(step: int) -> None:
            with lock:
                launched[0] += step
                done = rows * launched[0] // pixels
                new = done - launched[1]
                launched[1] = done
            if new:
                on_rows(new)

        return advance

    def _render_views(
        self, ds: DeviceScene, views: list[Camera], frame: int, targets: list[ViewBuffers], clock: PassClock
    ) -> None:
        plans = self._plan_views(ds, views)
        # The mesh k-buffers first: the texel rays split at them (the cube k-buffer).
        self._meshes = [mesh_layers_pass(ds, cam, targets[view], self.config.mesh_layers, clock,
                                         self._surface_light(ds)) for view, cam in enumerate(views)]
        segments = self._segments(ds)
        cubes = [self._allocate(p, segments) for p in plans]
        with clock.measure("cube_march"):
            self._march_cubes(ds, views, plans, cubes, targets, clock)
        for view, cam in enumerate(views):
            oit = self._layers.params(ds, cam, clock)
            mesh = self._meshes[view]
            with clock.measure("resample"):
                self._resample(ds, cam, view, plans[view], cubes[view], oit, mesh, targets[view], clock)
            self._frame_info["volumes"].append([
                {"view": view, "volume": v, "scheme": SCHEME_NAMES[p["scheme"]],
                 "faces": p["faces"], "level": p["lod"].level, "face_size": p["lod"].size,
                 "samples": p["lod"].samples, "visible_texels": p["texels"], "projected_pixels": round(p["pixels"]),
                 "tiles": p.get("tiles", 0), "live_tiles": p.get("live_tiles", 0),
                 "tile_levels": p.get("tile_levels", [0] * (MAX_TILE_LEVEL + 1))}
                for v, p in enumerate(plans[view])
            ])
            self._frame_info["mesh_layers"] = layer_stats(mesh, self.config.mesh_layers,
                                                          self._frame_info.get("mesh_layers"))
        self._frame_info["cube_map_bytes"] = sum(c.texels * (CUBE_TEXEL_BYTES + c.segments * SEGMENT_BYTES)
                                                 for c in cubes)
