"""The ``volren`` command line, run in-process through ``volren.cli.main`` (plus one run of the installed script).

Every render is tiny (24x16 pixels, 64^3 built-ins, V 16, L 8, light grid 16, CPU), so the whole file takes seconds.

Output is captured at the file-descriptor level (``capfd``, a superset of ``capsys``), so text that Warp's native
library writes to fd 2 counts as stderr too. Python warnings raised during a call are recorded as well: pytest would
swallow them, but a real ``volren`` run prints them on stderr, so a warning is an extra stderr line.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import re
import shutil
import signal
import subprocess
import sys
import threading
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import nibabel as nib
import nrrd
import numpy as np
import pytest
import warp as wp

from conftest import DEVICE
from volren.cli import main
from volren.device import init_warp
from volren.errors import VolrenError

BASE = ("--width", "24", "--height", "16", "--samples", "16", "--light-samples", "8", "--device", "cpu")
"""Tiny settings every method takes (render's built-in scenes default to 64 voxels per axis; --volume and fog
scenes refuse --resolution)."""
TINY = (*BASE, "--light-grid", "16")
"""Tiny settings for dssrm and demo (reference takes no --light-grid)."""
W, H = 24, 16
SCENES = ("smoke", "cloud", "phantom", "multi")
LISTED_SCENES = (*SCENES, "instances", "instances-overlap", "smoke-floor", "fire")
"""every built-in volume scene in `volren scenes` order (SCENES: those rendered one by one here)"""
FOG_SCENE_NAMES = ("hall", "courtyard", "dynamic")
COUNTERS = ("density_samples", "light_samples", "lightmap_lookups", "rays", "shared_samples", "interleaved_samples",
            "shadow_rays", "shadow_voxels", "box_tests", "tile_box_tests", "bvh_queries", "ao_bvh_queries",
            "joint_rays", "skipped_steps", "light_skipped", "jumped_steps", "idle_runs")
GARBAGE = b"this is not a volume \x00\x01\x02\xff" * 8


# ---------------------------------------------------------------- helpers


@dataclass
class Result:
    code: int
    out: str
    err: str
    warnings: list[str]


def run(capfd: pytest.CaptureFixture[str], *argv: object) -> Result:
    """``main(argv)``; an exception escaping it (a traceback for the user) fails the test with its type and text."""
    capfd.readouterr()
    # what earlier tests left for the garbage collector (a socket of a server test: a ResourceWarning) is collected
    # here, not during the call, whose own warnings are recorded
    gc.collect()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = main([str(a) for a in argv])
        except TimeoutError:  # from deadline(): the call took too long, which is reported as such
            raise
        except Exception as exc:  # any escape is the bug being reported
            out, err = capfd.readouterr()
            pytest.fail(f"main() raised {type(exc).__name__}: {exc} (the user sees a traceback)\nstderr: {err}")
    out, err = capfd.readouterr()
    return Result(code, out, err, [f"{w.category.__name__}: {w.message}" for w in caught])


PROGRESS_LINE = re.compile(r"volren: .+: (\d+% \(\d+/\d+ \w+\), \d+ s, about (\d+|nan) s left|case \d+ done .+, \d+ s)")
"""`volren.progress`'s plain lines: a run of several frames prints ten, a bench suite one per measured case"""


def ok(capfd: pytest.CaptureFixture[str], *argv: object) -> Result:
    """Run and require success: exit 0, nothing on stderr but progress lines, no warnings, no traceback."""
    r = run(capfd, *argv)
    assert r.code == 0, f"exit {r.code}; stderr: {r.err}"
    assert "Traceback" not in r.out + r.err
    assert all(PROGRESS_LINE.fullmatch(line) for line in r.err.splitlines()), r.err
    assert not r.warnings, r.warnings
    return r


def render(capfd: pytest.CaptureFixture[str], out: Path, *extra: object, method: str = "dssrm") -> Result:
    settings = TINY if method in ("dssrm", "cmsrm", "cacrm") else BASE
    return ok(capfd, "render", *settings, "--method", method, "--out", out, *extra)


def assert_error(capfd: pytest.CaptureFixture[str], argv: list[object], *fragments: str,
                 no_out: Path | None = None) -> str:
    """Exit 2 with exactly one stderr line ``volren: error: ...`` holding every fragment (case-insensitive), nothing
    on stdout, no warning, no traceback; with ``no_out``, that output folder must not have been created."""
    r = run(capfd, *argv)
    assert "Traceback" not in r.out + r.err, r.err
    assert r.code == 2, f"exit {r.code}; stdout: {r.out!r}; stderr: {r.err!r}"
    lines = [line for line in r.err.splitlines() if not PROGRESS_LINE.fullmatch(line)]  # the frames before it
    assert len(lines) == 1, f"expected one stderr line, got {r.err!r}"
    line = lines[0]
    assert line.startswith("volren: error: "), line
    assert len(line) > len("volren: error: ") + 5, line
    for fragment in fragments:
        assert fragment.lower() in line.lower(), f"{fragment!r} not in {line!r}"
    assert r.out == "", r.out
    assert not r.warnings, f"a real run would also print {r.warnings}"
    if no_out is not None:
        assert not no_out.exists(), f"bad input created {no_out}"
    return line


def render_error(capfd: pytest.CaptureFixture[str], tmp_path: Path, extra: list[object], *fragments: str,
                 early: bool = True) -> str:
    """A bad ``render``; ``early``: refused before the output folder is created (input checks, not render-time)."""
    out = tmp_path / "out"
    return assert_error(capfd, ["render", *TINY, "--out", out, *extra], *fragments, no_out=out if early else None)


def stats_of(folder: Path) -> dict:
    return json.loads((folder / "stats.json").read_text())


def png(path: Path) -> np.ndarray:
    return iio.imread(path)


def has_cuda() -> bool:
    init_warp()
    return wp.get_cuda_device_count() > 0


@contextlib.contextmanager
def deadline(seconds: int) -> Iterator[None]:
    """Fail (TimeoutError) if the block runs longer than ``seconds`` (SIGALRM; the main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("SIGALRM needs the main thread")

    def expire(signum: int, frame: object) -> None:
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def asymmetric_density() -> np.ndarray:
    """float32 [z, y, x] = (8, 16, 24) with values in (0, 1] that vary along every axis: any axis mix-up changes the
    shape or the image. Sizes are multiples of 8 because Warp writes NanoVDB grids in 8^3 tiles whose every voxel is
    active, so other sizes come back padded with background voxels (documented in test_data.py)."""
    return (((np.arange(8 * 16 * 24).reshape(8, 16, 24) * 7) % 37 + 1) / 37).astype(np.float32)


def write_npy(path: Path, a: np.ndarray) -> Path:
    np.save(path, a)
    return path


# ---------------------------------------------------------------- end to end: demo, render


def test_demo_writes_stereo_pair_and_stats(capfd, tmp_path: Path) -> None:
    out = tmp_path / "demo"
    r = ok(capfd, "demo", *TINY, "--resolution", "64", "--out", out)
    assert sorted(p.name for p in out.iterdir()) == ["stats.json", "stereo.png", "view0.png", "view1.png"]
    for name in ("view0.png", "view1.png"):
        assert png(out / name).shape == (H, W, 3)
    assert png(out / "stereo.png").shape == (H, 2 * W, 3)
    stereo = png(out / "stereo.png")
    np.testing.assert_array_equal(stereo[:, :W], png(out / "view0.png"))
    np.testing.assert_array_equal(stereo[:, W:], png(out / "view1.png"))
    for name in ("view0.png", "view1.png", "stereo.png", "stats.json"):
        assert name in r.out
    assert "ms per pass" in r.out and "march" in r.out
    assert "dssrm on cpu" in r.out
    stats = stats_of(out)
    assert stats["frames"][0]["method"] == "dssrm"
    assert stats["frames"][0]["settings"]["views"] == 2


def test_stats_json_content(capfd, tmp_path: Path) -> None:
    out = tmp_path / "r"
    r = render(capfd, out)
    stats = stats_of(out)
    assert stats["scene"] == "smoke"
    assert len(stats["frames"]) == 1
    frame = stats["frames"][0]
    assert frame["index"] == 0
    assert frame["device"] == "cpu"
    assert frame["method"] == "dssrm"
    settings = frame["settings"]
    assert settings["samples"] == 16
    assert settings["light_samples"] == 8
    assert settings["light_grid"] == 16
    assert settings["views"] == 2
    assert settings["resolution"] == [[W, H], [W, H]]
    times = frame["times_ms"]
    assert {"light_map", "march", "readback"} <= set(times)
    assert all(isinstance(v, int | float) and v >= 0 and math.isfinite(v) for v in times.values())
    counters = frame["counters"]
    assert set(counters) == set(COUNTERS)
    for key, value in counters.items():
        assert type(value) is int and value >= 0, (key, value)
    assert counters["density_samples"] > 0
    assert 0 < counters["rays"] <= 2 * W * H
    # stdout repeats the counters
    for key in COUNTERS:
        assert key in r.out


def test_stats_json_records_the_given_command(capfd, tmp_path: Path) -> None:
    out = tmp_path / "r"
    render(capfd, out, "--views", "mono")
    command = stats_of(out)["command"]
    assert command.startswith("volren render "), command
    assert "--views mono" in command


def test_render_mono_writes_one_view(capfd, tmp_path: Path) -> None:
    out = tmp_path / "mono"
    render(capfd, out, "--views", "mono")
    assert sorted(p.name for p in out.iterdir()) == ["stats.json", "view0.png"]
    assert png(out / "view0.png").shape == (H, W, 3)
    assert stats_of(out)["frames"][0]["settings"]["views"] == 1


def test_render_three_views_on_an_arc(capfd, tmp_path: Path) -> None:
    out = tmp_path / "three"
    render(capfd, out, "--views", "3", "--save-linear")
    names = sorted(p.name for p in out.iterdir())
    assert names == ["contact.png", "stats.json", "view0.npy", "view0.png", "view1.npy", "view1.png", "view2.npy",
                     "view2.png"]
    settings = stats_of(out)["frames"][0]["settings"]
    assert settings["views"] == 3 and settings["resolution"] == [[W, H]] * 3
    images = [np.load(out / f"view{i}.npy") for i in range(3)]
    assert not np.array_equal(images[0], images[2])  # different viewpoints


def test_save_linear_writes_float32_rgba(capfd, tmp_path: Path) -> None:
    out = tmp_path / "lin"
    r = render(capfd, out, "--save-linear")
    for i in range(2):
        image = np.load(out / f"view{i}.npy")
        assert image.dtype == np.float32
        assert image.shape == (H, W, 4)
        assert np.isfinite(image).all()
        alpha = image[..., 3]
        assert alpha.min() >= 0 and alpha.max() <= 1
        assert alpha.max() > 0  # the smoke is visible
        assert image[..., :3].min() >= 0
        assert f"view{i}.npy" in r.out
    assert (out / "stereo.png").is_file()


def test_jittered_frames_are_kept_and_differ(capfd, tmp_path: Path) -> None:
    out = tmp_path / "seq"
    r = render(capfd, out, "--frames", "3", "--jitter", "--seed", "3", "--save-linear")
    for f in range(3):
        for name in ("view0.png", "view1.png", "stereo.png", "view0.npy", "view1.npy"):
            assert (out / f"frame{f:04d}_{name}").is_file(), name
    assert not (out / "view0.png").exists()
    stats = stats_of(out)
    assert [f["index"] for f in stats["frames"]] == [0, 1, 2]
    assert all(f["settings"]["jitter"] is True for f in stats["frames"])
    frames = [np.load(out / f"frame{f:04d}_view0.npy") for f in range(3)]
    assert not np.array_equal(frames[0], frames[1])
    assert not np.array_equal(frames[1], frames[2])
    assert "3 frame(s)" in r.out


def test_frames_without_jitter_repeat_exactly(capfd, tmp_path: Path) -> None:
    out = tmp_path / "seq"
    render(capfd, out, "--frames", "2", "--views", "mono", "--save-linear")
    np.testing.assert_array_equal(np.load(out / "frame0000_view0.npy"), np.load(out / "frame0001_view0.npy"))


def test_reference_method(capfd, tmp_path: Path) -> None:
    out = tmp_path / "ref"
    r = render(capfd, out, method="reference")
    assert "reference on cpu" in r.out
    frame = stats_of(out)["frames"][0]
    assert frame["method"] == "reference"
    assert frame["settings"]["samples"] == 16 and frame["settings"]["light_samples"] == 8
    assert "march" in frame["times_ms"]
    assert set(frame["counters"]) == set(COUNTERS)
    assert frame["counters"]["density_samples"] > 0
    assert (out / "stereo.png").is_file()


@pytest.mark.parametrize(("extra", "scene_name"), [
    (["--scene", "cloud"], "cloud"),
    (["--scene", "phantom"], "phantom"),
    (["--scene", "multi", "--count", "4"], "multi"),
])
def test_builtin_scenes_render(capfd, tmp_path: Path, extra: list[str], scene_name: str) -> None:
    out = tmp_path / "s"
    render(capfd, out, "--views", "mono", "--save-linear", *extra)
    stats = stats_of(out)
    assert stats["scene"].startswith(scene_name)
    assert stats["frames"][0]["counters"]["density_samples"] > 0
    assert np.load(out / "view0.npy")[..., 3].max() > 0


# ---------------------------------------------------------------- every loader through --volume


def write_volume(path: Path, a: np.ndarray) -> None:
    """Write the [z, y, x] grid ``a`` in the format named by the file's extension, as each format stores it."""
    xyz = np.ascontiguousarray(a.transpose(2, 1, 0))  # NRRD, NIfTI and NanoVDB index (x, y, z)
    name = path.name
    if name.endswith(".npy"):
        np.save(path, a)
    elif name.endswith(".npz"):
        np.savez(path, density=a)
    elif name.endswith((".nrrd", ".nhdr")):
        nrrd.write(str(path), np.asfortranarray(xyz), index_order="F")
    elif name.endswith((".nii", ".nii.gz")):
        # placed as a .npy is (cubic voxels, longest side 2 m, centred): RAS -x, S, A are world x, y, z
        n = np.array(xyz.shape, dtype=float)
        affine = np.eye(4)
        affine[:3, :3] = 2.0 / n.max() * np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
        affine[:3, 3] = -affine[:3, :3] @ (n - 1) / 2
        image = nib.Nifti1Image(xyz, affine)
        image.header.set_xyzt_units("meter")
        nib.save(image, path)
    elif name.endswith(".nvdb"):
        init_warp()
        wp.Volume.load_from_numpy(xyz, bg_value=0.0, device=DEVICE).save_to_nvdb(str(path))
    else:
        raise AssertionError(name)


LOADERS = ["vol.npy", "vol.npz", "vol.nrrd", "vol.nhdr", "vol.nii", "vol.nii.gz", "vol.nvdb"]


def _linear_render(capfd, out: Path, *volume_args: object) -> np.ndarray:
    render(capfd, out, "--views", "mono", "--save-linear", "--volume", *volume_args)
    return np.load(out / "view0.npy")


@pytest.mark.parametrize("name", LOADERS)
def test_volume_formats_render_like_npy(capfd, tmp_path: Path, name: str) -> None:
    a = asymmetric_density()
    reference = _linear_render(capfd, tmp_path / "ref", write_npy(tmp_path / "reference.npy", a))
    assert reference[..., 3].max() > 0
    path = tmp_path / name
    write_volume(path, a)
    image = _linear_render(capfd, tmp_path / "out", path)
    atol = 1e-5 if ".nii" in name else 1e-6  # NIfTI stores its affine (2 / 24 m voxels) in float32
    np.testing.assert_allclose(image, reference, rtol=0, atol=atol)
    assert stats_of(tmp_path / "out")["scene"]


def test_raw_volume_with_shape_and_dtype(capfd, tmp_path: Path) -> None:
    a = asymmetric_density()
    u8 = np.round(a * 255).astype(np.uint8)
    u8.tofile(tmp_path / "vol.raw")  # C order of [z, y, x]: x varies fastest
    image = _linear_render(capfd, tmp_path / "out", tmp_path / "vol.raw", "--shape", "24,16,8", "--dtype", "uint8")
    reference = _linear_render(capfd, tmp_path / "ref", write_npy(tmp_path / "ref.npy", u8.astype(np.float32) / 255))
    np.testing.assert_allclose(image, reference, rtol=1e-5, atol=1e-6)


def test_axis_order_matters(capfd, tmp_path: Path) -> None:
    """The loader comparisons above would catch an axis mix-up: a transposed grid renders differently."""
    a = asymmetric_density()
    reference = _linear_render(capfd, tmp_path / "ref", write_npy(tmp_path / "a.npy", a))
    swapped = _linear_render(capfd, tmp_path / "t", write_npy(tmp_path / "t.npy", np.ascontiguousarray(a.transpose())))
    assert np.abs(swapped - reference).max() > 1e-3


# ---------------------------------------------------------------- material, light and output overrides


@pytest.fixture(scope="module")
def baseline(tmp_path_factory: pytest.TempPathFactory) -> np.ndarray:
    out = tmp_path_factory.mktemp("baseline")
    assert main(["render", *TINY, "--views", "mono", "--save-linear", "--out", str(out)]) == 0
    return np.load(out / "view0.npy")


def _mono(capfd, tmp_path: Path, *extra: object) -> tuple[np.ndarray, np.ndarray]:
    out = tmp_path / "o"
    render(capfd, out, "--views", "mono", "--save-linear", *extra)
    return np.load(out / "view0.npy"), png(out / "view0.png")


def test_density_scale_zero_is_empty(capfd, tmp_path: Path) -> None:
    image, pixels = _mono(capfd, tmp_path, "--density-scale", "0")
    assert np.all(image[..., 3] == 0)
    assert np.all(image[..., :3] == 0)
    assert np.all(pixels == pixels[0, 0])  # only the background


def test_albedo_zero_keeps_alpha_and_drops_scattering(capfd, tmp_path: Path, baseline: np.ndarray) -> None:
    image, _ = _mono(capfd, tmp_path, "--albedo", "0")
    np.testing.assert_allclose(image[..., 3], baseline[..., 3], atol=1e-6)
    assert np.all(image[..., :3] == 0)


def test_albedo_per_channel(capfd, tmp_path: Path) -> None:
    image, _ = _mono(capfd, tmp_path, "--albedo", "0.1,0.5,0.9")
    red, blue = image[..., 0].sum(), image[..., 2].sum()
    assert blue > red > 0


def test_emission_adds_light_not_opacity(capfd, tmp_path: Path, baseline: np.ndarray) -> None:
    image, _ = _mono(capfd, tmp_path, "--emission", "2")
    np.testing.assert_allclose(image[..., 3], baseline[..., 3], atol=1e-6)
    assert image[..., :3].sum() > baseline[..., :3].sum()


def test_no_light_and_no_ambient_is_black(capfd, tmp_path: Path, baseline: np.ndarray) -> None:
    image, _ = _mono(capfd, tmp_path, "--light-irradiance", "0", "--ambient", "0")
    assert np.all(image[..., :3] == 0)
    np.testing.assert_allclose(image[..., 3], baseline[..., 3], atol=1e-6)


@pytest.mark.parametrize("extra", [["--g", "0.8"], ["--g", "-0.5"], ["--light-dir", "0,1,0"],
                                   ["--light-irradiance", "1,2,3"], ["--ambient", "0.5"]])
def test_light_and_phase_overrides_change_the_image(capfd, tmp_path: Path, baseline: np.ndarray,
                                                    extra: list[str]) -> None:
    image, _ = _mono(capfd, tmp_path, *extra)
    assert np.isfinite(image).all()
    assert not np.allclose(image[..., :3], baseline[..., :3])
    np.testing.assert_allclose(image[..., 3], baseline[..., 3], atol=1e-6)  # opacity depends on density only


# Every vector option with negative components written the natural way (issue 13 item 4): flag -> (value, parsed).
NEGATIVE_VECTORS = {
    "--light-dir": ("-1,-1,0", (-1.0, -1.0, 0.0)),
    "--camera-pos": ("-2,1,3", (-2.0, 1.0, 3.0)),
    "--look-at": ("-.5,-1e-1,2E0", (-0.5, -0.1, 2.0)),
    "--up": ("-0,-1,0", (0.0, -1.0, 0.0)),
    "--mesh-translate": ("-1.5,0,-2.", (-1.5, 0.0, -2.0)),
    "--clip": ("-1,1,-0.5,1,-1,0", (-1.0, 1.0, -0.5, 1.0, -1.0, 0.0)),
    "--albedo": ("-1", (-1.0, -1.0, -1.0)),
    "--emission": ("-1,2,3", (-1.0, 2.0, 3.0)),
    "--light-irradiance": ("-3", (-3.0, -3.0, -3.0)),
    "--ambient": ("-0.25,0,0", (-0.25, 0.0, 0.0)),
    "--background": ("-1,-1,-1", (-1.0, -1.0, -1.0)),
    "--sphere": ("-1,0,-2,0.5", [(-1.0, 0.0, -2.0, 0.5)]),
    "--rect-light": ("-2,3,-4,1,1,5", [(-2.0, 3.0, -4.0, 1.0, 1.0, 5.0)]),
    "--spacing": ("-1,2e-3,3", (-1.0, 0.002, 3.0)),  # parsed; the loader refuses a non-positive spacing
}


def test_every_vector_option_takes_negative_components() -> None:
    from volren.cli import build_parser
    from volren.plan.argv import floats4, floats6, rgb, vec3

    parser = build_parser()
    render_parser = next(a for a in parser._actions if a.dest == "command").choices["render"]
    vector_flags = {a.option_strings[-1] for a in render_parser._actions if a.type in (vec3, floats4, floats6, rgb)}
    assert vector_flags == set(NEGATIVE_VECTORS), "a vector option is missing from NEGATIVE_VECTORS"
    for flag, (text, expected) in NEGATIVE_VECTORS.items():
        args = parser.parse_args(["render", flag, text, "--width", "-7", "--ground", "-1e-3"])
        assert getattr(args, flag[2:].replace("-", "_")) == expected, flag
        assert (args.width, args.ground) == (-7, -0.001)  # the following options are still options


def test_a_negative_number_list_does_not_hide_a_missing_value(capfd) -> None:
    assert_error(capfd, ["render", "--light-dir", "--width", "3"], "--light-dir", "expected one argument")
    assert_error(capfd, ["render", "--light-dir", "-1,-x,0"], "--light-dir", "'-1,-x,0' is not a list of numbers")


def test_light_dir_with_negative_components_renders(capfd, tmp_path: Path, baseline: np.ndarray) -> None:
    """The README's ``--light-dir -1,-1,0``: parsed as the direction, so the image equals the ``=`` spelling's."""
    image, _ = _mono(capfd, tmp_path, "--light-dir", "-1,-1,0")
    same, _ = _mono(capfd, tmp_path / "b", "--light-dir=-1,-1,0")
    np.testing.assert_array_equal(image, same)
    assert not np.allclose(image[..., :3], baseline[..., :3])


def test_background_shows_where_the_volume_is_transparent(capfd, tmp_path: Path) -> None:
    image, pixels = _mono(capfd, tmp_path, "--background", "1,0,0")
    empty = image[..., 3] == 0
    assert empty.any()
    assert np.all(pixels[empty] == (255, 0, 0))


def test_exposure_and_tonemaps_change_only_the_png(capfd, tmp_path: Path) -> None:
    base, base_png = _mono(capfd, tmp_path / "a")
    bright, bright_png = _mono(capfd, tmp_path / "b", "--exposure", "2")
    np.testing.assert_array_equal(bright, base)
    assert bright_png.astype(int).sum() > base_png.astype(int).sum()
    for tonemap in ("aces", "reinhard"):
        mapped, mapped_png = _mono(capfd, tmp_path / tonemap, "--tonemap", tonemap, "--exposure", "3")
        np.testing.assert_array_equal(mapped, base)
        assert not np.array_equal(mapped_png, base_png)


def test_environment_image(capfd, tmp_path: Path, baseline: np.ndarray) -> None:
    env = write_npy(tmp_path / "env.npy", np.full((8, 16, 3), 0.5, np.float32))
    image, _ = _mono(capfd, tmp_path, "--environment", env)
    assert image[..., :3].sum() > baseline[..., :3].sum()


# ---------------------------------------------------------------- scenes, compare, bench, help


def test_scenes_lists_builtins(capfd) -> None:
    r = ok(capfd, "scenes")
    names = [line.split()[0] for line in r.out.splitlines() if line.strip()]
    assert names == [*LISTED_SCENES, *FOG_SCENE_NAMES]


def _images(tmp_path: Path) -> tuple[Path, Path]:
    rng = np.random.default_rng(0)
    ref = rng.random((H, W, 4), dtype=np.float32)
    test = np.clip(ref + rng.normal(0, 0.05, ref.shape).astype(np.float32), 0, None)
    return write_npy(tmp_path / "ref.npy", ref), write_npy(tmp_path / "test.npy", test)


def _psnr(out: str) -> float:
    match = re.search(r"PSNR (\S+) dB", out)
    assert match, out
    return float(match.group(1))


def test_compare_prints_metrics_and_writes_default_heatmap(capfd, tmp_path: Path) -> None:
    ref, test = _images(tmp_path)
    r = ok(capfd, "compare", ref, test)
    assert "SSIM" in r.out and "FLIP" in r.out
    assert 0 < _psnr(r.out) < math.inf
    heatmap = tmp_path / "test_error.png"
    assert heatmap.is_file()
    assert str(heatmap.name) in r.out
    assert png(heatmap).shape == (H, W, 3)


def test_compare_heatmap_path(capfd, tmp_path: Path) -> None:
    ref, test = _images(tmp_path)
    heatmap = tmp_path / "new" / "folder" / "err.png"
    r = ok(capfd, "compare", ref, test, "--heatmap", heatmap)
    assert png(heatmap).shape == (H, W, 3)
    assert str(heatmap) in r.out
    assert not (tmp_path / "test_error.png").exists()


def test_compare_identical_files_gives_infinite_psnr(capfd, tmp_path: Path) -> None:
    ref, _ = _images(tmp_path)
    copy = tmp_path / "copy.npy"
    shutil.copy(ref, copy)
    r = ok(capfd, "compare", ref, copy)
    assert _psnr(r.out) == math.inf
    heat = png(tmp_path / "copy_error.png")
    assert np.all(heat == heat[0, 0])  # no error anywhere


def test_compare_reports_the_true_error_of_a_too_bright_image(capfd, tmp_path: Path) -> None:
    """Not clipped to the reference's peak: PSNR = 10 log10(peak^2 / mean((99 ref)^2)) over RGB."""
    ref_path, _ = _images(tmp_path)
    ref = np.load(ref_path)
    bright = write_npy(tmp_path / "bright.npy", ref * 100)
    rgb = ref[..., :3].astype(np.float64)
    expected = 10 * math.log10(rgb.max() ** 2 / np.mean((99 * rgb) ** 2))
    r = ok(capfd, "compare", ref_path, bright)
    assert _psnr(r.out) == pytest.approx(expected, abs=0.005)
    assert f"PSNR {expected:.2f} dB" in r.out and expected < -30


def test_compare_rendered_methods(capfd, tmp_path: Path) -> None:
    render(capfd, tmp_path / "ref", "--views", "mono", "--save-linear", method="reference")
    render(capfd, tmp_path / "test", "--views", "mono", "--save-linear")
    r = ok(capfd, "compare", tmp_path / "ref" / "view0.npy", tmp_path / "test" / "view0.npy")
    assert math.isfinite(_psnr(r.out))
    assert (tmp_path / "test" / "view0_error.png").is_file()


def test_bench_list(capfd) -> None:
    r = ok(capfd, "bench", "list")
    assert r.out.startswith("dssrm:")


def test_bench_dssrm_quick(capfd, tmp_path: Path) -> None:
    """About 4 s on 2 CPU cores."""
    r = ok(capfd, "bench", "dssrm", "--quick", "--device", "cpu", "--out", tmp_path)
    json_path, md_path = tmp_path / "dssrm-cpu-quick.json", tmp_path / "dssrm-cpu-quick.md"
    doc = json.loads(json_path.read_text())
    assert doc["suite"] == "dssrm" and doc["quick"] is True
    assert doc["machine"]["device"] == "cpu"
    assert doc["rows"]
    assert md_path.read_text().count("|") > 10
    assert str(json_path) in r.out and str(md_path) in r.out


def test_memory_estimate_closed_form() -> None:
    """Device buffers 40 B/px, 20 B/px host copies per frame, cube maps 6 S0^2 x 24 B per view and volume, three
    fog froxel grids of ceil(W/tile) ceil(H/tile) (slices + 1) x 16 B per view."""
    from volren.plan import render_parser
    from volren.plan.render import estimate_memory
    from volren.plan.scene import scene_from_args
    from volren.plan.views import views_from_args

    def estimate(*argv: str) -> int:
        args = render_parser().parse_args(["render", *TINY, *argv])
        return estimate_memory(args, scene_from_args(args), views_from_args(args), args.method)

    assert estimate("--frames", "3") == 2 * W * H * (40 + 3 * 20)  # stereo
    assert estimate("--views", "mono", "--method", "cmsrm", "--cube-size", "10") == W * H * 60 + 6 * 10**2 * 24
    assert (estimate("--views", "3", "--rig", "arc", "--method", "fog", "--slices", "4", "--froxel-size", "5")
            == 3 * W * H * 60 + 3 * 3 * (5 * 4 * 5) * 16)  # ceil(24 / 5) = 5, ceil(16 / 5) = 4


def test_a_render_that_cannot_fit_is_refused_with_the_figure_before_work(capfd, tmp_path: Path) -> None:
    """1024 views of 640x360 for 1000 frames: 1024 x 230400 px x (40 + 20 x 1000) B, on no machine's free memory."""
    need = 1024 * 640 * 360 * (40 + 20 * 1000) / 2**30
    render_error(capfd, tmp_path, ["--views", "1024", "--width", "640", "--height", "360", "--frames", "1000"],
                 f"1024 view(s) of 640x360 for 1000 frame(s) with dssrm needs {need:.1f} GiB but only")


def test_a_reader_that_leaves_early_gets_no_traceback() -> None:
    """``volren scenes | head -1``: stdout's reader is gone before volren writes; quiet exit 141 (as SIGPIPE)."""
    exe = [sys.executable, "-c", "import sys; from volren.cli import main; sys.exit(main(['scenes']))"]
    proc = subprocess.Popen(exe, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # long before volren has imported and written
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141
    assert err == ""


def test_help_exits_zero(capfd) -> None:
    try:
        code = main(["--help"])
    except SystemExit as exc:  # argparse exits after printing help
        code = exc.code
    out, err = capfd.readouterr()
    assert code in (0, None)
    assert "render" in out and "compare" in out
    assert err == ""


def _help(capfd, *argv: str) -> str:
    with pytest.raises(SystemExit) as done:
        main([*argv, "--help"])
    out, err = capfd.readouterr()
    assert done.value.code == 0 and err == ""
    return " ".join(out.split())  # argparse wraps lines at the terminal width


@pytest.mark.parametrize("command", ["demo", "render", "animate", "compare", "bench", "serve"])
def test_help_gives_every_option_a_default(capfd, command: str) -> None:
    """Issue 13 item 11: each option's help says its default (flags that are simply off excepted)."""
    from volren.cli import build_parser

    _help(capfd, command)  # it prints
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices[command]
    formatter = sub._get_formatter()
    options = [a for a in sub._actions if a.option_strings and a.nargs != 0]  # not --help or on/off flags
    assert options
    for action in options:
        assert "default" in formatter._get_help_string(action), action.option_strings


def test_help_shows_ranges_the_tf_format_and_usd_meshes(capfd) -> None:
    text = _help(capfd, "render")
    for fragment in ("--width WIDTH [px] in [1, 16384], width x height at most 67,108,864 pixels (default: 640)",
                     "--up UP x,y,z (default: 0,1,0)",
                     "--seed SEED random seed (jitter, scenes, viewers): an integer >= 0 (default: 0)",
                     "--exposure EXPOSURE PNG exposure in stops, in [-64, 64] (default: 0.0)",
                     "N in [1, 1024]", "in (0, 180)", "--mesh-scale MESH_SCALE scale applied to every --mesh (about "
                     "the origin), > 0 (default: 1.0)", "OFF, or USD (.usd .usda .usdc .usdz)",
                     '{"points": [{"position": u, "extinction": mu_t, "albedo": [r, g, b], "p_brdf": p}, ...]}'):
        assert fragment in text, fragment
    from volren.transfer import PRESETS

    assert f"a preset ({', '.join(PRESETS)})" in text


def test_console_script(tmp_path: Path) -> None:
    """The installed ``volren`` entry point: success and a user error, each without a traceback."""
    exe = shutil.which("volren", path=str(Path(sys.executable).parent)) or shutil.which("volren")
    if exe is None:
        pytest.skip("the volren console script is not installed")
    done = subprocess.run([exe, "scenes"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert "Traceback" not in done.stdout
    assert [line.split()[0] for line in done.stdout.splitlines()] == [*LISTED_SCENES, *FOG_SCENE_NAMES]
    bad = subprocess.run([exe, "render", "--device", "tpu"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert bad.returncode == 2
    assert bad.stdout == ""
    assert bad.stderr.splitlines() == [bad.stderr.strip()]
    assert bad.stderr.startswith("volren: error: ") and "tpu" in bad.stderr
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- bad input: one line, exit 2


BAD_RENDER_ARGS = {
    "width-0": (["--width", "0"], ["--width must lie in [1, 16384] pixels, got 0"]),
    "height-negative": (["--height", "-5"], ["--height must lie in [1, 16384] pixels, got -5"]),
    "image-too-large": (["--width", "100000", "--height", "100000"], ["--width must lie in [1, 16384] pixels"]),
    "height-too-large": (["--height", "16385"], ["--height must lie in [1, 16384] pixels, got 16385"]),
    "width-not-int": (["--width", "1e3"], ["--width", "1e3"]),
    "up-parallel": (["--camera-pos", "0,3,0", "--look-at", "0,0,0", "--up", "0,1,0"], ["parallel"]),
    "up-zero": (["--up", "0,0,0"], ["up"]),
    "camera-at-look-at": (["--camera-pos", "1,1,1", "--look-at", "1,1,1"], ["coincide"]),
    "camera-nan": (["--camera-pos", "nan,0,0"], ["camera position", "finite"]),
    "fov-0": (["--fov", "0"], ["fov", "180"]),
    "fov-180": (["--fov", "180"], ["fov", "180"]),
    "near-0": (["--near", "0"], ["near"]),
    "far-before-near": (["--near", "1", "--far", "0.5"], ["near", "far"]),
    "ipd-negative": (["--ipd", "-1"], ["ipd"]),
    "unknown-scene": (["--scene", "fog"], ["unknown scene", "fog", "smoke"]),
    "unknown-method": (["--method", "bogus"], ["unknown method", "bogus", "dssrm"]),
    "reference-no-light-grid": (["--method", "reference", "--jitter"], ["reference", "--jitter", "--light-grid"]),
    "unknown-device": (["--device", "tpu"], ["unknown device", "tpu"]),
    "samples-0": (["--samples", "0"], ["samples", "0"]),
    "samples-huge": (["--samples", "10000000000"], ["samples", "10000000000"]),
    "light-samples-negative": (["--light-samples", "-1"], ["light samples", "-1"]),
    "light-grid-1": (["--light-grid", "1"], ["light grid", "1"]),
    "light-grid-huge": (["--light-grid", "100000"], ["light grid", "100000"]),
    "frames-0": (["--frames", "0"], ["--frames", "0"]),
    "frames-not-int": (["--frames", "abc"], ["--frames", "abc"]),
    "views-0": (["--views", "0"], ["view", "0"]),
    "views-abc": (["--views", "abc"], ["--views", "abc"]),
    "views-negative": (["--views", "-1"], ["--views", "-1"]),
    "views-fraction": (["--views", "2.5"], ["--views", "2.5"]),
    "resolution-10": (["--resolution", "10"], ["resolution", "10"]),
    "resolution-5000": (["--resolution", "5000"], ["resolution", "5000"]),
    "multi-count-5": (["--scene", "multi", "--count", "5"], ["count", "5"]),
    "count-without-multi": (["--scene", "cloud", "--count", "4"], ["--count applies to --scene multi, instances, "
                                                                   "instances-overlap only, not to scene 'cloud'"]),
    "seed-negative": (["--seed", "-1"], ["--seed must be an integer >= 0, got -1"]),
    # issue 22.7: flags that would do nothing, and ranges --help gives, refused before any work
    "spacing-without-volume": (["--spacing", "1,1,1"], ["built-in scenes ignore --spacing"]),
    "units-dtype-without-volume": (["--units", "mm", "--dtype", "uint8"], ["ignore --dtype, --units"]),
    "shape-without-volume": (["--shape", "4,4,4"], ["built-in scenes ignore --shape"]),
    "mesh-alpha-without-mesh": (["--mesh-alpha", "0.5"], ["--mesh-alpha: there is no --mesh"]),
    "mesh-scale-without-mesh": (["--mesh-scale", "2"], ["--mesh-scale: there is no --mesh"]),
    "mesh-translate-without-mesh": (["--mesh-translate", "0,1,0"], ["--mesh-translate: there is no --mesh"]),
    "ipd-without-stereo": (["--views", "mono", "--ipd", "0.1"], ["--ipd", "--views mono has none"]),
    "ipd-range-without-stereo": (["--views", "3", "--ipd", "20"], ["--ipd must lie in [0, 10) m, got 20"]),
    "background-negative": (["--background", "-1"], ["--background must be >= 0", "-1,-1,-1"]),
    "pixels-over-cap": (["--width", "16000", "--height", "16000"], ["--width x --height", "67,108,864"]),
    "out-empty": (["--out", ""], ["--out", "empty"]),
    "fog-density-scale": (["--method", "fog", "--scene", "hall", "--density-scale", "2"],
                          ["fog scene 'hall'", "--density-scale would do nothing"]),
    "fog-albedo": (["--method", "fog", "--scene", "courtyard", "--albedo", "0.5"], ["--albedo would do nothing"]),
    "light-dir-two-numbers": (["--light-dir", "1,2"], ["--light-dir", "1,2"]),
    "light-dir-zero": (["--light-dir", "0,0,0"], ["light direction", "zero"]),
    "albedo-not-numbers": (["--albedo", "a,b,c"], ["--albedo", "a,b,c"]),
    "albedo-two-numbers": (["--albedo", "1,2"], ["--albedo", "1,2"]),
    "albedo-above-1": (["--albedo", "1.5"], ["albedo", "1.5"]),
    "albedo-nan": (["--albedo", "nan"], ["albedo"]),
    "g-1": (["--g", "1.0"], ["g", "(-1, 1)"]),
    "g-nan": (["--g", "nan"], ["g", "nan"]),
    "density-scale-negative": (["--density-scale", "-1"], ["density_scale", "-1"]),
    "density-scale-inf": (["--density-scale", "inf"], ["density_scale", "inf"]),
    "emission-negative": (["--emission", "-1"], ["emission"]),
    "irradiance-negative": (["--light-irradiance", "-1"], ["irradiance"]),
    "irradiance-inf": (["--light-irradiance", "inf"], ["irradiance"]),
    "ambient-negative": (["--ambient", "-1"], ["radiance"]),
    "background-nan": (["--background", "nan"], ["background"]),
    "shape-two-numbers": (["--shape", "5,4"], ["--shape", "5,4"]),
    "unknown-option": (["--bogus-option"], ["unrecognized arguments", "--bogus-option"]),
    # issue 13 item 10: every message names the flag and what is wrong
    "unknown-scene-lists-all": (["--scene", "tornado"], ["--scene: unknown scene 'tornado': choose from smoke, cloud, "
                                                         "phantom, multi, instances, instances-overlap, smoke-floor, "
                                                         "fire, hall, courtyard, dynamic"]),
    "mesh-scale-0": (["--mesh-scale", "0"], ["--mesh-scale must be a positive number, got 0"]),
    "mesh-scale-negative": (["--mesh-scale", "-2"], ["--mesh-scale must be a positive number, got -2"]),
    "rig-with-stereo": (["--rig", "wander", "--views", "stereo"], ["--rig wander places N viewers, not --views "
                                                                   "stereo"]),
    "rig-with-default-views": (["--rig", "arc"], ["--rig arc", "--views stereo"]),
    "overlap-without-rig": (["--views", "3", "--overlap", "0.2"], ["--overlap needs --rig overlap"]),
    # refused before the file is read (it does not exist): the file sets its own voxels
    "resolution-with-volume": (["--volume", "missing.npy", "--resolution", "128"],
                               ["--resolution applies to built-in volume scenes only; --volume's file sets its own "
                                "voxels"]),
    **{f"resolution-with-{name}": (["--method", "fog", "--scene", name, "--resolution", "64"],
                                   [f"--resolution applies to built-in volume scenes only, not to fog scene '{name}'"])
       for name in FOG_SCENE_NAMES},
}


LATE_CHECKS = {"light-grid-1", "light-grid-huge"}
"""Checked when the scene is uploaded, just after the (empty) output folder is created: cheap, so accepted."""


@pytest.mark.parametrize("case", list(BAD_RENDER_ARGS))
def test_bad_render_argument(capfd, tmp_path: Path, case: str) -> None:
    extra, fragments = BAD_RENDER_ARGS[case]
    render_error(capfd, tmp_path, extra, *fragments, early=case not in LATE_CHECKS)


@pytest.mark.parametrize("device", ["cuda", "cuda:0"])
def test_cuda_without_gpu(capfd, tmp_path: Path, device: str) -> None:
    if has_cuda():
        pytest.skip("this machine has a CUDA GPU")
    render_error(capfd, tmp_path, ["--device", device], "no CUDA GPU", device)


def test_bad_device_for_bench_and_demo(capfd, tmp_path: Path) -> None:
    assert_error(capfd, ["bench", "dssrm", "--quick", "--device", "tpu", "--out", tmp_path / "b"], "tpu",
                 no_out=tmp_path / "b")
    assert_error(capfd, ["demo", *TINY, "--device", "tpu", "--out", tmp_path / "d"], "tpu", no_out=tmp_path / "d")


def test_demo_takes_no_scene_or_method(capfd, tmp_path: Path) -> None:
    for option in (["--scene", "cloud"], ["--method", "reference"], ["--volume", "x.npy"]):
        assert_error(capfd, ["demo", *TINY, "--out", tmp_path / "d", *option], "unrecognized", option[0],
                     no_out=tmp_path / "d")


def test_no_command(capfd) -> None:
    assert_error(capfd, [], "command")


def test_tonemap_unknown(capfd, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert_error(capfd, ["render", *TINY, "--out", out, "--tonemap", "bogus"], "tonemap", "bogus", "aces")
    assert not out.exists() or not any(out.iterdir())  # no partial files


def test_tonemap_unknown_is_refused_before_rendering(capfd, tmp_path: Path) -> None:
    render_error(capfd, tmp_path, ["--tonemap", "bogus"], "bogus")


def test_scene_and_volume_together(capfd, tmp_path: Path) -> None:
    vol = write_npy(tmp_path / "v.npy", asymmetric_density())
    render_error(capfd, tmp_path, ["--scene", "smoke", "--volume", vol], "--scene", "--volume")


@pytest.mark.parametrize("with_volume", [False, True])
def test_empty_scene_name(capfd, tmp_path: Path, with_volume: bool) -> None:
    extra: list[object] = ["--scene", ""]
    if with_volume:
        extra += ["--volume", write_npy(tmp_path / "v.npy", asymmetric_density())]
    render_error(capfd, tmp_path, extra, "scene")


def test_output_folder_is_a_file(capfd, tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert_error(capfd, ["render", *TINY, "--out", blocker], "--out", "is a file, not a folder", str(blocker))
    assert_error(capfd, ["render", *TINY, "--out", blocker / "sub"], "output folder")


def test_views_too_many_for_memory(capfd, tmp_path: Path) -> None:
    # estimated before any work (issue 13 item 8), so no output folder is created
    render_error(capfd, tmp_path, ["--views", "1024", "--width", "8192", "--height", "8192"],
                 "1024 view(s) of 8192x8192 for 1 frame(s) with dssrm needs", "GiB")


def test_absurd_view_count_is_refused_quickly(capfd, tmp_path: Path) -> None:
    with deadline(5):
        render_error(capfd, tmp_path, ["--views", "100000000"], "view", early=False)


def test_views_superscript_digit(capfd, tmp_path: Path) -> None:
    render_error(capfd, tmp_path, ["--views", "²"], "--views")


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_exposure_not_finite(capfd, tmp_path: Path, value: str) -> None:
    render_error(capfd, tmp_path, [f"--exposure={value}", "--background", "0"], "exposure", early=False)


def test_exposure_huge(capfd, tmp_path: Path) -> None:
    r = run(capfd, "render", *TINY, "--out", tmp_path / "out", "--exposure", "1e10")
    assert "Traceback" not in r.err and not r.warnings
    if r.code == 2:  # refused: one line naming the option
        assert r.err.startswith("volren: error: ") and len(r.err.splitlines()) == 1 and "exposure" in r.err
    else:  # or saturates to white
        assert r.code == 0 and r.err == ""


# ---------------------------------------------------------------- bad volume files


def _raw(p: Path) -> None:
    p.write_bytes(bytes(range(60)))


BAD_VOLUMES: dict[str, tuple[str, Callable[[Path], object], list[str], list[str]]] = {
    # case: (file name, writer, extra args, fragments)
    "missing": ("missing.npy", lambda p: None, [], ["not found"]),
    "directory": ("adir.npy", lambda p: p.mkdir(), [], ["not a regular file"]),
    "empty-folder": ("adir", lambda p: p.mkdir(), [], ["adir: empty folder; a DICOM series needs its slice files"]),
    "garbage-npy": ("bad.npy", lambda p: p.write_bytes(GARBAGE), [], ["not a .npy file"]),
    "garbage-npz": ("bad.npz", lambda p: p.write_bytes(GARBAGE), [], ["cannot read"]),
    "garbage-nrrd": ("bad.nrrd", lambda p: p.write_bytes(GARBAGE), [], ["cannot read"]),
    "garbage-nii": ("bad.nii", lambda p: p.write_bytes(GARBAGE), [], ["cannot read"]),
    "garbage-nii-gz": ("bad.nii.gz", lambda p: p.write_bytes(GARBAGE), [], ["cannot read"]),
    "garbage-nvdb": ("bad.nvdb", lambda p: p.write_bytes(GARBAGE), [], ["nanovdb"]),
    "empty-file-npy": ("empty.npy", lambda p: p.write_bytes(b""), [], ["the file is empty"]),
    "empty-file-nrrd": ("empty.nrrd", lambda p: p.write_bytes(b""), [], ["the file is empty"]),
    "unknown-extension": ("vol.txt", lambda p: p.write_text("hi"), [], ["unknown extension", "--shape"]),
    "raw-no-shape": ("vol.raw", _raw, [], ["shape"]),
    "raw-no-dtype": ("vol.raw", _raw, ["--shape", "5,4,3"], ["dtype"]),
    "raw-size-mismatch": ("vol.raw", _raw, ["--shape", "4,4,3", "--dtype", "uint8"], ["60 bytes", "48 bytes"]),
    "raw-size-mismatch-dtype": ("vol.raw", _raw, ["--shape", "5,4,3", "--dtype", "uint16"], ["60", "120"]),
    "raw-bad-dtype": ("vol.raw", _raw, ["--shape", "5,4,3", "--dtype", "bogus"], ["dtype", "bogus"]),
    "raw-complex-dtype": ("vol.raw", _raw, ["--shape", "5,4,3", "--dtype", "complex64"], ["complex64"]),
    "raw-zero-axis": ("vol.raw", _raw, ["--shape", "0,4,15", "--dtype", "uint8"], ["shape"]),
    "shape-for-npy": ("v.npy", lambda p: np.save(p, asymmetric_density()), ["--shape", "24,16,8", "--dtype", "float32"],
                      ["raw"]),
    "nan": ("nan.npy", lambda p: np.save(p, np.full((3, 4, 5), np.nan, np.float32)), [], ["nan"]),
    "inf": ("inf.npy", lambda p: np.save(p, np.where(np.arange(60).reshape(3, 4, 5) == 7, np.inf, 1.0)), [],
            ["1 NaN/Inf"]),
    "negative": ("neg.npy", lambda p: np.save(p, np.where(np.arange(60).reshape(3, 4, 5) < 3, -1.0, 1.0)), [],
                 ["3 negative"]),
    "one-voxel-axis": ("thin.npy", lambda p: np.save(p, np.ones((1, 4, 5), np.float32)), [], ["(1, 4, 5)", "2 voxels"]),
    "2d": ("flat.npy", lambda p: np.save(p, np.ones((4, 5), np.float32)), [], ["3D", "2 dimension"]),
    "empty-array": ("empty.npy", lambda p: np.save(p, np.ones((0, 4, 5), np.float32)), [], ["(0, 4, 5)"]),
    "complex": ("c.npy", lambda p: np.save(p, np.ones((3, 4, 5), np.complex64)), [], ["complex64"]),
    "npz-several-arrays": ("two.npz", lambda p: np.savez(p, a=np.ones((3, 4, 5)), b=np.ones((3, 4, 5))), [],
                           ["a, b", "density"]),
    "nifti-vectors": ("t.nii", lambda p: nib.save(nib.Nifti1Image(np.ones((3, 4, 5, 1, 3), np.float32), np.eye(4)),
                                                  p), [], ["shape (3, 4, 5, 1, 3)", "3 values per voxel"]),
}


@pytest.mark.parametrize("case", list(BAD_VOLUMES))
def test_bad_volume(capfd, tmp_path: Path, case: str) -> None:
    name, writer, extra, fragments = BAD_VOLUMES[case]
    path = tmp_path / name
    writer(path)
    line = render_error(capfd, tmp_path, ["--volume", path, *extra], *fragments)
    assert name in line  # the message names the file


def test_one_dcm_file_renders_its_series(capfd, tmp_path: Path) -> None:
    """``--volume ct/im003.dcm`` reads the series in ct/ (issue 13 item 2): all 9 slices, the image of ``--volume
    ct``."""
    from test_loaders import write_dicom_series
    from volren.plan import render_parser
    from volren.plan.scene import scene_from_args

    write_dicom_series(tmp_path / "ct", [(-12.0, -12.0, z) for z in np.arange(-12.0, 13.0, 3.0)], size=(16, 16),
                       spacing=(1.5, 1.5))
    file = tmp_path / "ct" / "im003.dcm"
    assert scene_from_args(render_parser().parse_args(["render", "--volume", str(file)])).volumes[0].density.shape == (
        9, 16, 16)
    series = _linear_render(capfd, tmp_path / "dir", tmp_path / "ct")
    assert series[..., 3].max() > 0
    np.testing.assert_array_equal(_linear_render(capfd, tmp_path / "file", file), series)


def test_one_dcm_file_refused_naming_it(capfd, tmp_path: Path) -> None:
    """A .dcm that is no DICOM, or one whose series has a gap: one line naming the file given."""
    from test_loaders import write_dicom_series

    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "j.dcm").write_bytes(GARBAGE)
    line = render_error(capfd, tmp_path, ["--volume", tmp_path / "junk" / "j.dcm"],
                        f"{tmp_path / 'junk' / 'j.dcm'}: not a DICOM file")
    assert line.count("j.dcm") == 1  # named once: the loader's message names the file given
    write_dicom_series(tmp_path / "gap", [(0, 0, z) for z in (0.0, 2.0, 6.0)], size=(4, 4), radius=1.0)
    file = tmp_path / "gap" / "im001.dcm"
    render_error(capfd, tmp_path, ["--volume", file], f"--volume {file}: reading the DICOM series in its folder: "
                 f"{tmp_path / 'gap'}: uneven slice spacing")


def test_one_dcm_file_picks_its_series_among_several(tmp_path: Path) -> None:
    """A folder holding two series (as scanners export them): ``--volume ct/FILE.dcm`` reads FILE's series only; the
    folder itself stays refused, naming both series."""
    from test_loaders import write_dicom_series
    from volren.plan import render_parser
    from volren.plan.scene import scene_from_args

    write_dicom_series(tmp_path / "ct", [(0, 0, z) for z in (0.0, 2.0, 4.0)], size=(4, 4), radius=1.0, series="1.2.3")
    write_dicom_series(tmp_path / "b", [(0, 0, z) for z in (0.0, 3.0)], size=(6, 5), radius=1.0, series="1.2.4")
    for f in (tmp_path / "b").iterdir():
        f.rename(tmp_path / "ct" / f"b{f.name}")

    def shape(path: Path) -> tuple[int, ...]:
        return scene_from_args(render_parser().parse_args(["render", "--volume", str(path)])).volumes[0].density.shape

    assert shape(tmp_path / "ct" / "im001.dcm") == (3, 4, 4)
    assert shape(tmp_path / "ct" / "bim001.dcm") == (2, 6, 5)
    with pytest.raises(VolrenError, match="holds 2 DICOM series"):
        shape(tmp_path / "ct")


def test_volume_beyond_float32_range(capfd, tmp_path: Path) -> None:
    path = write_npy(tmp_path / "big.npy", np.full((3, 4, 5), 1e300))
    render_error(capfd, tmp_path, ["--volume", path], "big.npy")


def test_environment_errors(capfd, tmp_path: Path) -> None:
    env = write_npy(tmp_path / "env.npy", np.ones((8, 16, 3), np.float32))
    render_error(capfd, tmp_path, ["--environment", env, "--ambient", "0.1"], "--ambient", "--environment")
    render_error(capfd, tmp_path, ["--environment", tmp_path / "missing.npy"], "missing.npy")
    negative = write_npy(tmp_path / "neg.npy", -np.ones((8, 16, 3), np.float32))
    render_error(capfd, tmp_path, ["--environment", negative], "environment")


# ---------------------------------------------------------------- bad compare and bench input


def _compare_case(tmp_path: Path, case: str) -> tuple[list[object], list[str]]:
    ref, test = _images(tmp_path)
    if case == "missing":
        return [ref, tmp_path / "nope.npy"], ["nope.npy"]
    if case == "shape-mismatch":
        return [ref, write_npy(tmp_path / "small.npy", np.zeros((H, W - 4, 4), np.float32))], ["differ"]
    if case == "nan":
        a = np.load(test)
        a[3, 4, 1] = np.nan
        return [ref, write_npy(tmp_path / "nan.npy", a)], ["NaN"]
    if case == "nan-reference":
        a = np.load(ref)
        a[3, 4, 1] = np.inf
        return [write_npy(tmp_path / "inf.npy", a), test], ["reference", "infinite"]
    if case == "integer":
        return [ref, write_npy(tmp_path / "int.npy", np.zeros((H, W, 4), np.uint8))], ["int.npy", "uint8"]
    if case == "2d":
        return [ref, write_npy(tmp_path / "flat.npy", np.zeros((H, W), np.float32))], ["flat.npy", "(H, W, 3)"]
    if case == "garbage":
        (tmp_path / "bad.npy").write_bytes(GARBAGE)
        return [ref, tmp_path / "bad.npy"], ["bad.npy"]
    if case == "garbage-png":
        (tmp_path / "bad.png").write_bytes(GARBAGE)
        return [tmp_path / "bad.png", test], ["bad.png"]
    if case == "unsupported":
        (tmp_path / "x.txt").write_text("x")
        return [ref, tmp_path / "x.txt"], [".txt"]
    if case == "too-small-for-ssim":
        a = np.zeros((8, 8, 4), np.float32)
        return [write_npy(tmp_path / "s1.npy", a + 0.5), write_npy(tmp_path / "s2.npy", a)], ["SSIM", "11"]
    if case == "heatmap-not-png":
        return [ref, test, "--heatmap", tmp_path / "err.jpg"], [".png"]
    if case == "one-file":
        return [ref], ["test"]
    if case == "black-reference":
        return [write_npy(tmp_path / "black.npy", np.zeros((H, W, 4), np.float32)), test], ["black.npy", "no signal"]
    raise AssertionError(case)


COMPARE_CASES = ["missing", "shape-mismatch", "nan", "nan-reference", "integer", "2d", "garbage", "garbage-png",
                 "unsupported", "too-small-for-ssim", "heatmap-not-png", "one-file", "black-reference"]


@pytest.mark.parametrize("case", COMPARE_CASES)
def test_bad_compare(capfd, tmp_path: Path, case: str) -> None:
    args, fragments = _compare_case(tmp_path, case)
    assert_error(capfd, ["compare", *args], *fragments)
    assert not (tmp_path / "test_error.png").exists()


def test_bench_unknown_suite(capfd, tmp_path: Path) -> None:
    assert_error(capfd, ["bench", "nonexistent", "--out", tmp_path / "b"], "unknown bench suite", "nonexistent",
                 "dssrm", no_out=tmp_path / "b")


def test_bench_cuda_without_gpu(capfd, tmp_path: Path) -> None:
    if has_cuda():
        pytest.skip("this machine has a CUDA GPU")
    assert_error(capfd, ["bench", "dssrm", "--quick", "--device", "cuda", "--out", tmp_path / "b"], "no CUDA GPU",
                 no_out=tmp_path / "b")


@pytest.mark.parametrize("views", ["mono", "stereo"])
@pytest.mark.parametrize("scene", SCENES)
def test_cmsrm_renders_every_builtin(capfd, tmp_path: Path, scene: str, views: str) -> None:
    out = tmp_path / "c"
    count = ("--count", "4") if scene == "multi" else ()
    render(capfd, out, "--scene", scene, *count, "--views", views, "--no-hybrid", method="cmsrm")
    stats = stats_of(out)["frames"][0]
    assert stats["method"] == "cmsrm" and "cube_march" in stats["times_ms"] and "resample" in stats["times_ms"]
    plans = stats["info"]["volumes"]
    assert len(plans) == (1 if views == "mono" else 2)
    assert all(p["scheme"] == "cube" for view in plans for p in view)
    assert (out / "stereo.png").exists() == (views == "stereo")


def test_cmsrm_options(capfd, tmp_path: Path) -> None:
    out = tmp_path / "c"
    render(capfd, out, "--views", "mono", "--cube-faces", "exterior", "--cube-size", "32", "--no-lod", "--no-cull",
           method="cmsrm")
    plan = stats_of(out)["frames"][0]["info"]["volumes"][0][0]
    assert plan["face_size"] == 32 and plan["level"] == 0


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        (["--method", "cmsrm", "--cube-size", "1"], "cube size"),
        (["--method", "cmsrm", "--cube-faces", "sideways"], "cube-faces"),
        (["--method", "dssrm", "--no-lod"], "--no-lod"),
        (["--method", "cmsrm", "--jitter"], "--jitter"),
    ],
)
def test_cmsrm_bad_options(capfd, tmp_path: Path, extra: list[str], fragment: str) -> None:
    render_error(capfd, tmp_path, extra, fragment)


def test_opaque_geometry_options(capfd, tmp_path: Path) -> None:
    out = tmp_path / "o"
    render(capfd, out, "--views", "mono", "--sphere", "0,0,1.5,0.4", "--sphere", "0.5,0,0,0.2", "--ground", "-0.8",
           "--save-linear", method="cmsrm")
    image = np.load(out / "view0.npy")
    assert image[H // 2, W // 2, 3] == 1.0  # the sphere in front is opaque
    assert "surfaces" in stats_of(out)["frames"][0]["times_ms"]


def test_depth_image_option(capfd, tmp_path: Path) -> None:
    depth = tmp_path / "z.npy"
    np.save(depth, np.full((H, W), 0.5, np.float32))  # in front of the whole volume: nothing left
    out = tmp_path / "d"
    render(capfd, out, "--views", "stereo", "--depth-image", depth, "--save-linear")
    assert np.load(out / "view1.npy")[..., 3].max() == 0.0


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        (["--sphere", "1,2"], "4 comma-separated"),
        (["--sphere", "0,0,0,-1"], "radius"),
        (["--depth-image", "missing.npy"], "depth image"),
        (["--method", "cmsrm", "--k-z", "-1"], "k_z"),
    ],
)
def test_opaque_bad_options(capfd, tmp_path: Path, extra: list[str], fragment: str) -> None:
    render_error(capfd, tmp_path, extra, fragment)


@pytest.mark.parametrize("extra", [[], ["--no-coupling"], ["--no-share"], ["--no-vsa"], ["--no-interleave"]])
def test_cacrm_switches(capfd, tmp_path: Path, extra: list[str]) -> None:
    out = tmp_path / "a"
    render(capfd, out, "--no-hybrid", "--no-lod", *extra, method="cacrm")
    counters = stats_of(out)["frames"][0]["counters"]
    assert (counters["shared_samples"] > 0) == (extra in ([], ["--no-vsa"], ["--no-interleave"]))
    assert (out / "stereo.png").exists()


def test_cacrm_switch_refused_by_other_methods(capfd, tmp_path: Path) -> None:
    render_error(capfd, tmp_path, ["--method", "cmsrm", "--no-coupling"], "--no-coupling")


def test_k_a_option_reaches_the_ramp(capfd, tmp_path: Path) -> None:
    """--k-a sets Eq. 4's ramp: the paper's 3 lengthens the steps (fewer samples than the default 1.5, more with 0)."""
    samples = {}
    for k_a in ("0", None, "3"):
        out = tmp_path / f"k{k_a}"
        render(capfd, out, "--no-hybrid", "--no-lod", *(["--k-a", k_a] if k_a else []), method="cacrm")
        samples[k_a] = stats_of(out)["frames"][0]["counters"]["density_samples"]
    assert samples["0"] > samples[None] > samples["3"]


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        (["--method", "cmsrm", "--k-a", "3"], "does not take --k-a"),
        (["--method", "cacrm", "--k-a", "3", "--no-vsa"], "--k-a sets VSA's ramp"),
        (["--method", "cacrm", "--k-a", "3", "--mode", "mip"], "--k-a sets VSA's ramp"),
        (["--method", "cacrm", "--k-a", "-1"], "k_a must be a finite number >= 0"),
    ],
)
def test_k_a_refused_where_it_would_do_nothing(capfd, tmp_path: Path, extra: list[str], fragment: str) -> None:
    render_error(capfd, tmp_path, extra, fragment)


@pytest.mark.parametrize("method", ["cmsrm", "cacrm"])
def test_tile_lod_option(capfd, tmp_path: Path, method: str) -> None:
    out = tmp_path / "t"
    render(capfd, out, "--no-hybrid", "--no-lod", "--camera-pos", "0,0.4,8", "--tile-lod", method=method)
    plan = stats_of(out)["frames"][0]["info"]["volumes"][0][0]
    assert plan["tile_levels"][0] < plan["live_tiles"]


def test_tile_lod_refused_by_dssrm(capfd, tmp_path: Path) -> None:
    render_error(capfd, tmp_path, ["--method", "dssrm", "--tile-lod"], "--tile-lod")


def test_mesh_option(capfd, tmp_path: Path) -> None:
    import trimesh

    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(0.4, 0.4, 0.4)).export(path)
    out = tmp_path / "m"
    render(capfd, out, "--views", "mono", "--mesh", path, "--mesh-translate", "0,0,2", "--save-linear")
    assert np.load(out / "view0.npy")[H // 2, W // 2, 3] == 1.0  # the box in front is opaque
    render_error(capfd, tmp_path, ["--mesh", tmp_path / "missing.obj"], "mesh file not found")
    (tmp_path / "random.obj").write_bytes(bytes(range(256)) * 4)
    render_error(capfd, tmp_path, ["--mesh", tmp_path / "random.obj"], "random.obj: not a text .obj mesh (byte 128 "
                 "is not UTF-8 text)")


FOG = ("--method", "fog", "--width", "32", "--height", "18", "--slices", "16", "--device", "cpu")


def test_fog_render_of_many_viewers_writes_views_and_a_contact_sheet(capfd, tmp_path: Path) -> None:
    out = tmp_path / "f"
    ok(capfd, "render", *FOG, "--scene", "hall", "--views", "16", "--out", out)
    assert all((out / f"view{v}.png").exists() for v in range(16))
    assert (out / "contact.png").exists()
    frame = stats_of(out)["frames"][0]
    assert frame["counters"]["shadow_voxels"] > 0 and "shadow_grid" in frame["times_ms"]


def test_fog_options_and_an_animated_scene(capfd, tmp_path: Path) -> None:
    out = tmp_path / "g"
    ok(capfd, "render", *FOG, "--scene", "dynamic", "--views", "mono", "--fog-sharing", "none", "--frames", "2",
       "--no-temporal", "--froxel-size", "4", "--fog-far", "20", "--out", out)
    frames = stats_of(out)["frames"]
    assert frames[1]["counters"]["shadow_voxels"] == 0 and frames[1]["settings"]["tile"] == 4


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        (["--scene", "hall", "--voxel-size", "0"], "voxel size"),
        (["--scene", "hall", "--slices", "2"], "slices"),
        (["--scene", "smoke", "--resolution", "64"], "needs a scene with fog"),
        (["--scene", "hall", "--samples", "8"], "--samples"),
    ],
)
def test_fog_bad_options(capfd, tmp_path: Path, extra: list[str], fragment: str) -> None:
    assert_error(capfd, ["render", *FOG, "--out", tmp_path / "o", *extra], fragment)


def test_volume_methods_refuse_a_fog_scene(capfd, tmp_path: Path) -> None:
    assert_error(capfd, ["render", "--scene", "hall", "--method", "dssrm", "--width", "8", "--height", "8",
                         "--device", "cpu", "--out", tmp_path / "o"], "has none")


@pytest.mark.parametrize("scene", SCENES)
def test_vpt_renders_every_builtin_scene(capfd, tmp_path: Path, scene: str) -> None:
    out = tmp_path / scene
    ok(capfd, "render", "--method", "vpt", "--scene", scene, "--resolution", "64", "--width", "24", "--height", "16",
       "--spp", "2", "--device", "cpu", "--views", "mono", "--out", out)
    assert stats_of(out)["frames"][0]["info"]["majorant_bytes"] > 0


def test_vpt_options_on_a_loaded_volume(capfd, tmp_path: Path) -> None:
    volume = tmp_path / "ct.npy"
    np.save(volume, np.random.default_rng(0).random((32, 32, 32), dtype=np.float32))
    out = tmp_path / "ct"
    ok(capfd, "render", "--method", "vpt", "--volume", volume, "--tf", "ct-bone", "--shading", "er",
       "--max-bounces", "1", "--clip=-1,1,-1,0,-1,1", "--spp", "2", "--width", "24", "--height", "16", "--device",
       "cpu", "--out", out)
    settings = stats_of(out)["frames"][0]["settings"]
    assert settings["transfer"] == "ct-bone" and settings["shading"] == "er"


def test_vpt_tf_ct_bone_reads_hounsfield_units_of_a_signed_ct(capfd, tmp_path: Path) -> None:
    """An int16 CT of soft tissue (40 HU) in air (-1000 HU) holds no bone: under ct-bone it renders empty (alpha 0),
    although the loader maps 40 HU to density 1, where the preset's normalised form is bone. The scene's volume
    carries the HU range; a uint8 file's 0..255 is no HU, and a constant file has no scale: they carry none."""
    from volren.plan import render_parser
    from volren.plan.scene import scene_from_args

    z, y, x = np.mgrid[0:16, 0:16, 0:16] / 7.5 - 1
    ct = np.where(x**2 + y**2 + z**2 < 0.5, 40, -1000).astype(np.int16)
    nrrd.write(str(tmp_path / "ct.nrrd"), ct, index_order="C")
    nrrd.write(str(tmp_path / "u8.nrrd"), ct.astype(np.uint8), index_order="C")
    args = render_parser().parse_args(["render", "--volume", str(tmp_path / "ct.nrrd")])
    assert scene_from_args(args).volumes[0].value_range == (-1000.0, 40.0)
    nrrd.write(str(tmp_path / "flat.nrrd"), np.full((4, 4, 4), 40, np.int16), index_order="C")
    for name in ("u8.nrrd", "flat.nrrd"):  # no HU; a constant CT has no HU scale
        args = render_parser().parse_args(["render", "--volume", str(tmp_path / name)])
        assert scene_from_args(args).volumes[0].value_range is None
    for tf, empty in (("ct-bone", True), ("ct-muscle", False)):
        out = tmp_path / tf
        ok(capfd, "render", "--method", "vpt", "--volume", tmp_path / "ct.nrrd", "--tf", tf, "--spp", "2",
           "--width", "24", "--height", "16", "--device", "cpu", "--views", "mono", "--save-linear", "--out", out)
        alpha = np.load(out / "view0.npy")[..., 3]
        assert (alpha.max() == 0) == empty, (tf, alpha.max())


@pytest.mark.parametrize(("extra", "fragment"), [(["--tf", "nope"], "neither a preset"), (["--spp", "0"], "spp"),
                                                 (["--clip", "1,2,3"], "6 comma-separated")])
def test_vpt_bad_options(capfd, tmp_path: Path, extra: list[str], fragment: str) -> None:
    assert_error(capfd, ["render", "--method", "vpt", "--scene", "smoke", "--width", "8", "--height", "8",
                         "--device", "cpu", "--out", tmp_path / "o", *extra], fragment)


@pytest.mark.parametrize("denoise", ["ours", "svgf", "wrls"])
def test_vpt_denoise_and_rect_light_options(capfd, tmp_path: Path, denoise: str) -> None:
    out = tmp_path / denoise
    ok(capfd, "render", "--method", "vpt", "--scene", "cloud", "--resolution", "64", "--width", "24", "--height", "16",
       "--spp", "2", "--frames", "2", "--denoise", denoise, "--rect-light", "0,3,0,1,1,20", "--views", "mono",
       "--device", "cpu", "--out", out)
    frame = stats_of(out)["frames"][1]
    assert frame["settings"]["denoise"] == denoise and "denoise" in frame["times_ms"]


def test_bad_rect_light(capfd, tmp_path: Path) -> None:
    assert_error(capfd, ["render", "--method", "vpt", "--scene", "cloud", "--rect-light", "0,3,0,0,1,20", "--device",
                         "cpu", "--out", tmp_path / "o"], "positive width")


def test_run_time_estimate_refuses_before_output(capfd, tmp_path: Path) -> None:
    # issue 13 item 8: 1,024 views of 640x360 once ran minutes and died; a quarter-size probe estimates it up front.
    # 256 views here: 1,024 need 13.2 GiB, and on a machine with less free the memory check refuses first
    render_error(capfd, tmp_path, ["--views", "256", "--rig", "arc", "--width", "640", "--height", "360",
                                   "--max-minutes", "0.001"],
                 "256 view(s) of 640x360", "would take about", "160x90 probe", "--max-minutes 0.001")


def test_run_time_check_refuses_over_the_limit_and_passes_under_it() -> None:
    from volren.plan import CliError, render_parser
    from volren.plan.render import check_run_time
    from volren.plan.scene import scene_from_args
    from volren.plan.views import views_from_args

    def check(*extra: str) -> None:
        args = render_parser().parse_args(["render", "--views", "64", "--rig", "arc", "--width", "1280", "--height",
                                          "720", "--samples", "8", "--light-samples", "4",
                                          *extra])
        check_run_time(args, scene_from_args(args), views_from_args(args), "dssrm")

    with pytest.raises(CliError, match=r"would take about .* over --max-minutes 1e-06"):
        check("--max-minutes", "0.000001")
    check("--max-minutes", "600")  # the same probe, well under the limit
    check("--max-minutes", "0")  # no limit: no probe


def test_run_time_estimate_extrapolates_each_pass_by_its_own_work() -> None:
    from types import SimpleNamespace

    from volren.camera import Camera
    from volren.estimates import estimate_seconds

    probed = []

    def probe(cam: Camera):
        probed.append((cam.width, cam.height))
        times = {"upload": 10.0, "light_map": 5.0, "cube_march": 2.0, "march": 3.0}
        return SimpleNamespace(stats=SimpleNamespace(times_ms=times))

    views = [Camera(width=400, height=400), Camera(position=(1.0, 0.0, 3.0), width=400, height=400)]
    est = estimate_seconds(views, 3, probe)
    assert probed == [(100, 100)]
    # upload once, the light map per frame, cube maps per view, the march per pixel (2 x 400^2 / 100^2 = 32x)
    assert est.seconds == pytest.approx((10.0 + 3 * (5.0 + 2 * 2.0 + 32 * 3.0)) / 1e3)
    assert est.probe_ms == 20.0


def test_contact_sheet_of_many_views_is_bounded() -> None:
    from volren.output import MAX_SHEET_SIDE, contact_sheet

    images = [np.full((360, 640, 4), float(i), np.float32) for i in range(100)]
    sheet = contact_sheet(images)
    # 10 x 10 cells of 640x360 halved (the whole factor that brings 6400 px under MAX_SHEET_SIDE)
    assert MAX_SHEET_SIDE == 4096 and sheet.shape == (1800, 3200, 4)
    assert sheet[180 * 3 + 5, 320 * 7 + 9, 0] == 37.0  # block means keep each view's value in its cell
    small = contact_sheet(images[:5])
    assert small.shape == (2 * 360, 3 * 640, 4) and small[360, 640, 0] == 4.0
