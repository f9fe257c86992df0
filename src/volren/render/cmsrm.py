"""CMSRM: cube-map-space ray marching on the interior faces of each volume's box (paper 001; paper 000 §3.1.1).

Per volume and view: (1) the cube ray-marching pass casts a ray from the eye through the centre of every texel of
the visible faces (Eq. 1) of a cube map over the box and marches it from the box entry (or the near plane, with the
eye inside) to the texel, storing premultiplied colour and transmittance; (2) the cube resampling pass casts each
pixel's ray, finds where it leaves the box and samples the cube map there bilinearly (seamless across face edges).
The march is DSSRM's (`march_volume_light_map`), lit by the same light map. Cost follows the cube-map size, not the
viewport: S x S texels per visible face.

Adaptive LOD (§3.3) picks per volume and view the cube-map/density mip level and the sample count N from the box's
projected size; the hybrid choice (§3.4, first paragraph) marches a volume directly in screen space when its
projected pixels are fewer than its visible texels. ``cube_faces="exterior"`` casts rays to the exterior faces the eye
sees instead (paper 001 Fig. 2 (a)); it exists to show the texel aliasing that the interior scheme avoids.

Mesh occlusion (§3.2): each texel ray stops at the opaque surface of the z-buffer pixel its texel projects to
(nearest), its end depth is kept in a cube depth map, and resampling weights the 2x2 texels by the bilateral
edge-stopping w_z = max(1 - k_z |z_buffer - z_cube|, 0) (k_z = 0.5) so that texels cut at a different depth than
the pixel's own ray do not bleed across occlusion edges (the halo of plain bilinear).

Empty-tile culling (paper 000 §3's coarse phase, shared with CACRM): faces are marched in 32x32-texel tiles, and a
coarse pass drops the tiles whose rays can only meet zero density according to the conservative max-density pyramid
(`tile_occupancy_kernel`). Culled texels keep the transparent fill, which is what marching them would have given.
"""

from __future__ import annotations

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
    new_march_state,
    pixel_ray,
    project_pixel,
    write_pixel,
)
from volren.render.base import LightMapMarchConfig, Renderer
from volren.render.cubemap import (
    FACE_COUNT,
    TILE,
    cube_lod,
    cube_sample,
    face_point,
    face_tiles,
    point_face,
    texel_index,
    tile_occupancy_kernel,
    visible_faces,
)
from volren.render.dssrm import MarchParams, march_volume_light_map
from volren.render.frame import DENSITY_SAMPLES, LIGHTMAP_LOOKUPS, RAYS, PassClock
from volren.render.lightmap import compute_light_map
from volren.upload import DeviceScene, camera_struct, depth_order

SCHEME_DIRECT = 0
SCHEME_CUBE = 1


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


@dataclass(frozen=True)
class CMSRMConfig(LightMapMarchConfig):
    cube_size: int | None = None
    """S0: level-0 face size [texels]; None = the density grid's longest axis"""
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

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.cube_faces not in ("interior", "exterior"):
            raise VolrenError(f"cube faces must be interior or exterior, got '{self.cube_faces}'")
        if self.cube_size is not None and not 2 <= self.cube_size <= 4096:
            raise VolrenError(f"cube size must lie in [2, 4096] texels, got {self.cube_size}")
        if not (np.isfinite(self.k_z) and self.k_z >= 0):
            raise VolrenError(f"k_z must be >= 0, got {self.k_z}")
        if not (self.k_u > 0 and self.k_c > 0):
            raise VolrenError(f"k_u and k_c must be > 0, got {self.k_u} and {self.k_c}")


@wp.kernel
def cube_march_kernel(
    cam: CameraGPU,
    vol: VolumeGPU,
    tiles: wp.array(dtype=wp.vec3i),
    tile: int,
    size: int,
    exterior: int,
    medium: Medium,
    params: MarchParams,
    buffers: ViewBuffers,
    cube: wp.array(dtype=wp.vec4),
    cube_t: wp.array(dtype=float),
    cube_z: wp.array(dtype=float),
    offset: int,
    counters: wp.array(dtype=wp.int64),
    row0: int,
):
    """One ray per texel of the visible faces: from the eye through the texel centre, marched from the box entry
    (or near plane) to the texel (interior), or from the texel to the box exit (exterior), and cut at the opaque
    surface of the z-buffer pixel the texel projects to (nearest, the paper's blit into a cube depth map)."""
    r, c = wp.tid()
    row = r + row0
    k = row / tile
    t = tiles[k]
    f = t[0]
    i = t[1] + c
    j = t[2] + row - k * tile
    if i >= size or j >= size:
        return
    h = 2.0 / float(size)
    x = wp.transform_point(vol.to_world, face_point(f, -1.0 + (float(i) + 0.5) * h, -1.0 + (float(j) + 0.5) * h))
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
        pix = project_pixel(cam, x)
        col = int(wp.floor(pix[0]))
        row_z = int(wp.floor(pix[1]))
        if col >= 0 and col < cam.width and row_z >= 0 and row_z < cam.height:
            t1 = wp.min(t1, buffers.occluder_depth[row_z, col] / facing)
        if t1 > t0:
            count(counters, RAYS, 1)
            s = march_volume_light_map(s, vol, cam.origin, d, t0, t1, 0.5, medium, params)
    texel = offset + texel_index(f, i, j, size)
    cube[texel] = wp.vec4(s.color[0], s.color[1], s.color[2], s.transmittance)
    cube_t[texel] = s.depth_t
    cube_z[texel] = t1 * facing
    count(counters, DENSITY_SAMPLES, s.samples)
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
def cube_resample_kernel(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    order: wp.array(dtype=int),
    scheme: wp.array(dtype=int),
    cube_offset: wp.array(dtype=int),
    cube_size: wp.array(dtype=int),
    exterior: int,
    k_z: float,
    cube: wp.array(dtype=wp.vec4),
    cube_t: wp.array(dtype=float),
    cube_z: wp.array(dtype=float),
    medium: Medium,
    params: MarchParams,
    buffers: ViewBuffers,
    counters: wp.array(dtype=wp.int64),
    row0: int,
):
    """Per pixel, front to back over the volumes: a cube-scheme volume is looked up bilinearly where the pixel's ray
    leaves its box (enters, for exterior faces); a direct-scheme volume is marched here, as in DSSRM."""
    r, col = wp.tid()
    row = r + row0
    d, planes = pixel_ray(cam, buffers, row, col)
    s = new_march_state()
    direct = int(0)
    for k in range(order.shape[0]):
        v = order[k]
        vol = volumes[v]
        o_l = wp.transform_point(vol.to_local, cam.origin)
        d_l = wp.transform_vector(vol.to_local, d)
        h = box_hit(o_l, d_l)
        t0 = wp.max(h[0], planes[0])
        t1 = wp.min(h[1], planes[1])
        if t1 > t0:
            if scheme[v] == SCHEME_CUBE:
                t_face = h[1]
                if exterior != 0:
                    t_face = h[0]
                p = o_l + t_face * d_l
                c = cube_sample(cube, cube_z, cube_offset[v], cube_size[v], p, t1 * wp.dot(d, cam.forward), k_z)
                after = s.transmittance * c[3]
                if s.transmittance > 0.5 and after <= 0.5:
                    s.depth_t = cube_nearest_t(cube_t, cube_offset[v], cube_size[v], p)
                s.color = s.color + s.transmittance * wp.vec3(c[0], c[1], c[2])
                s.transmittance = after
            else:
                direct = 1
                s = march_volume_light_map(s, vol, cam.origin, d, t0, t1, 0.5, medium, params)
            if s.transmittance < params.min_transmittance:
                break
    count(counters, RAYS, direct)
    count(counters, LIGHTMAP_LOOKUPS, s.shaded * medium.lights.shape[0])
    write_pixel(s, cam, d, row, col, buffers, counters, DENSITY_SAMPLES)


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


class CMSRM(Renderer):
    """Cube-map-space ray marching; ``config`` is a `CMSRMConfig`."""

    name = "cmsrm"

    def __init__(self, config: CMSRMConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or CMSRMConfig(), device)

    def _prepare(self, scene, clock: PassClock, frame: int) -> DeviceScene:
        ds = self._upload(scene, clock, self.config.light_grid, mip_levels=True)
        compute_light_map(ds, self.config.light_samples, clock)
        self._frame_info["volumes"] = []
        return ds

    def _params(self, ds: DeviceScene, view: int, samples: int) -> MarchParams:
        params = MarchParams()
        params.samples = samples
        params.jitter = 0
        params.seed = 0
        params.view = view
        params.min_transmittance = self.config.min_transmittance
        params.ambient = ds.ambient
        return params

    def _plan(self, ds: DeviceScene, cam: Camera) -> list[dict]:
        """Per volume: visible faces (Eq. 1), LOD (§3.3) and scheme (hybrid, §3.4)."""
        c = self.config
        plans = []
        for vol in ds.scene.volumes:
            eye = (vol.to_local @ np.r_[cam.position, 1.0])[:3]
            faces = visible_faces(eye, c.cube_faces)
            base = c.cube_size or max(vol.resolution)
            lod = cube_lod(vol, cam, base, c.samples, c.k_u, c.k_c, c.adaptive_lod)
            texels = len(faces) * lod.size**2
            pixels = projected_pixels(vol.corners_world, cam)
            scheme = SCHEME_DIRECT if (c.hybrid and pixels < texels) or not faces else SCHEME_CUBE
            plans.append({"faces": faces, "lod": lod, "texels": texels, "pixels": pixels, "scheme": scheme})
        return plans

    def _plan_views(self, ds: DeviceScene, views: list[Camera]) -> list[list[dict]]:
        return [self._plan(ds, cam) for cam in views]

    def _allocate(self, plans: list[dict]) -> CubeMaps:
        """One view's cube maps: colour + transmittance, half-transmittance distance and end depth per texel."""
        offsets, sizes, total = [], [], 0
        for plan in plans:
            offsets.append(total)
            sizes.append(plan["lod"].size)
            if plan["scheme"] == SCHEME_CUBE:
                total += FACE_COUNT * plan["lod"].size ** 2
        n = max(total, 1)
        return CubeMaps(
            color=wp.full(n, wp.vec4(0.0, 0.0, 0.0, 1.0), dtype=wp.vec4, device=self.device),
            t_half=wp.full(n, INF, dtype=float, device=self.device),
            z_end=wp.full(n, INF, dtype=float, device=self.device),
            offsets=offsets,
            sizes=sizes,
            texels=total,
        )

    def _live_tiles(
        self, ds: DeviceScene, v: int, plan: dict, cams: list[Camera], clock: PassClock
    ) -> tuple[wp.array, int]:
        """The tiles of the plan's faces to march, after the coarse empty-tile culling pass (when on); records the
        counts in the plan."""
        lod = plan["lod"]
        tiles = face_tiles(plan["faces"], lod.size)
        tile = min(TILE, lod.size)
        plan["tiles"] = len(tiles)
        if self.config.cull_tiles and len(tiles):
            vol = ds.scene.volumes[v]
            eyes = [(vol.to_local @ np.r_[c.position, 1.0])[:3] for c in cams]
            offset, res = ds.max_grids[v]
            # A coarser density level reads voxels up to 2^level base voxels away (its trilinear support).
            margin = (2**lod.level) * 2.0 / min(vol.resolution)
            live = wp.zeros(len(tiles), dtype=int, device=self.device)
            with clock.measure("tile_cull"):
                wp.launch(tile_occupancy_kernel, dim=len(tiles),
                          inputs=[wp.array(tiles, dtype=wp.vec3i, device=self.device), tile, lod.size,
                                  wp.vec3(*eyes[0]), wp.vec3(*eyes[-1]), margin, ds.max_density, offset,
                                  wp.vec3i(*res), live], device=self.device)
            tiles = tiles[live.numpy() > 0]
        plan["live_tiles"] = len(tiles)
        return wp.array(tiles, dtype=wp.vec3i, device=self.device), tile

    def _march_cubes(
        self,
        ds: DeviceScene,
        views: list[Camera],
        plans: list[list[dict]],
        cubes: list[CubeMaps],
        targets: list[ViewBuffers],
        clock: PassClock,
    ) -> None:
        """The cube ray-marching pass of every view, each view on its own."""
        exterior = int(self.config.cube_faces == "exterior")
        for view, cam in enumerate(views):
            cam_gpu = camera_struct(cam)
            for v, plan in enumerate(plans[view]):
                if plan["scheme"] != SCHEME_CUBE:
                    continue
                lod = plan["lod"]
                level = ds.levels[v][min(lod.level, len(ds.levels[v]) - 1)]
                tiles, tile = self._live_tiles(ds, v, plan, [cam], clock)
                c = cubes[view]
                launch_rows(
                    cube_march_kernel,
                    len(tiles) * tile,
                    tile,
                    [cam_gpu, level, tiles, tile, lod.size, exterior, ds.medium(),
                     self._params(ds, view, lod.samples), targets[view], c.color, c.t_half, c.z_end, c.offsets[v]],
                    self.device,
                    clock.counters,
                )

    def _render_views(
        self, ds: DeviceScene, views: list[Camera], frame: int, targets: list[ViewBuffers], clock: PassClock
    ) -> None:
        plans = self._plan_views(ds, views)
        cubes = [self._allocate(p) for p in plans]
        with clock.measure("cube_march"):
            self._march_cubes(ds, views, plans, cubes, targets, clock)
        exterior = int(self.config.cube_faces == "exterior")
        for view, cam in enumerate(views):
            c = cubes[view]
            per_volume = [wp.array(a, dtype=int, device=self.device)
                          for a in ([p["scheme"] for p in plans[view]], c.offsets, c.sizes)]
            order = wp.array(depth_order(ds.scene, cam), dtype=int, device=self.device)
            with clock.measure("resample"):
                launch_rows(
                    cube_resample_kernel,
                    cam.height,
                    cam.width,
                    [camera_struct(cam), ds.volumes, order, *per_volume, exterior, self.config.k_z, c.color,
                     c.t_half, c.z_end, ds.medium(),
                     self._params(ds, view, self.config.samples), targets[view]],
                    self.device,
                    clock.counters,
                    self.on_rows,
                )
            self._frame_info["volumes"].append([
                {"view": view, "volume": v, "scheme": "cube" if p["scheme"] == SCHEME_CUBE else "direct",
                 "faces": p["faces"], "level": p["lod"].level, "face_size": p["lod"].size,
                 "samples": p["lod"].samples, "visible_texels": p["texels"], "projected_pixels": round(p["pixels"]),
                 "tiles": p.get("tiles", 0), "live_tiles": p.get("live_tiles", 0)}
                for v, p in enumerate(plans[view])
            ])
        self._frame_info["cube_map_bytes"] = sum(c.texels for c in cubes) * 24
