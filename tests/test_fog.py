"""Froxel fog (paper 003): closed forms for homogeneous fog, shadows, the shared shadow grid against brute force,
frustum-limited updates, convergence of the shared pipeline to the per-viewer reference, temporal integration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera
from volren.errors import VolrenError
from volren.metrics import flip, psnr
from volren.render import FogConfig, FogRenderer
from volren.scene import DirectionalLight, Environment, Fog, Plane, Scene, Sphere

CAM = Camera(position=(0.0, 1.5, 6.0), look_at=(0.0, 1.0, 0.0), width=96, height=64)
SUN = DirectionalLight(direction=(0.3, -1.0, 0.2), irradiance=(3.0, 3.0, 3.0))
BASE = {"far": 30.0, "temporal": False, "near": 1e-3}
INNER = np.s_[4:-4, 4:-4]
"""pixels at least half a froxel (8 px) from the border: nearer the border the lookup clamps to the outermost froxel
column (measured: 0.28% off Beer-Lambert inside, 4.6% at the corners)"""


def render(scene, views=(CAM,), frames=1, **config):
    r = FogRenderer(FogConfig(**{**BASE, **config}), device=DEVICE)
    for f in range(frames):
        frame = r.render(scene, list(views), f)
    return frame, r


def test_transmittance_to_a_wall_is_beer_lambert():
    """A wall at 8 m lit by ambient only, fog that only absorbs: every pixel is the wall's colour times
    exp(-sigma_t d), d the pixel ray's length to the wall."""
    sigma = 0.15
    wall = Plane(point=(0.0, 0.0, -2.0), normal=(0.0, 0.0, 1.0), albedo=(0.5, 0.5, 0.5))
    scene = Scene(volumes=(), lights=(), environment=Environment((1.0, 1.0, 1.0)), opaque=(wall,),
                  fog=Fog(extinction=sigma, albedo=(0.0, 0.0, 0.0)))
    frame, _ = render(scene)
    d = CAM.ray_directions()
    dist = (-2.0 - CAM.position[2]) / d[..., 2]
    expected = 0.5 * np.exp(-sigma * dist)
    np.testing.assert_allclose(frame.images[0][..., 0][INNER], expected[INNER], rtol=5e-3)
    np.testing.assert_allclose(frame.images[0][..., 0], expected, rtol=5e-2)


def test_unshadowed_fog_matches_single_scattering_closed_form():
    """No surface, isotropic phase, a directional light and ambient: L = sigma_s / sigma_t (E / 4 pi + L_a)
    (1 - exp(-sigma_t l)) along the fog range l = (far - near) / cos."""
    sigma, albedo, ambient = 0.05, 0.8, 0.2
    scene = Scene(volumes=(), lights=(SUN,), environment=Environment((ambient,) * 3),
                  fog=Fog(extinction=sigma, albedo=(albedo,) * 3, g=0.0))
    frame, _ = render(scene)
    cos = CAM.ray_directions() @ CAM.basis()[2]
    length = (BASE["far"] - BASE["near"]) / cos
    expected = albedo * (3.0 / (4 * math.pi) + ambient) * (1 - np.exp(-sigma * length))
    np.testing.assert_allclose(frame.images[0][..., 0][INNER], expected[INNER], rtol=5e-3)
    np.testing.assert_allclose(frame.images[0][..., 3][INNER], 1 - np.exp(-sigma * length)[INNER], rtol=5e-3)


@pytest.mark.parametrize("sharing", ["none", "grid"])
def test_a_fully_occluded_light_adds_nothing(sharing):
    """A ceiling over everything blocks the sun: the image equals the same scene without the sun."""
    ceiling = Plane(point=(0.0, 40.0, 0.0), normal=(0.0, -1.0, 0.0))  # above every froxel of the fog range
    fog = Fog(extinction=0.05, g=0.4)
    lit = Scene(volumes=(), lights=(SUN,), opaque=(ceiling,), fog=fog)
    dark = Scene(volumes=(), lights=(), opaque=(ceiling,), fog=fog)
    a, _ = render(lit, sharing=sharing, voxel_size=1.0)
    b, _ = render(dark, sharing=sharing, voxel_size=1.0)
    np.testing.assert_allclose(a.images[0], b.images[0], atol=1e-6)


SHADOWED = Scene(volumes=(), lights=(SUN,), environment=Environment((0.05, 0.05, 0.05)),
                 opaque=(Plane(point=(0.0, 0.0, 0.0)), Sphere(center=(0.0, 2.0, 0.0), radius=1.0)),
                 fog=Fog(extinction=0.08, g=0.3))


def test_shadow_grid_bits_equal_brute_force_shadow_rays():
    _, r = render(SHADOWED, sharing="grid", voxel_size=0.5)
    g = r._grid
    bits = g.bits.numpy()
    lo, size = np.array(g.lo), g.voxel_size
    k, j, i = np.nonzero(np.ones_like(bits))
    centres = lo + (np.stack([i, j, k], 1) + 0.5) * size
    # Brute force: the ray towards the sun hits the sphere or the ground plane (from below).
    to_sun = -np.array(SUN.direction)
    oc = centres - np.array([0.0, 2.0, 0.0])
    b = oc @ to_sun
    disc = b**2 - (np.sum(oc**2, 1) - 1.0)
    hit_sphere = (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 1e-4)
    below_ground = centres[:, 1] < 0
    visible = ~(hit_sphere | below_ground)
    # Compare where the camera's frustum surely covers the voxel (the kernel updates a margin beyond it).
    right, up, forward = CAM.basis()
    q = centres - np.array(CAM.position)
    z = q @ forward
    inside = (z > CAM.near + size) & (z < BASE["far"] - size)
    inside &= np.abs(q @ right) < z * CAM.tan_half_fov * CAM.width / CAM.height - size
    inside &= np.abs(q @ up) < z * CAM.tan_half_fov - size
    # Skip voxel centres on a shadow boundary (a grazing ray), where float rounding may decide either way.
    edge = np.abs(disc) < 1e-3
    check = inside & ~edge
    assert check.sum() > 1000
    np.testing.assert_array_equal(bits.reshape(-1)[check] & 1, visible[check].astype(np.uint8))


def test_a_viewer_inside_another_frustum_adds_almost_no_grid_work():
    narrow = Camera(position=CAM.position, look_at=(0.0, 1.0, 0.0), fov_y=20.0, width=96, height=64)
    one, _ = render(SHADOWED, sharing="grid", voxel_size=0.5)
    two, _ = render(SHADOWED, [CAM, narrow], sharing="grid", voxel_size=0.5)
    assert two.stats.counters["shadow_voxels"] <= 1.01 * one.stats.counters["shadow_voxels"]


def test_shared_pipeline_converges_to_the_reference_as_voxels_shrink():
    ref, _ = render(SHADOWED, sharing="none")
    images = [render(SHADOWED, sharing="grid", voxel_size=v)[0].images[0] for v in (2.0, 0.5, 0.125)]
    scores = [psnr(ref.images[0], image) for image in images]
    errors = [flip(ref.images[0], image) for image in images]
    assert scores[0] < scores[1] < scores[2] and errors[0] > errors[1] > errors[2]
    assert scores[2] > 35.0


def test_temporal_integration_supersamples_the_slices():
    """Jittered depths blended over frames average each froxel over its slice: closer to 4x finer slicing than one
    frame sampled at slice centres."""
    fine, _ = render(SHADOWED, slices=512)
    still, _ = render(SHADOWED, slices=32)
    r = FogRenderer(FogConfig(**{**BASE, "temporal": True, "slices": 32, "temporal_weight": 0.1}), device=DEVICE)
    for f in range(32):
        accumulated = r.render(SHADOWED, [CAM], f).images[0]
    assert psnr(fine.images[0], accumulated) > psnr(fine.images[0], still.images[0]) + 1.0


@pytest.mark.parametrize(
    ("config", "fragment"),
    [({"sharing": "sometimes"}, "sharing"), ({"slices": 1}, "slices"), ({"near": 2.0, "far": 1.0}, "near"),
     ({"voxel_size": 0.0}, "voxel"), ({"temporal_weight": 0.0}, "temporal")],
)
def test_bad_fog_settings(config, fragment):
    with pytest.raises(VolrenError, match=fragment):
        FogConfig(**config)


def test_fog_needs_a_fog_scene_and_volume_methods_need_volumes():
    from volren.data import builtin_scene
    from volren.render import DSSRM

    with pytest.raises(VolrenError, match="needs a scene with fog"):
        FogRenderer(device=DEVICE).render(builtin_scene("smoke", 64), [CAM])
    with pytest.raises(VolrenError, match="has none"):
        DSSRM(device=DEVICE).render(SHADOWED, [CAM])


def test_moving_objects_keep_the_grid_and_move_their_shadows():
    from volren.data.fog_scenes import fog_scene, fog_scene_camera

    spot = fog_scene_camera("dynamic")
    cam = Camera(position=spot["position"], look_at=spot["look_at"], width=64, height=36)
    r = FogRenderer(FogConfig(voxel_size=0.5, slices=32, temporal=False), device=DEVICE)
    a = r.render(fog_scene("dynamic", 0.0), [cam], 0)
    b = r.render(fog_scene("dynamic", 2.0), [cam], 1)
    # The re-built scene keeps the room's bounds, so the grid is kept and re-traced by parity (about half).
    assert 0 < b.stats.counters["shadow_voxels"] < 0.6 * a.stats.counters["shadow_voxels"]
    assert not np.allclose(a.images[0], b.images[0])


def per_view_psnr(scene, views, **config) -> list[float]:
    ref, _ = render(scene, views, sharing="none", **config)
    grid, _ = render(scene, views, sharing="grid", **config)
    return [psnr(a, b) for a, b in zip(ref.images, grid.images, strict=True)]


ARC_FOG = {"far": 64.0, "near": 0.1, "voxel_size": 1.0}
"""the fog's default range (the issue's goal is at 1 m voxels)"""


@pytest.mark.parametrize("name", ["hall", "courtyard"])
def test_every_view_of_the_arc_rig_is_within_25_db_of_the_reference(name):
    """The CLI's arc rig (16 viewers kept in the walkable space), 1 m voxels: each viewer's image within 25 dB of the
    per-viewer reference (measured minimum at 96x54: hall 30.7, courtyard 32.4 dB)."""
    from volren.data.fog_scenes import fog_scene, fog_scene_camera, fog_scene_walk_area
    from volren.viewers import arc_viewers

    spot = fog_scene_camera(name)
    base = Camera(position=spot["position"], look_at=spot["look_at"], width=96, height=54)
    views = arc_viewers(base, 16, fog_scene_walk_area(name))
    scores = per_view_psnr(fog_scene(name), views, **ARC_FOG)
    assert min(scores) > 25.0, np.round(scores, 1)


def test_viewers_outside_the_shadow_grid_see_the_scene_s_shadow():
    """Viewers outside the hall (the plain arc of `--views 8` before the rigs kept to the walkable space) look through
    fog outside the shadow grid, part of it in the hall's own shadow: within 25 dB of the reference per view (counting
    the outside as lit, as before the fix, the worst view scored 9.1 dB)."""
    from volren.camera import orbit_views
    from volren.data.fog_scenes import fog_scene, fog_scene_camera

    spot = fog_scene_camera("hall")
    views = orbit_views(Camera(position=spot["position"], look_at=spot["look_at"], width=96, height=54), 8)
    assert sum(v.position[2] < -6.5 for v in views) >= 2  # beyond the grid (the hall's wall at z = -5.5, a voxel)
    scores = per_view_psnr(fog_scene("hall"), views, **ARC_FOG)
    assert min(scores) > 25.0, np.round(scores, 1)


def test_the_shadow_frustum_resolves_the_near_field_the_grid_misses():
    """2 m voxels blur the sphere's shadow shaft; the per-viewer shadow frustum (paper 003 §3.1.2, 16 px froxels over
    its own near range, here up to 6.9 m where its froxels grow as wide as a voxel) restores it. Measured at 96x64:
    31.1 dB without the frustum, 38.2 dB with it."""
    ref, _ = render(SHADOWED, sharing="none")
    off, _ = render(SHADOWED, sharing="grid", voxel_size=2.0, frustum_range=0.0)
    on, _ = render(SHADOWED, sharing="grid", voxel_size=2.0)
    with_frustum, without = psnr(ref.images[0], on.images[0]), psnr(ref.images[0], off.images[0])
    assert with_frustum > 36.0 and with_frustum > without + 4.0, (with_frustum, without)
    assert on.stats.info["shadow_frustum_bytes_per_viewer"] == (128 // 3) * 4 * 6  # 16 px froxels, a third of slices


def test_the_history_follows_a_turning_camera():
    """Temporal integration reprojects each froxel into the previous frame's camera: a camera turning for 12 frames
    ends where a camera that stood still at its last pose for 12 frames does (measured 48.3 dB at 96x64; reading the
    history at the same froxel of the current camera 35.0 dB, the nearest previous froxel instead of trilinear 39.5)."""
    from dataclasses import replace

    def turned(f: int) -> Camera:
        return replace(CAM, look_at=(CAM.look_at[0] + 0.3 * f, CAM.look_at[1], CAM.look_at[2]))

    frames = 12
    config = FogConfig(**{**BASE, "temporal": True, "slices": 32})
    moving, still = FogRenderer(config, device="cpu"), FogRenderer(config, device="cpu")
    for f in range(frames):
        a = moving.render(SHADOWED, [turned(f)], f).images[0]
        b = still.render(SHADOWED, [turned(frames - 1)], f).images[0]
    assert psnr(b, a) > 44.0


def brute_force_sun_visibility(centres: np.ndarray, sphere_centre) -> np.ndarray:
    """Whether the sun reaches each point past the sphere of radius 1 at ``sphere_centre`` and the ground plane."""
    to_sun = -np.array(SUN.direction)
    oc = centres - np.asarray(sphere_centre)
    b = oc @ to_sun
    disc = b**2 - (np.sum(oc**2, 1) - 1.0)
    hit_sphere = (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 1e-4)
    return ~(hit_sphere | (centres[:, 1] < 0)), np.abs(disc) < 1e-3


def frustum_voxels(centres: np.ndarray, margin: float) -> np.ndarray:
    """Voxel centres inside CAM's frustum up to the fog's far depth, shrunk (margin < 0) or grown by |margin|."""
    right, up, forward = CAM.basis()
    q = centres - np.array(CAM.position)
    z = q @ forward
    out = (z > -margin) & (z < BASE["far"] + margin)
    slack = margin * np.sqrt(1 + CAM.tan_half_fov**2 * (1 + (CAM.width / CAM.height) ** 2))
    out &= np.abs(q @ right) < np.maximum(z, 0) * CAM.tan_half_fov * CAM.width / CAM.height + slack
    return out & (np.abs(q @ up) < np.maximum(z, 0) * CAM.tan_half_fov + slack)


def test_the_grid_re_traces_one_z_parity_per_frame_and_only_inside_the_frusta():
    """Frame 0 traces every voxel in the frustum and nothing outside it (bits stay 0 there, though the sun reaches
    thousands of them); the sphere then moves and frame 1 re-traces only the odd z slices (frame parity): they see the
    new sphere, the even ones still the old."""
    moved = Scene(volumes=(), lights=(SUN,), environment=SHADOWED.environment,
                  opaque=(SHADOWED.opaque[0], Sphere(center=(1.5, 2.0, 0.0), radius=1.0)), fog=SHADOWED.fog)
    r = FogRenderer(FogConfig(**{**BASE, "sharing": "grid", "voxel_size": 0.5}), device="cpu")
    first = r.render(SHADOWED, [CAM], 0)
    g = r._grid
    k, j, i = np.nonzero(np.ones(g.bits.shape, dtype=bool))
    centres = np.array(g.lo) + (np.stack([i, j, k], 1) + 0.5) * g.voxel_size
    outside = ~frustum_voxels(centres, 2 * g.voxel_size)
    lit_before, edge_before = brute_force_sun_visibility(centres, (0.0, 2.0, 0.0))
    assert outside.sum() > 1000 and lit_before[outside].sum() > 1000
    assert not g.bits.numpy().reshape(-1)[outside].any()
    assert first.stats.counters["shadow_voxels"] < (~outside).sum()
    second = r.render(moved, [CAM], 1)
    bits = g.bits.numpy().reshape(-1) & 1
    lit_after, edge_after = brute_force_sun_visibility(centres, (1.5, 2.0, 0.0))
    check = frustum_voxels(centres, -g.voxel_size) & ~edge_before & ~edge_after & (lit_before != lit_after)
    odd = k % 2 == 1
    assert (check & odd).sum() > 50 and (check & ~odd).sum() > 50
    np.testing.assert_array_equal(bits[check & odd], lit_after[check & odd])
    np.testing.assert_array_equal(bits[check & ~odd], lit_before[check & ~odd])
    assert second.stats.counters["shadow_voxels"] == pytest.approx(first.stats.counters["shadow_voxels"] / 2, rel=0.05)
