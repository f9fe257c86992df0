"""The renderer interface: ``render(scene, views, frame) -> Frame``; subclasses supply the per-view pass."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict
from typing import Any, ClassVar

import numpy as np
import warp as wp

from volren.camera import Camera
from volren.device import check_allocation, resolve_device
from volren.errors import VolrenError
from volren.render.frame import Frame, PassClock, Stats
from volren.scene import Scene
from volren.upload import DeviceScene, upload_scene


def frame_seed(seed: int, frame: int) -> int:
    """A 31-bit RNG seed per (seed, frame), so jittered frames differ and the same inputs repeat bit for bit."""
    return (seed * 1_000_003 + frame * 7_919 + 12_345) % (2**31 - 1)


MAX_SAMPLES = 65536
"""Cap on V and L: kernels count steps in 32-bit ints, and more samples than this per diagonal buys nothing."""


def check_transmittance_threshold(value: float) -> None:
    if not 0 <= value < 1:
        raise VolrenError(f"min_transmittance (early termination) must lie in [0, 1), got {value}")


def check_sample_count(name: str, value: int) -> None:
    if int(value) != value or not 1 <= value <= MAX_SAMPLES:
        raise VolrenError(f"{name} must be an integer in [1, {MAX_SAMPLES}], got {value}")


class Renderer:
    """Base class. A subclass has a frozen config dataclass and implements ``_render_view``."""

    name: ClassVar[str] = ""

    def __init__(self, config: Any, device: str = "auto") -> None:
        self.config = config
        self.device = resolve_device(device)
        self._device_scene: DeviceScene | None = None
        self._upload_key: tuple[int | None, bool] | None = None
        self.on_rows: Callable[[int], None] | None = None
        """Progress hook: called with the number of image rows the view pass just finished."""

    def _upload(
        self, scene: Scene, clock: PassClock, light_grid: int | None = None, mip_levels: bool = False
    ) -> DeviceScene:
        """The scene on the device, uploaded once per scene object (the cache holds the scene, so ids stay valid)."""
        ds = self._device_scene
        key = (light_grid, mip_levels)
        if ds is None or ds.scene is not scene or self._upload_key != key:
            with clock.measure("upload"):
                ds = upload_scene(scene, self.device, light_grid, mip_levels)
            self._device_scene, self._upload_key = ds, key
        return ds

    def _prepare(self, scene: Scene, clock: PassClock, frame: int) -> DeviceScene:
        """Per-frame passes shared by all views (upload, light map, ...)."""
        return self._upload(scene, clock)

    def _render_view(
        self, ds: DeviceScene, cam: Camera, view: int, frame: int, image: wp.array, depth: wp.array, clock: PassClock
    ) -> None:
        raise NotImplementedError

    def render(self, scene: Scene, views: Sequence[Camera], frame: int = 0) -> Frame:
        views = list(views)
        if not views:
            raise VolrenError("render needs at least one view")
        # RGBA + depth on the device, and their host copies.
        pixels = sum(c.width * c.height for c in views)
        check_allocation(pixels * 20 * (1 if self.device == "cpu" else 2), self.device, f"{len(views)} view image(s)")
        clock = PassClock(self.device)
        self._frame_info: dict[str, Any] = {}
        ds = self._prepare(scene, clock, frame)
        targets = []
        for v, cam in enumerate(views):
            image = wp.zeros((cam.height, cam.width), dtype=wp.vec4, device=self.device)
            depth = wp.zeros((cam.height, cam.width), dtype=float, device=self.device)
            self._render_view(ds, cam, v, frame, image, depth, clock)
            targets.append((image, depth))
        with clock.measure("readback"):
            images = [np.ascontiguousarray(img.numpy().reshape(img.shape[0], img.shape[1], 4)) for img, _ in targets]
            depths = [d.numpy() for _, d in targets]
        for d in depths:
            d[d >= 1e29] = np.inf
        settings = {"views": len(views), "resolution": [[c.width, c.height] for c in views], **asdict(self.config)}
        stats = Stats(self.device, self.name, settings, clock.times_ms, clock.counter_values(), self._frame_info)
        return Frame(images, depths, stats, frame)
