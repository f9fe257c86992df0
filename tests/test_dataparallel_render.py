"""`volren.dataparallel.render` (issue 43 items 2 and 3): a volume split into N regions, each rendered by its own
DSSRM over only the samples whose cell it owns, light maps summed across the regions and partial images composited
sort-last in each view's visibility order, is the one-process picture: DVR with shadows that cross every region
boundary to float rounding, MIP and iso bit for bit. Every sample of the one-process march is taken by exactly one
region; regions with nothing in them render nothing; a region's grid holds its bricks and only those; and what does
not split into regions is refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from volren.camera import Camera, StereoRig
from volren.dataparallel.composite import composite_over
from volren.dataparallel.order import visibility_order
from volren.dataparallel.regions import box_in_voxels
from volren.dataparallel.render import (
    RegionSet,
    check_data_parallel,
    composite_views,
    split_volume,
    view_orders,
)
from volren.dataparallel.volume import brick_weights, region_grid
from volren.errors import VolrenError
from volren.metrics import psnr
from volren.render import DSSRM, DSSRMConfig
from volren.render.gi.ambient import GIConfig
from volren.scene import DirectionalLight, Fog, PointLight, Scene, Sphere, Volume, scale_translate
from volren.sparse.grid import EMPTY, brick_dense


def one_channel(rs: RegionSet) -> tuple[list, list]:
    """A one-volume `RegionSet`'s renderers and scenes, region by region."""
    return [r[0] for r in rs.renderers], [s[0] for s in rs.scenes]

pytestmark = pytest.mark.timeout(120)

N = 64
"""[voxels] per axis: 4 bricks of 16 (the regions' k-d tree splits along z, y and x for 4 and 8 regions)"""
SUN = DirectionalLight(direction=(0.6, -0.7, 0.4))
"""a slanted light: every node's shadow path crosses the region planes of all three axes"""
CAMERA = Camera(position=(1.3, 0.8, 2.6), look_at=(0.0, 0.0, 0.0), width=96, height=64)
DVR_PSNR = 50.0
DVR_MAX_DIFF = 2e-3
"""[linear RGB] the regions' DVR against one process: the summed light map differs in float rounding of the sum
(observed max 4.7e-4, PSNR ~100 dB; the regions without the exchange are 18 to 30 dB)"""


def noisy_ball(n: int = N, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z, y, x = np.mgrid[0:n, 0:n, 0:n] / (n - 1) * 2 - 1
    ball = np.clip(1 - np.sqrt(x**2 + y**2 + z**2) / 0.9, 0, None)
    return (ball * (0.5 + rng.random((n, n, n)))).astype(np.float32)


BALL = noisy_ball()


def ball_scene(lights=(SUN,), density=BALL, scale: float = 8.0) -> Scene:
    return Scene((Volume(density, density_scale=scale),), lights=lights)


def config(**kw) -> DSSRMConfig:
    return DSSRMConfig(**{"samples": 128, "light_samples": 48, "iso_value": 0.4, **kw})


def renders(scene: Scene, views, regions: int, **kw):
    """(one-process frame, the RegionSet's frame, the RegionSet) of ``scene`` from ``views``."""
    cfg = config(**kw)
    one = DSSRM(cfg, device="cpu").render(scene, list(views))
    rs = RegionSet(scene, regions, lambda: DSSRM(cfg, device="cpu"))
    return one, rs.render(list(views)), rs


def assert_dvr_equal(one, got) -> None:
    for a, b in zip(one.images, got.images, strict=True):
        assert a[..., 3].max() > 0.5  # something to see
        assert psnr(a[..., :3], b[..., :3]) >= DVR_PSNR
        assert np.abs(a - b).max() <= DVR_MAX_DIFF


def split_axes(rs: RegionSet) -> set[int]:
    """The axes along which the regions' boxes are cut."""
    return {a for r in rs.tree.regions for a in range(3) if r.lo[a] > 0}


@pytest.mark.parametrize("regions", [2, 3, 4, 8])
def test_dvr_regions_with_shadows_across_them_equal_one_process(regions):
    one, got, rs = renders(ball_scene(), [CAMERA], regions)
    assert len(split_axes(rs)) == {2: 1, 3: 2, 4: 2, 8: 3}[regions]
    assert got.stats.info["light_exchange_bytes"] > 0
    assert_dvr_equal(one, got)


@pytest.mark.parametrize("mode", ["dvr", "iso"])
def test_a_moved_and_stretched_volume_splits_in_its_own_coordinates(mode):
    """A box not the unit one, rotated about y and off the origin: the visibility order is of the eye in the volume's
    local coordinates."""
    c, s = np.cos(0.6), np.sin(0.6)
    to_world = scale_translate((1.4, 0.7, 1.1), (0.4, -0.3, 0.2)) @ np.array(
        [[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]], np.float64)
    scene = Scene((Volume(BALL, to_world=to_world, density_scale=6.0),), lights=(SUN,))
    eye = Camera(position=(1.0, -0.1, 2.6), look_at=(0.4, -0.3, 0.2), width=96, height=64)
    one, got, rs = renders(scene, [eye], 8, mode=mode)
    # the eye's local position (-0.88, 0.29, 2.04) is on another side of the x and y planes than its world one
    local = (np.linalg.inv(to_world) @ np.append(eye.position, 1.0))[:3]
    assert got.stats.info["orders"][0] == visibility_order(rs.tree, local)
    assert got.stats.info["orders"][0] != visibility_order(rs.tree, np.array(eye.position))
    if mode == "dvr":
        assert_dvr_equal(one, got)
    else:
        assert np.array_equal(one.images[0], got.images[0]) and np.array_equal(one.depths[0], got.depths[0])


def test_without_the_light_map_exchange_the_shadows_are_wrong():
    """Each region shaded from its own partial map (only its part of every shadow path), composited the same way:
    far from the one-process picture, so the exchange is what test_dvr_regions... checks."""
    scene = ball_scene()
    one, got, _ = renders(scene, [CAMERA], 3)
    rs = RegionSet(scene, 3, lambda: DSSRM(config(), device="cpu"))  # fresh: its maps not yet filled
    partials = [r.region_light_map(s) for r, s in zip(*one_channel(rs), strict=True)]
    assert all(p is not None and p.max() > 0 for p in partials)
    for r, p in zip(one_channel(rs)[0], partials, strict=True):
        r.light_map_total = p
    frames = [r.render(s, [CAMERA]) for r, s in zip(*one_channel(rs), strict=True)]
    images, _ = composite_views([f.images for f in frames], [f.depths for f in frames],
                                view_orders(rs.tree, scene.volumes[0].to_local, [CAMERA]), "dvr")
    assert psnr(one.images[0][..., :3], images[0][..., :3]) < 35.0  # observed 20.8 dB
    assert psnr(one.images[0][..., :3], got.images[0][..., :3]) >= DVR_PSNR


@pytest.mark.parametrize("regions", [2, 3, 8])
def test_mip_regions_are_bit_exact(regions):
    one, got, _ = renders(ball_scene(), [CAMERA], regions, mode="mip")
    assert one.images[0][..., :3].max() > 0.5
    assert np.array_equal(one.images[0], got.images[0])


@pytest.mark.parametrize("regions", [2, 3, 8])
def test_iso_regions_are_bit_exact_with_their_depths(regions):
    one, got, _ = renders(ball_scene(), [CAMERA], regions, mode="iso")
    depth = one.depths[0]
    assert np.isfinite(depth).any() and np.isinf(depth).any()  # hits and misses
    assert np.array_equal(one.images[0], got.images[0])
    assert np.array_equal(depth, got.depths[0])  # inf (no hit) where one process has none


@pytest.mark.parametrize("mode", ["dvr", "mip", "iso"])
def test_stereo_eyes_each_equal_one_process(mode):
    eyes = StereoRig(CAMERA, ipd=0.3).eyes()
    one, got, _ = renders(ball_scene(), eyes, 4, mode=mode)
    assert len(got.images) == 2 and len(got.stats.info["orders"]) == 2
    assert not np.array_equal(one.images[0], one.images[1])  # the eyes see different pictures
    if mode == "dvr":
        assert_dvr_equal(one, got)
    else:
        for v in range(2):
            assert np.array_equal(one.images[v], got.images[v])
            assert np.array_equal(one.depths[v], got.depths[v]) or mode == "mip"


def test_a_point_light_inside_the_volume_shades_as_in_one_process():
    """Its shadow paths start inside one region and end in others (the light map's march stops at the light)."""
    scene = ball_scene(lights=(PointLight(position=(0.3, 0.2, -0.1), intensity=(2.0, 2.0, 2.0)),))
    one, got, _ = renders(scene, [CAMERA], 4)
    assert_dvr_equal(one, got)


@pytest.mark.parametrize("mode", ["dvr", "mip", "iso"])
def test_an_eye_inside_the_volume_sees_the_one_process_picture(mode):
    """The eye's region is composited first; the regions behind the eye in some pixels are in front in others."""
    eye = Camera(position=(0.1, 0.05, 0.3), look_at=(-0.5, -0.2, -1.0), width=96, height=64, near=0.001)
    one, got, _ = renders(ball_scene(scale=2.0), [eye], 4, mode=mode)
    if mode == "dvr":
        assert_dvr_equal(one, got)
    else:
        assert one.images[0][..., :3].max() > 0.1
        assert np.array_equal(one.images[0], got.images[0])
        if mode == "iso":
            assert np.array_equal(one.depths[0], got.depths[0])


@pytest.mark.parametrize("samples, light_samples", [(128, 48), (20, 6)])
def test_every_sample_is_taken_by_exactly_one_region(samples, light_samples):
    """The regions' frame counters sum: MIP's view samples and DVR's light-map samples (skipping off, the map
    recomputed each frame so its pass is counted) are the one-process counts exactly, with fine steps and with
    coarse ones (20 across the diagonal: a step spans about 5 voxels, more than the one voxel `region_steps`' box
    spares). (With skipping on the regions take more light samples than one process (276861 against 239748 here):
    a region's skip grid is of its own bricks; and DVR's view marches do not stop at the one-process early
    termination: each region marches to its own end; neither changes the picture.)"""
    steps = {"samples": samples, "light_samples": light_samples}
    one, got, _ = renders(ball_scene(), [CAMERA], 4, mode="mip", skip_empty=False, **steps)
    assert one.stats.counters["density_samples"] > 500
    assert got.stats.counters["density_samples"] == one.stats.counters["density_samples"]
    assert np.array_equal(one.images[0], got.images[0])
    one, got, _ = renders(ball_scene(), [CAMERA], 3, skip_empty=False, reuse_light_map=False, **steps)
    assert one.stats.counters["light_samples"] > 10_000
    assert got.stats.counters["light_samples"] == one.stats.counters["light_samples"]
    assert_dvr_equal(one, got)


def test_the_light_map_pass_of_the_regions_is_in_the_frames_stats():
    """The regions' light-map passes (run by `RegionSet.render` before the views, the map kept for the next frame)
    are counted in the frame that ran them, as one process counts its own: their samples summed, the slowest one's
    time; a frame that reuses the maps has none, as one process's second frame."""
    scene = ball_scene()
    cfg = config(skip_empty=False)
    single = DSSRM(cfg, device="cpu")
    one = single.render(scene, [CAMERA])
    rs = RegionSet(scene, 3, lambda: DSSRM(cfg, device="cpu"))
    got = rs.render([CAMERA])
    assert one.stats.counters["light_samples"] > 100_000
    assert got.stats.counters["light_samples"] == one.stats.counters["light_samples"]
    assert got.stats.times_ms.get("light_map", 0.0) > 0.0
    again, again_one = rs.render([CAMERA], 1), single.render(scene, [CAMERA], 1)
    assert again.stats.counters["light_samples"] == again_one.stats.counters["light_samples"] == 0
    assert again.stats.info["light_exchange_bytes"] == 0


def corner_blob(n: int = N) -> np.ndarray:
    """Density only in voxels 2..13 of each axis: the first brick's cells alone (its apron block 0..16)."""
    z, y, x = np.mgrid[0:n, 0:n, 0:n]
    r = np.sqrt((x - 8.0) ** 2 + (y - 8.0) ** 2 + (z - 8.0) ** 2)
    return (np.clip(1 - r / 6.0, 0, None) * 4).astype(np.float32)


def test_regions_without_an_active_brick_render_nothing_and_change_nothing():
    scene = ball_scene(density=corner_blob(), scale=8.0)
    near = Camera(position=(-0.2, -0.3, 0.6), look_at=(-0.75, -0.75, -0.75), width=96, height=64)
    one, got, rs = renders(scene, [near], 4)
    weights = [r.weight for r in rs.tree.regions]
    assert weights.count(0.0) >= 2 and sum(weights) == 1.0
    assert_dvr_equal(one, got)
    for r, s, region in zip(*one_channel(rs), rs.tree.regions, strict=True):
        if region.weight == 0:
            assert len(s.volumes[0].density.pool) == 0
            partial = r.render(s, [near])
            assert np.all(partial.images[0] == 0.0)  # transparent: no colour, no alpha
    for mode in ("mip", "iso"):
        one, got, _ = renders(scene, [near], 4, mode=mode)
        assert np.array_equal(one.images[0], got.images[0])


def test_the_regions_composited_in_the_wrong_order_differ():
    """What test_dvr_regions... would catch of a sort that reverses the visibility order: the same partial images
    composited back to front are far from the picture."""
    scene = ball_scene()
    one, got, rs = renders(scene, [CAMERA], 2)
    frames = [r.render(s, [CAMERA]) for r, s in zip(*one_channel(rs), strict=True)]
    order = view_orders(rs.tree, scene.volumes[0].to_local, [CAMERA])[0]
    alphas = [f.images[0][..., 3] for f in frames]
    assert np.sum((alphas[0] > 0.2) & (alphas[1] > 0.2)) > 100  # the regions overlap in the image
    right = composite_over([f.images[0] for f in frames], order)
    wrong = composite_over([f.images[0] for f in frames], order[::-1])
    assert np.array_equal(right, got.images[0])
    assert psnr(one.images[0][..., :3], wrong[..., :3]) < 35.0


# --- region grids -----------------------------------------------------------------------------------------------


def ring_of(rs_tree, region, halo: int):
    lo = tuple(max(a - halo, 0) for a in region.lo)
    hi = tuple(min(b + halo, g) for b, g in zip(region.hi, rs_tree.grid, strict=True))
    return lo, hi


@pytest.mark.parametrize("source", ["dense", "sparse"])
@pytest.mark.parametrize("halo", [0, 1])
def test_a_region_grid_holds_the_regions_voxels_and_nothing_else(source, halo):
    density = noisy_ball(48, seed=3)  # 3 bricks an axis
    whole = brick_dense(density, 16)
    tree = split_volume(ball_scene(density=density), 5)
    for region in tree.regions:
        grid = region_grid(density if source == "dense" else whole, region, tree, halo)
        assert grid.shape == density.shape and grid.brick == 16
        assert grid.max() == np.float32(density.max())  # the whole volume's peak, for MIP's normalisation
        lo, hi = ring_of(tree, region, halo)
        held = np.zeros(tree.grid, bool)
        held[tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))] = True
        assert np.all(grid.table[~held] == EMPTY)
        assert np.array_equal(grid.table[held] != EMPTY, whole.table[held] != EMPTY)
        # every voxel read through a held brick is the volume's, every other one EMPTY (0)
        owner = [np.minimum(np.arange(n) // 16, g - 1) for n, g in zip(density.shape, tree.grid, strict=True)]
        mask = held[np.ix_(*owner)]
        assert mask.any() and (halo or not mask.all())
        assert np.array_equal(grid.read((0, 0, 0), density.shape), np.where(mask, density, 0.0))
        if halo == 0:
            assert len(grid.pool) == int(np.sum(whole.table[held] >= 0))


def test_a_region_grid_with_a_halo_holds_one_more_ring_of_bricks():
    density = np.ones((N, N, N), np.float32) + noisy_ball()
    tree = split_volume(ball_scene(density=density), 8)
    for region in tree.regions:
        bare, ring = region_grid(density, region, tree, 0), region_grid(density, region, tree, 1)
        lo, hi = ring_of(tree, region, 1)
        assert int(np.sum(bare.table != EMPTY)) == int(np.prod(np.subtract(region.hi, region.lo)))
        assert int(np.sum(ring.table != EMPTY)) == int(np.prod(np.subtract(hi, lo)))


def test_brick_weights_mark_the_bricks_a_sample_can_read_density_in():
    weights = brick_weights(corner_blob(), 16)
    assert weights.shape == (4, 4, 4) and weights[0, 0, 0] == 1.0 and weights.sum() == 1.0
    assert np.array_equal(brick_weights(brick_dense(corner_blob(), 16), 16), weights)


def test_a_streamed_pyramids_region_grid_is_the_finest_levels(tmp_path):
    pytest.importorskip("ome_zarr")
    from tests.test_stream_render import scene_of, write_pyramid

    write_pyramid(tmp_path / "blobs.zarr")
    dense = scene_of(tmp_path / "blobs.zarr", level=0).volumes[0].density
    streamed = scene_of(tmp_path / "blobs.zarr", memory_budget=2**26, stream=True).volumes[0].density
    assert getattr(streamed, "streamed", False)
    tree = split_volume(ball_scene(density=np.asarray(dense)), 3)
    for region in tree.regions:
        a = region_grid(dense, region, tree, 1)
        b = region_grid(streamed, region, tree, 1)
        assert np.array_equal(a.table != EMPTY, b.table != EMPTY)
        lo, hi = box_in_voxels(region, tree.brick, tree.shape)
        assert np.allclose(a.read(lo, hi), b.read(lo, hi), rtol=1e-6, atol=1e-6)


def test_a_streamed_pyramids_active_bricks_are_judged_from_its_coarsest_level(tmp_path):
    """Every brick the finest level has density in is active (the split never starves a region of its cost), and
    the empty ones far from the data are not."""
    pytest.importorskip("ome_zarr")
    from tests.test_stream_render import scene_of, write_levels

    fine = np.zeros((64, 64, 64), np.float32)
    fine[4:20, 40:60, 8:30] = 1000.0
    levels = [fine]
    for _ in range(2):
        n = levels[-1].shape[0] // 2
        levels.append(levels[-1].reshape(n, 2, n, 2, n, 2).mean(axis=(1, 3, 5)))
    write_levels(tmp_path / "box.zarr", [np.round(v).astype(np.uint16) for v in levels], [1, 2, 4], centred=True)
    dense = scene_of(tmp_path / "box.zarr", level=0).volumes[0].density
    streamed = scene_of(tmp_path / "box.zarr", memory_budget=2**26, stream=True).volumes[0].density
    judged, truth = brick_weights(streamed, 16), brick_weights(dense, 16)
    assert np.all(judged >= truth) and 0 < truth.sum() <= judged.sum() <= truth.sum() + 24


# --- refusals ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cells", [((0, 0, 0), (64, 63, 63)), ((-1, 0, 0), (10, 10, 10)), ((5, 5, 5), (5, 9, 9)),
                                   ((0, 0, 0), (8, 8))])
def test_owned_cells_outside_the_volume_are_refused_in_one_line(cells):
    with pytest.raises(VolrenError, match="owned_cells") as e:
        Volume(BALL, owned_cells=cells)
    assert "\n" not in str(e.value)


def test_owned_cells_inside_are_kept():
    assert Volume(BALL, owned_cells=((0, 16, 32), (63, 63, 48))).owned_cells == ((0, 16, 32), (63, 63, 48))


@pytest.mark.parametrize("method, cfg, scene, names", [
    ("cmsrm", DSSRMConfig(), None, "cmsrm"),
    ("vpt", DSSRMConfig(), None, "vpt"),
    ("dssrm", DSSRMConfig(mode="mida"), None, "mida"),
    ("dssrm", DSSRMConfig(gi=GIConfig(method="major")), None, "gi"),
    ("dssrm", DSSRMConfig(), Scene((Volume(BALL), Volume(BALL)), name="two"), "two"),
    ("dssrm", DSSRMConfig(), Scene((Volume(BALL),), opaque=(Sphere(),), name="walls"), "meshes"),
    ("dssrm", DSSRMConfig(), Scene((Volume(BALL),), fog=Fog(extinction=0.1), name="misty"), "fog"),
])
def test_what_does_not_split_into_regions_is_refused_naming_it(method, cfg, scene, names):
    with pytest.raises(VolrenError) as e:
        check_data_parallel(method, cfg, scene)
    assert names in str(e.value).lower() and "\n" not in str(e.value)
    if scene is not None:
        with pytest.raises(VolrenError):
            RegionSet(scene, 2, lambda: DSSRM(cfg, device="cpu"))
