"""Issue 42 item 2: `vr.load` reads what ``--volume`` reads. A multi-channel file is `vr.Channels`, rendered as the CLI
composes channels (each in its colour, where it lies); a numbered sequence or a 4-D NIfTI is a lazy
`vr.VolumeSequence` whose frames `vr.render(..., frames=)` renders in order and `vr.Viewer` plays; OME-Zarr levels and
budgets pass through; refusals name the keywords, not the CLI's flags."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tests.conftest import DEVICE

import volren as vr
from volren.errors import VolrenError, VolrenWarning

SMALL = {"samples": 32, "light_samples": 8, "light_grid": 16, "device": DEVICE, "width": 64, "height": 48}
Z, Y, X = np.mgrid[0:16, 0:20, 0:32]


def ball(cx: float, cy: float = 10.0, cz: float = 8.0) -> np.ndarray:
    return np.exp(-((X - cx) ** 2 + (Y - cy) ** 2 + (Z - cz) ** 2) / 12.0)


def two_channels() -> np.ndarray:
    """(C, Z, Y, X) 12-bit: channel 0 a ball on the left, channel 1 one on the right."""
    return (np.stack([ball(8), ball(24)]) * 3000).astype(np.uint16)


@pytest.fixture
def cells_tif(tmp_path) -> Path:
    import tifffile

    path = tmp_path / "cells.tif"
    tifffile.imwrite(path, two_channels().transpose(1, 0, 2, 3), imagej=True, metadata={"axes": "ZCYX"})
    return path


def halves(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The premultiplied RGB summed over the left and right halves of an (H, W, 4) image."""
    w = image.shape[1] // 2
    return image[:, :w, :3].sum(axis=(0, 1)), image[:, w:, :3].sum(axis=(0, 1))


def alpha_centre_x(image: np.ndarray) -> float:
    """The alpha-weighted mean column of an image."""
    a = image[..., 3]
    return float((a.sum(axis=0) * np.arange(a.shape[1])).sum() / a.sum())


def test_a_multi_channel_tiff_is_channels_each_in_its_colour_where_it_lies(cells_tif):
    channels = vr.load(cells_tif, channel_colors="green,magenta", channel_opacity=(4, 2))
    assert isinstance(channels, vr.Channels) and len(channels) == 2
    assert channels.colors == ((0.0, 1.0, 0.0), (1.0, 0.0, 1.0))
    assert channels.opacity == pytest.approx((4.0, 2.0))
    text = repr(channels)
    assert text.startswith("Channels('cells', 2 channels of 32x20x16 float32") and "green opacity 4" in text
    assert "magenta opacity 2" in text and len(text) < 300
    image = vr.render(channels, **SMALL).images[0]
    (lr, lg, lb), (rr, rg, rb) = halves(image)
    assert lg > 5 * max(lr, lb)  # channel 0, green, on the left
    assert min(rr, rb) > 5 * rg and rr == pytest.approx(rb)  # channel 1, magenta, on the right
    assert lg > rr  # channel 0's opacity 4 against channel 1's 2
    assert image[0, 0, 3] < 0.01 and image[:, :32, 3].max() > 0.3  # a corner empty, the left ball covered


def test_channels_render_mip_as_each_channels_maximum_in_its_colour(cells_tif):
    image = vr.render(cells_tif, mode="mip", **SMALL).images[0]  # a path: the default colours, green then magenta
    (lr, lg, lb), (rr, rg, rb) = halves(image)
    assert lg > 5 * max(lr, lb) and min(rr, rb) > 5 * rg
    assert image[..., 1].max() > 0.85  # each channel's maximum is 1 in its own range (between voxel centres)


def test_an_ome_zarr_with_a_channel_axis_is_channels_and_its_level_and_budget_pass_through(tmp_path):
    import warnings

    import zarr

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from ome_zarr.writer import write_image

        write_image(two_channels(), zarr.open_group(str(tmp_path / "c.zarr"), mode="w"), axes="czyx",
                    scale_factors=(2,), axes_units={a: "micrometer" for a in "zyx"})
    fine, coarse = vr.load(tmp_path / "c.zarr"), vr.load(tmp_path / "c.zarr", level=1)
    assert isinstance(coarse, vr.Channels) and coarse[0].resolution == (16, 10, 16)  # ome-zarr halves y and x
    assert fine[0].resolution == (32, 20, 16)
    level1_bytes = 2 * 4 * 16 * 10 * 16  # two channels of float32
    budget = 1.5 * level1_bytes / 2**30  # read whole, the level that fits (streamed, it is level 0's resolution)
    assert vr.load(tmp_path / "c.zarr", memory_budget=budget, stream=False)[0].resolution == (16, 10, 16)
    image = vr.render(coarse, **SMALL).images[0]
    (lr, lg, lb), (rr, rg, rb) = halves(image)
    assert lg > 5 * max(lr, lb) and min(rr, rb) > 5 * rg
    with pytest.raises(VolrenError, match=r"memory_budget= chooses a level by its size; level= 1 names") as err:
        vr.load(tmp_path / "c.zarr", level=1, memory_budget=0.5)
    assert "--" not in str(err.value)
    with pytest.raises(VolrenError, match="memory_budget= must be a positive number of GiB, got -1"):
        vr.load(tmp_path / "c.zarr", memory_budget=-1)
    with pytest.raises(VolrenError, match=r"level 5 is out of range: the pyramid has levels 0 to 1"):
        vr.load(tmp_path / "c.zarr", level=5)


def test_a_numbered_sequence_is_lazy_and_renders_its_frames_in_order(tmp_path):
    for i in range(3):  # the ball moves right 6 voxels a frame
        np.save(tmp_path / f"sim_{i:04d}.npy", ball(8 + 6 * i).astype(np.float32))
    seq = vr.load(tmp_path / "sim_####.npy")
    assert isinstance(seq, vr.VolumeSequence) and len(seq) == 3
    assert [f.name for f in seq.files] == ["sim_0000.npy", "sim_0001.npy", "sim_0002.npy"]
    text = repr(seq)
    assert "3 frames (sim_0000.npy .. sim_0002.npy)" in text and "32x20x16 (x, y, z)" in text and len(text) < 300
    np.testing.assert_array_equal(seq[-1].density, seq[2].density)
    assert isinstance(seq[1], vr.Volume) and [v.density.shape for v in seq] == [(16, 20, 32)] * 3
    with pytest.raises(IndexError):
        seq[3]
    frames = vr.render(seq, frames=range(0, 3, 2), **SMALL)
    assert [f.index for f in frames] == [0, 2]
    first, last = (alpha_centre_x(f.images[0]) for f in frames)
    assert last > first + 5  # frame 2 shows the ball further right
    assert len(vr.render(seq, **SMALL)) == 3  # without frames=: every frame
    with pytest.raises(VolrenError, match=r"frames= 4: the sequence has 3 frames \(0 to 2\)"):
        vr.render(seq, frames=4, **SMALL)


def test_a_4d_nifti_is_a_sequence_of_its_time_points(tmp_path):
    import nibabel as nib

    series = np.stack([ball(8 + 12 * t) for t in range(2)], axis=-1).transpose(2, 1, 0, 3).astype(np.float32)
    nib.save(nib.Nifti1Image(series, np.diag([2.0, 2.0, 2.0, 1.0])), str(tmp_path / "f.nii.gz"))
    seq = vr.load(tmp_path / "f.nii.gz")
    assert isinstance(seq, vr.VolumeSequence) and len(seq) == 2 and "f.nii.gz (time point 1)" in repr(seq)
    one = vr.load(tmp_path / "f.nii.gz", time_point=1)
    assert isinstance(one, vr.Volume)
    np.testing.assert_array_equal(one.density, seq[1].density)
    # x runs right in RAS as in the world (RAS x -> -x: the file's +x is the patient's right, shown on the left)
    first, second = (alpha_centre_x(f.images[0]) for f in vr.render(seq, frames=2, **SMALL))
    assert abs(second - first) > 5


def test_load_refusals_name_keywords(tmp_path, cells_tif):
    np.save(tmp_path / "one.npy", ball(16).astype(np.float32))
    with pytest.raises(VolrenError, match=r"load: channel_colors= apply to a multi-channel file only"):
        vr.load(tmp_path / "one.npy", channel_colors="green")
    with pytest.raises(VolrenError, match=r"unlit: density_scale= would do nothing \(give channel_colors="):
        vr.load(cells_tif, density_scale=3.0)
    with pytest.raises(VolrenError, match=r"channel_colors= gives 3 colour\(s\) for a volume of 2 channels"):
        vr.load(cells_tif, channel_colors=["red", "green", "blue"])
    with pytest.raises(VolrenError, match=r"channel_colors=: 'teal' is neither a colour name"):
        vr.load(cells_tif, channel_colors=["teal", "green"])
    with pytest.raises(VolrenError, match=r"channel_opacity= must be one value >= 0 or one per channel \(2\)"):
        vr.load(cells_tif, channel_opacity=(1, 2, 3))
    with pytest.raises(VolrenError, match=r"environment= would do nothing"):
        vr.render(cells_tif, environment="sky", **SMALL)
    with pytest.raises(VolrenError, match=r"resolution= and count= build a built-in scene"):
        vr.render(tmp_path / "one.npy", resolution=64)


def test_the_viewer_plays_a_sequence(tmp_path):
    for i in range(3):
        np.save(tmp_path / f"s{i}.npy", ball(8 + 8 * i).astype(np.float32))
    seq = vr.load(tmp_path / "s*.npy")
    viewer = vr.Viewer(seq, width=64, height=48, device=DEVICE, samples=32, light_samples=8, light_grid=16)
    try:
        still = viewer.get_frame()
        assert np.array_equal(viewer.get_frame(), still)  # not playing: frame 0 stays
        viewer.playing = True
        moved = [viewer.get_frame() for _ in range(4)]
        assert any(not np.array_equal(m, still) for m in moved)
    finally:
        viewer.close()
    with pytest.raises(VolrenError, match="Viewer: a multi-channel volume renders each channel"):
        vr.Viewer(vr.load(tmp_path / "s0.npy") and vr.Channels((seq[0], seq[1])), device=DEVICE)


@pytest.mark.timeout(120)
def test_iso_without_a_value_takes_otsus_threshold_as_the_cli_does(tmp_path, capsys):
    """``mode="iso"`` without ``iso_value=`` is not a silent 0.5: Otsu's threshold of the densities, said in one
    warning, the value ``volren render --mode iso`` picks (a CT of values 0 to 2200 has its surface far above 0.5)."""
    from volren.cli import main

    z, y, x = np.mgrid[-1:1:32j, -1:1:32j, -1:1:32j]
    np.save(tmp_path / "ct.npy", np.where(x * x + y * y + z * z < 0.4, 2200.0, 0.0).astype(np.float32))
    said = r"mode='iso' without iso_value=: the isosurface is at density ([-\d.e+]+)"
    with pytest.warns(VolrenWarning, match=said) as caught:
        frame = vr.render(tmp_path / "ct.npy", mode="iso", width=48, height=32, light_grid=8, device=DEVICE)
    value = float(str(caught[0].message).split("density ")[1].split(",")[0])
    assert 0 < value < 2200  # between the two materials (Otsu's first bin above 0 for two values)
    assert main(["render", "--volume", str(tmp_path / "ct.npy"), "--mode", "iso", "--width", "48", "--height", "32",
                 "--views", "mono", "--light-grid", "8", "--device", DEVICE, "--out", str(tmp_path / "cli")]) == 0
    assert f"density {value:.4g}" in capsys.readouterr().err
    alpha = frame.images[0][..., 3]
    assert alpha[16, 24] > 0.99 and alpha[0, 0] == 0.0  # the ball's surface in the middle, nothing in the corner


@pytest.mark.timeout(120)
def test_a_renderer_given_channels_of_another_count_renders_every_channel():
    """One `vr.Renderer` handed two channels, then three: the three render as a fresh renderer renders them (one
    renderer per channel), the third channel's colour in the picture."""
    from volren.render.compositing.channels import channel_volumes

    blobs = [ball(cx).astype(np.float32) for cx in (6.0, 16.0, 26.0)]
    colors = ((0.0, 1.0, 0.0), (1.0, 0.0, 1.0), (0.0, 0.0, 1.0))
    two = vr.Channels(channel_volumes(blobs[:2], np.eye(4), colors=colors[:2]))
    three = vr.Channels(channel_volumes(blobs, np.eye(4), colors=colors))
    from volren._api import framed_views

    cameras = framed_views(three, None, "mono", 48, 32)
    kept = vr.Renderer(device=DEVICE, samples=32)
    kept.render(two, cameras)
    got = kept.render(three, cameras).images[0]
    want = vr.Renderer(device=DEVICE, samples=32).render(three, cameras).images[0]
    assert np.array_equal(got, want)
    assert want[:, 32:, 2].sum() > 2 * want[:, 32:, 0].sum()  # the blue channel on the right


@pytest.mark.timeout(120)
def test_environment_as_a_radiance_lights_the_volume_as_that_environment():
    """``environment=(r, g, b)`` (``--ambient``) is that radiance's `Environment`: the same image as passing it, and
    brighter than black."""
    volume = vr.Volume(ball(16.0).astype(np.float32), density_scale=20.0)
    grey = vr.render(volume, environment=(0.5, 0.5, 0.5), **SMALL).images[0]
    same = vr.render(volume, environment=vr.Environment((0.5, 0.5, 0.5)), **SMALL).images[0]
    black = vr.render(volume, environment=0.0, **SMALL).images[0]
    assert np.array_equal(grey, same)
    assert grey[..., :3].sum() > 1.05 * black[..., :3].sum()


def test_channels_of_no_volume_are_refused_in_one_line():
    with pytest.raises(VolrenError, match=r"^Channels holds one volren.Volume per channel, at least one$"):
        vr.Channels([])


@pytest.mark.timeout(60)
def test_a_sequence_refuses_options_its_frames_cannot_take_when_loaded(tmp_path):
    """``vr.load("sim_####.npy", channel_colors=...)`` of one-channel frames is refused by ``load`` itself, as for one
    file, not later at the first frame asked for."""
    for i in range(2):
        np.save(tmp_path / f"sim_{i:04d}.npy", ball(8 + 6 * i).astype(np.float32))
    with pytest.raises(VolrenError, match=r"load: channel_colors= apply to a multi-channel file only"):
        vr.load(tmp_path / "sim_####.npy", channel_colors="green")


@pytest.mark.timeout(60)
def test_a_sequence_is_indexed_by_frame_numbers_only(tmp_path):
    for i in range(2):
        np.save(tmp_path / f"sim_{i:04d}.npy", ball(8 + 6 * i).astype(np.float32))
    seq = vr.load(tmp_path / "sim_####.npy")
    for key, name in ((True, "bool"), (1.0, "float"), (slice(0, 1), "slice")):
        with pytest.raises(VolrenError, match=f"^a VolumeSequence is indexed by a frame number, got {name}$"):
            seq[key]
