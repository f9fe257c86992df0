"""CACRM: coupled adaptive cube-map ray marching for binocular views (paper 000 §3.1), built on CMSRM.

Ray coupling (§3.1.2): the two eyes' rays that end on the same interior-face texel are marched by one work item.
Each eye's ray runs from its box entry (or near plane) to the texel (its t_min, t_max), cut at that eye's z-buffer,
in uniform steps of Delta t = diagonal / N anchored at the texel; the pair takes max(n_0, n_1) synchronised steps
front to back, and the eye whose segment is shorter skips the steps that lie outside it while keeping the step
(the paper's joint length t_d = max(t_max - t_min) with both rays starting at t_max - t_d). Where the two samples of
a step fall in the same trilinear cell (the paper's floor((x0 + t v) S + 0.5) test on voxel coordinates), its 8 voxels
are fetched once and interpolated for both rays (the explicit two-phase version); the counters record those as
``shared_samples``. The rays converge at the texel, so sharing grows towards the far faces. With empty-space
skipping a sample in the same cell as the other eye's sample in an empty skip cell reads 0 without a fetch (counted
as skipped): the cell is zero, though its own skip cell is not empty. Coupled against independent gathers, cloud 64^3,
stereo 160x90, defaults and --no-hybrid (issue 19 item 6): 0.711 with the fixed 2x VSA, 0.729 with the adaptive VSA
(Eq. 4's ramp lengthens the steps near the texels, where the eyes share most; uniform steps 0.712), 0.761 once
skipping left only the occupied cells to fetch (uniform 0.760), 0.763 with the face-rim pixels marched directly, 0.748
with the empty cells shared.

Both eyes get their own cube map (the visible faces of either eye, the finer LOD of the two) and are resampled to
their own views as in CMSRM. Views are coupled in pairs (0, 1), (2, 3), ...; an odd last view is marched alone.
``coupling=False`` marches each eye alone with the same anchored steps, so coupled marching without sharing gives the
same images; ``share_voxels=False`` keeps coupling but fetches per ray.

Variable step amplification (§3.1.3, Eq. 4-6): after each sample, each eye proposes the next step as
Delta t (N) max(k_a t / t_max, f_lambda^w_lambda f_T^w_T f_A^w_A, 1) with the base step Delta t = diagonal / N (the
paper's (t_max - t_min) / N; here the same base step as DSSRM and CMSRM, so that N means the same in all three), and
the pair takes the larger proposal (`marching.vsa`). Steps are real multiples of the base step counted back from
the texel, so uniform stepping (k_a = 0, w = 0) is exactly the texel-anchored lattice. An earlier version floored the
multiple to whole base steps: with f_lambda_max = 2 and f_T, f_A <= 1 every product below 2 became a uniform step, VSA
degenerated into a fixed 2x step and the density derivative never changed the image (issue 12). rho' is the
difference of the last two samples per base step (the paper uses Bergner et al.'s estimate). The constants come from
``scripts/fit_vsa.py`` (``vsa_fit.json``), fitted for quality at equal voxel gathers.

Empty-tile culling and tile LOD (32x32 tiles, the coarse phase) come from CMSRM; with a coupled pair a tile's level
bounds the footprint in both eyes. Interleaved spatial reuse (§3.1.3) routes the tiles where 2x2 quads can share
samples to `volren.render.marching.interleave`'s quad kernel.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

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
    cell_fraction,
    count,
    counter_row,
    first_skip_check,
    gather_cell,
    grid_cell,
    grid_coords,
    half_depth,
    interpolate_cell,
    skip_cell_ray,
    skip_lookup,
)
from volren.render.compositing.mesh_layers import (
    MeshLayers,
    next_layer_t,
    segment_advance,
    segment_finish,
    texel_layers,
)
from volren.render.frame import DENSITY_SAMPLES, LIGHTMAP_LOOKUPS, RAYS, SHARED_SAMPLES, SKIPPED_STEPS, PassClock
from volren.render.marching.cmsrm import CMSRM, CMSRMConfig, TileGroup
from volren.render.marching.cubemap import (
    CubeLOD,
    CubeTarget,
    eye_segment,
    store_texel,
    texel_index,
    texel_point,
    tile_texel,
)
from volren.render.marching.interleave import interleave_tiles, quad_march_kernel
from volren.render.marching.march import MarchParams, mode_step
from volren.render.marching.modes import MODE_MIP, skippable
from volren.render.marching.vsa import END, VSA_FIT, VSAParams, vsa_amplification
from volren.upload import DeviceScene, camera_struct


@dataclass(frozen=True)
class CACRMConfig(CMSRMConfig):
    coupling: bool = True
    """march both eyes' rays to a texel in one work item (off: each eye alone, same steps)"""
    share_voxels: bool = True
    """fetch a trilinear cell once when both eyes' samples fall in it"""
    vsa: bool = True
    """variable step amplification (Eq. 4-6); off = uniform steps"""
    interleave: bool = True
    """interleaved spatial reuse (§3.1.3): 2x2 texel quads share their samples where their rays run < 1/2 voxel
    apart (`volren.render.marching.interleave`)"""
    k_a: float = VSA_FIT["k_a"]
    """Eq. 4: ray-length amplification k_a t / t_max (paper: 3; fitted: 1.5, see vsa_fit.json)"""
    k_b: float = VSA_FIT["k_b"]
    """Eq. 5: wave-length factor f_lambda = min(k_b / |rho'|, f_lambda_max), rho' per base step"""
    f_lambda_max: float = VSA_FIT["f_lambda_max"]
    """Eq. 5's cap (paper: 2; fitted: 4)"""
    w_lambda: float = VSA_FIT["w_lambda"]
    w_t: float = VSA_FIT["w_t"]
    w_a: float = VSA_FIT["w_a"]

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("k_a", "k_b", "f_lambda_max", "w_lambda", "w_t", "w_a"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise VolrenError(f"{name} must be a finite number >= 0, got {value}")
        if self.cube_faces != "interior":
            raise VolrenError("cacrm couples rays on interior cube faces only (--cube-faces interior)")


@wp.func
def anchored_steps(seg: wp.vec4, dt: float) -> int:
    """Steps of dt from the texel back to t_min (the last one clipped), 0 for an empty segment."""
    if seg[3] == 0.0:
        return 0
    return wp.max(int(wp.ceil((seg[1] - seg[0]) / dt - 1.0e-6)), 1)


@wp.func
def lattice_step(seg: wp.vec4, pos: float, m: float, dt: float) -> wp.vec2:
    """(midpoint, length) of the step covering [pos - m, pos) base steps counted back from the texel:
    [t_max - pos dt, t_max - (pos - m) dt], clipped at t_min (a step wholly before t_min has length <= 0)."""
    hi = seg[1] - (pos - m) * dt
    lo = wp.max(seg[1] - pos * dt, seg[0])
    return wp.vec2(0.5 * (lo + hi), hi - lo)


@wp.func
def eye_update(
    acc: wp.vec4,
    half: float,
    peak: float,
    prev: float,
    prev_t: float,
    rho: float,
    vol: VolumeGPU,
    medium: Medium,
    o_l: wp.vec3,
    d_l: wp.vec3,
    origin: wp.vec3,
    d: wp.vec3,
    step: wp.vec2,
    seg: wp.vec4,
    vp: VSAParams,
    dt: float,
    absorb: float,
    params: MarchParams,
):
    """One eye's step of the coupled march: composite the sample (density rho on the local ray o_l + t d_l / world
    ray origin + t d, step midpoint and length ``step``) in ``params.mode`` (`march.mode_step`; ``peak``: MIDA's
    running max) and propose the next step's amplification by VSA. Returns (acc, half-transmittance distance, peak,
    previous density, previous distance, 1 if the sample was lit, extra density fetches, amplification)."""
    out, out_peak, lit, fetches, t_event = mode_step(acc, peak, rho, vol, medium, o_l, d_l, origin, d, step[0],
                                                     step[1], wp.max(step[0] - dt, seg[0]), params)
    out_half = half_depth(half, acc[3], out[3], t_event)
    m = float(1.0)
    out_prev = prev
    out_prev_t = prev_t
    if vp.enabled != 0:
        drho = float(0.0)
        if prev >= 0.0:
            drho = (rho - prev) * dt / wp.max(step[0] - prev_t, 1.0e-9)
        m = vsa_amplification(vp, step[0], seg[1], rho, drho, out[3], absorb)
        out_prev = rho
        out_prev_t = step[0]
    return out, out_half, out_peak, out_prev, out_prev_t, lit, fetches, m


@wp.kernel
def coupled_march_kernel(
    cam0: CameraGPU,
    cam1: CameraGPU,
    eyes: int,
    share: int,
    vol: VolumeGPU,
    tiles: wp.array(dtype=wp.vec3i),
    tile: int,
    apron: int,
    size: int,
    medium: Medium,
    params: MarchParams,
    vp: VSAParams,
    buffers0: ViewBuffers,
    buffers1: ViewBuffers,
    mesh0: MeshLayers,
    mesh1: MeshLayers,
    target0: CubeTarget,
    target1: CubeTarget,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """One texel, both eyes (eye 1 only when eyes == 2): synchronised anchored steps, shared cell fetches; with
    translucent meshes each eye's ray is cut into its cube k-buffer's segments at the mesh layers of the pixel the
    texel projects to in that eye (`segment_advance`)."""
    r, c = wp.tid()
    counters = counter_row(counter_rows, r, c)
    q = tile_texel(tiles, tile, apron, size, r + row0, c)
    if q[0] < 0:
        return
    x = wp.transform_point(vol.to_world, texel_point(q, size))
    seg0 = eye_segment(cam0, vol, x, buffers0)
    seg1 = wp.vec4(0.0)
    if eyes == 2:
        seg1 = eye_segment(cam1, vol, x, buffers1)
    d0 = wp.normalize(x - cam0.origin)
    d1 = wp.normalize(x - cam1.origin)
    o0 = wp.transform_point(vol.to_local, cam0.origin)
    o1 = wp.transform_point(vol.to_local, cam1.origin)
    dl0 = wp.transform_vector(vol.to_local, d0)
    dl1 = wp.transform_vector(vol.to_local, d1)
    # Empty-space skipping per eye (as `march_volume_light_map`): the skip cell holding a step's midpoint is looked
    # up when the step leaves the last cell (or empty cube) looked up; a step in an empty one reads density 0 without
    # a fetch, exactly what the fetch would read, so the lattice, VSA's proposals and the image are unchanged.
    oc0, dc0, inv0 = skip_cell_ray(vol, o0, dl0)
    oc1, dc1, inv1 = skip_cell_ray(vol, o1, dl1)
    check0 = first_skip_check(vol, medium.skip)
    check1 = check0
    empty0 = int(0)
    empty1 = int(0)
    skipped = int(0)
    dt = vol.diagonal / float(params.samples)
    n0 = anchored_steps(seg0, dt)
    n1 = anchored_steps(seg1, dt)
    n = wp.max(n0, n1)
    acc0 = wp.vec4(0.0, 0.0, 0.0, 1.0)
    acc1 = wp.vec4(0.0, 0.0, 0.0, 1.0)
    half0 = float(INF)
    half1 = float(INF)
    peak0 = float(0.0)
    peak1 = float(0.0)
    samples = int(0)
    shared = int(0)
    shaded = int(0)
    # VSA state per eye: the previous sample's density and position (for rho'), and the optical depth of a base step.
    prev0 = float(-1.0)
    prev1 = float(-1.0)
    prev_t0 = float(0.0)
    prev_t1 = float(0.0)
    absorb = vol.density_scale * dt
    # The pair walks back from each eye's texel in units of the base step, front to back: pos base steps remain
    # before the texel, and each step covers m of them (m = 1: uniform steps on the texel-anchored lattice).
    # Cube k-buffer per eye (paper 000 §3.3): the texel's pixel and layers, the open segment and where it began.
    texel = texel_index(q[0], q[1], q[2], size)
    pix0 = texel_layers(mesh0, cam0, x, target0.segments)
    pix1 = texel_layers(mesh1, cam1, x, target1.segments)
    j0 = int(0)
    j1 = int(0)
    snap0 = acc0
    snap1 = acc1
    next0 = next_layer_t(mesh0, pix0, 0, seg0)
    next1 = next_layer_t(mesh1, pix1, 0, seg1)
    pos = float(n)
    m = float(1.0)
    while pos > END:
        m = wp.min(m, pos)
        in0 = pos - m < float(n0) and acc0[3] >= params.min_transmittance
        in1 = pos - m < float(n1) and acc1[3] >= params.min_transmittance
        if not in0 and not in1:
            break
        # Each eye's work only while it is inside its segment (eye 1 is absent when marching one view alone).
        s0 = wp.vec2(0.0)
        s1 = wp.vec2(0.0)
        p0 = wp.vec3(0.0)
        p1 = wp.vec3(0.0)
        f0 = wp.vec3(0.0)
        f1 = wp.vec3(0.0)
        # no cell (-2, -1: never equal): the eye is outside its segment or in an empty skip cell, and fetches nothing
        c0 = wp.vec3i(-2)
        c1 = wp.vec3i(-1)
        if in0:
            s0 = lattice_step(seg0, pos, m, dt)
            if s0[0] >= check0:
                cell0 = skip_lookup(vol, medium.max_density, oc0 + s0[0] * dc0, oc0, inv0)
                check0 = cell0[1]
                empty0 = int(skippable(params.mode, cell0[0], acc0, params.inv_max, params.iso_value))
            p0 = o0 + s0[0] * dl0
            if empty0 == 0:
                f0 = grid_coords(vol.res, p0)
                c0 = grid_cell(vol.res, f0)
        if in1:
            s1 = lattice_step(seg1, pos, m, dt)
            if s1[0] >= check1:
                cell1 = skip_lookup(vol, medium.max_density, oc1 + s1[0] * dc1, oc1, inv1)
                check1 = cell1[1]
                empty1 = int(skippable(params.mode, cell1[0], acc1, params.inv_max, params.iso_value))
            p1 = o1 + s1[0] * dl1
            if empty1 == 0:
                f1 = grid_coords(vol.res, p1)
                c1 = grid_cell(vol.res, f1)
        rho0 = float(0.0)
        rho1 = float(0.0)
        if share != 0 and in0 and in1 and empty0 + empty1 == 1 and params.mode != MODE_MIP:
            # One eye in an empty skip cell: every trilinear cell read there is zero in all 8 voxels
            # (`volren.upload.skip_grid`), so where the other eye's sample falls in the same cell it reads 0 too,
            # without a fetch (a coupled saving the eyes alone cannot make: the other eye's skip cell is not empty).
            # Iso skips cells below V, where reading 0 decides the same; MIP skips cells below the eye's own max.
            if empty0 != 0:
                c0 = grid_cell(vol.res, grid_coords(vol.res, p0))
            else:
                c1 = grid_cell(vol.res, grid_coords(vol.res, p1))
        same = in0 and in1 and share != 0 and c0 == c1
        get0 = in0 and empty0 == 0 and not (same and empty1 != 0)
        get1 = in1 and empty1 == 0 and not (same and empty0 != 0)
        if get0 and get1 and same:
            cell = gather_cell(medium.density, vol.offset, vol.res, c0)
            rho0 = interpolate_cell(cell, cell_fraction(f0, c0))
            rho1 = interpolate_cell(cell, cell_fraction(f1, c0))
            shared += 1
        else:
            if get0:
                rho0 = interpolate_cell(gather_cell(medium.density, vol.offset, vol.res, c0), cell_fraction(f0, c0))
            if get1:
                rho1 = interpolate_cell(gather_cell(medium.density, vol.offset, vol.res, c1), cell_fraction(f1, c1))
        next_m = float(1.0)
        if in0:
            samples += int(get0)
            skipped += 1 - int(get0)
            if s0[0] > next0:
                j0, snap0 = segment_advance(mesh0, pix0, target0, (target0.offset + texel) * target0.segments, seg0,
                                            j0, snap0, acc0, s0[0])
                next0 = next_layer_t(mesh0, pix0, j0, seg0)
            acc0, half0, peak0, prev0, prev_t0, lit, fetches, m0 = eye_update(
                acc0, half0, peak0, prev0, prev_t0, rho0, vol, medium, o0, dl0, cam0.origin, d0, s0,
                seg0, vp, dt, absorb, params,
            )
            shaded += lit
            samples += fetches
            next_m = wp.max(next_m, m0)
        if in1:
            samples += int(get1)
            skipped += 1 - int(get1)
            if s1[0] > next1:
                j1, snap1 = segment_advance(mesh1, pix1, target1, (target1.offset + texel) * target1.segments, seg1,
                                            j1, snap1, acc1, s1[0])
                next1 = next_layer_t(mesh1, pix1, j1, seg1)
            acc1, half1, peak1, prev1, prev_t1, lit, fetches, m1 = eye_update(
                acc1, half1, peak1, prev1, prev_t1, rho1, vol, medium, o1, dl1, cam1.origin, d1, s1,
                seg1, vp, dt, absorb, params,
            )
            shaded += lit
            samples += fetches
            next_m = wp.max(next_m, m1)
        pos = pos - m
        m = next_m
    store_texel(target0, texel, acc0, half0, seg0[1] * seg0[2])
    if seg0[3] > 0.0:
        segment_finish(mesh0, pix0, target0, (target0.offset + texel) * target0.segments, seg0, j0, snap0, acc0)
    if eyes == 2:
        store_texel(target1, texel, acc1, half1, seg1[1] * seg1[2])
        if seg1[3] > 0.0:
            segment_finish(mesh1, pix1, target1, (target1.offset + texel) * target1.segments, seg1, j1, snap1, acc1)
    count(counters, DENSITY_SAMPLES, samples)
    count(counters, SHARED_SAMPLES, shared)
    count(counters, SKIPPED_STEPS, skipped)
    count(counters, LIGHTMAP_LOOKUPS, shaded * medium.lights.shape[0])
    count(counters, RAYS, int(seg0[3] + seg1[3]))


def merge_lods(a: CubeLOD, b: CubeLOD) -> CubeLOD:
    """One LOD for a coupled pair: the finer level, and the larger face size and sample count of the two eyes."""
    finer = a if a.level <= b.level else b
    return replace(finer, size=max(a.size, b.size), samples=max(a.samples, b.samples),
                   edge_pixels=max(a.edge_pixels, b.edge_pixels))


class CACRM(CMSRM):
    """Coupled binocular cube-map ray marching; ``config`` is a `CACRMConfig`."""

    name = "cacrm"

    def __init__(self, config: CACRMConfig | None = None, device: str = "auto") -> None:
        super().__init__(config or CACRMConfig(), device)

    def _vsa_on(self) -> bool:
        """VSA (and with it interleaving) in mode dvr only: Eq. 4-6's factors are fitted to DVR's transmittance and
        accumulated opacity; the other modes march the uniform texel-anchored lattice."""
        return self.config.vsa and self.config.mode == "dvr"

    def _vsa_params(self) -> VSAParams:
        c = self.config
        vp = VSAParams()
        vsa = self._vsa_on()
        vp.enabled = int(vsa)
        vp.k_a, vp.k_b, vp.f_lambda_max = (c.k_a, c.k_b, c.f_lambda_max) if vsa else (0.0, 1.0, 1.0)
        vp.w_lambda, vp.w_t, vp.w_a = (c.w_lambda, c.w_t, c.w_a) if vsa else (0.0, 0.0, 0.0)
        return vp

    def _plan_views(self, ds: DeviceScene, views: list[Camera]) -> list[list[dict]]:
        """Per pair, one plan for both eyes: faces seen by either, the finer LOD, cube unless both would go direct."""
        plans = super()._plan_views(ds, views)
        for a, b in zip(plans[0::2], plans[1::2], strict=False):
            for pa, pb in zip(a, b, strict=True):
                merged = {
                    "faces": sorted(set(pa["faces"]) | set(pb["faces"])),
                    "lod": merge_lods(pa["lod"], pb["lod"]),
                    "scheme": max(pa["scheme"], pb["scheme"]),
                }
                merged["texels"] = len(merged["faces"]) * merged["lod"].size ** 2
                pa.update(merged)
                pb.update(merged)
        return plans

    def _view_groups(self, n: int) -> list[tuple[int, ...]]:
        """Coupled pairs (0, 1), (2, 3), ... and an odd last view alone; every view alone without coupling."""
        if not self.config.coupling:
            return super()._view_groups(n)
        return [tuple(range(v, min(v + 2, n))) for v in range(0, n, 2)]

    def _launch_march(self, ds: DeviceScene, views: list[Camera], group: tuple[int, ...], v: int, level: VolumeGPU,
                      tiles: TileGroup, samples: int, dest: list[CubeTarget], targets: list[ViewBuffers],
                      clock: PassClock) -> None:
        first, last = group[0], group[-1]
        # InS: one work item per 2x2 quad in the tiles where some quad can interleave; one per texel elsewhere.
        routes = [(coupled_march_kernel, tiles.origins, tiles.rows)]
        if self.config.interleave and self._vsa_on():
            vol = ds.scene.volumes[v]
            origins = tiles.origins.numpy()
            res = np.array([level.res[0], level.res[1], level.res[2]], dtype=float)
            quad = interleave_tiles(vol.to_world, [views[i].position for i in group], views[first].near, origins,
                                    tiles.rows, tiles.size, vol.diagonal / float(np.linalg.norm(res)))
            routes = [(kernel, wp.array(origins[mask], dtype=wp.vec3i, device=self.device), cols)
                      for kernel, mask, cols in ((coupled_march_kernel, ~quad, tiles.rows),
                                                 (quad_march_kernel, quad, (tiles.rows + 1) // 2))
                      if mask.any()]
        for kernel, origins, cols in routes:
            launch_rows(
                kernel,
                len(origins) * cols,
                cols,
                [camera_struct(views[first]), camera_struct(views[last]), len(group), int(self.config.share_voxels),
                 level, origins, tiles.rows, tiles.apron, tiles.size, ds.medium(),
                 self._params(ds, first, samples), self._vsa_params(), targets[first], targets[last],
                 self._meshes[first], self._meshes[last], dest[0], dest[-1]],
                self.device,
                clock.counters,
            )
