"""The public API's functions and its temporal renderer (re-exported by `volren`): load a file, build views, render.

Heavy modules (Warp, the kernels) are imported inside the functions, so that ``import volren`` stays cheap.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from volren.errors import VolrenError, keyword
from volren.plan.options import SCENE_COUNT
from volren.plan.scene import flame_defaults

# the API's names for the plan's rules (tests and docs name them here)
from volren.plan.volume import BOX_OPTICAL_DEPTH, box_density_scale, volume_from_file  # noqa: F401

if TYPE_CHECKING:
    from volren.camera import Camera
    from volren.data.loaders import LoadedVolume
    from volren.plan.volume import VolumeSequence
    from volren.render.compositing.channels import Channels
    from volren.render.frame import Frame
    from volren.scene import Scene, Volume

DEFAULT_METHOD = "dssrm"
DEFAULT_QUALITY = "interactive"
"""what `volren serve` starts with; `volren render`'s default is ``default`` (the papers' settings)"""


MATERIAL = ("density_scale", "albedo", "g", "emission")
"""`Volume` fields ``load`` takes besides the reader's options"""
CHANNEL_OPTIONS = ("channel_colors", "channel_opacity")
"""what ``load`` takes for a multi-channel file (``--channel-colors``, ``--channel-opacity``)"""


def load(path: str | Path, **options: Any) -> Volume | Channels | VolumeSequence:
    """What ``volren render --volume PATH`` reads, placed in the world as it places it:

    - one volume: a `Volume`;
    - a multi-channel file (a (C, Z, Y, X) ``.npy``, an ImageJ ZCYX or OME-TIFF CZYX stack, an OME-Zarr with a
      ``c`` axis): `Channels`, one unlit volume per channel glowing in its colour, which `render` adds as the CLI
      does (``channel_colors``: names ``["green", "magenta"]``, r, g, b triples or the flag's ``"green,magenta"``;
      default the file's OME-Zarr colours, else green, magenta, cyan, ...; ``channel_opacity``: optical depth at
      density 1 across the box's longest side, one for all or one per channel, default 4);
    - a sequence: numbered files (``"sim_####.npy"``: # the zero-padded frame number; ``"sim_%04d.vdb"``; a glob
      ``"sim_*.npy"``; a folder of numbered files) or a 4-D NIfTI's time points (without ``time_point``): a lazy
      `VolumeSequence` (``len``, ``seq[i]`` a Volume or Channels read then, the next frames read ahead), which
      ``render(seq, frames=...)`` renders and `Viewer` plays.

    ``options``: the reader's (`volren.data.loaders.load_volume`): ``spacing`` (x, y, z) and ``units`` (m, cm, mm,
    um) to place a file that stores no placement; ``shape`` (X, Y, Z) and ``dtype`` for raw files; ``grid`` and
    ``emission_grid`` of a ``.vdb`` (read as bricks of its active voxels, never a dense copy of its box); ``time_point``
    of a 4-D NIfTI (one volume); an OME-Zarr's ``level`` (0 = finest) or ``memory_budget`` [GiB] (default 1), as
    ``--level`` and ``--memory-budget``: a pyramid whose finest level does not fit the budget streams, its bricks
    read as the views need them within it, a multi-channel one each channel alone in budget / C (``stream=True``
    streams any pyramid, ``stream=False`` reads the finest level that fits instead); a ``.vdb`` over
    ``memory_budget`` is refused before its leaves are read; the channel options
    above; and material fields of `Volume` (``density_scale``,
    ``albedo``, ``g``, ``emission``) to replace its defaults (not for channels: they glow unlit).
    ``density_scale`` [1/m] defaults to `box_density_scale`: density 1 has optical depth `BOX_OPTICAL_DEPTH` across
    the box's longest side, so a specimen in micrometres shows as one in metres does.

    >>> vr.load("cells.tif", channel_colors=["green", "magenta"])  # doctest: +SKIP
    Channels('cells', 2 channels of 24x24x16 float32 (x, y, z), box ... m at (0, 0, 0), green opacity 4, ...)
    """
    import inspect

    from volren.data.loaders import load_volume
    from volren.data.sequence import SequenceConfig, frame_files
    from volren.data.sequence import VolumeSequence as Reader
    from volren.plan.volume import VolumeSequence, check_memory_budget, file_channels
    from volren.scene import Scene

    reader = [n for n, p in inspect.signature(load_volume).parameters.items() if p.kind is p.KEYWORD_ONLY]
    unknown = [k for k in options if k not in reader and k not in MATERIAL and k not in CHANNEL_OPTIONS]
    if unknown:
        raise VolrenError(f"load: unknown argument {unknown[0]}: choose from "
                          f"{', '.join([*reader, *MATERIAL, *CHANNEL_OPTIONS])}")
    check_memory_budget(options.get("memory_budget"), options.get("level"), keyword)
    read = {k: v for k, v in options.items() if k in reader}
    if read.get("memory_budget") is not None:
        read["memory_budget"] = read["memory_budget"] * 2**30  # GiB, as --memory-budget; the reader counts bytes
    material = {k: v for k, v in options.items() if k in MATERIAL}
    colors, opacity = options.get("channel_colors"), options.get("channel_opacity")
    url = isinstance(path, str) and "://" in path  # an fsspec URL of an OME-Zarr store: read as `load_volume` reads it
    path = path if url else Path(path)
    name = path.rstrip("/").rsplit("/", 1)[-1] if url else path.name

    def made(loaded: LoadedVolume) -> Volume | Channels:
        if loaded.channels:
            if material:
                raise VolrenError(f"load: {path} holds {len(loaded.channels)} channels, which glow in their colours, "
                                  f"unlit: {', '.join(map(keyword, material))} would do nothing (give "
                                  "channel_colors=, channel_opacity=)")
            return file_channels(loaded, Path(name) if url else path, colors, opacity, keyword)
        given = [keyword(k) for k in CHANNEL_OPTIONS if options.get(k) is not None]
        if given:
            raise VolrenError(f"load: {', '.join(given)} apply to a multi-channel file only (a (C, Z, Y, X) array, a "
                              f"TIFF or OME-Zarr with a channel axis); {path} holds one channel")
        volume = volume_from_file(loaded, name, **material)
        if volume.emission_grid is None:
            return volume
        # a flame's emission scale for the default light and environment it renders in (`render` of a Volume), as
        # ``--volume FILE --emission-grid NAME`` sets it
        scene = Scene((volume,))
        return flame_defaults(scene.volumes, scene.lights, scene.environment)[0]

    files = None if url or options.get("time_point") is not None else frame_files(path)
    if files is None:
        return made(load_volume(path, **read))
    return VolumeSequence(path, Reader(SequenceConfig(files), lambda f, **box: load_volume(f, **read, **box)), made)


def builtin_scene(name: str, resolution: int | None = None, *, count: int | None = None, seed: int | None = None,
                  time: float | None = None) -> Scene:
    """A scene of `volren scenes`: a built-in volume scene of ``resolution`` voxels per axis (default 64; ``count``
    instances for the scenes that have several), or a fog scene at ``time`` [s] (default 0). An argument the scene
    would ignore is refused, as the CLI refuses the flag."""
    from volren.data import COUNTED_SCENES
    from volren.data import builtin_scene as volume_scene
    from volren.data.fog_scenes import FOG_SCENES, fog_scene

    given = {k: v for k, v in (("resolution", resolution), ("count", count), ("seed", seed), ("time", time))
             if v is not None}
    if name in FOG_SCENES:
        takes = {"time"}
    else:
        takes = {"resolution", "count", "seed"} if name in COUNTED_SCENES else {"resolution", "seed"}
    ignored = sorted(set(given) - takes)
    if ignored:
        raise VolrenError(f"builtin_scene: scene '{name}' takes no {', '.join(ignored)}")
    if name in FOG_SCENES:
        return fog_scene(name, **given)
    return volume_scene(name, given.pop("resolution", 64), **given)


def views(camera: Camera, mode: str | int = "stereo", *, ipd: float = 0.063) -> list[Camera]:
    """The views of ``camera``: ``mono`` (itself), ``stereo`` (two eyes ``ipd`` [m] apart, left first) or N (N
    viewers on an arc), as ``--views`` gives them."""
    from volren.camera import make_views

    return make_views(_camera(camera, "views: camera"), mode, ipd, lambda _: "views: mode")


def _camera(value: Any, what: str) -> Camera:
    from volren.camera import Camera

    if not isinstance(value, Camera):
        raise VolrenError(f"{what} must be a volren.Camera, got {type(value).__name__}")
    return value


def _view_list(value: Camera | Sequence[Camera]) -> list[Camera]:
    """A Camera is one view; a list or tuple gives several."""
    from volren.camera import Camera

    if isinstance(value, Camera):
        return [value]
    if not isinstance(value, list | tuple):
        raise VolrenError(f"views must be a volren.Camera or a list of them (volren.views), got {type(value).__name__}")
    return [_camera(v, f"views[{i}]") for i, v in enumerate(value)]


class Renderer:
    """``method`` at ``quality`` (`volren.presets`) with ``settings`` (its config's fields) on top, as ``volren
    render --method M --quality Q --samples ...`` builds it, kept across frames: temporal state (GI, denoiser and fog
    history, the light map) carries from one ``render`` call to the next. Other attributes are the method's renderer's
    (`volren.render`): ``config``, ``device``, ``gi_state``, ..."""

    def __init__(self, method: str = DEFAULT_METHOD, quality: str = DEFAULT_QUALITY, *, device: str = "auto",
                 **settings: Any) -> None:
        from volren.presets import quality_config
        from volren.render import METHODS

        config = quality_config(method, quality, **settings)  # refuses an unknown method, quality or setting
        self.method, self.quality = method, quality
        self._make = lambda: METHODS[method][0](config, device=device)
        self._renderer = self._make()
        self._channels: Any = None
        """`AdditiveChannels` for `Channels`, made at the first (one renderer per channel, as the CLI's)"""

    def __getattr__(self, name: str) -> Any:
        if name == "_renderer":  # not set: __init__ failed
            raise AttributeError(name)
        return getattr(self._renderer, name)

    def render(self, scene: Scene | Channels, views: Camera | Sequence[Camera], frame: int = 0) -> Frame:
        """Frame ``frame`` of ``scene`` for each of ``views`` (one Camera or a list, e.g. from `volren.views`). A
        `Channels` is rendered as ``volren render --volume`` renders a multi-channel file: each channel by a renderer
        of its own, the images added (`volren.render.compositing.channels.AdditiveChannels`)."""
        from volren.render.compositing.channels import AdditiveChannels, Channels
        from volren.scene import Scene, Volume

        if isinstance(scene, Channels):
            if self._channels is None or len(self._channels.renderers) != len(scene):
                self._channels = AdditiveChannels(self._make, len(scene))
            return self._channels.render(scene.scene, _view_list(views), frame)
        if not isinstance(scene, Scene):
            hint = ": wrap it as volren.Scene([volume])" if isinstance(scene, Volume) else ""
            raise VolrenError(f"scene must be a volren.Scene or Channels, got {type(scene).__name__}{hint}")
        return self._renderer.render(scene, _view_list(views), frame)


def render(scene: Scene | Volume | Channels | VolumeSequence | str | Path,
           views: Camera | Sequence[Camera] | str | int | None = None, method: str = DEFAULT_METHOD,
           quality: str = DEFAULT_QUALITY, device: str = "auto", *, width: int | None = None,
           height: int | None = None, frames: int | Iterable[int] | None = None, resolution: int | None = None,
           count: int | None = None, environment: Any = None, data_parallel: int | None = None,
           ray_address: str | None = None, **settings: Any) -> Frame | list[Frame]:
    """One frame of ``scene`` (a list of them with ``frames=``) by ``method`` at ``quality``, with ``settings``
    (fields of the method's config, e.g. ``samples=720``, ``light_grid=16``, ``mode="mip"``, ``transfer="ct-bone"``
    for ``--tf``, ``jitter=True``, ``gi=vr.GIConfig(method="sresir")``) on top of the preset, as ``volren render``
    renders it.

    ``scene`` is what ``volren render`` renders: a `Scene`; a `Volume` (e.g. from `load`), in a Scene with the
    default light and environment, as ``--volume`` gives a file; `Channels` (a multi-channel file from `load`: each
    channel rendered alone, the images added, as ``--volume`` does; dvr, mip or mida); a `VolumeSequence` (from
    `load`: frame i of the render is its frame i); a path of a file or sequence (``str`` or ``Path``, read as `load`
    reads it, an emission grid's flame scale as ``--volume`` sets it); or a built-in scene's name (`builtin_scene`
    with ``resolution`` and ``count``, as ``--scene``; a fog scene needs ``method="fog"``, as on the command line).
    ``environment``: replaces the scene's, as ``--environment`` or ``--ambient`` (a name such as ``"sky"``, an
    image file, a radiance or r, g, b, or an `Environment`).

    ``views``: a Camera or a list of them (e.g. from `volren.views`), or framed as the command line frames its
    ``--views``: ``"mono"`` (the default), ``"stereo"`` or N viewers on an arc, each ``width`` x ``height`` pixels
    (default 640 x 360, ``--width`` and ``--height``'s; `Camera`'s other defaults): a built-in volume scene by where
    its medium is (`volren.framing.framed_content`), from the direction of (0, 0.4, 3.2), a fog scene from its own
    viewpoint, anything else (a file, a Volume, a Scene of volumes) whole, looking at its volumes' box's centre from
    that direction (`volren.framing.framed_eye`),
    whatever its units (``vr.render(vr.load("stack.tif"))`` shows a micrometre stack; a stereo pair's eyes at most
    its box's size apart). Given cameras, ``width`` and ``height`` are refused (the cameras carry their size).

    ``frames``: without it, one `Frame` (a sequence: every frame, a list); given, a list of Frames (``--frames N``),
    rendered by one renderer, so temporal methods build on the frames before: an int N (frames 0 .. N-1) or the frame
    numbers (``range(2, 5)``: a sequence's frames 2, 3, 4; their index seeds the jitter). Frame i of a sequence
    shows its volume i, of an animated fog scene its time i / 30 s. ``frame.save(folder, exposure=, tonemap=)``
    writes what ``volren render --out folder --exposure --tonemap`` writes (for one frame of a run of one).

    For frames that build on each other across calls (GI, denoising, fog), keep a `Renderer`: its ``render`` takes a
    Scene (or Channels) and views, always.

    ``data_parallel``: the volume split into that many regions, each held and rendered by its own Ray actor (on the
    cluster at ``ray_address``, else a local Ray), the images composited, as ``--data-parallel`` does
    (`volren.distributed.regions`: dssrm in modes dvr, mip and iso; a path is read by each actor, a Scene or Volume
    is sent to them).

    >>> frame = vr.render(vr.load("head.nrrd"), width=320, height=180)  # doctest: +SKIP
    >>> frames = vr.render(vr.load("sim_####.npy"), frames=range(3))  # doctest: +SKIP
    """
    from volren.data.fog_scenes import FOG_SCENES

    source = _source(scene, resolution, count, settings.get("seed"))
    if source.name in FOG_SCENES and method != "fog":
        raise VolrenError(f"render: '{source.name}' is a fog scene, which method '{method}' does not render: give "
                          "method='fog'")
    if environment is not None:
        source = dataclasses.replace(source, environment=_environment(environment, source))
    indices = _frame_numbers(frames, source.length)
    if views is None or (isinstance(views, str | int) and not isinstance(views, bool)):
        views = framed_views(source.at(0), source.name, "mono" if views is None else views, width, height)
    elif width is not None or height is not None:
        raise VolrenError("render: width= and height= size the framed views; the cameras given carry their own size")
    else:
        views = _view_list(views)
    if settings.get("mode") == "iso" and "iso_value" not in settings:
        settings["iso_value"] = _otsu_iso_value(source.at(0))
    renderer = Renderer(method, quality, device=device, **settings)
    if data_parallel is not None:
        region_source = _RegionSource(scene if isinstance(scene, str | Path) else source.at(0), resolution, count,
                                      settings.get("seed"), source.environment)
        return _render_regions(region_source, source, renderer, views, indices, data_parallel, ray_address)
    if indices is None:
        return renderer.render(source.at(0), views, 0)
    return [renderer.render(source.at(i), views, i) for i in indices]


@dataclasses.dataclass(frozen=True)
class _RegionSource:
    """`render`'s scene as each region actor of ``data_parallel=`` builds it (`volren.distributed.regions`): a path
    read there, a scene passed whole; a multi-channel file's channels as their Scene."""

    value: Any
    resolution: int | None
    count: int | None
    seed: int | None
    environment: Any

    def __call__(self) -> Any:
        from volren.render.compositing.channels import Channels

        source = dataclasses.replace(_source(self.value, self.resolution, self.count, self.seed),
                                     environment=self.environment)
        scene = source.at(0)
        return scene.scene if isinstance(scene, Channels) else scene


def _render_regions(region_source: _RegionSource, source: _Source, renderer: Renderer, views: list[Camera],
                    indices: list[int] | None, n: int, address: str | None) -> Frame | list[Frame]:
    """`render`'s frames with ``data_parallel=n`` (`volren.distributed.regions.RegionEngine`)."""
    from volren.distributed.regions import RegionEngine
    from volren.render.compositing.channels import AdditiveChannels, Channels

    if source.frame is not None:
        raise VolrenError("render: data_parallel= splits one volume; a sequence or an animated scene changes it "
                          "every frame")
    first = source.at(0)
    scene, impl = first, renderer._renderer
    if isinstance(first, Channels):
        scene, impl = first.scene, AdditiveChannels(renderer._make, len(first))
    with RegionEngine(region_source, scene, n, impl, address=address, flag="render: data_parallel=") as engine:
        frames = []
        for i in [0] if indices is None else indices:
            frame = engine.render(views, i)
            frame.background, frame.scene_name = scene.background, scene.name
            frames.append(frame)
    return frames[0] if indices is None else frames


def _otsu_iso_value(scene: Any) -> float:
    """``mode="iso"`` without ``iso_value=``: Otsu's threshold of the scene's densities, said in one line, as
    ``--mode iso`` without ``--iso-value`` chooses it (a fixed 0.5 would miss a CT in Hounsfield units)."""
    import warnings

    from volren.errors import VolrenWarning
    from volren.render.marching.modes import otsu_iso_value

    densities = [v.density for v in getattr(scene, "volumes", ())]
    if not densities:
        raise VolrenError("render: mode='iso' needs iso_value= for a scene without volumes")
    value = otsu_iso_value(densities)
    warnings.warn(f"render: mode='iso' without iso_value=: the isosurface is at density {value:.4g}, Otsu's "
                  "threshold of the densities (give iso_value= to choose)", VolrenWarning, stacklevel=3)
    return value


@dataclasses.dataclass(frozen=True)
class _Source:
    """What `render` renders, frame by frame."""

    scene: Any
    """frame 0's Scene or Channels"""
    name: str | None = None
    """the built-in scene's name"""
    frame: Any = None
    """frame i's Scene or Channels (a sequence, an animated fog scene); None: ``scene`` always"""
    length: int | None = None
    """a sequence's frame count"""
    file: bool = False
    """read from a file here: its emission grid's flame scale as ``--volume`` sets it (`flame_defaults`)"""
    environment: Any = None
    """the environment that replaces the scene's"""

    def at(self, i: int) -> Any:
        """Frame i's Scene (or Channels), with the environment and the flame scale set as the CLI sets them."""
        from volren.scene import Scene

        scene = self.scene if self.frame is None or i == 0 else self.frame(i)
        if not isinstance(scene, Scene):
            return scene  # Channels: unlit, no flame
        if self.environment is not None:
            scene = dataclasses.replace(scene, environment=self.environment)
        if self.file:
            scene = dataclasses.replace(scene, volumes=flame_defaults(scene.volumes, scene.lights, scene.environment))
        return scene


def _source(value: Any, resolution: int | None, count: int | None, seed: int | None) -> _Source:
    """`render`'s ``scene`` as a `_Source`; ``resolution``, ``count`` and ``seed`` (the setting: ``--seed`` seeds a
    built-in volume scene's noise too) build a built-in scene of that name."""
    from volren.data import BUILTIN_SCENES, COUNTED_SCENES
    from volren.data.fog_scenes import ANIMATED_FOG_SCENES, FOG_SCENES
    from volren.plan.options import ANIMATION_FPS
    from volren.plan.volume import VolumeSequence
    from volren.render.compositing.channels import Channels
    from volren.scene import Scene, Volume

    names = [*BUILTIN_SCENES, *FOG_SCENES]
    if isinstance(value, str) and value in names:
        if value in FOG_SCENES:
            time = (lambda i: builtin_scene(value, time=i / ANIMATION_FPS)) if value in ANIMATED_FOG_SCENES else None
            if resolution is not None or count is not None:
                raise VolrenError(f"render: fog scene '{value}' takes no resolution= or count=")
            return _Source(builtin_scene(value), value, time)
        counted = SCENE_COUNT if count is None and value in COUNTED_SCENES else count
        return _Source(builtin_scene(value, resolution, count=counted, seed=seed), value)
    if resolution is not None or count is not None:
        raise VolrenError("render: resolution= and count= build a built-in scene: give its name, not "
                          f"a {type(value).__name__}")
    if isinstance(value, Scene | Channels):
        return _Source(value)
    if isinstance(value, Volume):
        return _Source(Scene((value,), name=Path(value.name).stem))
    if isinstance(value, VolumeSequence):
        def frame(i: int) -> Scene | Channels:
            got = value[i]
            return got if isinstance(got, Channels) else Scene((got,), name=value.path.stem)

        return _Source(frame(0), frame=frame, length=len(value), file=True)
    if not isinstance(value, str | Path):
        raise VolrenError(f"render: scene must be a volren.Scene, a Volume, Channels, a VolumeSequence, a file path or "
                          f"a built-in scene name, got {type(value).__name__}")
    from volren.data.sequence import frame_files

    if not Path(value).exists() and frame_files(value) is None:
        hint = f" nor a built-in scene ({', '.join(names)})" if isinstance(value, str) else ""
        raise VolrenError(f"render: scene '{value}' is no file{hint}")
    loaded = load(value)
    if isinstance(loaded, Volume):
        return _Source(Scene((loaded,), name=Path(value).stem), file=True)
    return _source(loaded, None, None, None)


def _environment(value: Any, source: _Source) -> Any:
    """``render``'s ``environment=``: as ``--environment`` (a name or an image file) or ``--ambient`` (a radiance
    or r, g, b), or an `Environment`; refused for channels, as the CLI refuses the flags."""
    from volren.plan.scene import named_environment
    from volren.render.compositing.channels import Channels
    from volren.scene import Environment

    if isinstance(source.scene, Channels):
        raise VolrenError("render: a multi-channel volume glows in its channel colours, unlit: environment= would do "
                          "nothing")
    if isinstance(value, Environment):
        return value
    if isinstance(value, str | Path):
        return named_environment(value)
    return Environment(value)


def _frame_numbers(frames: Any, length: int | None) -> list[int] | None:
    """``render``'s ``frames=`` as frame numbers (None: one frame, returned alone); a sequence's, all of them."""
    if frames is None:
        return None if length is None else list(range(length))
    if isinstance(frames, int) and not isinstance(frames, bool):
        if frames < 1:
            raise VolrenError(f"render: frames= must be >= 1, got {frames}")
        numbers = list(range(frames))
    else:
        try:
            numbers = list(frames)
        except TypeError:
            raise VolrenError(f"render: frames= must be a count or frame numbers, got {type(frames).__name__}") \
                from None
        if not numbers or not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in numbers):
            raise VolrenError(f"render: frames= must be a count or frame numbers >= 0, got {frames!r}")
    if length is not None and max(numbers) >= length:
        raise VolrenError(f"render: frames= {frames!r}: the sequence has {length} frames (0 to {length - 1})")
    return numbers


def framed_views(scene: Scene | Channels, name: str | None, views: str | int, width: int | None = None,
                 height: int | None = None) -> list[Camera]:
    """The views `render` frames for ``views`` (mono, stereo or N), as ``volren render --views`` places them:
    `framed_camera`, whose stereo eyes are at most the box's size apart (`volren.plan.views.framed_ipd`) and whose
    distance leaves room for them; N viewers on the arc (a fog scene's within its walkable area)."""
    from volren.camera import make_views
    from volren.data.fog_scenes import FOG_SCENES, fog_scene_walk_area
    from volren.plan.views import framed_ipd
    from volren.render.compositing.channels import Channels
    from volren.viewers import arc_viewers

    scene = scene.scene if isinstance(scene, Channels) else scene
    fog = name in FOG_SCENES or (scene.fog is not None and scene.name in FOG_SCENES)
    ipd = 0.063
    if name is None and not fog and scene.volumes:
        import numpy as np

        ipd = framed_ipd(np.concatenate([v.corners_world for v in scene.volumes]))
    stereo = isinstance(views, str) and views.strip().lower() == "stereo"
    camera = framed_camera(scene, name, width, height, eye_offset=ipd / 2 if stereo else 0.0)
    cameras = make_views(camera, views, ipd, keyword)
    if len(cameras) > 1 and not stereo:  # N viewers: on the arc, as ``--rig arc``
        cameras = arc_viewers(camera, len(cameras), fog_scene_walk_area(scene.name) if fog else None)
    return cameras


def framed_camera(scene: Scene, name: str | None = None, width: int | None = None,
                  height: int | None = None, *, eye_offset: float = 0.0) -> Camera:
    """The one camera `render` uses without views, as ``volren render`` places it (`Camera`'s defaults else): for
    the built-in volume scene ``name``, its content framed (`volren.framing.framed_content`, as for ``--scene``), or a
    fog scene's own viewpoint (also for a Scene with fog named as one); else ``scene``'s volumes framed whole
    (`volren.framing.framed_eye`, as for ``--volume``); ``eye_offset`` [m] leaves room for eyes shifted sideways
    (stereo's ipd / 2); a scene of no volumes, the default eye."""
    import numpy as np

    from volren.camera import Camera
    from volren.data.fog_scenes import FOG_SCENES, fog_scene_camera
    from volren.framing import DEFAULT_EYE, framed_content, framed_eye

    for key, value in (("width", width), ("height", height)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise VolrenError(f"render: {key}= must be a positive number of pixels, got {value!r}")
    size = {"width": Camera.width if width is None else width, "height": Camera.height if height is None else height}
    fog = name if name in FOG_SCENES else scene.name if scene.fog is not None and scene.name in FOG_SCENES else None
    if fog is not None:
        viewpoint = fog_scene_camera(fog)
        return Camera(position=viewpoint["position"], look_at=viewpoint["look_at"], **size)
    if not scene.volumes:
        return Camera(position=DEFAULT_EYE, **size)
    if name is not None:
        position, look_at, near, far = framed_content(scene.volumes, Camera.up, Camera.fov_y,
                                                      size["width"] / size["height"], eye_offset)
        return Camera(position=position, look_at=look_at, near=near, far=far, **size)
    corners = np.concatenate([v.corners_world for v in scene.volumes])
    position, look_at, near, far = framed_eye(corners, Camera.up, Camera.fov_y, size["width"] / size["height"],
                                              eye_offset=eye_offset)
    return Camera(position=position, look_at=look_at, near=near, far=far, **size)
