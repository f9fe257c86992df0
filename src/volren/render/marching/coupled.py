"""What CACRM's two coupled kernels share (paper 000 §3.1.2): the launch's inputs for a pair of eyes, one eye's texel
ray with its march state, and the end of an eye's march (its cube texel and cube k-buffer segments).

Both kernels start each eye's ray by `pair_eye_ray` and end it by `pair_finish`; in between they keep each eye's
state in a row of small vectors and matrices and loop over the eyes (or lanes), so eye 0 and eye 1 run the same code.
Warp passes structs to functions by value: a function called every step with the launch's structs (volume, medium,
buffers) copies them every step, so the per-eye code of a step stays in the kernel's loop over eyes.

An eye marches a tile only where the coarse pass found density on its own rays there (`tile_eyes`, as CMSRM culls
each eye alone): the pair's tile is live where either eye's is, and the other eye's texels keep the transparent fill
there, with no ray. Culling the pair's tiles jointly marched 7.5% more eye rays than CMSRM on the smoke 256^3 at
1080p stereo, and its empty texels stored a finite end depth where CMSRM's keep the fill's."""

from __future__ import annotations

import warp as wp

from volren.kernels.common import INF, CameraGPU, Medium, ViewBuffers, VolumeGPU, skip_cell_ray
from volren.render.compositing.mesh_layers import MeshLayers, next_layer_t, segment_finish, texel_layers
from volren.render.marching.cubemap import CubeTarget, eye_segment, store_texel
from volren.render.marching.march import MarchParams
from volren.render.marching.vsa import VSAParams


@wp.struct
class CoupledJob:
    """One coupled march launch: the pair's cameras, z-buffers, mesh k-buffers and cube maps (eye 1's only read when
    ``eyes`` == 2), voxel sharing on/off, the density level, the tiles ((face, row, col) origins of ``tile`` rows,
    ``apron`` texels of margin, face size ``size``; per tile, bit e set where eye e marches it) and the march
    constants."""

    cam0: CameraGPU
    cam1: CameraGPU
    buffers0: ViewBuffers
    buffers1: ViewBuffers
    mesh0: MeshLayers
    mesh1: MeshLayers
    target0: CubeTarget
    target1: CubeTarget
    eyes: int
    share: int
    vol: VolumeGPU
    tiles: wp.array(dtype=wp.vec3i)
    tile_eyes: wp.array(dtype=int)
    tile: int
    apron: int
    size: int
    medium: Medium
    params: MarchParams
    vp: VSAParams


@wp.struct
class EyeRay:
    """One eye's ray to a texel as a coupled march starts it (`eye_ray`)."""

    seg: wp.vec4
    """(t_min, t_max, facing, 1 if the ray has a segment), `eye_segment`"""
    origin: wp.vec3
    """the eye (world)"""
    d: wp.vec3
    """unit direction to the texel (world)"""
    o: wp.vec3
    """the eye in the volume's local frame"""
    dl: wp.vec3
    """the direction in the local frame"""
    oc: wp.vec3
    """the ray in skip-cell coordinates (`skip_cell_ray`): origin, direction, inverse direction"""
    dc: wp.vec3
    inv: wp.vec3
    n: int
    """anchored base steps from the texel back to t_min"""
    pix: wp.vec3i
    """cube k-buffer: the texel's pixel and layer count (`texel_layers`), the texel's first segment and where the
    first segment closes (INF: no layer ahead)"""
    base: int
    next_t: float


@wp.func
def anchored_steps(seg: wp.vec4, dt: float) -> int:
    """Steps of dt from the texel back to t_min (the last one clipped), 0 for an empty segment."""
    if seg[3] == 0.0:
        return 0
    return wp.max(int(wp.ceil((seg[1] - seg[0]) / dt - 1.0e-6)), 1)


@wp.func
def eye_ray(cam: CameraGPU, buffers: ViewBuffers, mesh: MeshLayers, target: CubeTarget, vol: VolumeGPU,
            x: wp.vec3, texel: int, dt: float) -> EyeRay:
    """The ray of one eye to world texel point x: its segment cut at the eye's z-buffer, frames, skip-cell ray, step
    count and cube k-buffer cursor."""
    r = EyeRay()
    r.seg = eye_segment(cam, vol, x, buffers)
    r.origin = cam.origin
    r.d = wp.normalize(x - cam.origin)
    r.o = wp.transform_point(vol.to_local, cam.origin)
    r.dl = wp.transform_vector(vol.to_local, r.d)
    oc, dc, inv = skip_cell_ray(vol, r.o, r.dl)
    r.oc = oc
    r.dc = dc
    r.inv = inv
    r.n = anchored_steps(r.seg, dt)
    r.pix = texel_layers(mesh, cam, x, target.segments)
    r.base = (target.offset + texel) * target.segments
    r.next_t = next_layer_t(mesh, r.pix, 0, r.seg)
    return r


@wp.func
def tile_views(job: CoupledJob, k: int) -> int:
    """The eyes that march tile k: bit e for eye e (never eye 1 of a single view)."""
    if job.eyes < 2:
        return job.tile_eyes[k] & 1
    return job.tile_eyes[k]


@wp.func
def pair_eye_ray(job: CoupledJob, e: int, views: int, vol: VolumeGPU, x: wp.vec3, texel: int, dt: float) -> EyeRay:
    """`eye_ray` of eye e of the pair; an eye that does not march the tile (``views``, `tile_views`) has no
    segment."""
    if (views >> e) & 1 == 0:
        r = EyeRay()
        r.next_t = INF
        return r
    if e == 0:
        return eye_ray(job.cam0, job.buffers0, job.mesh0, job.target0, vol, x, texel, dt)
    return eye_ray(job.cam1, job.buffers1, job.mesh1, job.target1, vol, x, texel, dt)


@wp.func
def job_constants(job: CoupledJob):
    """The launch's volume level, medium, march and VSA constants, and the base step Delta t = diagonal / N, read
    once per work item (a struct member read in a loop is copied there each time)."""
    return job.vol, job.medium, job.params, job.vp, job.vol.diagonal / float(job.params.samples)


@wp.func
def pair_mesh(job: CoupledJob, e: int) -> MeshLayers:
    """Eye e's mesh k-buffer."""
    if e == 0:
        return job.mesh0
    return job.mesh1


@wp.func
def pair_target(job: CoupledJob, e: int) -> CubeTarget:
    """Eye e's cube map."""
    if e == 0:
        return job.target0
    return job.target1


@wp.func
def finish_eye(mesh: MeshLayers, target: CubeTarget, texel: int, seg: wp.vec4, acc: wp.vec4, half: float,
               pix: wp.vec3i, base: int, j: int, snap: wp.vec4):
    """Store one eye's texel (colour, transmittance, half-transmittance distance, end depth) and close its open cube
    k-buffer segment."""
    store_texel(target, texel, acc, half, seg[1] * seg[2])
    if seg[3] > 0.0:
        segment_finish(mesh, pix, target, base, seg, j, snap, acc)


@wp.func
def pair_finish(job: CoupledJob, e: int, views: int, texel: int, seg: wp.vec4, acc: wp.vec4, half: float,
                pix: wp.vec3i, base: int, j: int, snap: wp.vec4):
    """`finish_eye` for eye e of the pair where it marches the tile (``views``); elsewhere its texel keeps the
    fill."""
    if (views >> e) & 1 == 0:
        return
    if e == 0:
        finish_eye(job.mesh0, job.target0, texel, seg, acc, half, pix, base, j, snap)
    else:
        finish_eye(job.mesh1, job.target1, texel, seg, acc, half, pix, base, j, snap)
