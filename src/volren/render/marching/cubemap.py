"""Cube-map addressing over a volume's box, the visible-face mask (paper 001 Eq. 1) and adaptive LOD (§3.3).

Faces are numbered 0..5 = +x, -x, +y, -y, +z, -z: face f lies on axis a = f / 2 at sign s = +1 for even f, -1 for
odd f. Its texels are indexed (i, j) along the tangent axes b = (a + 1) % 3 and c = (a + 2) % 3; texel (i, j) of an
S x S face is centred at local P[a] = s, P[b] = -1 + (i + 0.5) 2 / S, P[c] = -1 + (j + 0.5) 2 / S. Texel f holds
``f * S * S + j * S + i`` in a flat array. Sampling by direction uses the point where a ray leaves the box, which is
what a hardware cube map does with the direction from the box centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.kernels.common import INF, CameraGPU, ViewBuffers, VolumeGPU, box_hit, occluded_end, project_pixel
from volren.scene import Volume

FACE_COUNT = 6


@wp.func
def axis_unit(k: int) -> wp.vec3:
    if k == 0:
        return wp.vec3(1.0, 0.0, 0.0)
    if k == 1:
        return wp.vec3(0.0, 1.0, 0.0)
    return wp.vec3(0.0, 0.0, 1.0)


@wp.func
def face_point(f: int, u: float, v: float) -> wp.vec3:
    """Local point on face f at tangent coordinates (u, v) in [-1, 1]^2 (may overflow for seam handling)."""
    a = f / 2
    s = 1.0 - 2.0 * float(f % 2)
    return s * axis_unit(a) + u * axis_unit((a + 1) % 3) + v * axis_unit((a + 2) % 3)


@wp.func
def texel_point(q: wp.vec3i, size: int) -> wp.vec3:
    """Local centre of texel q = (face, i, j) of an S x S face."""
    h = 2.0 / float(size)
    return face_point(q[0], -1.0 + (float(q[1]) + 0.5) * h, -1.0 + (float(q[2]) + 0.5) * h)


@wp.func
def point_face(p: wp.vec3) -> int:
    """The face a point on (or near) the box surface belongs to: the axis of largest |component|, and its sign."""
    ax = wp.abs(p[0])
    ay = wp.abs(p[1])
    az = wp.abs(p[2])
    a = int(2)
    if ax >= ay and ax >= az:
        a = 0
    elif ay >= az:
        a = 1
    f = 2 * a
    if p[a] < 0.0:
        f = f + 1
    return f


@wp.func
def canonical_texel(f: int, i: int, j: int, size: int) -> wp.vec3i:
    """(face, i, j) of texel (i, j) of face f; indices one past a face edge wrap onto the adjacent face, so that
    bilinear filtering is seamless across edges (the texel half a texel beyond the edge is the neighbour face's
    first row: P[b] = +-1, P[a] = s (1 - h / 2))."""
    if i >= 0 and i < size and j >= 0 and j < size:
        return wp.vec3i(f, i, j)
    h = 2.0 / float(size)
    u = wp.clamp(-1.0 + (float(i) + 0.5) * h, -1.0, 1.0)
    v = wp.clamp(-1.0 + (float(j) + 0.5) * h, -1.0, 1.0)
    a = f / 2
    s = 1.0 - 2.0 * float(f % 2)
    p = s * (1.0 - 0.5 * h) * axis_unit(a) + u * axis_unit((a + 1) % 3) + v * axis_unit((a + 2) % 3)
    g = point_face(p)
    ga = g / 2
    gi = wp.clamp(int((p[(ga + 1) % 3] + 1.0) * 0.5 * float(size)), 0, size - 1)
    gj = wp.clamp(int((p[(ga + 2) % 3] + 1.0) * 0.5 * float(size)), 0, size - 1)
    return wp.vec3i(g, gi, gj)


@wp.func
def texel_index(f: int, i: int, j: int, size: int) -> int:
    """Flat index of texel (i, j) of face f, seamless past the edges (`canonical_texel`)."""
    if i >= 0 and i < size and j >= 0 and j < size:
        return (f * size + j) * size + i
    q = canonical_texel(f, i, j, size)
    return (q[0] * size + q[2]) * size + q[1]


@wp.func
def tile_texel(tiles: wp.array(dtype=wp.vec3i), rows: int, apron: int, size: int, row: int, col: int) -> wp.vec3i:
    """The texel (face, i, j) that launch cell (row, col) of a tile-row launch marches: tile k = row / rows has
    origin tiles[k]; a tile with an apron of 1 texel also marches its border ring (wrapped onto the adjacent face at
    an edge) so that bilinear filtering inside it needs no other tile. Face -1: past the face, nothing to do."""
    k = row / rows
    t = tiles[k]
    i = t[1] + col
    j = t[2] + row - k * rows
    if i < -apron or j < -apron or i >= size + apron or j >= size + apron:
        return wp.vec3i(-1, 0, 0)
    return canonical_texel(t[0], i, j, size)


@wp.struct
class CubeTarget:
    """One volume's cube map in a view's packed arrays: colour + transmittance, half-transmittance distance and end
    depth per texel, the volume's texels starting at ``offset``."""

    color: wp.array(dtype=wp.vec4)
    t_half: wp.array(dtype=float)
    z_end: wp.array(dtype=float)
    offset: int
    seg: wp.array(dtype=wp.vec4)
    """the cube k-buffer (paper 000 §3.3): per texel ``segments`` (premultiplied colour, transmittance) of the volume
    between the mesh layers of the pixel the texel projects to, texel i's at [i segments, (i + 1) segments)"""
    seg_z: wp.array(dtype=float)
    """linear depth where each segment ends (INF for a texel not marched, a culled empty tile: transparent)"""
    segments: int
    """K + 1 for a mesh k-buffer of K layers; 0: no cube k-buffer (no translucent mesh)"""


@wp.func
def store_texel(target: CubeTarget, texel: int, acc: wp.vec4, t_half: float, z_end: float):
    """Write a marched texel (index within the volume's faces)."""
    i = target.offset + texel
    target.color[i] = acc
    target.t_half[i] = t_half
    target.z_end[i] = z_end


@wp.func
def edge_stop(z_pixel: float, z_cube: float, k_z: float) -> float:
    """w_z = max(1 - k_z |z_buffer - z_cube|, 0) (paper 001 §3.2); 1 for a texel that was never marched (a culled,
    empty tile: transparent whatever its depth)."""
    if z_cube >= INF:
        return 1.0
    return wp.max(1.0 - k_z * wp.abs(z_pixel - z_cube), 0.0)


@wp.func
def cube_quad(offset: int, size: int, p: wp.vec3):
    """The 2x2 texels bilinear filtering uses at the box-surface point ``p`` (seamless across face edges): their
    indices (texels ``offset ...``), bilinear weights, and 1 where the quad straddles a face edge (p within half a
    texel of it: a rim lookup, `rim_needs_march`). One call gives a lookup all three: the resampling pass found the
    face and the texel twice per pixel before (rim test, then filter; 204 against 197 ms at 1080p stereo, smoke
    128^3, one thread)."""
    f = point_face(p)
    a = f / 2
    x = (p[(a + 1) % 3] + 1.0) * 0.5 * float(size) - 0.5
    y = (p[(a + 2) % 3] + 1.0) * 0.5 * float(size) - 0.5
    x0 = int(wp.floor(x))
    y0 = int(wp.floor(y))
    fx = x - float(x0)
    fy = y - float(y0)
    i00 = int(0)
    i10 = int(0)
    i01 = int(0)
    i11 = int(0)
    rim = int(x0 < 0 or y0 < 0 or x0 >= size - 1 or y0 >= size - 1)
    if x0 >= 0 and y0 >= 0 and x0 < size - 1 and y0 < size - 1:
        # Inside the face (all but a half-texel rim): plain 2x2 addressing.
        i00 = offset + (f * size + y0) * size + x0
        i10 = i00 + 1
        i01 = i00 + size
        i11 = i00 + size + 1
    else:
        i00 = offset + texel_index(f, x0, y0, size)
        i10 = offset + texel_index(f, x0 + 1, y0, size)
        i01 = offset + texel_index(f, x0, y0 + 1, size)
        i11 = offset + texel_index(f, x0 + 1, y0 + 1, size)
    return (wp.vec4i(i00, i10, i01, i11),
            wp.vec4((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy), rim)


@wp.func
def ray_face_point(o_l: wp.vec3, d_l: wp.vec3, h: wp.vec2, exterior: int) -> wp.vec3:
    """Where the cube map is read for the local ray o_l + t d_l with box hit h (`box_hit`): the point where it leaves
    the box (enters, for exterior faces)."""
    t_face = h[1]
    if exterior != 0:
        t_face = h[0]
    return o_l + t_face * d_l


@wp.func
def cube_face_point(vol: VolumeGPU, origin: wp.vec3, d: wp.vec3, exterior: int) -> wp.vec3:
    """`ray_face_point` of the world ray origin + t d."""
    o_l = wp.transform_point(vol.to_local, origin)
    d_l = wp.transform_vector(vol.to_local, d)
    return ray_face_point(o_l, d_l, box_hit(o_l, d_l), exterior)


RIM_CONTRAST = 0.01
"""the transmittance spread over a rim pixel's 2x2 texels above which it is marched directly (`rim_needs_march`)"""


@wp.func
def rim_needs_march(cube: wp.array(dtype=wp.vec4), idx: wp.vec4i, rim: int) -> int:
    """1 where a lookup's 2x2 texels (`cube_quad`: indices idx, ``rim`` 1 where they straddle a face edge) lie on a
    face rim and their transmittances spread by more than RIM_CONTRAST: a silhouette or a steep edge of the box,
    which is sharper than any texel (the quad blends across it), so the pixel is marched directly. A rim of
    transparent (or uniform) texels, the empty border of most data sets, keeps its cube lookup, which is exact
    there."""
    if rim == 0:
        return 0
    lo = wp.min(wp.min(cube[idx[0]][3], cube[idx[1]][3]), wp.min(cube[idx[2]][3], cube[idx[3]][3]))
    hi = wp.max(wp.max(cube[idx[0]][3], cube[idx[1]][3]), wp.max(cube[idx[2]][3], cube[idx[3]][3]))
    return int(hi - lo > RIM_CONTRAST)


@wp.func
def cube_sample(
    cube: wp.array(dtype=wp.vec4),
    cube_z: wp.array(dtype=float),
    idx: wp.vec4i,
    b: wp.vec4,
    z_pixel: float,
    k_z: float,
) -> wp.vec4:
    """Sample the cube map at a lookup's 2x2 texels (`cube_quad`: indices idx, bilinear weights b), each weighted by
    its bilinear weight times the edge-stopping w_z = max(1 - k_z |z_pixel - z_cube|, 0) of paper 001 §3.2 (z:
    linear depth where the texel's / pixel's ray ends). k_z = 0 is plain bilinear; where every w_z is 0 the plain
    bilinear weights are used (summed only then)."""
    out = wp.vec4(0.0)
    total = float(0.0)
    for k in range(4):
        w = b[k] * edge_stop(z_pixel, cube_z[idx[k]], k_z)
        out += cube[idx[k]] * w
        total += w
    if total < 1.0e-6:
        plain = wp.vec4(0.0)
        for k in range(4):
            plain += cube[idx[k]] * b[k]
        return plain
    return out / total


@wp.func
def cube_segment_weights(seg_z: wp.array(dtype=float), segments: int, offset: int, size: int, p: wp.vec3, j: int,
                         z_start: float, z_end: float, k_z: float) -> wp.vec4:
    """Eq. 13 across segment depths for segment j of the cube k-buffer (`CubeTarget.seg`): per texel of the 2x2
    quad at p its bilinear weight times w_z(z_cube, z_pixel) at both ends of the segment, z_cube the depths where the
    texel's segments j - 1 and j end (the mesh layers of the pixel the texel projects to, or its ray's end) and
    z_start, z_end the pixel's. The start is compared from j = 1 on (segment 0 starts at the box entry in both).
    Both ends, not the paper's one depth: a texel whose pixel has no layer where this pixel has one holds the whole
    ray in one segment and an empty one after it, each matching this pixel's at one end only."""
    idx, b, _rim = cube_quad(offset, size, p)
    w = wp.vec4(0.0)
    for k in range(4):
        base = idx[k] * segments
        w[k] = b[k] * edge_stop(z_end, seg_z[base + j], k_z)
        if j > 0:
            w[k] = w[k] * edge_stop(z_start, seg_z[base + j - 1], k_z)
    return w


@wp.func
def cube_segment(seg: wp.array(dtype=wp.vec4), segments: int, offset: int, size: int, p: wp.vec3, j: int,
                 w: wp.vec4) -> wp.vec4:
    """Segment j's (premultiplied colour, transmittance) filtered with the weights ``w`` (`cube_segment_weights`,
    summing to more than 0)."""
    idx, _b, _rim = cube_quad(offset, size, p)
    out = wp.vec4(0.0)
    for k in range(4):
        out += seg[idx[k] * segments + j] * w[k]
    return out / (w[0] + w[1] + w[2] + w[3])


@wp.func
def eye_segment(cam: CameraGPU, vol: VolumeGPU, x: wp.vec3, buffers: ViewBuffers) -> wp.vec4:
    """(t_min, t_max, facing, steps-valid flag) of the ray from this eye to the world texel point x: from the box
    entry or near plane to the texel, cut at the opaque surface of the z-buffer pixel x projects to."""
    dist = wp.length(x - cam.origin)
    d = (x - cam.origin) / dist
    facing = wp.dot(d, cam.forward)
    if facing <= 0.0:
        return wp.vec4(0.0, 0.0, facing, 0.0)
    hb = box_hit(wp.transform_point(vol.to_local, cam.origin), wp.transform_vector(vol.to_local, d))
    t0 = wp.max(hb[0], cam.near / facing)
    t1 = occluded_end(cam, buffers, x, dist, facing)
    valid = float(0.0)
    if t1 > t0 + 1.0e-6:
        valid = 1.0
    return wp.vec4(t0, t1, facing, valid)


def visible_faces(eye_local: np.ndarray, faces: str = "interior") -> list[int]:
    """Paper 001 Eq. 1: interior face i is visible when E[i / 2] < 1 for even i (the + face) and E[i / 2] > -1 for
    odd i (the - face); an eye inside the box sees all six. Exterior faces are visible from the other side:
    E[i / 2] > 1 for even i and E[i / 2] < -1 for odd i."""
    interior = faces == "interior"
    out = []
    for i in range(FACE_COUNT):
        # Signed distance of the eye beyond the face's plane along its outward normal.
        beyond = float(eye_local[i // 2]) * (1.0 if i % 2 == 0 else -1.0) - 1.0
        if (beyond < 0.0) == interior:
            out.append(i)
    return out


@dataclass(frozen=True)
class CubeLOD:
    """Adaptive LOD of one volume in one view (paper 001 §3.3)."""

    level: int
    """cube-map and density mip level: 0 is the finest"""
    size: int
    """face size S at that level [texels]"""
    samples: int
    """N: view samples across the box diagonal"""
    edge_pixels: float
    """longest projected box edge [pixels]"""


MAX_FACE_SIZE = 64
"""[texels] the largest face the screen sizing picks for a grid coarser than this (`face_size_cap`). A cap that
follows the screen would make every near box's faces hold more texels than its pixels, so the hybrid would march it
directly and CMSRM's viewport independence (bench resolution) would be lost; 64 lifts 16^3 grids 4x (6 x 64^2
texels, 0.6 MB a volume and view) and leaves grids of 64 and more at S0. The edges a capped face still blurs are
the face rims, marched directly (`rim_needs_march`)."""
FACE_SIZE_STEP = 4
"""screen-sized faces are rounded up to a multiple of this, so that tile levels up to 2 halve them exactly"""


def face_size_cap(base: int) -> int:
    """S_max of the screen sizing: max(S0, MAX_FACE_SIZE), whatever the viewport."""
    return max(base, MAX_FACE_SIZE)


EDGES = [(i, i ^ bit) for i in range(8) for bit in (1, 2, 4) if i < i ^ bit]
"""the 12 box edges as corner pairs (corners x fastest, `Volume.corners_world`)"""


def screen_texels(vol: Volume, cam: Camera) -> float:
    """S_screen: texels per face so that no texel the view reads covers more than a pixel along any face axis, where
    that is hardest: the box's silhouettes and the kinks of its faces' path lengths lie on its edges, sharper than
    any voxel, and the faces an eye inside or close to the box sees are magnified. The paper's S_ideal (§3.3 step 3,
    the longest projected edge) is taken where the view is densest, over candidate points of the interior faces in
    view: the nearest visible point of each edge clipped to the view frustum (near plane and the four side planes;
    corners may lie behind the eye), and where the view axis and the four frustum corner rays leave the box. At a
    point p (view coordinates, depth z) the pixel Jacobian J w = f / z (w_xy - p_xy w_z / z) of the box's full
    extent w_k along axis k gives the pixels per face width along k; the square face takes the largest (an
    elongated box needs its long axis' texels on every face). Along a line |dP/ds| = f |c| / z^2 with c constant,
    so an edge is densest at its nearest visible point; over a face the candidates are the vertices of its part in
    view, near enough its densest point for the 1 / z^2 that dominates. 0 when the box is not in view. Float64
    reference of `culling.screen_texels_gpu`."""
    right, up, forward = cam.basis()
    basis = np.stack([right, up, forward])
    origin = np.asarray(cam.position)
    view = (vol.corners_world - origin) @ basis.T
    extents = (2.0 * vol.to_world[:3, :3]).T @ basis.T
    focal = cam.height / (2 * cam.tan_half_fov)
    tx, ty = cam.tan_half_fov * cam.width / cam.height, cam.tan_half_fov
    points = []
    # Frustum half-spaces g . p + h >= 0 in view coordinates (right, up, depth).
    planes = [((0.0, 0.0, 1.0), -cam.near), ((-1.0, 0.0, tx), 0.0), ((1.0, 0.0, tx), 0.0), ((0.0, -1.0, ty), 0.0),
              ((0.0, 1.0, ty), 0.0)]
    for i, j in EDGES:
        a, d = view[i], view[j] - view[i]
        s0, s1 = 0.0, 1.0
        for g, h in planes:
            fa, fd = float(np.dot(g, a)) + h, float(np.dot(g, d))
            if fd == 0.0:
                s1 = s1 if fa >= 0.0 else -1.0
            elif fd > 0.0:
                s0 = max(s0, -fa / fd)
            else:
                s1 = min(s1, -fa / fd)
        if s0 <= s1:
            points.append(a + (s0 if d[2] >= 0.0 else s1) * d)
    eye = (vol.to_local @ np.r_[origin, 1.0])[:3]
    for sx, sy in ((0.0, 0.0), (-tx, -ty), (tx, -ty), (-tx, ty), (tx, ty)):
        ray = np.array([sx, sy, 1.0])
        t_exit = box_exit(eye, vol.to_local[:3, :3] @ (ray @ basis))
        if t_exit >= cam.near:
            points.append(t_exit * ray)
    best = 0.0
    for p in points:
        for w in extents:
            best = max(best, float(np.hypot(*(w[:2] - p[:2] * w[2] / p[2]))) * focal / p[2])
    return best


def box_exit(o: np.ndarray, d: np.ndarray) -> float:
    """Ray parameter where o + t d leaves [-1, 1]^3 (-inf when the line misses the box or leaves it behind o)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (-1.0 - o) / d, (1.0 - o) / d
    lo = np.where(d == 0.0, np.where(np.abs(o) <= 1.0, -np.inf, np.inf), np.minimum(ta, tb))
    hi = np.where(d == 0.0, np.where(np.abs(o) <= 1.0, np.inf, -np.inf), np.maximum(ta, tb))
    t0, t1 = float(lo.max()), float(hi.min())
    return t1 if t1 >= max(t0, 0.0) else -math.inf


def screen_face_size(s_screen: float, k_u: float, size: int, cap: int) -> int:
    """The face size with screen sizing: the LOD's size S raised to S_screen / k_u (rounded up to FACE_SIZE_STEP),
    at most ``cap`` (`face_size_cap`); never below the LOD's S, so a distant volume keeps the viewport-independent
    size of §3.3."""
    need = FACE_SIZE_STEP * math.ceil(s_screen / k_u / FACE_SIZE_STEP)
    return max(size, min(need, cap))


def cube_lod(vol: Volume, cam: Camera, base_size: int, max_samples: int, k_u: float, k_c: float,
             adaptive: bool, screen_sizing: bool = False) -> CubeLOD:
    """Steps 1-5 of paper 001 §3.3, with the face size optionally raised to what the screen needs.

    S_ideal = max projected edge / k_u, N_ideal = k_c S_ideal / sqrt 3, N = min(ceil(N_ideal), N_max),
    S = sqrt 3 min(N_ideal, N) / k_c, and the level l = max(floor(log2(S0 / S)), 0). The paper prints
    log2(S / S0), which would give a finer level for a smaller S; the reading used here makes a volume that shrinks
    on screen march a coarser cube map and density level. A corner behind the eye (the eye close to or inside the
    box) counts as an unbounded edge: level 0 and N_max. ``adaptive=False`` keeps level 0 and N = N_max.

    ``screen_sizing`` (adaptive only; the default when no S0 is given): the level and N stay the paper's (they
    follow the density's detail), but the face is at least `screen_texels` / k_u texels wide, up to
    `face_size_cap`: with S0 the grid's resolution, a near, elongated or coarse-grid box (or one around the eye)
    had texels of several pixels, and bilinear resampling blurred its silhouettes and face edges.
    """
    levels = len(vol.mip_pyramid)
    if not adaptive:
        return CubeLOD(0, base_size, max_samples, math.inf)
    view = cam.view_matrix()
    corners = np.c_[vol.corners_world, np.ones(8)] @ view.T
    depth = -corners[:, 2]
    level, n, edge = 0, max_samples, math.inf
    if not np.any(depth <= cam.near):
        focal = cam.height / (2 * cam.tan_half_fov)
        px = corners[:, :2] / depth[:, None] * focal
        edge = max(float(np.linalg.norm(px[i] - px[j])) for i, j in EDGES)
        s_ideal = edge / k_u
        n_ideal = k_c * s_ideal / math.sqrt(3)
        n = max(1, min(math.ceil(n_ideal), max_samples))
        s = math.sqrt(3) * min(n_ideal, n) / k_c
        level = 0 if s >= base_size else min(int(math.floor(math.log2(base_size / max(s, 1e-9)))), levels - 1)
    size = max(base_size >> level, 2)
    if screen_sizing:
        size = screen_face_size(screen_texels(vol, cam), k_u, size, face_size_cap(base_size))
    return CubeLOD(level, size, n, edge)


TILE = 32
"""Cube faces are marched in tiles of TILE x TILE texels (paper 000 §3.1.3); a smaller face is one tile."""
MAX_TILE_LEVEL = 2
"""Tile LOD l in {0, 1, 2}: 1x1, 2x2 or 4x4 fine texels per coarse texel (paper 000 §3.1.3)."""


def face_tiles(faces: list[int], size: int) -> np.ndarray:
    """(face, i0, j0) of every tile of the given faces, int32 (n, 3)."""
    t = min(TILE, size)
    per_axis = math.ceil(size / t)
    return np.array([(f, a * t, b * t) for f in faces for b in range(per_axis) for a in range(per_axis)],
                    dtype=np.int32).reshape(-1, 3)


@wp.func
def ray_box_point(eye: wp.vec3, q: wp.vec3, exterior: int) -> wp.vec3:
    """Where the line from the eye through the box-surface point q enters the box (the eye itself when inside), or,
    for ``exterior`` rays that start at q, where it leaves the box."""
    h = box_hit(eye, q - eye)
    if exterior != 0:
        return eye + h[1] * (q - eye)
    return eye + wp.max(h[0], 0.0) * (q - eye)


@wp.func
def pyramid_bounds(eye: wp.vec3, q00: wp.vec3, q10: wp.vec3, q01: wp.vec3, q11: wp.vec3, exterior: int) -> wp.mat33:
    """Rows 0 and 1: a box bounding, inside [-1, 1]^3, the far end of the rays' in-box segments that run between the
    quad q00..q11 and the box surface: interior rays run from their entry points to the quad, exterior rays from the
    quad to their exit points. When the four corner rays meet the box surface on one face (or an interior eye is
    inside) those points and the quad span the segments (the box is convex); otherwise the patch may bend over a box
    edge, and the bound falls back to the eye clamped into the box (interior: the rays converge there) or to the whole
    box (exterior: they diverge). Looser, still conservative."""
    a = ray_box_point(eye, q00, exterior)
    b = ray_box_point(eye, q10, exterior)
    c = ray_box_point(eye, q01, exterior)
    d = ray_box_point(eye, q11, exterior)
    one = wp.vec3(1.0)
    inside = wp.abs(eye[0]) <= 1.0 and wp.abs(eye[1]) <= 1.0 and wp.abs(eye[2]) <= 1.0
    fa = point_face(a)
    same = point_face(b) == fa and point_face(c) == fa and point_face(d) == fa
    lo = wp.min(wp.min(a, b), wp.min(c, d))
    hi = wp.max(wp.max(a, b), wp.max(c, d))
    if exterior != 0 and not same:
        lo = -one
        hi = one
    elif not (inside or same):
        e = wp.max(wp.min(eye, one), -one)
        lo = wp.min(lo, e)
        hi = wp.max(hi, e)
    return wp.mat33(lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], 0.0, 0.0, 0.0)


@wp.func
def box_peak(lo: wp.vec3, hi: wp.vec3, max_density: wp.array(dtype=float), offset: int, res: wp.vec3i) -> float:
    """The largest max-pyramid value over the cells that the local box [lo, hi] (clamped to [-1, 1]^3) touches."""
    a = wp.vec3i(0)
    b = wp.vec3i(0)
    for axis in range(3):
        n = float(res[axis])
        a[axis] = wp.clamp(int(wp.floor((wp.max(lo[axis], -1.0) + 1.0) * 0.5 * n)), 0, res[axis] - 1)
        b[axis] = wp.clamp(int(wp.floor((wp.min(hi[axis], 1.0) + 1.0) * 0.5 * n)), 0, res[axis] - 1)
    peak = float(0.0)
    for z in range(a[2], b[2] + 1):
        for y in range(a[1], b[1] + 1):
            for x in range(a[0], b[0] + 1):
                peak = wp.max(peak, max_density[offset + (z * res[1] + y) * res[0] + x])
    return peak


@wp.kernel
def tile_occupancy_kernel(
    tiles: wp.array(dtype=wp.vec3i),
    tile: int,
    size: int,
    eye0: wp.vec3,
    eye1: wp.vec3,
    exterior: int,
    margin: float,
    tile_level: wp.array(dtype=int),
    max_density: wp.array(dtype=float),
    offset: int,
    res: wp.vec3i,
    live: wp.array(dtype=int),
):
    """Coarse pass of empty-tile culling: every ray of a tile runs from an eye to the tile's quad (interior faces) or
    from the quad on to the box exit (``exterior`` faces), so inside the box it stays in the box-clamped bounding box
    of the quad and the rays' other ends (`pyramid_bounds`), widened for the trilinear support of a coarser
    density level (``margin`` at the volume's level, times 2^l at tile level l; the tile's apron ring adds a texel).
    Per eye, bit e of ``live`` is set when the conservative max-density pyramid is non-zero anywhere in that eye's
    box: a coupled pair marches the tile where either bit is set, each eye only where its own is (as CMSRM culls
    each eye alone)."""
    k = wp.tid()
    t = tiles[k]
    level = tile_level[k]
    f = t[0]
    h = 2.0 / float(size)
    scale = wp.pow(2.0, float(level))
    apron = float(0.0)
    if level > 0:
        apron = h * scale
    u0 = wp.max(-1.0 + float(t[1]) * h - apron, -1.0)
    u1 = wp.min(-1.0 + float(t[1] + tile) * h + apron, 1.0)
    v0 = wp.max(-1.0 + float(t[2]) * h - apron, -1.0)
    v1 = wp.min(-1.0 + float(t[2] + tile) * h + apron, 1.0)
    q00 = face_point(f, u0, v0)
    q10 = face_point(f, u1, v0)
    q01 = face_point(f, u0, v1)
    q11 = face_point(f, u1, v1)
    quad_lo = wp.min(wp.min(q00, q10), wp.min(q01, q11))
    quad_hi = wp.max(wp.max(q00, q10), wp.max(q01, q11))
    # An apron texel wrapped onto the adjacent face lies up to half a coarse texel off this face's plane.
    widen = wp.vec3(margin * scale + apron)
    bits = int(0)
    for e in range(2):
        eye = eye0
        if e == 1:
            eye = eye1
        b = pyramid_bounds(eye, q00, q10, q01, q11, exterior)
        lo = wp.min(quad_lo, wp.vec3(b[0, 0], b[0, 1], b[0, 2])) - widen
        hi = wp.max(quad_hi, wp.vec3(b[1, 0], b[1, 1], b[1, 2])) + widen
        if e == 1 and eye1 == eye0:
            bits = bits * 3
        elif box_peak(lo, hi, max_density, offset, res) > 0.0:
            bits = bits | (1 << e)
    live[k] = bits


def max_tile_level(tile: int) -> int:
    """The coarsest tile level that still leaves a tile 2 x 2 coarse texels."""
    return max(0, min(MAX_TILE_LEVEL, int(math.log2(tile)) - 1))


@wp.func
def projected_span(cam: CameraGPU, a: wp.vec3, b: wp.vec3) -> float:
    """Pixels the world segment a-b spans in the view; INF when an end is not in front of the near plane."""
    pa = project_pixel(cam, a)
    pb = project_pixel(cam, b)
    if pa[2] <= cam.near or pb[2] <= cam.near:
        return INF
    return wp.length(wp.vec2(pa[0] - pb[0], pa[1] - pb[1]))


@wp.func
def tile_pixels_per_texel(cam: CameraGPU, q00: wp.vec3, q10: wp.vec3, q01: wp.vec3, q11: wp.vec3, n_u: float,
                          n_v: float) -> float:
    """The largest screen footprint of one texel along the tile's edges: projected edge length / texels along it."""
    pu = wp.max(projected_span(cam, q00, q10), projected_span(cam, q01, q11)) / n_u
    pv = wp.max(projected_span(cam, q00, q01), projected_span(cam, q10, q11)) / n_v
    return wp.max(pu, pv)


@wp.kernel
def tile_lod_kernel(
    tiles: wp.array(dtype=wp.vec3i),
    tile: int,
    size: int,
    vol: VolumeGPU,
    cam0: CameraGPU,
    cam1: CameraGPU,
    k_u: float,
    max_level: int,
    levels: wp.array(dtype=int),
):
    """Coarse phase, LOD half (paper 000 §3.1.3, Fig. 4 (b)): the tile level l from the ratio of viewport pixels to
    tile texels. p = the largest screen footprint of a texel along the tile's edges in either eye; a level-l texel
    covers 2^l texels, so l = floor(log2(k_u / p)), clamped to [0, max_level]: coarse texels never exceed k_u
    pixels, the screen up-scaling bound of the per-volume LOD. The paper's l = ceil(log2 max d tiles / d pixels)
    rounds the other way, which lets a coarse texel cover up to 2 k_u pixels; floor keeps the anti-aliasing bound.
    A tile with a corner behind an eye's near plane stays at level 0."""
    k = wp.tid()
    t = tiles[k]
    f = t[0]
    h = 2.0 / float(size)
    n_u = wp.min(tile, size - t[1])
    n_v = wp.min(tile, size - t[2])
    u0 = -1.0 + float(t[1]) * h
    v0 = -1.0 + float(t[2]) * h
    u1 = u0 + float(n_u) * h
    v1 = v0 + float(n_v) * h
    q00 = wp.transform_point(vol.to_world, face_point(f, u0, v0))
    q10 = wp.transform_point(vol.to_world, face_point(f, u1, v0))
    q01 = wp.transform_point(vol.to_world, face_point(f, u0, v1))
    q11 = wp.transform_point(vol.to_world, face_point(f, u1, v1))
    p = wp.max(tile_pixels_per_texel(cam0, q00, q10, q01, q11, float(n_u), float(n_v)),
               tile_pixels_per_texel(cam1, q00, q10, q01, q11, float(n_u), float(n_v)))
    level = int(0)
    if p < INF:
        level = wp.clamp(int(wp.floor(wp.log2(k_u / wp.max(p, 1.0e-9)))), 0, max_level)
    levels[k] = level


def coarse_tiles(tiles: np.ndarray, tile: int, size: int, level: int) -> tuple[np.ndarray, int, int]:
    """Where level-l texels of the given fine tiles lie: (launch origins in level-l texels with a 1-texel apron,
    launch width, level-l face size). The apron holds every coarse texel that bilinear filtering at the tile's fine
    texel centres reads, so a coarse tile is self-contained whatever the levels of its neighbours."""
    coarse = size >> level
    scale = coarse / size
    out = tiles.copy()
    width = 0
    for axis in (1, 2):
        first = np.floor((tiles[:, axis] + 0.5) * scale - 0.5).astype(np.int32)
        last = np.floor((np.minimum(tiles[:, axis] + tile, size) - 0.5) * scale - 0.5).astype(np.int32) + 1
        out[:, axis] = first
        width = max(width, int((last - first).max()) + 1)
    return out, width, coarse
