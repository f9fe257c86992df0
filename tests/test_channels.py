"""Multi-channel volumes (issue 21 item 4): per-channel colour and opacity, composed additively
(`volren.render.compositing.channels`), read from (C, Z, Y, X) arrays and multi-channel TIFF."""

from __future__ import annotations

import numpy as np
import pytest

from volren.camera import Camera
from volren.cli import main
from volren.data.loaders import load_volume
from volren.errors import VolrenError
from volren.metrics import psnr
from volren.render import METHODS
from volren.render.compositing.channels import AdditiveChannels, channel_volumes, parse_channel_colors
from volren.scene import Environment, Scene

N = 24
GREEN, MAGENTA = (0.0, 1.0, 0.0), (1.0, 0.0, 1.0)


def blobs(left: float = 7.0, right: float = 16.0) -> list[np.ndarray]:
    """Channel 0 a blob on the left (x index ``left``), channel 1 on the right; they overlap in the middle."""
    z, y, x = np.mgrid[0:N, 0:N, 0:N].astype(np.float32)
    return [np.exp(-((x - cx) ** 2 + (y - N / 2) ** 2 + (z - N / 2) ** 2) / 18.0) for cx in (left, right)]


def channel_scene(channels, colors=(GREEN, MAGENTA)) -> Scene:
    return Scene(channel_volumes(channels, np.eye(4), colors=colors, opacity=[3.0]), lights=(),
                 environment=Environment((0.0, 0.0, 0.0)))


def view() -> Camera:
    return Camera(position=(0.0, 0.0, 3.2), look_at=(0.0, 0.0, 0.0), fov_y=40.0, width=48, height=32)


def renderer(method: str, count: int) -> AdditiveChannels:
    cls, config_cls = METHODS[method]
    options = {"samples": 64} if method == "reference" else {"samples": 64, "light_samples": 16}
    options = options if method in AdditiveChannels.METHODS else {}
    return AdditiveChannels(lambda: cls(config_cls(**options), device="cpu"), count)


def test_two_channels_show_their_colours_and_add_up_to_the_separate_renders():
    scene = channel_scene(blobs())
    image = renderer("dssrm", 2).render(scene, [view()]).images[0]
    row = image[16]
    left, right = row[16], row[30]  # the blobs' centres project to about columns 18 and 28
    assert left[1] > 5 * left[0] and left[3] > 0.3  # green
    assert right[0] > 5 * right[1] and right[2] > 5 * right[1] and right[3] > 0.3  # magenta
    alone = [renderer("dssrm", 1).render(Scene((v,), lights=(), environment=scene.environment), [view()]).images[0]
             for v in scene.volumes]
    for im, color in zip(alone, (GREEN, MAGENTA), strict=True):  # emission in proportion to extinction: c * alpha
        np.testing.assert_allclose(im[..., :3], im[..., 3:] * np.array(color, np.float32), atol=2e-6)
    np.testing.assert_allclose(image[..., :3], alone[0][..., :3] + alone[1][..., :3], atol=1e-6)
    np.testing.assert_allclose(image[..., 3], 1 - (1 - alone[0][..., 3]) * (1 - alone[1][..., 3]), atol=1e-6)
    overlap = row[24]
    assert overlap[1] > 0.05 and overlap[0] > 0.05  # both channels reach the middle: the sum is tested there too


def test_channel_order_does_not_matter():
    a, b = blobs(9.0, 14.0)  # strongly overlapping: an "over" composition would depend on the order
    image = renderer("dssrm", 2).render(channel_scene([a, b], (GREEN, MAGENTA)), [view()]).images[0]
    swapped = renderer("dssrm", 2).render(channel_scene([b, a], (MAGENTA, GREEN)), [view()]).images[0]
    np.testing.assert_allclose(image, swapped, atol=1e-6)


@pytest.mark.parametrize("method", ["cmsrm", "cacrm"])
def test_channel_methods_agree_with_the_reference(method):
    scene = channel_scene(blobs())
    truth = renderer("reference", 2).render(scene, [view()]).images[0]
    image = renderer(method, 2).render(scene, [view()]).images[0]
    assert psnr(image[..., :3], truth[..., :3]) > 30.0


def test_channel_mip_is_each_channels_grey_mip_in_its_colour_added():
    """MIP of channels: each channel's own MIP (grey, its maximum P) tinted by its colour, summed (napari's additive
    MIP); alpha 1 - prod(1 - P_c). Before, the channels were added grey: the colours were dropped."""
    cls, config_cls = METHODS["dssrm"]
    scene = channel_scene(blobs())
    image = AdditiveChannels(lambda: cls(config_cls(samples=64, mode="mip"), device="cpu"), 2).render(
        scene, [view()]).images[0]
    alone = [cls(config_cls(samples=64, mode="mip"), device="cpu").render(
        Scene((v,), lights=(), environment=scene.environment), [view()]).images[0] for v in scene.volumes]
    for grey in alone:
        np.testing.assert_allclose(grey[..., 0], grey[..., 3], atol=1e-6)  # each alone: grey, RGB = alpha = P
    want = sum(grey[..., :3] * np.array(color, np.float32) for grey, color in zip(alone, (GREEN, MAGENTA), strict=True))
    np.testing.assert_allclose(image[..., :3], want, atol=1e-6)
    np.testing.assert_allclose(image[..., 3], 1 - (1 - alone[0][..., 3]) * (1 - alone[1][..., 3]), atol=1e-6)


def test_channel_iso_is_refused():
    cls, config_cls = METHODS["dssrm"]
    with pytest.raises(VolrenError, match=r"mode iso .* would be black"):
        AdditiveChannels(lambda: cls(config_cls(mode="iso"), device="cpu"), 2)
    channels = renderer("dssrm", 2)
    with pytest.raises(VolrenError, match=r"mode iso .* would be black"):
        channels.config = config_cls(mode="iso")


def test_vpt_and_fog_are_refused():
    for method in ("vpt", "fog"):
        with pytest.raises(VolrenError, match="multi-channel volume renders with"):
            renderer(method, 2)


def test_channel_colours_parse_names_and_triples():
    assert parse_channel_colors("green,magenta") == (GREEN, MAGENTA)
    assert parse_channel_colors("1,0,0;0,0.5,1") == ((1.0, 0.0, 0.0), (0.0, 0.5, 1.0))
    assert parse_channel_colors("red;0,0,1") == ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    with pytest.raises(VolrenError, match="--channel-colors"):
        parse_channel_colors("green;purple")
    with pytest.raises(VolrenError, match="--channel-colors gives 1"):
        channel_volumes(blobs(), np.eye(4), colors=[GREEN])


def test_opacity_is_optical_depth_across_the_longest_side():
    """k = 3 across a 2 um box: sigma_t = 3 / 2e-6 per metre, emission the colour times it."""
    to_world = np.diag([1e-6, 0.5e-6, 0.5e-6, 1.0])  # a micrometre box is a valid placement
    vols = channel_volumes(blobs(), to_world, opacity=[3.0, 1.0])
    assert vols[0].density_scale == pytest.approx(1.5e6) and vols[1].density_scale == pytest.approx(0.5e6)
    assert vols[1].emission == pytest.approx((0.5e6, 0.0, 0.5e6))  # default palette: green, magenta
    assert vols[0].albedo == (0.0, 0.0, 0.0)


def test_cczyx_npy_channels_are_normalised_each_by_its_own_range(tmp_path):
    data = np.zeros((2, 4, 5, 6), np.uint16)
    data[0, 1, 2, 3], data[1, 2, 3, 4] = 3000, 1000  # 12-bit microscopy channels of different gain
    np.save(tmp_path / "c.npy", data)
    loaded = load_volume(tmp_path / "c.npy")
    assert len(loaded.channels) == 2 and loaded.density is loaded.channels[0]
    assert loaded.channels[0][1, 2, 3] == 1.0 and loaded.channels[1][2, 3, 4] == 1.0
    assert loaded.channels[0].sum() == 1.0 and loaded.channels[1].sum() == 1.0
    np.save(tmp_path / "t.npy", np.zeros((20, 4, 5, 6), np.float32))
    with pytest.raises(VolrenError, match="1 to 16 channels"):
        load_volume(tmp_path / "t.npy")


def test_imagej_hyperstack_zcyx_reads_its_channels(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    data = np.zeros((5, 2, 8, 9), np.uint16)  # ImageJ order: z, c, y, x
    data[1, 0, 2, 3] = 500
    data[3, 1, 6, 7] = 900
    tifffile.imwrite(tmp_path / "h.tif", data, imagej=True, metadata={"axes": "ZCYX"})
    loaded = load_volume(tmp_path / "h.tif")
    assert len(loaded.channels) == 2 and loaded.density.shape == (5, 8, 9)
    for c in range(2):  # each channel where a grey stack of that channel alone puts it (the page orientation)
        tifffile.imwrite(tmp_path / f"g{c}.tif", data[:, c], imagej=True, metadata={"axes": "ZYX"})
        grey = load_volume(tmp_path / f"g{c}.tif")
        np.testing.assert_array_equal(np.argwhere(loaded.channels[c]), np.argwhere(grey.density))
        assert loaded.channels[c].sum() == 1.0  # its own range: 500 and 900 both map to 1
    np.testing.assert_allclose(loaded.to_world, grey.to_world)


@pytest.fixture(scope="module")
def two_channel_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("chan") / "two.npy"
    np.save(path, np.stack(blobs()))
    return path


def cli(*args: str) -> int:
    return main(["render", *args, "--views", "mono", "--width", "32", "--height", "24"])


def test_cli_renders_a_two_channel_volume_in_its_colours(two_channel_file, tmp_path):
    out = tmp_path / "out"
    assert cli("--volume", str(two_channel_file), "--channel-colors", "1,0,0;0,0,1", "--samples", "32",
               "--out", str(out), "--save-linear") == 0
    image = np.load(out / "view0.npy")
    left, right = image[:, :16, :3].sum(axis=(0, 1)), image[:, 16:, :3].sum(axis=(0, 1))
    assert left[0] > 3 * left[2] and right[2] > 3 * right[0] and left[1] == right[1] == 0.0


def test_cli_mip_keeps_each_channels_colour(two_channel_file, tmp_path, capsys):
    """``--mode mip`` on two channels: where channel 0 (green, left) is brightest the pixel is green, where channel 1
    (magenta, right) is, magenta; nothing on stderr. Before, the picture was grey."""
    out = tmp_path / "out"
    assert main(["render", "--volume", str(two_channel_file), "--mode", "mip", "--views", "mono", "--width", "64",
                 "--height", "48", "--samples", "64", "--out", str(out), "--save-linear"]) == 0
    assert capsys.readouterr().err == ""
    image = np.load(out / "view0.npy")
    green = image[np.unravel_index(np.argmax(image[..., 1]), image.shape[:2])]
    magenta = image[np.unravel_index(np.argmax(image[..., 0]), image.shape[:2])]
    assert green[1] > 0.8 and green[0] < 0.05 * green[1] and green[2] < 0.05 * green[1], green
    assert magenta[0] > 0.8 and magenta[2] == pytest.approx(magenta[0]) and magenta[1] < 0.05 * magenta[0], magenta


@pytest.mark.parametrize(("flags", "message"), [
    (["--mode", "iso"], "--mode iso draws a lit, opaque surface; the multi-channel --volume {file} glows unlit in its "
     "channel colours, so its surfaces would be black: use --mode dvr, mip or mida"),
    (["--mode", "mip", "--channel-opacity", "2"], "--channel-opacity would do nothing with --mode mip: each channel "
     "shows its maximum in its colour, whatever its opacity"),
])
def test_cli_refuses_iso_on_channels_and_opacity_with_mip_in_one_line(two_channel_file, tmp_path, capsys, flags,
                                                                       message):
    """``--mode iso`` on channels rendered a black image with exit 0; now one line naming both flags, exit 2."""
    assert cli("--volume", str(two_channel_file), *flags, "--out", str(tmp_path / "o")) == 2
    assert capsys.readouterr().err.splitlines() == [f"volren: error: {message.format(file=two_channel_file)}"]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("flags", "message"), [
    (["--channel-colors", "green"], "gives 1 colour"),
    (["--light-dir", "0,-1,0"], "--light-dir would do nothing"),
    (["--density-scale", "3"], "--density-scale would do nothing"),
    (["--method", "vpt"], "not with method 'vpt'"),
    (["--sphere", "0,0,0,0.2"], "without opaque geometry"),
    (["--level", "1"], "apply to .zarr only"),
])
def test_cli_refuses_what_a_channel_volume_cannot_take(two_channel_file, tmp_path, capsys, flags, message):
    assert cli("--volume", str(two_channel_file), *flags, "--out", str(tmp_path / "o")) == 2
    assert message in capsys.readouterr().err


def test_cli_refuses_channel_flags_for_one_channel(tmp_path, capsys):
    np.save(tmp_path / "one.npy", blobs()[0])
    assert cli("--volume", str(tmp_path / "one.npy"), "--channel-colors", "green", "--out", str(tmp_path / "o")) == 2
    assert "multi-channel --volume only" in capsys.readouterr().err
    assert cli("--scene", "cloud", "--resolution", "64", "--channel-opacity", "2", "--out", str(tmp_path / "o")) == 2
    assert "multi-channel --volume only" in capsys.readouterr().err


@pytest.mark.parametrize("method", ["dssrm", "cacrm"])
def test_a_second_scene_given_to_the_same_renderer_shows_its_own_channels(method):
    """An animated multi-channel sequence renders each frame's scene with one renderer: frame 1 (the blobs moved)
    shows frame 1's channels, as a fresh renderer shows them, not frame 0's again; and a scene with the same
    channels reused (the same object) stays bit-identical."""
    first, second = channel_scene(blobs()), channel_scene(blobs(left=12.0, right=20.0))
    r = renderer(method, 2)
    a = r.render(first, [view()]).images[0]
    b = r.render(second, [view()], frame=1).images[0]
    fresh = renderer(method, 2).render(second, [view()], frame=1).images[0]
    np.testing.assert_allclose(b, fresh, atol=1e-6)
    assert np.abs(b - a).max() > 0.1  # the blobs did move
    np.testing.assert_array_equal(r.render(second, [view()], frame=2).images[0], b)
