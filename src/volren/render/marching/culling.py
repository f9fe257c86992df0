"""Paper 001 §3.4's preemptive culling pass as one kernel: one thread per volume instance does, in sequence, the
viewport-visibility culling, the vertex projections and edge lengths (§3.3 steps 1-2), the cube-map LOD (§3.3 steps
3-5), the scheme choice (cube map or direct march) and the visible-face mask (Eq. 1), and writes a packed 16-byte
descriptor: (instance ID, N, level | (scheme + 1) << 8 | face mask << 16, face size S). The instance ID is also the
volume source ID (volren has no shared sources). The paper runs 8 threads per instance (2 edges each); on Warp one
thread per instance keeps the kernel short, the work being 8 corners and 12 edges.

It computes what `CMSRM._plan`'s host functions compute (`frustum_visible`, `projected_pixels`, `cube_lod`,
`visible_faces`), in float32 instead of float64; the test compares both on random instances.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.kernels.common import INF, CameraGPU, VolumeGPU, box_hit
from volren.render.marching.cubemap import FACE_COUNT, FACE_SIZE_STEP, axis_unit
from volren.upload import DeviceScene, camera_struct

SQRT3 = 1.7320508075688772
SCHEME_CULLED = -1
"""outside the view frustum: no cube map, no tiles, no rays (below the others so that CACRM's per-pair max keeps
the scheme of an eye that sees the volume)"""
SCHEME_DIRECT = 0
SCHEME_CUBE = 1


@wp.struct
class CullParams:
    samples: int
    """N_max"""
    k_u: float
    k_c: float
    adaptive: int
    hybrid: int
    exterior: int
    max_size: int
    """the screen sizing's cap (`cubemap.face_size_cap`: the kernel raises it to the base); 0: no screen sizing"""


@wp.func
def box_corner(vol: VolumeGPU, i: int) -> wp.vec3:
    """Corner i of the box, x fastest (the order of `Volume.corners_world`)."""
    c = wp.vec3(float(2 * (i % 2) - 1), float(2 * ((i / 2) % 2) - 1), float(2 * (i / 4) - 1))
    return wp.transform_point(vol.to_world, c)


@wp.func
def view_point(cam: CameraGPU, x: wp.vec3) -> wp.vec3:
    """(right, up, depth) coordinates of world x."""
    v = x - cam.origin
    return wp.vec3(wp.dot(v, cam.right), wp.dot(v, cam.up), wp.dot(v, cam.forward))


@wp.func
def frustum_corner_local(cam: CameraGPU, vol: VolumeGPU, tx: float, ty: float, i: int) -> wp.vec3:
    """Corner i of the view frustum (near plane for i < 4, far plane after; x fastest) in the box's local space."""
    z = cam.near
    if i >= 4:
        z = cam.far
    sx = float(2 * (i % 2) - 1)
    sy = float(2 * ((i / 2) % 2) - 1)
    return wp.transform_point(vol.to_local, cam.origin + z * (cam.forward + sx * tx * cam.right + sy * ty * cam.up))


@wp.func
def corner_pixel(cam: CameraGPU, vol: VolumeGPU, i: int, focal: float) -> wp.vec2:
    """Corner i projected to pixels from the viewport centre (meaningful in front of the eye only)."""
    p = view_point(cam, box_corner(vol, i))
    return wp.vec2(p[0], p[1]) * (focal / wp.max(p[2], 1.0e-30))


@wp.func
def frustum_visible_gpu(cam: CameraGPU, vol: VolumeGPU) -> int:
    """`frustum_visible` (cmsrm.py): 6 frustum planes against the 8 box corners, 6 box planes against the 8 frustum
    corners; visible unless one plane separates them (1e-6 relative tolerance)."""
    tx = cam.tan_half_fov * cam.aspect
    ty = cam.tan_half_fov
    scale = float(1.0)
    for i in range(8):
        p = view_point(cam, box_corner(vol, i))
        scale = wp.max(scale, wp.max(wp.abs(p[0]), wp.max(wp.abs(p[1]), wp.abs(p[2]))))
    tol = 1.0e-6 * scale
    n_near = int(0)
    n_far = int(0)
    n_right = int(0)
    n_left = int(0)
    n_top = int(0)
    n_bottom = int(0)
    for i in range(8):
        p = view_point(cam, box_corner(vol, i))
        if cam.near - p[2] > tol:
            n_near += 1
        if p[2] - cam.far > tol:
            n_far += 1
        if p[0] - tx * p[2] > tol:
            n_right += 1
        if -p[0] - tx * p[2] > tol:
            n_left += 1
        if p[1] - ty * p[2] > tol:
            n_top += 1
        if -p[1] - ty * p[2] > tol:
            n_bottom += 1
    if n_near == 8 or n_far == 8 or n_right == 8 or n_left == 8 or n_top == 8 or n_bottom == 8:
        return 0
    lscale = float(1.0)
    for i in range(8):
        q = frustum_corner_local(cam, vol, tx, ty, i)
        lscale = wp.max(lscale, wp.max(wp.abs(q[0]), wp.max(wp.abs(q[1]), wp.abs(q[2]))))
    ltol = 1.0e-6 * lscale
    for a in range(3):
        above = int(0)
        below = int(0)
        for i in range(8):
            q = frustum_corner_local(cam, vol, tx, ty, i)
            if q[a] > 1.0 + ltol:
                above += 1
            if q[a] < -1.0 - ltol:
                below += 1
        if above == 8 or below == 8:
            return 0
    return 1


@wp.func
def frustum_clip(fa: float, fd: float, s: wp.vec2) -> wp.vec2:
    """The parameter range [s0, s1] of a segment a + s d left inside the half-space f >= 0 (f(a) = fa, f's change
    along d = fd); s0 > s1 once empty."""
    if fd == 0.0:
        if fa < 0.0:
            return wp.vec2(s[0], -1.0)
        return s
    if fd > 0.0:
        return wp.vec2(wp.max(s[0], -fa / fd), s[1])
    return wp.vec2(s[0], wp.min(s[1], -fa / fd))


@wp.func
def view_density(cam: CameraGPU, vol: VolumeGPU, p: wp.vec3, focal: float) -> float:
    """Pixels per face width along the box axis that is densest on screen at the view point p (`screen_texels`)."""
    best = float(0.0)
    for k in range(3):
        # the box's full extent along axis k, in view coordinates
        w = view_point(cam, cam.origin + 2.0 * wp.transform_vector(vol.to_world, axis_unit(k)))
        best = wp.max(best, wp.length(wp.vec2(w[0] - p[0] * w[2] / p[2], w[1] - p[1] * w[2] / p[2])) * focal / p[2])
    return best


@wp.func
def screen_texels_gpu(cam: CameraGPU, vol: VolumeGPU, focal: float) -> float:
    """`cubemap.screen_texels`: the largest `view_density` over each box edge's nearest point in the view frustum
    and the points where the view axis and the frustum's corner rays leave the box (0 when the box is not in view)."""
    tx = cam.tan_half_fov * cam.aspect
    ty = cam.tan_half_fov
    best = float(0.0)
    for i in range(8):
        for bit in range(3):
            j = i ^ (1 << bit)
            if i < j:
                a = view_point(cam, box_corner(vol, i))
                d = view_point(cam, box_corner(vol, j)) - a
                s = wp.vec2(0.0, 1.0)
                s = frustum_clip(a[2] - cam.near, d[2], s)
                s = frustum_clip(tx * a[2] - a[0], tx * d[2] - d[0], s)
                s = frustum_clip(tx * a[2] + a[0], tx * d[2] + d[0], s)
                s = frustum_clip(ty * a[2] - a[1], ty * d[2] - d[1], s)
                s = frustum_clip(ty * a[2] + a[1], ty * d[2] + d[1], s)
                if s[0] <= s[1]:
                    t = s[1]
                    if d[2] >= 0.0:
                        t = s[0]
                    best = wp.max(best, view_density(cam, vol, a + t * d, focal))
    eye = wp.transform_point(vol.to_local, cam.origin)
    for r in range(5):
        sx = float(0.0)
        sy = float(0.0)
        if r > 0:
            sx = tx * float(2 * ((r - 1) % 2) - 1)
            sy = ty * float(2 * ((r - 1) / 2) - 1)
        ray = cam.forward + sx * cam.right + sy * cam.up
        h = box_hit(eye, wp.transform_vector(vol.to_local, ray))
        if h[1] >= wp.max(h[0], 0.0) and h[1] >= cam.near:
            best = wp.max(best, view_density(cam, vol, h[1] * wp.vec3(sx, sy, 1.0), focal))
    return best


@wp.kernel
def culling_kernel(
    cam: CameraGPU,
    volumes: wp.array(dtype=VolumeGPU),
    base_size: wp.array(dtype=int),
    levels: wp.array(dtype=int),
    params: CullParams,
    descriptors: wp.array(dtype=wp.vec4i),
    footprint: wp.array(dtype=wp.vec2),
):
    """One thread per instance: the packed descriptor and (projected pixels, longest projected edge [px])."""
    v = wp.tid()
    vol = volumes[v]
    base = base_size[v]
    visible = frustum_visible_gpu(cam, vol)
    # §3.3 steps 1-2: project the corners; a corner at or behind the near plane makes the footprint unbounded.
    focal = float(cam.height) / (2.0 * cam.tan_half_fov)
    behind = int(0)
    lo = wp.vec2(1.0e30)
    hi = wp.vec2(-1.0e30)
    for i in range(8):
        if view_point(cam, box_corner(vol, i))[2] <= cam.near:
            behind = 1
        q = corner_pixel(cam, vol, i, focal)
        lo = wp.vec2(wp.min(lo[0], q[0]), wp.min(lo[1], q[1]))
        hi = wp.vec2(wp.max(hi[0], q[0]), wp.max(hi[1], q[1]))
    w = float(cam.width)
    h = float(cam.height)
    pixels = w * h
    edge = float(INF)
    if behind == 0:
        pixels = (wp.clamp(hi[0] + 0.5 * w, 0.0, w) - wp.clamp(lo[0] + 0.5 * w, 0.0, w)) * (
            wp.clamp(hi[1] + 0.5 * h, 0.0, h) - wp.clamp(lo[1] + 0.5 * h, 0.0, h))
        edge = float(0.0)
        for i in range(8):
            for bit in range(3):
                j = i ^ (1 << bit)
                if i < j:
                    edge = wp.max(edge, wp.length(corner_pixel(cam, vol, i, focal) - corner_pixel(cam, vol, j, focal)))
    # §3.3 steps 3-5: S_ideal, N, S and the level (`cube_lod`).
    level = int(0)
    n = params.samples
    if params.adaptive != 0 and behind == 0:
        n_ideal = params.k_c * (edge / params.k_u) / SQRT3
        n = wp.max(1, wp.min(int(wp.ceil(n_ideal)), params.samples))
        s = SQRT3 * wp.min(n_ideal, float(n)) / params.k_c
        if s < float(base):
            level = wp.min(int(wp.floor(wp.log2(float(base) / wp.max(s, 1.0e-9)))), levels[v] - 1)
    size = wp.max(base >> level, 2)
    if params.max_size != 0 and params.adaptive != 0:
        # `cubemap.screen_face_size`: raised to what the screen needs, up to the cap.
        need = FACE_SIZE_STEP * int(wp.ceil(screen_texels_gpu(cam, vol, focal) / params.k_u / float(FACE_SIZE_STEP)))
        size = wp.max(size, wp.min(need, wp.max(base, params.max_size)))
    # Eq. 1: the visible-face mask from the eye in local space.
    eye = wp.transform_point(vol.to_local, cam.origin)
    mask = int(0)
    faces = int(0)
    if visible != 0:
        for f in range(FACE_COUNT):
            sign = float(1.0)
            if f % 2 == 1:
                sign = -1.0
            beyond = eye[f / 2] * sign - 1.0
            if (beyond < 0.0) == (params.exterior == 0):
                mask = mask | (1 << f)
                faces += 1
    else:
        pixels = 0.0
    texels = float(faces * size * size)
    scheme = int(SCHEME_CUBE)
    if visible == 0:
        scheme = SCHEME_CULLED
    elif (params.hybrid != 0 and pixels < texels) or faces == 0:
        scheme = SCHEME_DIRECT
    descriptors[v] = wp.vec4i(v, n, level | ((scheme + 1) << 8) | (mask << 16), size)
    footprint[v] = wp.vec2(pixels, edge)


def unpack(descriptor: np.ndarray) -> dict:
    """One descriptor row as the plan fields: scheme, level, face size S, N and the visible faces."""
    _, samples, packed, size = (int(x) for x in descriptor)
    mask = packed >> 16
    return {"scheme": ((packed >> 8) & 0xFF) - 1, "level": packed & 0xFF, "size": size, "samples": samples,
            "faces": [f for f in range(FACE_COUNT) if mask >> f & 1]}


def cull_instances(ds: DeviceScene, cam: Camera, base_sizes: list[int], params: CullParams
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Run the culling pass for one view: (descriptors (n, 4) int32, footprints (n, 2): projected pixels and the
    longest projected edge)."""
    n = ds.volume_count
    descriptors = wp.zeros(n, dtype=wp.vec4i, device=ds.device)
    footprint = wp.zeros(n, dtype=wp.vec2, device=ds.device)
    levels = [len(v.mip_pyramid) for v in ds.scene.volumes]
    wp.launch(culling_kernel, dim=n,
              inputs=[camera_struct(cam), ds.volumes, wp.array(base_sizes, dtype=int, device=ds.device),
                      wp.array(levels, dtype=int, device=ds.device), params, descriptors, footprint],
              device=ds.device)
    return descriptors.numpy(), footprint.numpy()
