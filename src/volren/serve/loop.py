"""The render loop of `volren serve`: one asyncio task owns the renderer, its temporal state and the shared scene.

Each tick takes every connected viewer's newest camera, renders all their views in ONE multi-view ``render`` call (a
stereo viewer's two eyes adjacent, so CACRM couples them; the light map, GI update, fog shadow grid and majorants are
computed once for everyone), splits the images, JPEG-encodes them, and hands each viewer its frame unless the
previous one is still being sent (then the frame is dropped: latest-camera-wins, no queue). The render and the
encoding run in a worker thread (`asyncio.to_thread`), so the event loop keeps reading messages meanwhile.

A tick runs only when some viewer that is free to receive needs a frame: its camera or size changed, the shared
settings changed, or the scene is playing. No viewers, no rendering.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from volren.camera import Camera
from volren.errors import VolrenError
from volren.presets import QUALITIES, quality_config
from volren.render import METHODS
from volren.render.base import LightMapMarchConfig
from volren.render.fog.renderer import FogRenderer
from volren.scene import DirectionalLight, Scene
from volren.serve.jpeg import JPEG_QUALITY, display_image, encode_jpeg
from volren.serve.protocol import Choices, Settings, error_message, pack_frame
from volren.serve.viewers import Limits, Viewer, ViewerSet
from volren.transfer import PRESETS

log = logging.getLogger("volren.serve")

ANIMATION_FPS = 30.0
"""[frames/s of scene time] one animation step per tick while playing, as `volren animate` renders them"""
DENSITY_TF = "density"
"""the transfer-function choice meaning none: extinction proportional to density (vpt's default)"""
LIVE_METHODS = ("dssrm", "cmsrm", "cacrm", "vpt", "fog")
"""offered live; the reference (per-sample shadow rays, seconds per frame) is the offline ground truth"""
FPS_WINDOW_S = 2.0


def scene_methods(scene: Scene) -> tuple[str, ...]:
    """The live methods that can render ``scene``: volume methods need volumes, fog needs the scene's fog."""
    out = []
    for m in LIVE_METHODS:
        cls = METHODS[m][0]
        if (cls is FogRenderer and scene.fog is None) or (cls.needs_volumes and not scene.volumes):
            continue
        out.append(m)
    return tuple(out)


def with_light(scene: Scene, direction: tuple[float, float, float] | None) -> Scene:
    """``scene`` with its first directional light travelling along ``direction`` (one added if it has none)."""
    if direction is None:
        return scene
    lights = list(scene.lights)
    idx = next((i for i, light in enumerate(lights) if isinstance(light, DirectionalLight)), None)
    if idx is None:
        lights.append(DirectionalLight(direction=direction))
    else:
        lights[idx] = dataclasses.replace(lights[idx], direction=direction)
    return dataclasses.replace(scene, lights=tuple(lights))


def animator(scene: Scene, name: str | None, device: str) -> Callable[[], Scene] | None:
    """The next scene of ``scene``'s animation at each call, or None when it has none: a volume scene plays the
    advected smoke (`volren.simulate`: its first volume one semi-Lagrangian step further per call), an animated fog
    scene (`ANIMATED_FOG_SCENES`, by ``name``) moves its geometry 1 / ANIMATION_FPS s on."""
    from volren.data.fog_scenes import ANIMATED_FOG_SCENES, fog_scene

    if scene.volumes:
        from volren.simulate import advected_frames

        frames = advected_frames(scene, 2**62, fps=ANIMATION_FPS, device=device)
        next(frames)  # the scene itself
        return lambda: next(frames)
    if name in ANIMATED_FOG_SCENES:
        steps = iter(range(1, 2**62))
        return lambda: fog_scene(name, next(steps) / ANIMATION_FPS)
    return None


class RenderLoop:
    """The shared renderer and its viewers. ``animate`` gives the next scene of an animation (None: not animated).
    ``shared=False`` is the naive server of the benchmark: each viewer rendered by its own renderer (own light map,
    shadow grid, majorants and history), one call per viewer, as if every viewer had a server of its own.
    ``overrides`` are config fields on top of the quality preset (tests use small light grids)."""

    def __init__(self, scene: Scene, method: str, quality: str = "interactive", *, limits: Limits | None = None,
                 camera: Camera | None = None, device: str = "cpu", shared: bool = True, ipd: float = 0.063,
                 jpeg_quality: int = JPEG_QUALITY, animate: Callable[[], Scene] | None = None,
                 overrides: dict[str, Any] | None = None) -> None:
        self.methods = scene_methods(scene)
        if method not in self.methods:
            raise VolrenError(f"--method: '{method}' cannot serve scene '{scene.name}': choose from "
                              f"{', '.join(self.methods)}")
        if quality not in QUALITIES:
            raise VolrenError(f"--quality: unknown quality '{quality}': choose from {', '.join(QUALITIES)}")
        if not 1 <= jpeg_quality <= 100:
            raise VolrenError(f"JPEG quality must lie in [1, 100], got {jpeg_quality}")
        self.limits = limits or Limits()
        self.choices = Choices(self.methods, QUALITIES, (DENSITY_TF, *PRESETS))
        self.viewers = ViewerSet(self.limits.max_viewers)
        self.camera = camera or Camera(position=(0.0, 0.4, 3.2))
        self.device, self.shared, self.ipd, self.jpeg_quality = device, shared, ipd, jpeg_quality
        self.overrides = dict(overrides or {})
        self.method, self.quality, self.tf = method, quality, DENSITY_TF
        self.light_dir: tuple[float, float, float] | None = None
        self.playing = False
        self._animate = animate
        self._frame_scene = scene
        """the scene of the current animation step, before the light override"""
        self.scene = scene
        self.version = 0
        """bumped by every change of the shared scene or settings; a viewer shown an older one needs a frame"""
        self._renderer_key: tuple | None = None
        self._config: Any = None
        self._renderer_cls: Any = None
        self.renderer: Any = None
        self._own: dict[int, Any] = {}
        """shared=False: viewer id -> that viewer's renderer"""
        self._build_renderer()
        # counters (/health, tests, the bench)
        self.tick = 0
        self.renders = 0
        self.views_last = 0
        self.pass_ms: dict[str, float] = {}
        self.render_ms = 0.0
        self.encode_ms = 0.0
        self._tick_times: deque[float] = deque(maxlen=256)
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None

    @property
    def animated(self) -> bool:
        return self._animate is not None

    # ---- settings -------------------------------------------------------------------------------------------

    def _build_renderer(self) -> None:
        """The renderer(s) for the current method and quality. A transfer-function switch only replaces the config's
        ``transfer`` (as `volren animate` does), so a renderer keeps its history (VPT's denoiser) and rebuilds its
        majorants itself."""
        cls, config_cls = METHODS[self.method]
        fields = {f.name for f in dataclasses.fields(config_cls)}
        if (self.method, self.quality) != self._renderer_key:
            self._renderer_cls = cls
            options = {k: v for k, v in self.overrides.items() if k in fields}
            if issubclass(config_cls, LightMapMarchConfig):
                options["reuse_light_map"] = True
            self._config = quality_config(self.method, self.quality, **options)
            self.renderer = self._make_renderer()
            self._own = {}
            self._renderer_key = (self.method, self.quality)
        transfer = None if self.tf == DENSITY_TF else self.tf
        if "transfer" in fields and self._config.transfer != transfer:
            self._config = dataclasses.replace(self._config, transfer=transfer)
            for r in (self.renderer, *self._own.values()):
                r.config = self._config

    def _make_renderer(self) -> Any:
        """(also from the worker thread, for a new viewer of the naive server: settings may change meanwhile, so
        the class and config are those `_build_renderer` fixed for this tick)"""
        return self._renderer_cls(self._config, device=self.device)

    def shared_settings(self) -> dict[str, Any]:
        return {"method": self.method, "quality": self.quality, "tf": self.tf,
                "light_dir": list(self.light_dir or self._scene_light()), "playing": self.playing}

    def _scene_light(self) -> tuple[float, float, float]:
        light = next((lt for lt in self.scene.lights if isinstance(lt, DirectionalLight)), DirectionalLight())
        return light.direction

    def apply(self, settings: Settings, viewer: Viewer) -> bool:
        """Apply a settings message from ``viewer``; True when a shared setting changed (to tell the others)."""
        if settings.stereo is not None and settings.stereo != viewer.stereo:
            viewer.resize(viewer.width, viewer.height, settings.stereo, self.limits)
        changed = {name for name in ("method", "quality", "tf", "light_dir", "playing")
                   if getattr(settings, name) is not None and getattr(settings, name) != getattr(self, name)}
        for name in changed:
            setattr(self, name, getattr(settings, name))
        if "light_dir" in changed:
            self.scene = with_light(self._frame_scene, self.light_dir)
        if changed:
            self.version += 1
        self.wake()
        return bool(changed)

    # ---- the loop -------------------------------------------------------------------------------------------

    def wake(self) -> None:
        self._wake.set()

    def start(self) -> None:
        self._task = asyncio.create_task(self.run(), name="volren render loop")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            except Exception:  # it had died already (a bug): say so, and still shut down
                log.exception("the render loop had failed")
        for v in list(self.viewers.viewers.values()):
            for task in (v.sending, v.texting):
                if task is not None:
                    task.cancel()

    def _due(self) -> bool:
        """Some viewer free to receive needs a frame (new camera, size or settings, or the scene plays)."""
        return any(not v.busy and ((self.playing and self.animated) or v.shown != (v.camera_id, self.version))
                   for v in self.viewers.render_order())

    async def run(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._due():
                try:
                    await self.step()
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # never let one bad tick end the loop: tell the viewers, carry on
                    log.exception("render tick failed")
                    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    self.broadcast(error_message(f"render failed: {text}"))
                    for v in self.viewers.render_order():
                        v.shown = (v.camera_id, self.version)
                await asyncio.sleep(0)  # let the event loop read messages between ticks

    async def step(self) -> None:
        """One tick: render every ready viewer in one call (or one per viewer when not shared), send the frames."""
        self._build_renderer()
        order = self.viewers.render_order()
        if not order:
            return
        jobs = [(v, v.camera_id, v.views(self.ipd)) for v in order]
        version, index = self.version, self.tick
        advance = self.playing and self.animated
        try:
            frames = await asyncio.to_thread(self._render_encode, jobs, index, advance, len(self.viewers))
        except VolrenError as exc:
            for v, cam_id, _ in jobs:
                v.shown = (cam_id, version)
            self.broadcast(error_message(str(exc)))
            return
        self.tick += 1
        self._tick_times.append(time.perf_counter())
        for (v, cam_id, _), payload in zip(jobs, frames, strict=True):
            v.shown = (cam_id, version)
            if v.closed:
                continue
            if v.busy:
                v.dropped += 1
                continue
            v.sending = asyncio.create_task(self._send(v, payload))

    def _render_encode(self, jobs: list[tuple[Viewer, int, list[Camera]]], index: int, advance: bool,
                       viewers: int) -> list[bytes]:
        """In the worker thread: advance the animation, render, encode; one packed frame per job."""
        if advance:
            self._frame_scene = self._animate()
            self.scene = with_light(self._frame_scene, self.light_dir)
        scene, renderer = self.scene, self.renderer
        start = time.perf_counter()
        if self.shared:
            frame = renderer.render(scene, [c for _, _, cams in jobs for c in cams], frame=index)
            self.renders += 1
            images, passes = frame.images, dict(frame.stats.times_ms)
        else:
            images, passes = [], {}
            self._own = {v.id: self._own.get(v.id) or self._make_renderer() for v, _, _ in jobs}
            for v, _, cams in jobs:
                frame = self._own[v.id].render(scene, cams, frame=index)
                self.renders += 1
                images += frame.images
                for k, ms in frame.stats.times_ms.items():
                    passes[k] = passes.get(k, 0.0) + ms
        self.render_ms = (time.perf_counter() - start) * 1e3
        self.pass_ms, self.views_last = passes, len(images)
        start = time.perf_counter()
        out, k = [], 0
        for _, cam_id, cams in jobs:
            rgb = display_image(images[k:k + len(cams)], scene.background)
            k += len(cams)
            header = {"camera_id": cam_id, "tick": index, "width": rgb.shape[1], "height": rgb.shape[0],
                      "stereo": len(cams) == 2, "render_ms": round(self.render_ms, 3),
                      "pass_ms": {p: round(ms, 3) for p, ms in passes.items()}, "viewers": viewers}
            out.append(pack_frame(header, encode_jpeg(rgb, self.jpeg_quality)))
        self.encode_ms = (time.perf_counter() - start) * 1e3
        return out

    async def _send(self, viewer: Viewer, payload: bytes) -> None:
        try:
            await viewer.send(payload)
            viewer.frames += 1
        except (ConnectionError, RuntimeError):  # the client went away mid-frame: drop it, the loop goes on
            self.viewers.remove(viewer)
        finally:
            self.wake()  # it may need the newest camera now

    def broadcast(self, text: str, skip: Viewer | None = None) -> None:
        """A text message to every viewer but ``skip``, never awaited: a viewer whose previous text message is still
        on its way misses this one (like frames: a stalled client stalls nobody; the messages are snapshots)."""
        for v in list(self.viewers.viewers.values()):
            if v is not skip and v.text is not None and (v.texting is None or v.texting.done()):
                v.texting = asyncio.create_task(self._send_text(v, text))

    @staticmethod
    async def _send_text(viewer: Viewer, text: str) -> None:
        with contextlib.suppress(ConnectionError, RuntimeError):  # gone: its handler drops it
            await viewer.text(text)

    # ---- reporting ------------------------------------------------------------------------------------------

    @property
    def fps(self) -> float:
        """Ticks per second over the last FPS_WINDOW_S seconds (0 when idle)."""
        now = time.perf_counter()
        recent = [t for t in self._tick_times if now - t <= FPS_WINDOW_S]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)
