"""The public API's functions and its temporal renderer (re-exported by `volren`): load a file, build views, render.

Heavy modules (Warp, the kernels) are imported inside the functions, so that ``import volren`` stays cheap.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from volren.errors import VolrenError

if TYPE_CHECKING:
    from volren.camera import Camera
    from volren.data.loaders import LoadedVolume
    from volren.render.frame import Frame
    from volren.scene import Scene, Volume

DEFAULT_METHOD = "dssrm"
DEFAULT_QUALITY = "interactive"
"""what `volren serve` starts with; `volren render`'s default is ``default`` (the papers' settings)"""


BOX_OPTICAL_DEPTH = 20.0
"""K: a loaded volume's default optical depth at density 1 (the top of its value mapping) across its box's longest
side, whatever its units (`box_density_scale`). 20 keeps the density_scale of 10 /m that files had before on the
2 m box of a file that stores no placement (so those render as before), shows a sparse specimen (a ball filling a
fifth of the box's side at density 1: optical depth 4), and makes a dense block opaque but not a solid wall of
one voxel (a 64-voxel side: 0.3 a voxel)."""


def box_density_scale(to_world: Any) -> float:
    """[1/m] a loaded volume's default density_scale: `BOX_OPTICAL_DEPTH` / its box's longest side, so density 1
    has the same optical depth across the box in micrometres as in metres (ParaView's scalar opacity unit distance
    relative to the data's bounds; the rule the channels of a multi-channel file follow with their own constant)."""
    from volren.scene import box_longest_side

    return BOX_OPTICAL_DEPTH / box_longest_side(to_world)


def volume_from_file(loaded: LoadedVolume, name: str, **material: Any) -> Volume:
    """A loaded file as a Volume (`volren load`, ``volren render --volume``): its placement, its emission grid, and
    its value range when that is Hounsfield units (CT transfer functions classify by HU; a constant file, lo = hi,
    has no HU scale). Without a ``density_scale`` in ``material`` it is `box_density_scale` (its box sets its
    opacity, whatever the file's units); given, it is per metre as everywhere. An emission grid whose values look like
    kelvin (`volren.blackbody.kelvin_span`) is read as kelvin, temperature range (0, its hottest): T = v; else its
    values are relative, 0+ to max at 1000-3000 K."""
    from volren.blackbody import kelvin_span
    from volren.scene import Volume

    hu = loaded.hounsfield and loaded.value_range[1] > loaded.value_range[0]
    if material.get("density_scale") is None:
        material["density_scale"] = box_density_scale(loaded.to_world)
    if loaded.emission_source is not None and "temperature_range" not in material:
        span = kelvin_span(loaded.emission_source)
        if span is not None:
            material = {**material, "temperature_range": (0.0, span[1])}
    return Volume(loaded.density, loaded.to_world, name=name, value_range=loaded.value_range if hu else None,
                  emission_grid=loaded.emission_source, **material)


def flame_defaults(volumes: tuple, lights, environment) -> tuple:
    """A file's volumes with the default emission scale of their emission grids (`flame_emission_scale`, relative
    to the white W = sum(Y(directional irradiance)) / pi + Y(mean environment radiance) of these lights; W = 3 / pi,
    the default light's, where there is no light)."""
    import numpy as np

    from volren.blackbody import flame_emission_scale, luminance
    from volren.scene import DirectionalLight

    white = sum(float(luminance(lt.irradiance)) for lt in lights if isinstance(lt, DirectionalLight)) / math.pi
    white += float(luminance(environment.mean_radiance()))
    white = white if white > 0 else float(luminance(DirectionalLight().irradiance)) / math.pi
    out = []
    for v in volumes:
        if v.emission_grid is not None:
            voxel = abs(float(np.linalg.det(v.to_world[:3, :3]))) * 8.0 / v.density.size
            scale = flame_emission_scale(v.emission_u, v.density, v.density_scale, *v.temperature_range, voxel, white)
            v = dataclasses.replace(v, emission_scale=scale)
        out.append(v)
    return tuple(out)


MATERIAL = ("density_scale", "albedo", "g", "emission")
"""`Volume` fields ``load`` takes besides the reader's options"""


def load(path: str | Path, **options: Any) -> Volume:
    """A density file placed in the world, as ``volren render --volume`` reads it. ``options``: the reader's
    (`volren.data.loaders.load_volume`: ``spacing`` and ``units`` to place a file that stores no placement, ``shape``
    and ``dtype`` for raw files, ...) and material fields of `Volume` (``density_scale``, ``albedo``, ``g``,
    ``emission``) to replace its defaults. ``density_scale`` [1/m] defaults to `box_density_scale`: density 1 has
    optical depth `BOX_OPTICAL_DEPTH` across the box's longest side, so a specimen in micrometres shows as one in
    metres does."""
    import inspect

    from volren.data.loaders import load_volume

    reader = [n for n, p in inspect.signature(load_volume).parameters.items() if p.kind is p.KEYWORD_ONLY]
    unknown = [k for k in options if k not in reader and k not in MATERIAL]
    if unknown:
        raise VolrenError(f"load: unknown argument {unknown[0]}: choose from {', '.join([*reader, *MATERIAL])}")
    loaded = load_volume(path, **{k: v for k, v in options.items() if k in reader})
    if loaded.channels:
        raise VolrenError(f"load: {path} holds {len(loaded.channels)} channels and load returns one volume "
                          "(`volren render --volume` renders them all)")
    return volume_from_file(loaded, Path(path).name, **{k: v for k, v in options.items() if k in MATERIAL})


SCENE_COUNT = 16
"""instances in a scene of several (`volren.data.COUNTED_SCENES`) that ``volren render --scene`` and `render` of its
name build without ``--count``"""


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

    return make_views(_camera(camera, "views: camera"), mode, ipd)


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
        self._renderer = METHODS[method][0](config, device=device)

    def __getattr__(self, name: str) -> Any:
        if name == "_renderer":  # not set: __init__ failed
            raise AttributeError(name)
        return getattr(self._renderer, name)

    def render(self, scene: Scene, views: Camera | Sequence[Camera], frame: int = 0) -> Frame:
        """Frame ``frame`` of ``scene`` for each of ``views`` (one Camera or a list, e.g. from `volren.views`)."""
        from volren.scene import Scene, Volume

        if not isinstance(scene, Scene):
            hint = ": wrap it as volren.Scene([volume])" if isinstance(scene, Volume) else ""
            raise VolrenError(f"scene must be a volren.Scene, got {type(scene).__name__}{hint}")
        return self._renderer.render(scene, _view_list(views), frame)


def render(scene: Scene | Volume | str | Path, views: Camera | Sequence[Camera] | None = None,
           method: str = DEFAULT_METHOD, quality: str = DEFAULT_QUALITY, device: str = "auto", *,
           width: int | None = None, height: int | None = None, **settings: Any) -> Frame:
    """One frame of ``scene`` for ``views`` (a Camera or a list, e.g. from `volren.views`) by ``method`` at
    ``quality``, with ``settings`` (fields of the method's config, e.g. ``samples=720``) on top of the preset.

    ``scene`` is what ``volren render`` renders: a `Scene`; a `Volume` (e.g. from `load`), in a Scene with the
    default light and environment, as ``--volume`` gives a file; a path of a file (``str`` or ``Path``, read as
    `load` reads it, an emission grid's flame scale as ``--volume`` sets it); or a built-in scene's name
    (`builtin_scene`, as ``--scene``; a fog scene needs ``method="fog"``, as on the command line).

    Without ``views`` it is framed as the command line frames it, in one view of ``width`` x ``height`` pixels
    (default 640 x 360, ``--width`` and ``--height``'s; `Camera`'s other defaults): a built-in volume scene from
    (0, 0.4, 3.2) m looking at the origin, a fog scene from its own viewpoint, anything else (a file, a Volume, a
    Scene of volumes) whole, looking at its volumes' box's centre from that direction (`volren.framing.framed_eye`),
    whatever its units: ``vr.render(vr.load("stack.tif"))`` shows a micrometre stack. Given ``views``, ``width``
    and ``height`` are refused (the cameras carry their size).

    For frames that build on each other (GI, denoising, fog), keep a `Renderer`: its ``render`` takes a Scene and
    views, always.

    >>> frame = vr.render(vr.load("head.nrrd"), width=320, height=240)  # doctest: +SKIP
    """
    from volren.data.fog_scenes import FOG_SCENES

    scene, name = _scene_of(scene)
    if name in FOG_SCENES and method != "fog":
        raise VolrenError(f"render: '{name}' is a fog scene, which method '{method}' does not render: give "
                          "method='fog'")
    if views is None:
        views = framed_camera(scene, name, width, height)
    elif width is not None or height is not None:
        raise VolrenError("render: width= and height= size the framed camera; the views= given carry their own size")
    return Renderer(method, quality, device=device, **settings).render(scene, views)


def _scene_of(value: Any) -> tuple[Scene, str | None]:
    """(the Scene `render` renders for ``value``, the built-in scene's name or None)."""
    from volren.data import BUILTIN_SCENES
    from volren.data.fog_scenes import FOG_SCENES
    from volren.scene import Scene, Volume

    if isinstance(value, Scene):
        return value, None
    if isinstance(value, Volume):
        return Scene((value,), name=Path(value.name).stem), None
    names = [*BUILTIN_SCENES, *FOG_SCENES]
    if isinstance(value, str) and value in names:
        from volren.data import COUNTED_SCENES

        return builtin_scene(value, count=SCENE_COUNT if value in COUNTED_SCENES else None), value
    if not isinstance(value, str | Path):
        raise VolrenError(f"render: scene must be a volren.Scene, a Volume, a file path or a built-in scene name, "
                          f"got {type(value).__name__}")
    if not Path(value).is_file():
        hint = f" nor a built-in scene ({', '.join(names)})" if isinstance(value, str) else ""
        raise VolrenError(f"render: scene '{value}' is no file{hint}")
    volume = load(value)
    scene = Scene((volume,), name=Path(value).stem)
    return dataclasses.replace(scene, volumes=flame_defaults(scene.volumes, scene.lights, scene.environment)), None


def framed_camera(scene: Scene, name: str | None = None, width: int | None = None,
                  height: int | None = None) -> Camera:
    """The one camera `render` uses without views, as ``volren render`` places it (`Camera`'s defaults else): for
    the built-in volume scene ``name``, its content framed (`volren.framing.framed_content`, as for ``--scene``), or a
    fog scene's own viewpoint (also for a Scene with fog named as one); else ``scene``'s volumes framed whole
    (`volren.framing.framed_eye`, as for ``--volume``); a scene of no volumes, the default eye."""
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
        position, look_at, near = framed_content(scene.volumes, Camera.up, Camera.fov_y,
                                                 size["width"] / size["height"])
        return Camera(position=position, look_at=look_at, near=near, **size)
    corners = np.concatenate([v.corners_world for v in scene.volumes])
    position, look_at, near = framed_eye(corners, Camera.up, Camera.fov_y, size["width"] / size["height"])
    return Camera(position=position, look_at=look_at, near=near, **size)
