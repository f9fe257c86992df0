"""Surfaces shaded by the volumes (issue 14 item 5, `volren.render.compositing.surface_light`): light-map shadows
against closed forms and brute-force shadow rays, stacked volumes, ambient occlusion under a smoke plume."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import DEVICE, homogeneous_volume, scene_of
from volren.camera import Camera
from volren.data import builtin_scene, classic_look
from volren.metrics import psnr
from volren.render import CACRM, CMSRM, DSSRM, CACRMConfig, CMSRMConfig, DSSRMConfig, Reference, ReferenceConfig
from volren.render.compositing.surface_light import AO_CONE_RAYS, SURFACE_BRUTE_FORCE, SURFACE_LIGHT_MAP, surface_light
from volren.render.compositing.surfaces import trace_surfaces, view_buffers
from volren.render.frame import PassClock
from volren.render.gi.ambient import GIConfig
from volren.scene import DirectionalLight, Environment, Plane
from volren.upload import camera_struct

SIGMA, E, ALBEDO = 1.5, 2.0, 0.5
LIGHT = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
COS = -LIGHT[1]
UNDER = Camera(position=(0.0, 0.3, 2.5), look_at=(0.0, 0.0, 0.0), width=48, height=32)
"""looks at the floor y = 0 from below the slabs (its rays never cross them)"""
TOP_DOWN = Camera(position=(0.0, 5.0, 0.01), look_at=(0.0, -1.0, 0.0), width=48, height=48, fov_y=40)


def slab(y0: float, y1: float):
    """A homogeneous slab 4 m wide between heights y0 and y1."""
    return homogeneous_volume(SIGMA, scale=(2.0, 0.5 * (y1 - y0), 2.0), translate=(0.0, 0.5 * (y0 + y1), 0.0))


def floor_scene(*volumes, ambient: float = 0.0):
    scene = scene_of(*volumes, lights=[DirectionalLight(tuple(LIGHT), E)], ambient=ambient)
    return dataclasses.replace(scene, opaque=(Plane((0, 0, 0), (0, 1, 0), ALBEDO),))


def shadowed_floor(cam: Camera, top: float) -> np.ndarray:
    """Pixels seeing floor points whose shadow ray leaves every slab (up to height ``top``) through its top face,
    at least 0.5 m from the slabs' sides (the light-map nodes around the shadow ray's box entry, 4/7 m apart, see only
    the top face too)."""
    d = cam.ray_directions()
    o = np.asarray(cam.position)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[1] / d[..., 1]
    x = o + t[..., None] * d
    exit_point = x + (top / LIGHT[1]) * LIGHT
    return (t > 0) & (np.abs(x[..., [0, 2]]).max(-1) < 1.5) & (np.abs(exit_point[..., [0, 2]]).max(-1) < 1.5)


def dssrm(**kw) -> DSSRM:
    return DSSRM(DSSRMConfig(samples=64, light_samples=32, light_grid=8, **kw), device=DEVICE)


MARCHERS = {
    "dssrm": dssrm,
    "cmsrm": lambda: CMSRM(CMSRMConfig(samples=64, light_samples=32, light_grid=8, hybrid=False), device=DEVICE),
    "cacrm": lambda: CACRM(CACRMConfig(samples=64, light_samples=32, light_grid=8, hybrid=False, vsa=False),
                           device=DEVICE),
}


def reference(light_samples: int = 32) -> Reference:
    return Reference(ReferenceConfig(samples=64, light_samples=light_samples), device=DEVICE)


def test_light_map_holds_the_mean_extinction_through_the_whole_box():
    """What the shadow lookup relies on: each light-map node holds the mean extinction along its path to the light
    through the rest of the box (`volren.render.lightmap`), for a homogeneous slab SIGMA at every node, whichever
    face the path leaves by (the top or a side) and on the faces too; no other volume: no optical depth entering."""
    r = dssrm()
    scene = floor_scene(slab(0.5, 1.0))
    ds = r._prepare(scene, PassClock(r.device), 0)
    nx, ny, nz = ds.light_res[0]
    planes = ds.lightmap.numpy()[: 2 * nx * ny * nz].reshape(2, nz, ny, nx)
    np.testing.assert_allclose(planes[0], SIGMA, rtol=1e-5)
    assert np.all(planes[1] == 0.0)


@pytest.mark.parametrize("name", [*MARCHERS, "reference"])
def test_floor_under_a_slab_matches_the_closed_form(name):
    """Floor under a homogeneous slab (thickness 0.5 m) lit obliquely: L = albedo / pi * E * cos * exp(-sigma 0.5 /
    cos) wherever the shadow ray crosses bottom and top face. The light-map lookup at the box entry reads the nodes on
    the bottom face (with the old voxel-centre layout, clamped half a voxel inside: 3% too bright on this 8^3 grid)."""
    r = MARCHERS[name]() if name in MARCHERS else reference()
    img = r.render(floor_scene(slab(0.5, 1.0)), [UNDER]).images[0]
    mask = shadowed_floor(UNDER, 1.0)
    assert mask.sum() >= 300
    expected = ALBEDO / np.pi * E * COS * np.exp(-SIGMA * 0.5 / COS)
    np.testing.assert_allclose(img[mask][:, :3], expected, rtol=2e-5)


@pytest.mark.parametrize(("name", "gi"), [("dssrm", "none"), ("dssrm", "major"), ("reference", "none")])
def test_stacked_volumes_multiply(name, gi):
    """Two slabs above the floor: exp(-sigma (0.5 + 0.5) / cos). Without GI each light map holds its own slab and
    the two lookups multiply; with GI the lower slab's map already holds the upper one, so it is read alone."""
    r = dssrm(gi=GIConfig(method=gi)) if name == "dssrm" else reference()
    img = r.render(floor_scene(slab(0.5, 1.0), slab(1.5, 2.0)), [UNDER]).images[0]
    mask = shadowed_floor(UNDER, 2.0)
    assert mask.sum() >= 150
    expected = ALBEDO / np.pi * E * COS * np.exp(-SIGMA * 1.0 / COS)
    np.testing.assert_allclose(img[mask][:, :3], expected, rtol=1e-4)


@pytest.mark.parametrize("up", [1.0, -1.0])
def test_gi_shadow_reads_the_first_box_along_the_ray(up):
    """With GI on, the near box's map holds both boxes, so the shadow is read from the box the shadow ray enters
    first, whatever order the BVH reports them in: a floor under two boxes 2 m apart lit from straight above, and
    the same mirrored (a ceiling over them lit from below; the BVH reports the boxes in the same spatial order
    both times), gets exp(-sigma (0.5 + 0.5)). The far box's map alone gives exp(-sigma 0.5), 2.1 times too
    bright."""
    boxes = [homogeneous_volume(SIGMA, scale=(0.5, 0.25, 0.5), translate=(0.0, up * y, 0.0)) for y in (0.75, 2.75)]
    scene = scene_of(*boxes, lights=[DirectionalLight((0.0, -up, 0.0), E)])
    scene = dataclasses.replace(scene, opaque=(Plane((0, 0, 0), (0, up, 0), ALBEDO),))
    cam = Camera(position=(0.0, 0.3 * up, 2.5), look_at=(0.0, 0.0, 0.0), width=48, height=32)
    img = dssrm(gi=GIConfig(method="major")).render(scene, [cam]).images[0]
    d = cam.ray_directions()
    o = np.asarray(cam.position)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[1] / d[..., 1]
    x = o + t[..., None] * d
    under = (t > 0) & (np.abs(x[..., [0, 2]]).max(-1) < 0.4)
    assert under.sum() >= 20
    np.testing.assert_allclose(img[under][:, :3], ALBEDO / np.pi * E * np.exp(-SIGMA), rtol=1e-4)


def surface_radiance(renderer, scene, cam: Camera) -> np.ndarray:
    """The surface pass's radiance alone (no volume composited over it), after the renderer's lighting passes."""
    clock = PassClock(renderer.device)
    renderer._frame_info = {}
    ds = renderer._prepare(scene, clock, 0)
    buffers = view_buffers(cam, renderer.device)
    trace_surfaces(ds, camera_struct(cam), cam, None, buffers, clock.counters, renderer._surface_light(ds))
    return buffers.occluder_color.numpy()[..., :3]


def smoke_over_floor(floor_y: float, lights: bool, ambient: float):
    scene = classic_look(builtin_scene("smoke", 64))  # the light the floors were measured under, its shadow in view
    return dataclasses.replace(scene, opaque=(Plane((0, floor_y, 0), (0, 1, 0), 1.0),),
                               lights=scene.lights if lights else (), environment=Environment(ambient))


def test_light_map_shadows_match_shadow_rays_on_smoke():
    """Smoke plume over a floor 0.25 m below its box, lit obliquely, seen from above: the light-map lookup (32^3 light
    grid, L = 128) against brute-force shadow rays (L = 128). Measured: 45.8 dB, max error 0.074 of a 0.815 peak
    (46.9 dB, 0.058 with voxel-centre light maps and the shell marched: `volren.render.lightmap`)."""
    scene = smoke_over_floor(-1.25, lights=True, ambient=0.0)
    cam = dataclasses.replace(TOP_DOWN, look_at=(-0.6, -1.25, -0.4))
    ref = surface_radiance(reference(128), scene, cam)
    got = surface_radiance(DSSRM(DSSRMConfig(samples=64, light_samples=128), device=DEVICE), scene, cam)
    assert ref.min() < 0.1 * ref.max()  # the shadow is in the picture
    assert psnr(ref, got) > 45.0
    assert np.abs(ref - got).max() < 0.08


def ambient_occlusion(renderer) -> np.ndarray:
    return surface_radiance(renderer, smoke_over_floor(-1.0, lights=False, ambient=1.0), TOP_DOWN)[..., 0]


@pytest.fixture(scope="module")
def reference_ao() -> np.ndarray:
    return ambient_occlusion(reference(128))


def test_ao_darkens_the_floor_under_the_plume(reference_ao):
    """No light, ambient 1, albedo 1: the floor's radiance is AO. Brute force (256 rays, L = 128) darkens the floor
    under the plume to 0.904; the light-map methods' coarse AO rays (L / 8; 8 in the cone toward the plume's
    occupied box, 32 near it) darken it as much (measured ratio of the darkening 0.996) and are within 0.038
    everywhere (fixed directions; the 32 hemisphere rays everywhere they replaced: 0.998 and 0.036)."""
    assert reference_ao.min() == pytest.approx(0.904, abs=0.01)
    got = ambient_occlusion(DSSRM(DSSRMConfig(samples=64, light_samples=128), device=DEVICE))
    under = reference_ao < 0.95
    ratio = (1.0 - got[under]).mean() / (1.0 - reference_ao[under]).mean()
    assert ratio == pytest.approx(1.0, abs=0.02)
    assert np.abs(got - reference_ao).max() < 0.042


def test_ao_from_the_gi_grid(reference_ao):
    """With GI on (PRT, 256 rays per voxel, 16^3 grid) the floor next to the box reads AO from the SH coefficients
    of T, cosine-convolved at the normal. Measured: 12% more darkening under the plume than brute force (order-3
    SH, and the floor reads the grid's bottom voxel centres, 1/16 of the box higher), within 0.036 everywhere."""
    r = DSSRM(DSSRMConfig(samples=64, light_samples=128, light_grid=16, gi=GIConfig(method="prt", rays=256)),
              device=DEVICE)
    got = ambient_occlusion(r)
    under = reference_ao < 0.95
    ratio = (1.0 - got[under]).mean() / (1.0 - reference_ao[under]).mean()
    assert ratio == pytest.approx(1.12, abs=0.05)
    assert np.abs(got - reference_ao).max() < 0.045


def test_per_frame_gi_keeps_the_ao_rays(reference_ao):
    """With a per-frame GI method (sresir, one frame) the surfaces keep the AO rays: its SH grid's bands 1-2 are
    still noise (read through the cosine lobe: max error 0.98, darkening 6.3 times brute force after one frame)."""
    r = DSSRM(DSSRMConfig(samples=64, light_samples=128, light_grid=16, gi=GIConfig(method="sresir")), device=DEVICE)
    got = ambient_occlusion(r)
    assert np.abs(got - reference_ao).max() < 0.045


def smoke_over_plane(height: float) -> object:
    """The smoke plume with a white plane at ``height`` (normal +y), ambient 1, no light: the plane's radiance is AO."""
    return smoke_over_floor(height, lights=False, ambient=1.0)


def ao_pass(scene, cam: Camera, light=None, cone_rays: int = AO_CONE_RAYS) -> tuple[np.ndarray, dict[str, int]]:
    """AO of the plane seen by ``cam`` (DSSRM, L = 96) or with ``light(ds)``, and the surface pass's counters alone."""
    r = DSSRM(DSSRMConfig(samples=64, light_samples=96, ao_cone_rays=cone_rays), device=DEVICE)
    clock = PassClock(r.device)
    r._frame_info = {}
    ds = r._prepare(scene, clock, 0)
    clock.counters.zero_()
    buffers = view_buffers(cam, r.device)
    sl = r._surface_light(ds) if light is None else light(ds)
    trace_surfaces(ds, camera_struct(cam), cam, None, buffers, clock.counters, sl)
    return buffers.occluder_color.numpy()[..., 0], clock.counter_values()


BESIDE = Camera(position=(-2.0, 1.5, 0.01), look_at=(-2.0, -0.2, 0.0), width=12, height=12, fov_y=30)
"""looks down at a plane at mid-plume height, 1.6-2.4 m beside the plume: it is seen in a cone, part of it below the
horizon"""


def test_ao_cone_beside_the_plume_matches_brute_force():
    """Points beside the plume at its mid height: 32 uniform rays in the cone about the occupied box (those below the
    horizon not marched) against 4096 cosine-distributed hemisphere rays at full L. Measured: occlusion 0.0023-0.0087,
    max error 0.0028, mean occlusion 1.003 times brute force's (8 cone rays: max error 0.0067; 32 hemisphere rays:
    0.0087, a pixel none of them saw occluded)."""
    scene = smoke_over_plane(-0.2)
    brute, _ = ao_pass(scene, BESIDE, lambda ds: surface_light(ds, SURFACE_BRUTE_FORCE, 96, 4096, 96))
    got, counters = ao_pass(scene, BESIDE, cone_rays=32)
    assert (1.0 - brute).min() > 0.002
    assert counters["ao_bvh_queries"] == 32 * got.size  # one BVH query per AO ray, every pixel casting them
    assert counters["bvh_queries"] == 0  # the OIT's queries are counted apart
    assert np.abs(got - brute).max() < 0.0035
    assert (1.0 - got).mean() / (1.0 - brute).mean() == pytest.approx(1.0, abs=0.03)  # no bias


def test_ao_without_a_box_above_the_horizon_is_one_and_free():
    """A plane above the smoke's box: no box above any point's horizon, so AO is exactly 1 and no AO ray is cast."""
    cam = dataclasses.replace(BESIDE, position=(0.5, 3.0, 0.01), look_at=(0.5, 1.2, 0.0))
    got, counters = ao_pass(smoke_over_plane(1.2), cam)
    assert np.all(got == 1.0)
    assert counters["ao_bvh_queries"] == 0 and counters["light_samples"] == 0


def test_ao_cones_of_several_volumes_merge():
    """Four boxes over a floor: their cones merge into one (`cone_union`), sampled with 128 rays per point, against
    2048 hemisphere rays. Measured: darkening 1.015 times brute force's, mean error 0.0008 (max 0.017: brute force's
    own noise, its fixed directions hit or miss a box). 48x32, default 8/32 rays: mean error 0.0049, 32 hemisphere
    rays everywhere 0.0077."""
    scene = builtin_scene("multi", 64, count=4)
    floor_y = min(np.asarray(v.to_world)[1, 3] - np.abs(np.asarray(v.to_world)[1, :3]).sum() for v in scene.volumes)
    scene = dataclasses.replace(scene, opaque=(Plane((0, floor_y - 0.1, 0), (0, 1, 0), 1.0),), lights=(),
                                environment=Environment(1.0))
    cam = Camera(position=(0.0, floor_y + 3.9, 4.0), look_at=(0.0, floor_y - 0.1, 0.0), width=32, height=24)
    brute, _ = ao_pass(scene, cam, lambda ds: surface_light(ds, SURFACE_BRUTE_FORCE, 64, 2048, 64))
    got, _ = ao_pass(scene, cam, lambda ds: surface_light(ds, SURFACE_LIGHT_MAP, 64, 128, 64, cone_rays=128))
    floor = brute > 0
    assert (1.0 - brute[floor]).max() > 0.05
    assert (1.0 - got[floor]).mean() / (1.0 - brute[floor]).mean() == pytest.approx(1.0, abs=0.03)
    assert np.abs(got - brute)[floor].mean() < 0.0015
