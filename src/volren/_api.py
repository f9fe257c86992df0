"""The public API's functions and its temporal renderer (re-exported by `volren`): load a file, build views, render.

Heavy modules (Warp, the kernels) are imported inside the functions, so that ``import volren`` stays cheap.
"""

from __future__ import annotations

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


def box_longest_side(to_world: Any) -> float:
    """[m] the longest side of the box that ``to_world`` maps the local cube [-1, 1]^3 onto."""
    import numpy as np

    return 2.0 * float(np.max(np.linalg.norm(np.asarray(to_world, dtype=np.float64)[:3, :3], axis=0)))


def box_density_scale(to_world: Any) -> float:
    """[1/m] a loaded volume's default density_scale: `BOX_OPTICAL_DEPTH` / its box's longest side, so density 1
    has the same optical depth across the box in micrometres as in metres (ParaView's scalar opacity unit distance
    relative to the data's bounds; the rule the channels of a multi-channel file follow with their own constant)."""
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


def render(scene: Scene, views: Camera | Sequence[Camera], method: str = DEFAULT_METHOD,
           quality: str = DEFAULT_QUALITY, device: str = "auto", **settings: Any) -> Frame:
    """One frame of ``scene`` for ``views`` (a Camera or a list) by ``method`` at ``quality``, with ``settings``
    (fields of the method's config, e.g. ``samples=720``) on top of the preset. For frames that build on each
    other (GI, denoising, fog), keep a `Renderer`."""
    return Renderer(method, quality, device=device, **settings).render(scene, views)
