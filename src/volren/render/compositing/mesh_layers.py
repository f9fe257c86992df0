"""Translucent meshes among the volumes: the mesh k-buffer of paper 000 §3.3.

A translucent mesh (`TriangleMesh.alpha` < 1) is a set of layers: each crossing of its surface along a view ray adds
alpha * c (c: the surface shaded like the opaque ones, `shade_lit_surface` with the renderer's `SurfaceLight`, so the
volumes shadow it the same way, either side facing the eye) and multiplies the transmittance behind it by 1 - alpha.
Translucent meshes cast no shadows. Volumes and layers are blended front to back in the order the ray meets
them; a layer inside a volume splits the march there (the paper's "insert the k-buffer depths of the mesh ... into
the ray marching").

The k-buffer holds, per pixel, the K nearest layers in front of the opaque surface (linear depth z, shaded colour and
alpha), near to far. It is built in one pass that visits the meshes one after another and inserts each of their hits
into the pixel's sorted list (the paper's k-buffer [37] fills it in rasterisation order, so the insertion sort is what
puts the layers in depth order). With more than K layers the farthest are dropped (a k-buffer keeps the K nearest):
those pixels miss the dropped layers' colour and attenuation, and ``dropped`` counts them per pixel so that a
renderer can report how many it lost. The paper requires closed meshes and reads the layers in pairs (entry, exit);
here every layer stands alone, so open sheets (a quad) and meshes that enclose a volume's samples work too.

DSSRM (paper 000 Fig. 9's ground truth) marches each run of boxes with `march_between_layers`: one box, or
overlapping boxes marched jointly (`volren.render.compositing.oit.march_joint`), in pieces between the layers inside
the run, each layer blended where it lies.

The cube methods write the paper's cube k-buffer: each texel ray is split at the layers of the pixel its texel
projects to (nearest, as the opaque cut) and stores K + 1 segments, the volume between that pixel's layers j - 1 and
j as (premultiplied colour, transmittance) from T = 1 with the depth where it ends (`march_texel_segments` for
CMSRM's texel march, exact splits; `segment_advance` / `segment_finish` for CACRM's coupled and quad kernels, per
eye, a sample belonging to the segment its step midpoint lies in). The resampling pass then blends, per pixel with
layers inside a cube-scheme box, segment j (2x2 texels, Eq. 13) and layer j in turn (`blend_cube_segments`), i.e.
c = c^V + c^M with each mesh colour behind the volume segments in front of it. Departures from the paper's
algorithms, and why: (1) a segment holds colour and transmittance, not only the transmittance, because layers stand
alone (no entry/exit pairs, the volume inside a closed mesh is not skipped), so the volume colour between two layers
must be attenuated by the layer in front of it and cannot be summed into c^V in cube-map space; (2) Eq. 13's
edge-stopping compares both ends of a segment (the texel's segments j - 1 and j end where that texel's pixel has
its layers), with its own k_z_layers = 2 /m (the opaque cut's 0.5 /m let texels without the layer bleed across a
sheet's silhouette: 42.1 against 49.5 dB, `CMSRMConfig.k_z_layers`). The fallback, a direct march of the box, is
left only where Eq. 13 has no weight for some segment (all four texels' segment depths more than 1/k_z from the
pixel's) and with tile LOD on (the composition of coarse tiles does not filter segments). On the Fig. 9 scene of
`volren bench binocular` (smoke 64^3, one sheet through the box, 240x135 stereo) the fallback took 4,418 of 64,800
pixels (6.8%) before and takes none now; PSNR against the reference at 160x90: CMSRM 55.65 -> 55.87 dB, CACRM
55.69 -> 55.83 dB; resampling pass 20.8 -> 12.8 ms (CMSRM) and 21.4 -> 12.7 ms (CACRM), texel march within noise
(CPU, 2 cores, shared). The cube k-buffer costs (K + 1) x 20 bytes per texel (5.2x the cube maps at K = 4) and is
allocated only in scenes with translucent meshes.

The reference renderer does not use the k-buffer: it walks the hits along each ray exactly (`next_layer`), any number
of them.
"""

from __future__ import annotations

import warp as wp

from volren.camera import Camera
from volren.device import launch_rows
from volren.kernels.common import (
    INF,
    CameraGPU,
    LightGPU,
    MarchState,
    Medium,
    OpaqueGPU,
    ViewBuffers,
    VolumeGPU,
    camera_ray,
    counter_row,
    half_depth,
    new_march_state,
    occluder_t,
    project_pixel,
    state_accumulator,
    with_accumulator,
)
from volren.render.compositing.oit import Layers, march_joint
from volren.render.compositing.surface_light import SurfaceLight, unlit
from volren.render.compositing.surfaces import MESH_RANGE, SURFACE_EPSILON, mesh_group, shade_lit_surface
from volren.render.frame import PassClock
from volren.render.marching.cubemap import CubeTarget, cube_segment, cube_segment_weights
from volren.render.marching.march import MarchParams, march_volume_light_map
from volren.scene import TriangleMesh
from volren.upload import DeviceScene, camera_struct

MAX_HITS = wp.constant(1024)
"""hits walked per ray and mesh at most (a guard against a ray that keeps re-hitting one edge)"""


@wp.struct
class LayerScene:
    """The translucent meshes and what shading their layers needs (the opaque objects cast the shadows)."""

    mesh_ids: wp.array(dtype=wp.uint64)
    albedo: wp.array(dtype=wp.vec3)
    alpha: wp.array(dtype=float)
    opaque: wp.array(dtype=OpaqueGPU)
    opaque_mesh_ids: wp.array(dtype=wp.uint64)
    lights: wp.array(dtype=LightGPU)
    ambient: wp.vec3
    light: SurfaceLight
    """how the volumes shade the layers: the renderer's, as for its opaque surfaces"""


@wp.struct
class MeshLayers:
    """One view's mesh k-buffer (paper 000 §3.3): per pixel ``count`` layers, near to far."""

    depth: wp.array3d(dtype=float)
    """(H, W, K) linear view depth [m]"""
    color: wp.array3d(dtype=wp.vec4)
    """(H, W, K) shaded colour (rgb, not premultiplied) and alpha"""
    count: wp.array2d(dtype=int)
    dropped: wp.array2d(dtype=int)
    """layers in front of the opaque surface beyond the K kept"""
    direct: wp.array2d(dtype=int)
    """set by the cube methods where a layer lies inside a cube-scheme box and the pixel was marched directly"""


@wp.struct
class LayerHit:
    t: float
    """ray distance, INF if none"""
    color: wp.vec4


@wp.func
def mesh_hit_after(mesh_id: wp.uint64, origin: wp.vec3, d: wp.vec3, t_after: float):
    """The first hit of mesh ``mesh_id`` along origin + t d with t > t_after + SURFACE_EPSILON: (t, normal), INF
    if none. The query starts past the previous hit, as a BVH ray query has no minimum distance."""
    start = wp.max(t_after, 0.0) + SURFACE_EPSILON
    q = wp.mesh_query_ray(mesh_id, origin + start * d, d, MESH_RANGE)
    if q.result:
        return start + q.t, q.normal
    return float(INF), wp.vec3(0.0)


@wp.func
def layer_color(sc: LayerScene, k: int, x: wp.vec3, normal: wp.vec3, d: wp.vec3,
                counters: wp.array(dtype=wp.int64)) -> wp.vec4:
    rgb = shade_lit_surface(x, normal, d, sc.albedo[k], sc.lights, sc.ambient, sc.opaque, sc.opaque_mesh_ids, sc.light,
                            counters)
    return wp.vec4(rgb[0], rgb[1], rgb[2], sc.alpha[k])


@wp.func
def next_layer(sc: LayerScene, origin: wp.vec3, d: wp.vec3, t_after: float,
               counters: wp.array(dtype=wp.int64)) -> LayerHit:
    """The nearest translucent layer past t_after over all meshes, shaded (the reference's exact walk)."""
    h = LayerHit()
    h.t = INF
    h.color = wp.vec4(0.0)
    best = int(-1)
    normal = wp.vec3(0.0)
    for k in range(sc.mesh_ids.shape[0]):
        t, n = mesh_hit_after(sc.mesh_ids[k], origin, d, t_after)
        if t < h.t:
            h.t = t
            normal = n
            best = k
    if best >= 0:
        h.color = layer_color(sc, best, origin + h.t * d, normal, d, counters)
    return h


@wp.func
def blend_layer(s: MarchState, c: wp.vec4, t: float) -> MarchState:
    """Composite the layer of colour c.rgb and alpha c.w at ray distance t front to back: colour += T alpha c,
    T *= 1 - alpha."""
    acc = state_accumulator(s)
    w = acc[3] * c[3]
    out = wp.vec4(acc[0] + w * c[0], acc[1] + w * c[1], acc[2] + w * c[2], acc[3] * (1.0 - c[3]))
    r = with_accumulator(s, out)
    r.depth_t = half_depth(s.depth_t, acc[3], out[3], t)
    return r


@wp.func
def insert_layer(layers: MeshLayers, row: int, col: int, z: float, c: wp.vec4):
    """Insert a layer at depth z into the pixel's sorted K-list; with the list full the farthest layer (the new one
    or the last kept) is dropped and counted."""
    k_max = layers.depth.shape[2]
    n = layers.count[row, col]
    if n == k_max:
        layers.dropped[row, col] = layers.dropped[row, col] + 1
        if z >= layers.depth[row, col, k_max - 1]:
            return
        n = k_max - 1
    i = n
    while i > 0 and layers.depth[row, col, i - 1] > z:
        layers.depth[row, col, i] = layers.depth[row, col, i - 1]
        layers.color[row, col, i] = layers.color[row, col, i - 1]
        i -= 1
    layers.depth[row, col, i] = z
    layers.color[row, col, i] = c
    layers.count[row, col] = n + 1


@wp.kernel
def mesh_layers_kernel(
    cam: CameraGPU,
    sc: LayerScene,
    buffers: ViewBuffers,
    layers: MeshLayers,
    counter_rows: wp.array2d(dtype=wp.int64),
    row0: int,
):
    """One pass per pixel: every translucent mesh's hits in front of the opaque surface into the k-buffer."""
    r, col = wp.tid()
    counters = counter_row(counter_rows, r, col)
    row = r + row0
    d = camera_ray(cam, row, col, 0.5, 0.5)
    t_end = occluder_t(buffers, cam, d, row, col)
    facing = wp.dot(d, cam.forward)
    for k in range(sc.mesh_ids.shape[0]):
        t = float(0.0)
        for _i in range(MAX_HITS):
            t, n = mesh_hit_after(sc.mesh_ids[k], cam.origin, d, t)
            if t >= t_end:
                break
            insert_layer(layers, row, col, t * facing, layer_color(sc, k, cam.origin + t * d, n, d, counters))


@wp.func
def blend_layers_before(
    s: MarchState, first: int, layers: MeshLayers, row: int, col: int, facing: float, t_limit: float
):
    """Blend the pixel's layers from index ``first`` on whose ray distance (depth / facing) is below t_limit;
    returns the state and the index of the first layer left."""
    out = s
    i = first
    n = layers.count[row, col]
    while i < n:
        t = layers.depth[row, col, i] / facing
        if t >= t_limit:
            break
        out = blend_layer(out, layers.color[row, col, i], t)
        i += 1
    return out, i


@wp.func
def layer_before(layers: MeshLayers, row: int, col: int, i: int, facing: float, t: float) -> bool:
    """Whether the pixel has a layer ``i`` and it lies before ray distance t."""
    if i < layers.count[row, col]:
        return layers.depth[row, col, i] / facing < t
    return False


@wp.func
def march_run_piece(
    s: MarchState,
    layers: Layers,
    i0: int,
    i1: int,
    volumes: wp.array(dtype=VolumeGPU),
    origin: wp.vec3,
    d: wp.vec3,
    offset: float,
    medium: Medium,
    params: MarchParams,
    span: wp.vec2,
) -> MarchState:
    """March ray distances ``span`` of the run of boxes [i0, i1) of the pixel's box k-buffer: one box alone with the
    light-map march, overlapping boxes jointly (`march_joint`)."""
    if i1 - i0 > 1:
        return march_joint(s, layers, i0, i1, volumes, origin, d, offset, medium, params, span)
    return march_volume_light_map(s, volumes[layers.volume[i0]], origin, d, span[0], span[1], offset, medium, params)


@wp.func
def march_between_layers(
    s: MarchState,
    first: int,
    mesh: MeshLayers,
    row: int,
    col: int,
    facing: float,
    layers: Layers,
    i0: int,
    i1: int,
    volumes: wp.array(dtype=VolumeGPU),
    origin: wp.vec3,
    d: wp.vec3,
    offset: float,
    medium: Medium,
    params: MarchParams,
):
    """DSSRM with the mesh k-buffer (paper 000 §3.3, Fig. 5 (b)): blend the mesh layers in front of the run of boxes
    [i0, i1) of the pixel's box k-buffer (one box, or overlapping boxes marched jointly), then march the run from its
    first entry to its last exit split at every mesh layer inside it, blending each layer where the march reaches it.
    Returns the state and the index of the first mesh layer not yet blended (those behind the run, for the next run
    or the end)."""
    t0 = layers.t_in[i0]
    t_stop = layers.t_out[i0]
    for j in range(i0 + 1, i1):
        t_stop = wp.max(t_stop, layers.t_out[j])
    out, i = blend_layers_before(s, first, mesh, row, col, facing, t0)
    t = t0
    n = mesh.count[row, col]
    while i < n and out.transmittance >= params.min_transmittance:
        tl = mesh.depth[row, col, i] / facing
        if tl >= t_stop:
            break
        if tl > t:
            out = march_run_piece(out, layers, i0, i1, volumes, origin, d, offset, medium, params, wp.vec2(t, tl))
            t = tl
        out = blend_layer(out, mesh.color[row, col, i], tl)
        i += 1
    if t < t_stop and out.transmittance >= params.min_transmittance:
        out = march_run_piece(out, layers, i0, i1, volumes, origin, d, offset, medium, params, wp.vec2(t, t_stop))
    return out, i


@wp.func
def append_segment(s: MarchState, g: MarchState, t_end: float) -> MarchState:
    """Composite the segment state g (marched from T = 1) behind s; the half-transmittance depth is g's own where
    the sum crosses 1/2 in g (its end t_end when g never reached 1/2 alone)."""
    out = s
    out.color = s.color + s.transmittance * g.color
    out.transmittance = s.transmittance * g.transmittance
    out.depth_t = half_depth(s.depth_t, s.transmittance, out.transmittance, wp.min(g.depth_t, t_end))
    out.samples = s.samples + g.samples
    out.shaded = s.shaded + g.shaded
    out.skipped = s.skipped + g.skipped
    return out


@wp.func
def march_texel_segments(
    mesh: MeshLayers,
    cam: CameraGPU,
    x: wp.vec3,
    seg: wp.array(dtype=wp.vec4),
    seg_z: wp.array(dtype=float),
    segments: int,
    texel: int,
    vol: VolumeGPU,
    d: wp.vec3,
    t0: float,
    t1: float,
    medium: Medium,
    params: MarchParams,
) -> MarchState:
    """A texel ray of the cube k-buffer (paper 000 §3.3, Fig. 5 (b)): the march over [t0, t1] towards the world
    texel point x is split at the mesh layers of the pixel x projects to (nearest, as the opaque cut), and segment
    j, the volume between that pixel's layers j - 1 and j, is stored as (premultiplied colour, transmittance) from
    T = 1 with the depth where it ends (``segments`` = K + 1 per texel; none stored when 0). Returns the whole ray
    (the segments composited, the volume alone) for the plain cube map."""
    out = new_march_state()
    facing = wp.dot(d, cam.forward)
    n = int(0)
    row = int(0)
    col = int(0)
    if segments > 0:
        pix = project_pixel(cam, x)
        col = int(wp.floor(pix[0]))
        row = int(wp.floor(pix[1]))
        if col >= 0 and col < cam.width and row >= 0 and row < cam.height:
            n = wp.min(mesh.count[row, col], segments - 1)
    t = t0
    base = texel * segments
    for j in range(n + 1):
        te = t1
        if j < n:
            te = wp.clamp(mesh.depth[row, col, j] / facing, t0, t1)
        g = new_march_state()
        if te > t and out.transmittance >= params.min_transmittance:
            g = march_volume_light_map(g, vol, cam.origin, d, t, te, 0.5, medium, params)
        t = wp.max(t, te)
        if segments > 0:
            seg[base + j] = wp.vec4(g.color[0], g.color[1], g.color[2], g.transmittance)
            seg_z[base + j] = te * facing
        out = append_segment(out, g, te)
    for j in range(n + 1, segments):
        seg[base + j] = wp.vec4(0.0, 0.0, 0.0, 1.0)
        seg_z[base + j] = t1 * facing
    return out


@wp.func
def texel_layers(mesh: MeshLayers, cam: CameraGPU, x: wp.vec3, segments: int) -> wp.vec3i:
    """(row, col, n) of the pixel the world texel point x projects to (nearest) and the n of its mesh layers the
    cube k-buffer splits at (at most K = segments - 1); n = 0 outside the viewport (one segment: the whole ray)."""
    pix = project_pixel(cam, x)
    col = int(wp.floor(pix[0]))
    row = int(wp.floor(pix[1]))
    if segments > 0 and col >= 0 and col < cam.width and row >= 0 and row < cam.height:
        return wp.vec3i(row, col, wp.min(mesh.count[row, col], segments - 1))
    return wp.vec3i(0, 0, 0)


@wp.func
def layer_ray_t(mesh: MeshLayers, pix: wp.vec3i, j: int, seg: wp.vec4) -> float:
    """Ray distance of the texel pixel's layer j (n: the ray's end), clamped to the eye segment
    seg = (t_min, t_max, facing, valid) of `cubemap.eye_segment`."""
    if j < pix[2]:
        return wp.clamp(mesh.depth[pix[0], pix[1], j] / seg[2], seg[0], seg[1])
    return seg[1]


@wp.func
def next_layer_t(mesh: MeshLayers, pix: wp.vec3i, j: int, seg: wp.vec4) -> float:
    """`layer_ray_t` of layer j, INF past the texel pixel's last layer: a march calls `segment_advance` only for a
    sample beyond it (one comparison per sample where no layer is near)."""
    if j < pix[2]:
        return layer_ray_t(mesh, pix, j, seg)
    return INF


@wp.func
def store_relative(target: CubeTarget, i: int, snap: wp.vec4, acc: wp.vec4, z: float):
    """Segment i of the cube k-buffer from two snapshots of a ray's accumulator (premultiplied rgb, T): what the ray
    gathered between them, relative to T = 1 at the first."""
    out = wp.vec4(0.0, 0.0, 0.0, 1.0)
    if snap[3] > 0.0:
        inv = 1.0 / snap[3]
        out = wp.vec4((acc[0] - snap[0]) * inv, (acc[1] - snap[1]) * inv, (acc[2] - snap[2]) * inv, acc[3] * inv)
    target.seg[i] = out
    target.seg_z[i] = z


@wp.func
def segment_advance(mesh: MeshLayers, pix: wp.vec3i, target: CubeTarget, base: int, seg: wp.vec4, j: int,
                    snap: wp.vec4, acc: wp.vec4, t: float):
    """The cube k-buffer of a march that composites sample by sample (CACRM's coupled and quad kernels): before the
    sample at ray distance t, close every segment whose layer lies before t (the sample belongs to the segment its
    midpoint lies in). Returns the current segment and the accumulator where it began."""
    jj = j
    sn = snap
    while target.segments > 0 and jj < pix[2]:
        tl = layer_ray_t(mesh, pix, jj, seg)
        if t <= tl:
            break
        store_relative(target, base + jj, sn, acc, tl * seg[2])
        sn = acc
        jj += 1
    return jj, sn


@wp.func
def segment_finish(mesh: MeshLayers, pix: wp.vec3i, target: CubeTarget, base: int, seg: wp.vec4, j: int,
                   snap: wp.vec4, acc: wp.vec4):
    """Close the current segment at the end of the march and write the empty ones after it."""
    if target.segments > 0:
        store_relative(target, base + j, snap, acc, layer_ray_t(mesh, pix, j, seg) * seg[2])
        for jj in range(j + 1, target.segments):
            target.seg[base + jj] = wp.vec4(0.0, 0.0, 0.0, 1.0)
            target.seg_z[base + jj] = layer_ray_t(mesh, pix, jj, seg) * seg[2]


@wp.func
def layers_inside(mesh: MeshLayers, row: int, col: int, first: int, facing: float, t_out: float) -> int:
    """One past the last layer from ``first`` on that lies before ray distance t_out."""
    m = first
    while layer_before(mesh, row, col, m, facing, t_out):
        m += 1
    return m


@wp.func
def segment_end(mesh: MeshLayers, row: int, col: int, j: int, first: int, m: int, z_in: float, z_out: float) -> float:
    """Linear depth where the pixel's segment j of a box (layers [first, m) inside it) ends: the box entry z_in
    for j < first, its layer j inside the box, else the box exit z_out."""
    if j < first:
        return z_in
    if j < m:
        return mesh.depth[row, col, j]
    return z_out


@wp.func
def blend_cube_segments(
    s: MarchState,
    first: int,
    mesh: MeshLayers,
    row: int,
    col: int,
    facing: float,
    seg: wp.array(dtype=wp.vec4),
    seg_z: wp.array(dtype=float),
    segments: int,
    offset: int,
    size: int,
    p: wp.vec3,
    t_in: float,
    t_out: float,
    k_z: float,
):
    """The integration pass with the cube k-buffer (paper 000 §3.3): the pixel's layers [first, m) inside a
    cube-scheme box and the volume segments between them, front to back: segment j (the 2x2 texels at the box-surface
    point p, weighted by Eq. 13 with z_cube the depth where each texel's segment j ends and z_buffer where the
    pixel's does), then layer j. Returns (state, m, 1), or (s, first, 0) where the scheme cannot apply: no cube
    k-buffer (``segments`` 0) or a segment whose four Eq. 13 weights all vanish (the texels' pixels have no layer
    near this pixel's, at a sheet's silhouette); the caller then marches the box directly."""
    m = layers_inside(mesh, row, col, first, facing, t_out)
    z_in = t_in * facing
    z_out = t_out * facing
    if segments == 0 or m >= segments:
        return s, first, 0
    for j in range(first, m + 1):
        w = cube_segment_weights(seg_z, segments, offset, size, p, j,
                                 segment_end(mesh, row, col, j - 1, first, m, z_in, z_out),
                                 segment_end(mesh, row, col, j, first, m, z_in, z_out), k_z)
        if w[0] + w[1] + w[2] + w[3] < 1.0e-6:
            return s, first, 0
    out = s
    for j in range(first, m + 1):
        w = cube_segment_weights(seg_z, segments, offset, size, p, j,
                                 segment_end(mesh, row, col, j - 1, first, m, z_in, z_out),
                                 segment_end(mesh, row, col, j, first, m, z_in, z_out), k_z)
        c = cube_segment(seg, segments, offset, size, p, j, w)
        after = out.transmittance * c[3]
        t_end = segment_end(mesh, row, col, j, first, m, z_in, z_out) / facing
        out.depth_t = half_depth(out.depth_t, out.transmittance, after, t_end)
        out.color = out.color + out.transmittance * wp.vec3(c[0], c[1], c[2])
        out.transmittance = after
        if j < m:
            out = blend_layer(out, mesh.color[row, col, j], t_end)
    return out, m, 1


def layer_scene(ds: DeviceScene, light: SurfaceLight | None = None) -> LayerScene:
    """The translucent meshes of ``ds``, shaded with ``light`` (None: the volumes do not shade them)."""
    sc = LayerScene()
    sc.light = light if light is not None else unlit(ds)
    sc.mesh_ids, sc.albedo, sc.alpha = mesh_group(ds, translucent=True)
    sc.opaque_mesh_ids = mesh_group(ds, translucent=False)[0]
    sc.opaque = ds.opaque
    sc.lights = ds.lights
    sc.ambient = ds.ambient
    return sc


def build_mesh_layers(
    ds: DeviceScene,
    cam_gpu: CameraGPU,
    cam: Camera,
    buffers: ViewBuffers,
    k: int,
    counters: wp.array,
    light: SurfaceLight | None = None,
) -> MeshLayers:
    """The view's mesh k-buffer with ``k`` layers per pixel (after the opaque pass filled ``buffers``), shaded with
    ``light`` (the renderer's `_surface_light`); an empty one (no layer anywhere, no pass run) when the scene has no
    translucent mesh."""
    sc = layer_scene(ds, light)
    shape = (cam.height, cam.width)
    layers = MeshLayers()
    layers.count = wp.zeros(shape, dtype=int, device=ds.device)
    layers.dropped = wp.zeros(shape, dtype=int, device=ds.device)
    layers.direct = wp.zeros(shape, dtype=int, device=ds.device)
    if sc.mesh_ids.shape[0] == 0:
        layers.depth = wp.zeros((1, 1, 1), dtype=float, device=ds.device)
        layers.color = wp.zeros((1, 1, 1), dtype=wp.vec4, device=ds.device)
        return layers
    layers.depth = wp.zeros((*shape, k), dtype=float, device=ds.device)
    layers.color = wp.zeros((*shape, k), dtype=wp.vec4, device=ds.device)
    launch_rows(mesh_layers_kernel, cam.height, cam.width, [cam_gpu, sc, buffers, layers], ds.device, counters)
    return layers


def has_translucent(ds: DeviceScene) -> bool:
    """Whether the scene has a translucent mesh (otherwise the mesh-layers pass is skipped: no launch, no time)."""
    return any(isinstance(o, TriangleMesh) and o.translucent for o in ds.scene.opaque)


def mesh_layers_pass(
    ds: DeviceScene,
    cam: Camera,
    buffers: ViewBuffers,
    k: int,
    clock: PassClock,
    light: SurfaceLight | None = None,
) -> MeshLayers:
    """The view's k-buffer (`build_mesh_layers`), timed as the "mesh layers" pass only when the scene has a
    translucent mesh: without one the empty k-buffer is made outside the clock, so no pass time is recorded."""
    if not has_translucent(ds):
        return build_mesh_layers(ds, camera_struct(cam), cam, buffers, k, clock.counters, light)
    with clock.measure("mesh layers"):
        return build_mesh_layers(ds, camera_struct(cam), cam, buffers, k, clock.counters, light)


def layer_stats(layers: MeshLayers, k: int, total: dict[str, int] | None = None) -> dict[str, int]:
    """For the frame info, summed over views into ``total``: pixels with at least one layer, layers kept, layers
    dropped beyond K, and pixels marched directly by the cube methods because of a layer inside a cube-scheme box."""
    n = layers.count.numpy()
    out = dict(total or {"k": k, "pixels": 0, "layers": 0, "dropped": 0, "direct_pixels": 0})
    out["pixels"] += int((n > 0).sum())
    out["layers"] += int(n.sum())
    out["dropped"] += int(layers.dropped.numpy().sum())
    out["direct_pixels"] += int(layers.direct.numpy().sum())
    return out
