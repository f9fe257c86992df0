"""Multi-channel volumes (fluorescence microscopy) composed additively, as napari's 'additive' blending does.

Each channel is its own density in the march, attenuating only itself: a scene of C channel volumes at one placement
is rendered one volume at a time, each by its own renderer (its own upload, light map, cube maps and history), and the
premultiplied images are summed. The cost is C renders of one volume each: C marches, C uploads.

Material (fluorescence is emission): a channel of colour c and opacity k has extinction sigma_t = k * rho / D (D the
box's longest side [m], so k is the optical depth at density 1 across it, whatever the sample's size: micrometres or
metres), emission c * sigma_t and no scattering (albedo 0: lights, ambient and GI do not light it). Emission in
proportion to extinction integrates in closed form along any ray to RGB = c * alpha_c (alpha_c = 1 - T_c): each
channel shows its colour, in proportion to its own opacity. The sum's alpha is 1 - prod_c (1 - alpha_c), the
transmittance of the background through every channel (always in [0, 1]); its RGB may exceed alpha where channels
overlap, as additive blending does (the tone map or the PNG's clamp limits it).

Sci-vis modes (`volren.render.marching.modes`): MIDA composites the channels' emission as DVR does. MIP renders each
channel's maximum intensity P (its own densities' maximum is P = 1) as a grey pixel, which `channel_mip` tints with
the channel's colour (emission / sigma_t; a channel of opacity 0 stays dark) before the sum: RGB = sum_c c_c P_c,
napari's additive MIP. Iso is refused: a surface lit by nothing would be black.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from volren.camera import Camera
from volren.errors import VolrenError, flag
from volren.render.frame import Frame, Stats
from volren.scene import RGB, Environment, Scene, Volume, box_longest_side, box_sides

NAMED_COLORS: dict[str, RGB] = {
    "green": (0.0, 1.0, 0.0), "magenta": (1.0, 0.0, 1.0), "cyan": (0.0, 1.0, 1.0), "yellow": (1.0, 1.0, 0.0),
    "red": (1.0, 0.0, 0.0), "blue": (0.0, 0.0, 1.0), "orange": (1.0, 0.5, 0.0), "white": (1.0, 1.0, 1.0),
    "gray": (0.5, 0.5, 0.5), "grey": (0.5, 0.5, 0.5),
}
PALETTE = ("green", "magenta", "cyan", "yellow", "red", "blue", "orange", "white")
"""default channel colours in order: green and magenta first (the colour-blind-safe pair of two-channel images)"""
DEFAULT_OPACITY = 4.0
"""k: optical depth at density 1 across the volume's longest side"""


def parse_channel_colors(text: str, words: Callable[[str], str] = flag) -> tuple[RGB, ...]:
    """``--channel-colors``: names (``green,magenta``) or ``r,g,b`` triples in [0, 1] separated by ``;``
    (``1,0,0;0,1,0``; names may mix in: ``red;0,0.5,1``)."""
    items = text.split(";") if ";" in text else text.split(",") if text.replace(",", "").isalpha() else [text]
    return tuple(_color(item, words) for item in items)


def _color(item: str | Sequence[float], words: Callable[[str], str] = flag) -> RGB:
    """One channel colour: a name of `NAMED_COLORS`, ``"r,g,b"`` or (r, g, b), each in [0, 1]."""
    if isinstance(item, str):
        if item.strip().lower() in NAMED_COLORS:
            return NAMED_COLORS[item.strip().lower()]
        try:
            rgb = tuple(float(v) for v in item.split(","))
        except ValueError:
            rgb = ()
    else:
        try:
            rgb = tuple(float(v) for v in item)
        except (TypeError, ValueError):
            rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        shown = item.strip().lower() if isinstance(item, str) else item
        raise VolrenError(f"{words('channel_colors')}: '{shown}' is neither a colour name ({', '.join(NAMED_COLORS)}) "
                          "nor r,g,b in [0, 1]; separate channels by ';' (or names by ',')")
    return rgb  # type: ignore[return-value]


def channel_volumes(
    channels: Sequence[np.ndarray],
    to_world: np.ndarray,
    *,
    colors: Sequence[RGB] | None = None,
    opacity: Sequence[float] | None = None,
    name: str = "volume",
    words: Callable[[str], str] = flag,
) -> tuple[Volume, ...]:
    """One emissive `Volume` per channel at ``to_world`` (module docstring): colour ``colors[c]`` (default
    `PALETTE`; a name of `NAMED_COLORS` or r, g, b), opacity ``opacity[c]`` (default `DEFAULT_OPACITY`, one value
    for all or one per channel); errors name the options in ``words`` (`volren.errors.flag` or `keyword`)."""
    count = len(channels)
    if colors is None:
        colors = [NAMED_COLORS[PALETTE[c % len(PALETTE)]] for c in range(count)]
    elif isinstance(colors, str):
        colors = parse_channel_colors(colors, words)
    else:
        colors = [_color(c, words) for c in colors]
    if len(colors) != count:
        raise VolrenError(f"{words('channel_colors')} gives {len(colors)} colour(s) for a volume of {count} channels")
    opacity = [DEFAULT_OPACITY] if opacity is None else list(np.atleast_1d(opacity))
    if len(opacity) not in (1, count) or not all(np.isfinite(k) and k >= 0 for k in opacity):
        raise VolrenError(f"{words('channel_opacity')} must be one value >= 0 or one per channel ({count}), got "
                          f"{[float(k) for k in opacity]}")
    opacity = opacity * count if len(opacity) == 1 else opacity
    longest = box_longest_side(to_world)  # [m]
    return tuple(
        Volume(density, to_world, density_scale=k / longest, albedo=(0.0, 0.0, 0.0),
               emission=tuple(float(v) * k / longest for v in rgb), name=f"{name}[c{c}]")
        for c, (density, rgb, k) in enumerate(zip(channels, colors, opacity, strict=True))
    )


@dataclass(frozen=True, repr=False)
class Channels:
    """A multi-channel volume, as `volren.load` reads a multi-channel TIFF, (C, Z, Y, X) array or OME-Zarr: one
    unlit, emissive `Volume` per channel at one placement (`channel_volumes`: its colour and opacity), which
    `volren.render` renders as ``volren render --volume`` does, each channel marched alone and the images added
    (`AdditiveChannels`; methods dssrm, cmsrm, cacrm, reference; modes dvr, mip, mida)."""

    volumes: tuple[Volume, ...]
    """channel c's volume: density normalised by the channel's own range, emission its colour x its extinction"""
    name: str = "channels"
    """the scene's name (the file's stem)"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "volumes", tuple(self.volumes))
        if not self.volumes or not all(isinstance(v, Volume) for v in self.volumes):
            raise VolrenError("Channels holds one volren.Volume per channel, at least one")

    def __len__(self) -> int:
        return len(self.volumes)

    def __getitem__(self, c: int) -> Volume:
        return self.volumes[c]

    @property
    def colors(self) -> tuple[RGB, ...]:
        """Each channel's colour (`channel_color`)."""
        return tuple(tuple(round(float(v), 6) for v in channel_color(vol)) for vol in self.volumes)

    @property
    def opacity(self) -> tuple[float, ...]:
        """Each channel's optical depth at density 1 across the box's longest side (``--channel-opacity``)."""
        return tuple(vol.density_scale * box_longest_side(vol.to_world) for vol in self.volumes)

    @property
    def scene(self) -> Scene:
        """The channels as ``volren render --volume`` renders them: no lights, a black environment (they glow)."""
        return Scene(self.volumes, lights=(), environment=Environment((0.0, 0.0, 0.0)), name=self.name)

    def __repr__(self) -> str:
        """A summary: the grid and box (`Volume.__repr__`'s words) and each channel's colour and opacity."""
        first = self.volumes[0]
        nx, ny, nz = first.resolution
        centre = ", ".join(f"{c:.3g}" for c in first.center_world)
        names = {rgb: n for n, rgb in reversed(NAMED_COLORS.items())}
        shown = [f"{names.get(rgb, rgb)} opacity {k:.3g}" for rgb, k in zip(self.colors, self.opacity, strict=True)]
        return (f"Channels({self.name!r}, {len(self)} channels of {nx}x{ny}x{nz} {first.density.dtype} (x, y, z), "
                f"box {' x '.join(f'{e:.3g}' for e in box_sides(first.to_world))} m at ({centre}), "
                f"{', '.join(shown)})")


def add_channels(frames: Sequence[Frame]) -> Frame:
    """The channels' frames summed: RGB added, alpha = 1 - prod (1 - alpha_c), depth the nearest channel's; pass
    times and work counters summed, each channel's info kept."""
    first = frames[0]
    images, depths = [], []
    for v in range(len(first.images)):
        image, depth = add_channel_images([f.images[v] for f in frames], [f.depths[v] for f in frames])
        images.append(image)
        depths.append(depth)
    times: dict[str, float] = {}
    counters: dict[str, int] = {}
    for f in frames:
        for k, t in f.stats.times_ms.items():
            times[k] = times.get(k, 0.0) + t
        for k, n in f.stats.counters.items():
            counters[k] = counters.get(k, 0) + n
    settings = {**first.stats.settings, "channels": len(frames), "channel_blending": "additive"}
    info = {"channels": [f.stats.info for f in frames]}
    return Frame(images, depths, Stats(first.stats.device, first.stats.method, settings, times, counters, info),
                 first.index)


def add_channel_images(rgba: Sequence[np.ndarray], depths: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """One view's channel images summed (`add_channels`): RGB added, alpha = 1 - prod (1 - alpha_c), depth the
    nearest channel's."""
    image = np.sum(rgba, axis=0, dtype=np.float32)
    image[..., 3] = 1.0 - np.prod([1.0 - im[..., 3] for im in rgba], axis=0)
    return image, np.min(depths, axis=0)


def tint_mip(image: np.ndarray, color: np.ndarray) -> np.ndarray:
    """A channel's grey MIP image (RGB = alpha = P) with its RGB tinted by ``color`` (`channel_color`)."""
    tinted = image.copy()
    tinted[..., :3] *= color
    return tinted


def channel_color(volume: Volume) -> np.ndarray:
    """A channel volume's colour (`channel_volumes`): its emission per unit extinction; black for opacity 0."""
    if volume.density_scale <= 0:
        return np.zeros(3, np.float32)
    return np.asarray(volume.emission, np.float32) / np.float32(volume.density_scale)


def channel_mip(frame: Frame, volume: Volume) -> Frame:
    """A channel's MIP frame (grey: RGB = alpha = P) with its RGB tinted by the channel's colour (`channel_color`)."""
    color = channel_color(volume)
    return replace(frame, images=[tint_mip(image, color) for image in frame.images])


class AdditiveChannels:
    """A renderer for a scene whose volumes are channels (`channel_volumes`): each volume rendered alone by its own
    renderer from ``make_renderer``, the frames added (`add_channels`). It takes and passes on what a renderer
    takes (``config``, ``on_rows``), so the CLI drives it as one."""

    METHODS = ("dssrm", "cmsrm", "cacrm", "reference")
    """the methods whose emission a channel uses: vpt's transfer function replaces the material, fog renders fog"""

    def __init__(self, make_renderer: Callable[[], Any], count: int) -> None:
        self.renderers = [make_renderer() for _ in range(count)]
        if self.renderers[0].name not in self.METHODS:
            raise VolrenError(f"a multi-channel volume renders with {', '.join(self.METHODS)}, not with method "
                              f"'{self.renderers[0].name}'")
        self.device = self.renderers[0].device
        self.name = self.renderers[0].name
        self._check_mode(self.renderers[0].config)
        self._scenes: tuple[Scene, tuple[Scene, ...]] | None = None

    @property
    def config(self) -> Any:
        return self.renderers[0].config

    @config.setter
    def config(self, value: Any) -> None:
        self._check_mode(value)
        for r in self.renderers:
            r.config = value

    @staticmethod
    def _check_mode(config: Any) -> None:
        if getattr(config, "mode", "dvr") == "iso":
            raise VolrenError("mode iso (--mode iso) draws a lit surface; a multi-channel volume glows unlit, so its "
                              "surfaces would be black: use mode dvr, mip or mida")

    @property
    def on_rows(self) -> Callable[[int], None] | None:
        return self.renderers[0].on_rows

    @on_rows.setter
    def on_rows(self, value: Callable[[int], None] | None) -> None:
        for r in self.renderers:
            r.on_rows = value

    def _channel_scenes(self, scene: Scene) -> tuple[Scene, ...]:
        """One scene per channel, made once per scene object (a renderer uploads a scene once per object)."""
        if len(scene.volumes) != len(self.renderers):
            raise VolrenError(f"scene '{scene.name}' has {len(scene.volumes)} volume(s) for {len(self.renderers)} "
                              "channel renderer(s)")
        if scene.opaque:
            raise VolrenError("a multi-channel volume is drawn without opaque geometry (--sphere, --ground, --mesh): "
                              "each channel's render would add the surfaces once more")
        if self._scenes is None or self._scenes[0] is not scene:
            self._scenes = (scene, tuple(replace(scene, volumes=(v,), name=f"{scene.name}[c{c}]")
                                         for c, v in enumerate(scene.volumes)))
        return self._scenes[1]

    def render(
        self,
        scene: Scene,
        views: Sequence[Camera],
        frame: int = 0,
        *,
        occluder_depth: Sequence[np.ndarray | None] | None = None,
    ) -> Frame:
        scenes = self._channel_scenes(scene)
        frames = [r.render(s, views, frame, occluder_depth=occluder_depth)
                  for r, s in zip(self.renderers, scenes, strict=True)]
        if getattr(self.config, "mode", "dvr") == "mip":
            frames = [channel_mip(f, s.volumes[0]) for f, s in zip(frames, scenes, strict=True)]
        return add_channels(frames)
