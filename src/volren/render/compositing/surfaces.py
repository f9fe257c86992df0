"""Opaque-surface pass: the scene's analytic spheres and planes and its triangle meshes (`wp.Mesh` BVH ray queries)
ray-traced per view into a colour + linear depth buffer, merged with an optional user depth image. Every renderer
clips its rays at this depth and composites the volume over the colour (paper 001 §3.2's z-buffer).

Surfaces are Lambertian, lit by every light (with ray-traced shadows from the other opaque objects) and by the
ambient environment (albedo * L_ambient). The volumes shade the opaque surfaces (`surface_light`, issue 14 item 5):
each light is attenuated by the volumes' transmittance (the light-map methods read their light maps where the shadow
ray enters each box, the reference marches the density) and the ambient by the volumes' ambient occlusion (the GI
grid's SH, or a few transmittance rays); methods without a light map leave them unshadowed here (fog), or shadow them
themselves (VPT re-shades each surface pixel with ratio-tracked shadows, `volren.render.vpt.tracer`). Surfaces
do not shadow volumes: the light map and the reference's shadow rays see only the media. Translucent meshes
(alpha < 1) are left out of this pass and cast no shadows; they are shaded with `shade_lit_surface` as layers
(`volren.render.compositing.mesh_layers`).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.errors import VolrenError
from volren.kernels.common import (
    INF,
    OPAQUE_PLANE,
    OPAQUE_SPHERE,
    CameraGPU,
    LightGPU,
    OpaqueGPU,
    ViewBuffers,
    camera_ray,
    counter_row,
    light_distance,
    light_irradiance,
    light_travel_dir,
)
from volren.render.compositing.surface_light import SurfaceLight, ambient_occlusion, unlit, volume_shadow
from volren.scene import TriangleMesh
from volren.upload import DeviceScene

SURFACE_EPSILON = 1.0e-4
"""[m] minimum hit distance, so a shadow ray does not hit the surface it leaves"""
MESH_RANGE = wp.constant(1.0e6)
"""[m] longest BVH ray query: "no limit" (INF = 1e30) overflows the traversal's arithmetic"""


@wp.func
def opaque_hit(obj: OpaqueGPU, o: wp.vec3, d: wp.vec3) -> float:
    """Nearest hit distance t > SURFACE_EPSILON of the unit-direction ray o + t d with obj, INF if none."""
    if obj.kind == OPAQUE_SPHERE:
        oc = o - obj.position
        b = wp.dot(oc, d)
        disc = b * b - (wp.dot(oc, oc) - obj.radius * obj.radius)
        if disc < 0.0:
            return INF
        root = wp.sqrt(disc)
        t = -b - root
        if t > SURFACE_EPSILON:
            return t
        t = -b + root
        if t > SURFACE_EPSILON:
            return t
        return INF
    denom = wp.dot(d, obj.normal)
    if wp.abs(denom) < 1.0e-12:
        return INF
    t = wp.dot(obj.position - o, obj.normal) / denom
    if t > SURFACE_EPSILON:
        return t
    return INF


@wp.func
def opaque_normal(obj: OpaqueGPU, x: wp.vec3) -> wp.vec3:
    if obj.kind == OPAQUE_PLANE:
        return obj.normal
    return wp.normalize(x - obj.position)


@wp.func
def occluded(x: wp.vec3, to_light: wp.vec3, dist: float, opaque: wp.array(dtype=OpaqueGPU),
             mesh_ids: wp.array(dtype=wp.uint64)) -> bool:
    """Whether any opaque object blocks the segment from x towards the light (shadow ray)."""
    for k in range(opaque.shape[0]):
        if opaque_hit(opaque[k], x, to_light) < dist:
            return True
    for k in range(mesh_ids.shape[0]):
        if wp.mesh_query_ray_anyhit(mesh_ids[k], x, to_light, wp.min(dist, MESH_RANGE)):
            return True
    return False


@wp.func
def shade_lit_surface(
    x: wp.vec3,
    normal: wp.vec3,
    d: wp.vec3,
    albedo: wp.vec3,
    lights: wp.array(dtype=LightGPU),
    ambient: wp.vec3,
    opaque: wp.array(dtype=OpaqueGPU),
    mesh_ids: wp.array(dtype=wp.uint64),
    sl: SurfaceLight,
    counters: wp.array(dtype=wp.int64),
) -> wp.vec3:
    """Lambertian radiance towards the eye of the surface point x seen along d, the side facing the eye lit:
    albedo * (L_ambient AO + sum_l E_l T_l cos / pi) over the lights not blocked by the opaque objects, with the
    volumes' ambient occlusion AO and transmittance T_l towards each light (`surface_light`)."""
    n = normal
    if wp.dot(n, d) > 0.0:
        n = -n
    lifted = x + SURFACE_EPSILON * n
    rgb = wp.cw_mul(albedo, ambient) * ambient_occlusion(sl, lifted, n, counters)
    for li in range(lights.shape[0]):
        light = lights[li]
        to_light = -light_travel_dir(light, x)
        cos = wp.dot(n, to_light)
        dist = light_distance(light, x)
        if cos > 0.0 and not occluded(lifted, to_light, dist, opaque, mesh_ids):
            shadow = volume_shadow(sl, li, light, lifted, to_light, dist, counters)
            rgb += wp.cw_mul(albedo, light_irradiance(light, x)) * (shadow * cos / wp.pi)
    return rgb


@wp.func
def nearest_surface(o: wp.vec3, d: wp.vec3, opaque: wp.array(dtype=OpaqueGPU), mesh_ids: wp.array(dtype=wp.uint64),
                    mesh_albedo: wp.array(dtype=wp.vec3)):
    """The nearest opaque object along o + t d: (t or INF, its normal at the hit, its albedo)."""
    t = float(INF)
    normal = wp.vec3(0.0)
    albedo = wp.vec3(0.0)
    for k in range(opaque.shape[0]):
        obj = opaque[k]
        tk = opaque_hit(obj, o, d)
        if tk < t:
            t = tk
            normal = opaque_normal(obj, o + tk * d)
            albedo = obj.albedo
    for k in range(mesh_ids.shape[0]):
        q = wp.mesh_query_ray(mesh_ids[k], o, d, wp.min(t, MESH_RANGE))
        if q.result and q.t > SURFACE_EPSILON and q.t < t:
            t = q.t
            normal = q.normal
            albedo = mesh_albedo[k]
    return t, normal, albedo


@wp.kernel
def surface_kernel(
    cam: CameraGPU,
    opaque: wp.array(dtype=OpaqueGPU),
    mesh_ids: wp.array(dtype=wp.uint64),
    mesh_albedo: wp.array(dtype=wp.vec3),
    lights: wp.array(dtype=LightGPU),
    ambient: wp.vec3,
    sl: SurfaceLight,
    user_depth: wp.array2d(dtype=float),
    buffers: ViewBuffers,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    r, col = wp.tid()
    counters = counter_row(counter_rows, r, col)
    row = r + row0
    d = camera_ray(cam, row, col, 0.5, 0.5)
    t, normal, albedo = nearest_surface(cam.origin, d, opaque, mesh_ids, mesh_albedo)
    color = wp.vec4(0.0)
    z = float(INF)
    if t < INF:
        rgb = shade_lit_surface(cam.origin + t * d, normal, d, albedo, lights, ambient, opaque, mesh_ids, sl,
                                counters)
        color = wp.vec4(rgb[0], rgb[1], rgb[2], 1.0)
        z = t * wp.dot(d, cam.forward)
    if user_depth[row, col] < z:
        z = user_depth[row, col]
        color = wp.vec4(0.0)
    buffers.occluder_color[row, col] = color
    buffers.occluder_depth[row, col] = z


def view_buffers(cam: Camera, device: str) -> ViewBuffers:
    """Render targets for one view, with empty surface buffers (no opaque surface anywhere)."""
    b = ViewBuffers()
    shape = (cam.height, cam.width)
    b.image = wp.zeros(shape, dtype=wp.vec4, device=device)
    b.depth = wp.zeros(shape, dtype=float, device=device)
    b.occluder_color = wp.zeros(shape, dtype=wp.vec4, device=device)
    b.occluder_depth = wp.full(shape, INF, dtype=float, device=device)
    return b


def check_user_depth(depth: np.ndarray, cam: Camera, view: int) -> np.ndarray:
    """A user depth image: linear view depth [m] per pixel, (H, W), +inf where nothing is opaque."""
    arr = np.asarray(depth, dtype=np.float32)
    if arr.shape != (cam.height, cam.width):
        need = (cam.height, cam.width)
        raise VolrenError(f"depth image for view {view} has shape {arr.shape}, the view needs {need}")
    if np.isnan(arr).any() or (arr <= 0).any():
        raise VolrenError(f"depth image for view {view} must hold positive depths or +inf (no NaN)")
    return np.minimum(arr, np.float32(INF))


def trace_surfaces(
    ds: DeviceScene,
    cam_gpu: CameraGPU,
    cam: Camera,
    user_depth: np.ndarray | None,
    buffers: ViewBuffers,
    counters: wp.array,
    light: SurfaceLight | None = None,
) -> None:
    """Fill ``buffers``' surface colour and depth (rows in parallel bands on the CPU); a no-op when there is nothing
    opaque. ``counters``: the frame's counter rows (`launch_rows`); ``light``: how the volumes shade the surfaces
    (None: they do not)."""
    if not ds.scene.opaque and user_depth is None:
        return
    if user_depth is None:
        user = wp.full((cam.height, cam.width), INF, dtype=float, device=ds.device)
    else:
        user = wp.array(user_depth, dtype=float, device=ds.device)
    ids, albedo, _ = mesh_group(ds, translucent=False)
    launch_rows(surface_kernel, cam.height, cam.width,
                [cam_gpu, ds.opaque, ids, albedo, ds.lights, ds.ambient, light or unlit(ds), user, buffers], ds.device,
                counters)


def mesh_group(ds: DeviceScene, translucent: bool) -> tuple[wp.array, wp.array, wp.array]:
    """(BVH ids, albedos, alphas) of the scene's opaque (alpha = 1) or translucent (alpha < 1) meshes."""
    meshes = [o for o in ds.scene.opaque if isinstance(o, TriangleMesh)]
    pick = [k for k, m in enumerate(meshes) if m.translucent == translucent]
    return (wp.array([ds.meshes[k].id for k in pick], dtype=wp.uint64, device=ds.device),
            wp.array([meshes[k].albedo for k in pick], dtype=wp.vec3, device=ds.device),
            wp.array([meshes[k].alpha for k in pick], dtype=float, device=ds.device))
