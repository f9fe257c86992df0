"""The public API (`import volren as vr`, issue 22 items 1 and 6): lazy names, render/Renderer over the presets,
Frame.save writing what `volren render` writes, Frame.show, one-line refusals, `--version`, a cheap start-up."""

from __future__ import annotations

import importlib.metadata
import json
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
from tests.conftest import DEVICE

import volren as vr
from volren.errors import VolrenError
from volren.render.frame import Frame, Stats

HEAVY = ("warp", "numpy", "skimage", "matplotlib", "imageio", "scipy", "trimesh", "volren.render")


def loaded_after(code: str) -> list[str]:
    """The heavy modules a fresh interpreter holds after running ``code``."""
    probe = f"{code}\nimport sys\nprint('loaded:' + ','.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return [m for m in out.rsplit("loaded:", 1)[1].strip().split(",") if m]


def test_import_volren_and_the_cli_parser_load_no_heavy_module():
    """Start-up (issue 22 item 6): `import volren`, building the CLI's parser and a refusal of a bad value import
    neither Warp nor numpy (machine-independent, unlike a timing)."""
    assert loaded_after("import volren; dir(volren)") == []
    refusals = """
import contextlib, io, volren.cli as cli
cli.build_parser()
for bad in (["render", "--method", "nope"], ["render", "--scene", "nope"], ["render", "--frames", "0"],
            ["render", "--width", "0"], ["render", "--exposure", "99"], ["render", "--gi", "x"], ["bogus"],
            ["serve", "--port", "0"], ["serve", "--scene", "nope"]):
    with contextlib.redirect_stderr(io.StringIO()) as err:
        assert cli.main(bad) == 2
    assert err.getvalue().count("\\n") == 1, err.getvalue()
"""
    assert loaded_after(refusals) == []


def test_cli_name_lists_equal_their_sources():
    """The parser's static name lists (kept so that building it imports nothing heavy) agree with the modules."""
    from volren.data import BUILTIN_SCENES
    from volren.data.fog_scenes import FOG_SCENES
    from volren.imageio import TONEMAPS
    from volren.plan import options
    from volren.render import METHODS
    from volren.render.gi.ambient import GI_METHODS
    from volren.transfer import PRESETS

    assert tuple(METHODS) == options.METHOD_NAMES
    assert options.GI_METHOD_NAMES == GI_METHODS
    assert tuple(PRESETS) == options.TF_PRESET_NAMES
    assert options.TONEMAPS == TONEMAPS
    assert (*BUILTIN_SCENES, *FOG_SCENES) == options.SCENE_NAMES


def test_public_names_are_their_modules_objects():
    from volren.camera import Camera
    from volren.render.frame import Frame
    from volren.render.gi.ambient import GIConfig
    from volren.render.marching.cacrm import CACRMConfig
    from volren.scene import Scene, Volume

    assert dir(vr) == sorted(vr.__all__)
    assert vr.Scene is Scene and vr.Volume is Volume
    assert vr.Camera is Camera and vr.Frame is Frame
    assert vr.CACRMConfig is CACRMConfig and vr.GIConfig is GIConfig
    from volren._api import render

    assert vr.render is render  # the function, though the renderer subpackage shares its name
    # ... also where nothing imported the subpackage yet: the first call does, loading Warp then
    first = "import volren as vr\nfrom volren._api import render\nassert vr.render is render"
    assert "warp" not in loaded_after(first)
    assert vr.__version__ == importlib.metadata.version("volren")
    import volren.notebook

    assert vr.Viewer is volren.notebook.Viewer
    for name in vr.__all__:
        assert getattr(vr, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        vr.nope  # noqa: B018


def test_version_flag_prints_the_installed_version(capsys):
    from volren.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == f"volren {importlib.metadata.version('volren')}\n"


SIZE = {"width": 32, "height": 24}
SETTINGS = {"samples": 16, "light_samples": 8, "light_grid": 16}


def test_render_and_save_write_what_volren_render_writes(tmp_path, capsys):
    """The Done-when line of issue 22: vr.render(...).save(out) gives `volren render`'s files, byte for byte (PNGs)
    and setting for setting (stats.json), with the quality preset under the settings: `high`'s early termination
    (1e-4) stays where the settings do not replace it."""
    from volren.cli import main

    args = ["render", "--scene", "smoke", "--resolution", "64", "--quality", "high", "--samples", "16",
            "--light-samples", "8", "--light-grid", "16", "--width", "32", "--height", "24", "--device", DEVICE,
            "--camera-pos", "0,0.4,3.2", "--out", str(tmp_path / "cli")]
    assert main(args) == 0
    capsys.readouterr()
    scene = vr.builtin_scene("smoke", 64)
    eyes = vr.views(vr.Camera(position=(0, 0.4, 3.2), **SIZE), "stereo")
    frame = vr.render(scene, eyes, method="dssrm", quality="high", device=DEVICE, **SETTINGS)
    files = frame.save(tmp_path / "api")
    assert [f.name for f in files] == ["view0.png", "view1.png", "stereo.png", "stats.json"]
    assert sorted(p.name for p in (tmp_path / "cli").iterdir()) == sorted(f.name for f in files)
    for name in ("view0.png", "view1.png", "stereo.png"):
        assert np.array_equal(iio.imread(tmp_path / "cli" / name), iio.imread(tmp_path / "api" / name)), name
    cli_stats, api_stats = (json.loads((tmp_path / d / "stats.json").read_text()) for d in ("cli", "api"))
    assert api_stats["scene"] == cli_stats["scene"] == "smoke"
    (cli_frame,), (api_frame,) = cli_stats["frames"], api_stats["frames"]
    assert api_frame["settings"] == cli_frame["settings"] and api_frame["settings"]["min_transmittance"] == 1e-4
    assert api_frame["counters"] == cli_frame["counters"]


def test_one_camera_is_one_view_and_a_renderer_keeps_its_state():
    """A Camera where a list is expected is one view; Renderer keeps its light map across frames (the interactive
    preset reuses it while the scene stands still: no light samples in frame 1), a fresh render does not."""
    scene = vr.builtin_scene("smoke", 64)
    camera = vr.Camera(position=(0, 0.4, 3.2), **SIZE)
    single = vr.render(scene, camera, device=DEVICE, **SETTINGS)
    listed = vr.render(scene, [camera], device=DEVICE, **SETTINGS)
    assert len(single.images) == 1 and np.array_equal(single.images[0], listed.images[0])
    renderer = vr.Renderer("dssrm", "interactive", device=DEVICE, **SETTINGS)
    first, second = (renderer.render(scene, camera, frame=i) for i in range(2))
    assert first.stats.counters["light_samples"] > 0 and second.stats.counters["light_samples"] == 0
    assert np.array_equal(first.images[0], second.images[0])
    assert renderer.config.light_grid == 16 and renderer.device == single.stats.device
    # the frame keeps what saving and showing it need of the scene
    mine = vr.Scene(scene.volumes, background=(0.1, 0.2, 0.3), name="mine")
    frame = renderer.render(mine, camera, frame=2)
    assert frame.background == (0.1, 0.2, 0.3) and frame.scene_name == "mine" and frame.index == 2


def test_load_places_a_file_as_the_cli_does(tmp_path):
    """vr.load: the reader's placement (spacing in units), the material arguments, a CT's Hounsfield range kept."""
    import nrrd

    ct = (np.arange(4 * 5 * 6).reshape(6, 5, 4) * 10 - 1000).astype(np.int16)  # [z, y, x], HU
    nrrd.write(str(tmp_path / "ct.nrrd"), np.asfortranarray(ct.transpose(2, 1, 0)), {"spacings": [2.0, 2.0, 2.0]},
               index_order="F")
    volume = vr.load(tmp_path / "ct.nrrd", density_scale=3.0)
    assert volume.density_scale == 3.0 and volume.name == "ct.nrrd"
    assert volume.value_range == (-1000.0, float(ct.max()))
    np.testing.assert_allclose(np.diag(volume.to_world)[:3], [0.004, 0.005, 0.006])  # half of 4, 5, 6 x 2 mm
    np.save(tmp_path / "cube.npy", np.ones((4, 4, 4), np.float32))
    cube = vr.load(tmp_path / "cube.npy", spacing=(1, 1, 1), units="cm")
    np.testing.assert_allclose(np.diag(cube.to_world)[:3], [0.02] * 3)
    # issue 45.1: without density_scale its box sets it, optical depth 20 at density 1 across its 4 cm side
    assert cube.value_range is None and cube.density_scale == pytest.approx(20 / 0.04)


@pytest.mark.parametrize(("call", "message"), [
    (lambda s, c: vr.render(s, c, method="nope"), "unknown method 'nope'"),
    (lambda s, c: vr.render(s, c, sample=3), "method 'dssrm' has no setting sample"),
    (lambda s, c: vr.render(s, c, method="vpt", samples=3), "method 'vpt' has no setting samples"),
    (lambda s, c: vr.render(s, c, quality="ultra"), "unknown quality 'ultra'"),
    (lambda s, c: vr.Renderer(device=DEVICE).render(s.volumes[0], c),
     "scene must be a volren.Scene or Channels, got Volume: wrap"),
    (lambda s, c: vr.render(3), "render: scene must be a volren.Scene, a Volume, Channels, a VolumeSequence, a file "
     "path or a built-in scene name, got int"),
    (lambda s, c: vr.render("nope.nrrd"), "render: scene 'nope.nrrd' is no file nor a built-in scene \\(smoke, "),
    (lambda s, c: vr.render("hall"), "render: 'hall' is a fog scene, which method 'dssrm' does not render: give "
     "method='fog'"),
    (lambda s, c: vr.render(s, c, width=32), "render: width= and height= size the framed views; the cameras given"),
    (lambda s, c: vr.render(s, height=0), r"render: height= must be a positive number of pixels, got 0"),
    (lambda s, c: vr.render(s, "three"), "views= must be mono, stereo or a positive integer, got 'three'"),
    (lambda s, c: vr.render(s, object()), "views must be a volren.Camera or a list of them"),
    (lambda s, c: vr.render(s, [c, "x"]), r"views\[1\] must be a volren.Camera, got str"),
    (lambda s, c: vr.views(c, "three"), "views: mode must be mono, stereo or a positive integer"),
    (lambda s, c: vr.views(s, "mono"), "views: camera must be a volren.Camera, got Scene"),
    (lambda s, c: vr.load("x.npy", spacng=(1, 1, 1)), "load: unknown argument spacng: choose from shape"),
    (lambda s, c: vr.builtin_scene("smoke", time=1.0), "builtin_scene: scene 'smoke' takes no time"),
    (lambda s, c: vr.builtin_scene("cloud", count=4), "builtin_scene: scene 'cloud' takes no count"),
    (lambda s, c: vr.builtin_scene("hall", 64), "builtin_scene: scene 'hall' takes no resolution"),
])
def test_bad_arguments_get_one_line_naming_them(call, message):
    scene = vr.Scene([vr.Volume(np.ones((2, 2, 2), np.float32))])  # a list is accepted
    with pytest.raises(VolrenError, match=message) as err:
        call(scene, vr.Camera(**SIZE))
    assert "\n" not in str(err.value)


def hand_frame(count: int) -> Frame:
    """``count`` views of 4x6 pixels, each its own grey, half covered, over a blue background."""
    images = [np.zeros((4, 6, 4), np.float32) for _ in range(count)]
    for v, image in enumerate(images):
        image[:, :3] = (0.2 + 0.2 * v, 0.2 + 0.2 * v, 0.2 + 0.2 * v, 1.0)
    depths = [np.full((4, 6), np.inf, np.float32)] * count
    return Frame(images, depths, Stats("cpu", "test", {}), background=(0.0, 0.0, 0.25), scene_name="hand")


@pytest.mark.parametrize(("count", "written"), [(1, "view0.png"), (2, "stereo.png"), (3, "contact.png")])
def test_show_displays_what_save_writes(count, written, tmp_path, monkeypatch):
    """Frame.show: in a notebook an IPython display, elsewhere Pillow's viewer; the picture is the one saved (the
    view, the stereo pair, the contact sheet) over the scene's background."""
    import IPython.display
    from PIL import Image

    frame = hand_frame(count)
    frame.save(tmp_path, exposure=1.0)
    saved = iio.imread(tmp_path / written)
    np.testing.assert_array_equal(frame.srgb(exposure=1.0), saved)
    assert tuple(saved[0, -1]) == (0, 0, 188)  # an uncovered pixel: the background, 0.25 x 2 -> sRGB 188
    shown = []
    monkeypatch.setattr(Image.Image, "show", lambda image, *a, **k: shown.append(("viewer", np.asarray(image))))
    monkeypatch.setattr(IPython.display, "display", lambda image: shown.append(("notebook", np.asarray(image))))
    frame.show(exposure=1.0)
    monkeypatch.setattr(sys.modules["volren.render.frame"], "_in_notebook", lambda: True)
    frame.show(exposure=1.0)
    assert [where for where, _ in shown] == ["viewer", "notebook"]
    for _, pixels in shown:
        np.testing.assert_array_equal(pixels, saved)


def test_reprs_summarise_instead_of_printing_arrays():
    """Issue 42 item 2: the repr of a Volume, a Scene and a Frame is a one-line summary (shape, dtype, world box,
    density range, opacity; views, sizes, method), not their arrays (a 48^3 volume's repr was 1,936 characters)."""
    import numpy as np

    import volren as vr

    d = np.zeros((48, 40, 32), np.float32)
    d[20:28, 16:24, 12:20] = 0.5
    vol = vr.Volume(d, to_world=np.diag([3e-6, 4e-6, 5e-6, 1.0]), density_scale=2e5, name="cells",
                    value_range=(-1000.0, 40.0))
    text = repr(vol)
    assert text == ("Volume('cells', 32x40x48 float32 (x, y, z), box 6e-06 x 8e-06 x 1e-05 m at (0, 0, 0), "
                    "density 0..0.5, density_scale 2e+05 /m, HU -1000..40)"), text
    scene = vr.Scene([vol], name="lab")
    assert repr(scene) == f"Scene('lab', volumes=[{text}], 1 light(s))"
    frame = vr.render(scene, vr.Camera(position=(0, 0, 3e-5), width=16, height=12), method="dssrm")
    assert repr(frame).startswith("Frame(1 view(s) 16x12, dssrm on cpu, ") and repr(frame).endswith(
        "ms, frame 0, scene 'lab')"), repr(frame)
    assert "\n" not in repr(scene) + repr(frame)


def test_render_is_a_function_with_its_own_signature_and_help():
    """Issue 42 item 2: `vr.render` is the API's function whatever imported the renderer subpackage of the same name:
    `help` shows its signature and docstring (before: the package's docstring and ``(*args, **kwargs)``)."""
    import inspect
    import pydoc

    import volren.render  # noqa: F401  (the import system binds the subpackage to volren.render: the function stays)
    from volren.render import METHODS

    assert inspect.isfunction(vr.render) and vr.render.__module__ == "volren._api"
    assert list(inspect.signature(vr.render).parameters)[:4] == ["scene", "views", "method", "quality"]
    text = pydoc.render_doc(vr.render, renderer=pydoc.plaintext)
    assert "render(scene" in text and "One frame of" in text and "dssrm" in METHODS
    # issue 42 item 2: what it takes, and the framing without views, are in its help
    assert "framed as the command line frames it" in text and "vr.render(vr.load(" in text
    params = inspect.signature(vr.render).parameters
    assert params["views"].default is None
    assert all(params[k].kind is params[k].KEYWORD_ONLY and params[k].default is None for k in ("width", "height"))
    assert sys.modules["volren.render"].__name__ == "volren.render" and "render" in dir(vr)


FAST = {"samples": 64, "light_samples": 4, "light_grid": 8}
"""a short light march: these renders take about a second each"""


def test_render_frames_a_micrometre_volume_without_views(tmp_path):
    """Issue 42 item 2: vr.render(vr.load(f)) of a 32 um ball (the default Camera at 3.5 m would show nothing) is
    framed whole: the ball in the centre, nothing in the corner; a Scene of it is framed alike."""
    from tests.test_opacity_units import ball, imagej_tiff

    volume = vr.load(imagej_tiff(tmp_path / "um.tif", ball(), 1.0, "um"))
    frame = vr.render(volume, width=48, height=32, device=DEVICE, **FAST)
    a = frame.images[0][..., 3]
    assert a.shape == (32, 48) and a[16, 24] > 0.3 and a[0, 0] < 0.01, (a[16, 24], a[0, 0])
    scene = vr.render(vr.Scene([volume]), width=48, height=32, device=DEVICE, **FAST)
    assert np.array_equal(scene.images[0], frame.images[0])


@pytest.mark.parametrize("what", ["smoke", "file"])
def test_render_without_views_frames_as_volren_render_does(what, tmp_path, capsys):
    """vr.render(name or path, width=, height=) is `volren render --scene NAME | --volume PATH --views mono` at the
    same size, method and settings: the same scene and the same camera, so the same linear image."""
    from tests.test_opacity_units import ball, imagej_tiff

    from volren.cli import main

    given = "smoke" if what == "smoke" else str(imagej_tiff(tmp_path / "um.tif", ball(), 2.0, "um"))
    flags = ["--scene", given] if what == "smoke" else ["--volume", given]
    assert main(["render", *flags, "--views", "mono", "--width", "48", "--height", "32", "--quality", "interactive",
                 "--samples", "64", "--light-samples", "4", "--light-grid", "8", "--device", DEVICE, "--save-linear",
                 "--out", str(tmp_path / "cli")]) == 0
    capsys.readouterr()
    frame = vr.render(given, width=48, height=32, device=DEVICE, **FAST)
    assert len(frame.images) == 1 and frame.images[0][..., 3].max() > 0.3  # it shows something
    np.testing.assert_allclose(frame.images[0], np.load(tmp_path / "cli" / "view0.npy"), rtol=0, atol=1e-6)


@pytest.mark.timeout(60)
def test_frames_zero_is_refused_in_one_line():
    volume = vr.Volume(np.ones((4, 4, 4), np.float32))
    with pytest.raises(VolrenError, match=r"^render: frames= must be >= 1, got 0$"):
        vr.render(volume, frames=0, device=DEVICE)


@pytest.mark.timeout(120)
def test_a_micrometre_stereo_pair_sees_the_ball_in_each_eye(tmp_path):
    """views="stereo" of a 32 um ball: its eyes at most the box's size apart (`framed_ipd`), not 63 mm (which
    would frame the pair from so far back that the ball is a speck), and each eye shows the ball large."""
    from tests.test_opacity_units import ball, imagej_tiff

    from volren._api import framed_views

    volume = vr.load(imagej_tiff(tmp_path / "um.tif", ball(), 1.0, "um"))
    left, right = framed_views(vr.Scene([volume]), None, "stereo", 48, 32)
    extent = float(np.ptp(volume.corners_world, axis=0).max())
    assert extent < 1e-3
    np.testing.assert_allclose(np.linalg.norm(np.subtract(left.position, right.position)), extent, rtol=1e-6)
    frame = vr.render(volume, "stereo", width=48, height=32, device=DEVICE, **FAST)
    assert [int((image[..., 3] > 0.3).sum()) > 80 for image in frame.images] == [True, True]  # 130 each


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", ["courtyard", "dynamic"])
def test_n_fog_viewers_stand_where_one_can_walk(name):
    """views=N of a fog scene: N viewers on the arc, each moved into the scene's walkable area as ``--views N``
    places them (the plain arc puts the outer ones inside walls)."""
    from volren._api import framed_views
    from volren.data.fog_scenes import fog_scene_walk_area

    cameras = framed_views(vr.builtin_scene(name), name, 3)
    area = fog_scene_walk_area(name)
    assert len({c.position for c in cameras}) == 3
    assert [bool(area.walkable(c.position[0], c.position[2])) for c in cameras] == [True, True, True]


@pytest.mark.timeout(60)
def test_frame_i_of_an_animated_fog_scene_is_its_time_i_over_30_s():
    """``render("dynamic", method="fog", frames=...)``: frame 30 shows the scene one second on, as ``volren animate``
    plays it at 30 fps (not 30 s on)."""
    from volren._api import _source

    def geometry(scene) -> list[np.ndarray]:
        return [np.asarray(o.vertices) for o in scene.opaque]

    source = _source("dynamic", None, None, None)
    for frame, seconds in ((0, 0.0), (30, 1.0), (45, 1.5)):
        want = geometry(vr.builtin_scene("dynamic", time=seconds))
        assert all(np.array_equal(a, b) for a, b in zip(geometry(source.at(frame)), want, strict=True))
    assert not all(np.array_equal(a, b) for a, b in zip(geometry(source.at(30)), geometry(source.at(0)), strict=True))
