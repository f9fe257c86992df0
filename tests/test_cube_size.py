"""Issue 19 item 4: cube faces sized for elongated, near and low-resolution boxes.

With S0 the grid's longest axis (the LOD only lowered it) a 16 x 2 x 1 m slab, an eye inside an 8 m box and a slab
close to the eye were read from texels of many pixels, and bilinear resampling blurred the boxes' silhouettes and
face edges. The faces are now raised to what the screen needs (`cubemap.screen_texels`, up to
`cubemap.face_size_cap`) and the pixels whose lookup straddles a face edge across differing texels are marched
directly (`cubemap.rim_needs_march`). Each scene is held to the reference at the default settings and with the
hybrid off (the cube maps themselves); the old sizing (S0 = the grid, no rim) is shown below the floors.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import DEVICE, scene_of
from volren.camera import Camera, make_views
from volren.metrics import psnr
from volren.render import CMSRM, CMSRMConfig, Reference, ReferenceConfig
from volren.render.marching.cacrm import CACRM, CACRMConfig
from volren.render.marching.cubemap import EDGES, screen_face_size, screen_texels
from volren.scene import Volume, scale_translate

METHODS = {"cmsrm": (CMSRM, CMSRMConfig), "cacrm": (CACRM, CACRMConfig)}
PSNR_FLOOR = 35.0
ALPHA_TOLERANCE = 0.01
WORST_ALPHA = 0.1
"""the largest alpha error of a pixel (the slab's was 0.24 in the issue)"""


def uniform_box(half, centre=(0.0, 0.0, 0.0), res=(16, 16, 16), emission=0.0) -> Volume:
    """A box of constant density (sigma_t 2 /m, albedo 0) with ``res`` voxels (x, y, z)."""
    return Volume(np.ones(res[::-1], np.float32), scale_translate(half, centre), density_scale=2.0, albedo=0.0,
                  emission=emission)


def slab_scene():
    """(a) the thin slab 16 x 2 x 1 m of 48x12x8 voxels (light grid 24x6x4), emitting, seen from above a corner."""
    scene = scene_of(uniform_box((8.0, 1.0, 0.5), res=(48, 12, 8), emission=1.0))
    return scene, [Camera(position=(3.0, 1.5, 4.0), look_at=(0.0, 0.0, 0.0), width=96, height=64, fov_y=60)]


def inside_scene():
    """(b) the eye inside an 8 m emitting box, 0.3 m from its wall, a 1 m emitting box just outside the wall."""
    scene = scene_of(uniform_box(4.0, emission=1.0), uniform_box(0.5, (0.2, 0.1, -4.55), emission=1.0))
    cam = Camera(position=(0.0, 0.0, -3.7), look_at=(0.2, 0.1, -4.5), width=48, height=48, fov_y=90)
    return scene, make_views(cam, "stereo")


def slab_cube_scene():
    """(c) an emitting 16 x 2 x 1 m slab of 16^3 voxels close in front of an emitting 1 m cube."""
    scene = scene_of(uniform_box((8.0, 1.0, 0.5), emission=1.0), uniform_box(0.5, (0.0, 0.0, -2.0), emission=1.0))
    cam = Camera(position=(-1.0, 1.2, 1.6), look_at=(0.0, 0.0, -2.0), width=48, height=48, fov_y=60)
    return scene, make_views(cam, "stereo")


SCENES = {"slab": slab_scene, "inside": inside_scene, "slab-cube": slab_cube_scene}
REFERENCES: dict[str, object] = {}


def against_reference(name: str, method: str, **config) -> tuple[list[float], list[float], float]:
    """(PSNR per view, alpha sum / the reference's per view, the largest alpha difference of a pixel)."""
    scene, views = SCENES[name]()
    if name not in REFERENCES:
        REFERENCES[name] = Reference(ReferenceConfig(samples=512, light_samples=64), device=DEVICE).render(scene,
                                                                                                         views)
    ref = REFERENCES[name]
    cls, cfg = METHODS[method]
    frame = cls(cfg(**config), device=DEVICE).render(scene, views)
    psnrs = [psnr(r, f) for r, f in zip(ref.images, frame.images, strict=True)]
    alphas = [float(f[..., 3].sum() / r[..., 3].sum()) for r, f in zip(ref.images, frame.images, strict=True)]
    worst = max(float(np.abs(f[..., 3] - r[..., 3]).max()) for r, f in zip(ref.images, frame.images, strict=True))
    return psnrs, alphas, worst


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", SCENES)
@pytest.mark.parametrize("hybrid", [True, False])
def test_cube_methods_meet_the_reference(name, method, hybrid):
    """Every view >= 35 dB, within 1% in alpha of the reference and no pixel 0.1 off in alpha. Measured (CMSRM,
    hybrid off; CACRM the same): slab 53.5 dB / alpha 0.9994 / worst pixel 0.062, inside 54.6 / 1.0017 / 0.005,
    slab-cube 51.9 / 0.9994 / 0.032 (default settings: the hybrid marches all three directly at these sizes,
    123-140 dB; before the fix it read the inside and slab-cube scenes from grid-sized faces, 30.3 and 33.2 dB)."""
    psnrs, alphas, worst = against_reference(name, method, hybrid=hybrid)
    assert min(psnrs) >= PSNR_FLOOR
    assert max(abs(a - 1.0) for a in alphas) <= ALPHA_TOLERANCE
    assert worst < WORST_ALPHA


@pytest.mark.parametrize("name", SCENES)
def test_the_grid_sized_faces_failed(name):
    """The floors are not met with the old sizing (S0 = the grid's axis, no rim marched directly), hybrid off.
    Measured: slab 43.3 dB but a pixel off by 0.27 in alpha, inside 30.3 dB / alpha 1.028, slab-cube 33.2 dB /
    a pixel off by 0.31."""
    scene, _ = SCENES[name]()
    grid = max(scene.volumes[0].resolution)
    psnrs, alphas, worst = against_reference(name, "cmsrm", hybrid=False, cube_size=grid, rim_direct=False)
    rim_psnrs, _, _ = against_reference(name, "cmsrm", hybrid=False, cube_size=grid)
    assert min(psnrs) < PSNR_FLOOR or max(abs(a - 1.0) for a in alphas) > ALPHA_TOLERANCE or worst >= WORST_ALPHA
    # The rim marched directly helps at any face size (slab 43.3 -> 51.3 dB, slab-cube 33.2 -> 41.5 dB; the inside
    # scene shows no box edge).
    if name != "inside":
        assert min(rim_psnrs) > min(psnrs) + 3.0


def test_faces_follow_the_screen_up_to_the_cap():
    """The slab 1 m away needs far more than 64 texels (its 16 m axis spans the view): capped at 64 (4x its 16
    voxels); the same slab 100 m away keeps the LOD's grid-sized faces (viewport-independent for far volumes)."""
    scene, views = slab_cube_scene()
    near = CMSRM(CMSRMConfig(hybrid=False), device=DEVICE).render(scene, views[:1]).stats.info["volumes"][0][0]
    assert screen_texels(scene.volumes[0], views[0]) > 64 and near["face_size"] == 64
    far_cam = Camera(position=(0.0, 0.0, 100.0), width=48, height=48)
    far = CMSRM(CMSRMConfig(hybrid=False), device=DEVICE).render(scene, [far_cam]).stats.info["volumes"][0][0]
    assert screen_texels(scene.volumes[0], far_cam) < far["face_size"] <= 16


def test_cacrm_pair_takes_the_larger_face():
    """A coupled pair shares one face size, the larger of its two eyes' (here a far and a near viewer of the slab:
    16 and 64 texels, both at level 0); the first eye's at the finer level would leave the near eye's faces
    grid-sized."""
    scene, views = slab_cube_scene()
    pair = [Camera(position=(0.0, 0.0, 100.0), width=48, height=48), views[0]]
    alone = CMSRM(CMSRMConfig(hybrid=False), device=DEVICE).render(scene, pair).stats.info["volumes"]
    coupled = CACRM(CACRMConfig(hybrid=False), device=DEVICE).render(scene, pair).stats.info["volumes"]
    sizes = [view[0]["face_size"] for view in alone]
    assert sizes[1] > sizes[0]
    assert [view[0]["face_size"] for view in coupled] == [max(sizes)] * 2


def brute_edge_density(vol: Volume, cam: Camera, n: int = 4001) -> float:
    """The largest pixels per box width along any axis over n points of each edge inside the view frustum."""
    right, up, forward = cam.basis()
    basis = np.stack([right, up, forward])
    view = (vol.corners_world - np.asarray(cam.position)) @ basis.T
    extents = (2.0 * vol.to_world[:3, :3]).T @ basis.T
    focal = cam.height / (2 * cam.tan_half_fov)
    tx, ty = cam.tan_half_fov * cam.width / cam.height, cam.tan_half_fov
    s = np.linspace(0.0, 1.0, n)[:, None]
    best = 0.0
    for i, j in EDGES:
        p = view[i] + s * (view[j] - view[i])
        p = p[(p[:, 2] >= cam.near) & (np.abs(p[:, 0]) <= tx * p[:, 2]) & (np.abs(p[:, 1]) <= ty * p[:, 2])]
        for w in extents:
            q = w[:2] - p[:, :2] * w[2] / p[:, 2:3]
            best = max(best, float((np.linalg.norm(q, axis=1) * focal / p[:, 2]).max(initial=0.0)))
    return best


@pytest.mark.parametrize("position", [(0.6, 0.5, 2.2), (3.0, -1.0, 1.5), (0.9, 0.7, 1.6)])
def test_screen_texels_is_the_densest_edge_point_and_the_kernel_agrees(position):
    """Along a line the screen density f |c| / z^2 peaks at the nearest visible point: `screen_texels` equals the
    brute-force maximum over 4001 points of each edge clipped to the frustum (from these eyes the view axis and the
    corner rays leave the box farther than its edges; from (0.3, 0.2, 0.9) their exit is denser, 56.4 against
    45.1), and the culling kernel (float32) picks the host's face size, here between the grid's 16 and the cap
    (24-52 texels)."""
    vol = uniform_box(0.5, res=(16, 16, 16))
    cam = Camera(position=position, look_at=(0.0, 0.0, 0.0), width=48, height=48)
    s_screen = screen_texels(vol, cam)
    assert s_screen == pytest.approx(brute_edge_density(vol, cam), rel=2e-3)
    size = screen_face_size(s_screen, 1.0, 16, 64)
    assert 16 < size < 64
    frame = CMSRM(CMSRMConfig(hybrid=False), device=DEVICE).render(scene_of(vol), [cam])
    assert frame.stats.info["volumes"][0][0]["face_size"] == size


def test_an_empty_rim_keeps_its_cube_lookup():
    """The cloud's box border is empty: its rim pixels read transparent texels, exact, and are not marched directly
    (at 192x128 measured 6 rays more than with the rim off, 624 more if every rim pixel were marched)."""
    from volren.data import builtin_scene

    scene = builtin_scene("cloud", 64)
    cam = Camera(position=(0.0, 0.4, 3.2), width=192, height=128)
    rays = [CMSRM(CMSRMConfig(hybrid=False, rim_direct=rim), device=DEVICE).render(scene, [cam]).stats.counters["rays"]
            for rim in (False, True)]
    assert rays[0] <= rays[1] < 1.01 * rays[0]
