"""The render loop of `volren serve`: one asyncio task owns the renderer, its temporal state and the shared scene.

Each tick takes every connected viewer's newest camera, renders all their views in ONE multi-view ``render`` call (a
stereo viewer's two eyes adjacent, so CACRM couples them; the light map, GI update, fog shadow grid and majorants are
computed once for everyone), splits the images, JPEG-encodes them, and hands each viewer its frame unless the
previous one is still being sent or not yet acknowledged by the page (then the frame is dropped: latest-camera-wins,
no queue). The render and the encoding run in a worker thread (`asyncio.to_thread`), so the event loop keeps reading
messages meanwhile. A viewer that acknowledges no frame for PARK_AFTER_S is parked (left out of the render) and closed
after ACK_TIMEOUT_S.

A tick runs only when some viewer that is free to receive needs a frame: its camera or size changed, the shared
settings changed, the scene is playing, or its still view is refining. No viewers, no rendering.

Progressive refinement: methods with temporal state converge over frames of a still view (VPT's paths, fog's jittered
froxels blended with their history, the GI passes' accumulation), so the loop keeps ticking while a viewer's camera,
size and the shared settings stay, up to `refine_frames` frames, then idles; any change starts the count again.
VPT without a denoiser has no history of its own: the loop averages its frames of the still view (a progressive path
tracer's running mean). Every refinement tick still renders all viewers in one call.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from volren.camera import Camera
from volren.errors import VolrenError
from volren.presets import QUALITIES, quality_config
from volren.render import METHODS
from volren.render.base import LightMapMarchConfig, check_scene_mode
from volren.render.fog.renderer import FogConfig, FogRenderer
from volren.render.marching.modes import MODES
from volren.render.vpt.tracer import VPTConfig
from volren.scene import DirectionalLight, Scene
from volren.serve.heap import trim_heap
from volren.serve.jpeg import JPEG_QUALITY, display_image, encode_jpeg
from volren.serve.protocol import Choices, ProtocolError, Settings, error_message, pack_frame
from volren.serve.viewers import Limits, TimeShares, Viewer, ViewerSet
from volren.transfer import PRESETS

log = logging.getLogger("volren.serve")

ANIMATION_FPS = 30.0
"""[frames/s of scene time] one animation step per tick while playing, as `volren animate` renders them"""
DENSITY_TF = "density"
"""the transfer-function choice meaning none: extinction proportional to density (vpt's default)"""
LIVE_METHODS = ("dssrm", "cmsrm", "cacrm", "vpt", "fog")
"""offered live; the reference (per-sample shadow rays, seconds per frame) is the offline ground truth"""
FPS_WINDOW_S = 2.0
REFINE_VPT_PATHS = 256
"""[paths per pixel] a still VPT view gathers before the loop idles: 256 frames at the interactive preset (1 path a
frame), 32 at default (8), 8 at high (32)"""
PARK_AFTER_S = 2.0
"""[s] without an acknowledgement of its frame a viewer is parked: not rendered (a page in a background tab, a stalled
reader) until the acknowledgement comes"""
ACK_TIMEOUT_S = 30.0
"""[s] without an acknowledgement the viewer's socket is closed (code CLOSE_NO_ACK)"""
CLOSE_NO_ACK = 1008
"""WebSocket close code: policy violation (no frame acknowledged)"""
WATCH_INTERVAL_S = 0.25
CALM_AFTER_S = 0.5
"""[s] with no viewer moving (no new camera, size or settings) and nothing playing for this long, the loop is calm: a
viewer whose last frame was shrunk to its time share gets one of its whole size (the pixel budget alone), so a still
view is sharp; a viewer that moves meanwhile waits for that one tick at most"""
REFINE_TOLERANCE = 0.01
"""fog refines until the first frame's weight in its exponential history is below this: 44 frames at weight 0.1"""


class RenderAbandoned(VolrenError):
    """The render loop stopped a render between passes (`RenderLoop.abandon`)."""


def refine_frames(config: Any, volumes: int = 1) -> int:
    """Frames a still view is rendered for (the first included) before the loop idles; 1 = no refinement (methods
    without temporal state: the light-map marchers without GI are deterministic). VPT: REFINE_VPT_PATHS paths per
    pixel; fog with temporal blending: until the first frame weighs < REFINE_TOLERANCE, ceil(ln tol / ln(1 - w));
    a light-map method with accumulating GI (not the precomputed prt and brute): the GI's convergence frame count N
    (its lambda(n) = 1 / min(n + 1, N)) per update of every one of the scene's ``volumes`` (volumes_per_frame a
    frame)."""
    if isinstance(config, VPTConfig):
        return math.ceil(REFINE_VPT_PATHS / config.spp)
    if isinstance(config, FogConfig):
        w = config.temporal_weight
        return math.ceil(math.log(REFINE_TOLERANCE) / math.log1p(-w)) if config.temporal and w < 1 else 1
    gi = getattr(config, "gi", None)
    if gi is None or gi.method in ("none", "prt", "brute"):
        return 1
    return gi.convergence_frames * math.ceil(volumes / gi.volumes_per_frame)


@dataclasses.dataclass
class Still:
    """A viewer's still view: ``key`` (its camera object, scene version and animation step) stays while nothing
    changes; ``frames`` rendered since; ``mean`` the running mean of its images when the loop averages (VPT without
    a denoiser), else None."""

    key: tuple
    frames: int
    mean: list[np.ndarray] | None


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


def sequence_player(length: int, scene_at: Callable[[int], Scene]) -> Callable[[], Scene]:
    """The next scene of a volume sequence of ``length`` frames at each call, ``scene_at(i)`` being frame i's (the
    loop shows frame 0 first, so the first call gives frame 1), from the last frame on to frame 0 again."""
    steps = iter(range(1, 2**62))
    return lambda: scene_at(next(steps) % length)


SHARED_SETTINGS = ("method", "quality", "tf", "light_dir", "playing", "mode", "iso_value")
"""the settings every viewer of a server shares (`RenderLoop.apply`, `RenderLoop.adopt`)"""


STREAM_POLL_S = 0.05
"""[s] how often an idle loop looks whether a streamed volume's bricks came (a new tick draws them)"""


class RenderLoop:
    """The shared renderer and its viewers. ``animate`` gives the next scene of an animation (None: not animated).
    ``shared=False`` is the naive server of the benchmark: each viewer rendered by its own renderer (own light map,
    shadow grid, majorants and history), one call per viewer, as if every viewer had a server of its own.
    ``overrides`` are config fields on top of the quality preset (tests use small light grids). ``refine``: frames a
    still view is refined for by a temporal method (None: `refine_frames` of the method's config; 1: off).
    ``encode`` turns a viewer's uint8 sRGB image into its frame's bytes (None: JPEG at ``jpeg_quality``; the notebook
    widget, `volren.notebook.Viewer`, takes the raw pixels).

    The loop has a socket part (viewers, settings, ticks: `step`) and a renderer part (`_build_renderer`,
    `_render_encode`, run by `_render` in a worker thread). `volren.serve.shards` runs the renderer part of a loop in
    each of its Ray actors and the socket part of one loop per shard in the front end (``local`` False there: the
    front end's loops keep no renderer, only its config)."""

    local = True
    """this loop renders in this process (False: its renderer part runs elsewhere, `_render` calls it)"""

    def __init__(self, scene: Scene, method: str, quality: str = "interactive", *, limits: Limits | None = None,
                 camera: Camera | None = None, device: str = "cpu", shared: bool = True, ipd: float = 0.063,
                 jpeg_quality: int = JPEG_QUALITY, animate: Callable[[], Scene] | None = None,
                 overrides: dict[str, Any] | None = None, refine: int | None = None,
                 lock_settings: bool = False, encode: Callable[[np.ndarray], bytes] | None = None,
                 data_parallel: Any = None) -> None:
        self.data_parallel = data_parallel
        """a `volren.distributed.regions.RegionEngine` the renderers render through (``serve --data-parallel``:
        dssrm in modes dvr, mip and iso only), else None"""
        self.methods = scene_methods(scene) if data_parallel is None else ("dssrm",)
        if method not in self.methods:
            raise VolrenError(f"--method: '{method}' cannot serve scene '{scene.name}': choose from "
                              f"{', '.join(self.methods)}")
        if quality not in QUALITIES:
            raise VolrenError(f"--quality: unknown quality '{quality}': choose from {', '.join(QUALITIES)}")
        if not 1 <= jpeg_quality <= 100:
            raise VolrenError(f"JPEG quality must lie in [1, 100], got {jpeg_quality}")
        if refine is not None and refine < 1:
            raise VolrenError(f"refine must be at least 1 frame, got {refine}")
        self.refine, self.lock_settings = refine, lock_settings
        self._abandoned = False
        self._still: dict[int, Still] = {}
        """viewer id -> its still view (refinement state), as of the last tick"""
        self._sent: dict[int, int] = {}
        """viewer id -> the refinement frame count of the last frame handed to it"""
        self._step = 0
        """animation steps taken (part of a still view's key)"""
        self._holding = False
        """a tick rendered since the view-sized state was last released (`release`)"""
        self._pixels_high = 0
        """[px] the most a tick rendered since the heap was last trimmed"""
        self.limits = limits or Limits()
        modes = MODES if data_parallel is None else tuple(m for m in MODES if m != "mida")
        self.choices = Choices(self.methods, QUALITIES, (DENSITY_TF, *PRESETS), modes)
        self.viewers = ViewerSet(self.limits.max_viewers, per_client=self.limits.max_per_client)
        self.time_shares = TimeShares(self.limits)
        self._settings_tick = -1
        """the tick count when a viewer's pending settings were last applied: one applied change per tick"""
        self._settle_timer: asyncio.TimerHandle | None = None
        self.camera = camera or Camera(position=(0.0, 0.4, 3.2))
        self.viewers.near = self.camera.near  # a framed micrometre specimen's, kept as viewers steer
        self.viewers.far = self.camera.far  # and a kilometre-wide simulation's
        self.device, self.shared, self.ipd, self.jpeg_quality = device, shared, ipd, jpeg_quality
        self.encode = encode
        self.overrides = dict(overrides or {})
        self.method, self.quality, self.tf = method, quality, DENSITY_TF
        self.mode, self.iso_value = "dvr", LightMapMarchConfig.iso_value
        """the light-map marchers' sci-vis mode and its iso value (`volren.render.marching.modes`)"""
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
        self._last_urgent = -math.inf
        """[s, time.monotonic] when a tick last had a viewer waiting for a new view (`CALM_AFTER_S`)"""
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None
        self._watch: asyncio.Task | None = None

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
            self.renderer = self._make_renderer() if self.local else None
            self._own = {}
            self._renderer_key = (self.method, self.quality)
        transfer = None if self.tf == DENSITY_TF else self.tf
        if "transfer" in fields and self._config.transfer != transfer:
            self._config = dataclasses.replace(self._config, transfer=transfer)
            for r in filter(None, (self.renderer, *self._own.values())):
                r.config = self._config
        # a mode switch, like the transfer function, keeps the renderer (its light map stays valid)
        if "mode" in fields and (self._config.mode, self._config.iso_value) != (self.mode, self.iso_value):
            self._config = dataclasses.replace(self._config, mode=self.mode, iso_value=self.iso_value)
            for r in filter(None, (self.renderer, *self._own.values())):
                r.config = self._config

    def _make_renderer(self) -> Any:
        """(also from the worker thread, for a new viewer of the naive server: settings may change meanwhile, so
        the class and config are those `_build_renderer` fixed for this tick)"""
        if self.data_parallel is not None:  # the regions' actors keep their renderers; this one sends the config
            from volren.distributed.regions import DataParallelRenderer

            renderer = DataParallelRenderer(self.data_parallel, self._config)
        else:
            renderer = self._renderer_cls(self._config, device=self.device)
        renderer.on_rows = self._check_abandoned  # called once a view's image pass is through
        renderer.stream_wait = False  # a streamed volume's tick draws what is resident; the rest comes meanwhile
        return renderer

    def abandon(self) -> None:
        """Shutting down: the render in flight stops after its current image pass (`RenderAbandoned`), so the worker
        thread is free within a pass instead of a whole tick (issue 20 item 10: Ctrl-C took 50 s)."""
        self._abandoned = True

    def _check_abandoned(self, rows: int) -> None:
        if self._abandoned:
            raise RenderAbandoned("render abandoned: the server is shutting down")

    def shared_settings(self) -> dict[str, Any]:
        return {"method": self.method, "quality": self.quality, "tf": self.tf,
                "light_dir": list(self.light_dir or self._scene_light()), "playing": self.playing,
                "mode": self.mode, "iso_value": self.iso_value}

    def _scene_light(self) -> tuple[float, float, float]:
        light = next((lt for lt in self.scene.lights if isinstance(lt, DirectionalLight)), DirectionalLight())
        return light.direction

    def check(self, settings: Settings) -> None:
        """Refuse ``settings`` (`ProtocolError`) before anything changes: shared ones under ``lock_settings`` (only
        the viewer's own stereo mode may change then), a mode the method or scene cannot take."""
        shared = [name for name in SHARED_SETTINGS if getattr(settings, name) is not None]
        if self.lock_settings and shared:
            raise ProtocolError(f"settings: {', '.join(shared)} locked by the operator (--lock-settings); only "
                                "stereo may change")
        self._check_mode(settings)

    def _take(self, settings: Settings, viewer: Viewer) -> dict[str, Any]:
        """Check a settings message from ``viewer`` (`check`), apply its stereo mode (the viewer's own); its shared
        settings, by name."""
        self.check(settings)
        if settings.stereo is not None and settings.stereo != viewer.stereo:
            viewer.resize(viewer.width, viewer.height, settings.stereo, self.limits)
        return {name: getattr(settings, name) for name in SHARED_SETTINGS if getattr(settings, name) is not None}

    def apply(self, settings: Settings, viewer: Viewer) -> bool:
        """Apply a settings message from ``viewer`` now; True when a shared setting changed (to tell the others)."""
        changed = self.adopt(self._take(settings, viewer))
        self.wake()
        return bool(changed)

    def offer(self, settings: Settings, viewer: Viewer) -> None:
        """A settings message from ``viewer``, checked now (its error goes back at once); its stereo mode applies now
        (the viewer's own), its shared settings join the viewer's pending ones (the newest value of each) and apply
        in turn (`settle`): at most one viewer's change per tick and SETTINGS_PER_S a second per viewer (issue 44
        item 4), so a flood of changes costs the others one renderer rebuild a tick at most."""
        viewer.pending.update(self._take(settings, viewer))
        self.settle()

    @property
    def ticks_done(self) -> int:
        return self.tick

    def settle(self) -> None:
        """Apply the pending settings of the viewer that has waited longest among those whose rate allows, if no
        change was applied since the last tick (or nothing is rendering); tell the others; come back when more wait."""
        if self._settle_timer is not None:
            self._settle_timer.cancel()
            self._settle_timer = None
        waiting = [v for v in self.viewers.viewers.values() if v.pending and not v.closed]
        if not waiting:
            return
        rendering = any(v.ready for v in self.viewers.viewers.values())
        if not rendering or self.ticks_done != self._settings_tick:
            now = time.monotonic()
            v = next((v for v in waiting if v.settings_rate.take(now)), None)
            if v is not None:
                values, v.pending = v.pending, {}
                try:
                    self._check_mode(Settings(**{k: values[k] for k in ("method", "mode") if k in values}))
                except ProtocolError as exc:  # another viewer's change since made it impossible: say so to it
                    self.tell(v, error_message(str(exc)))
                else:
                    if self.adopt(values):
                        self._settings_tick = self.ticks_done
                        self.announce_settings(skip=v)
                    self.wake()
                waiting = [u for u in waiting if u.pending]
        if waiting:  # the next turn: after a tick (`step` settles), or when a rate refills
            delay = min(u.settings_rate.wait() for u in waiting)
            self._settle_timer = asyncio.get_running_loop().call_later(max(delay, WATCH_INTERVAL_S / 5), self.settle)

    def adopt(self, values: dict[str, Any]) -> set[str]:
        """Take the shared settings in ``values`` (validated already); the names that changed. A change bumps the
        version, so every viewer gets a frame of it."""
        changed = {name for name, value in values.items() if value != getattr(self, name)}
        for name in changed:
            setattr(self, name, values[name])
        if "light_dir" in changed:
            self.scene = with_light(self._frame_scene, self.light_dir)
        if changed:
            self.version += 1
        return changed

    def _check_mode(self, settings: Settings) -> None:
        """Refuse, before anything changes, a mode other than dvr with a method that is no light-map marcher or a
        scene the mode does not composite (`check_scene_mode`)."""
        method = settings.method or self.method
        mode = settings.mode or self.mode
        if mode == "dvr":
            return
        if not issubclass(METHODS[method][1], LightMapMarchConfig):
            raise ProtocolError(f"settings.mode {mode} needs method dssrm, cmsrm or cacrm, not {method}")
        try:
            check_scene_mode(self.scene, mode)
        except VolrenError as exc:
            raise ProtocolError(f"settings.mode: {exc}") from None

    # ---- the loop -------------------------------------------------------------------------------------------

    def wake(self) -> None:
        self._wake.set()

    def start(self) -> None:
        self._task = asyncio.create_task(self.run(), name="volren render loop")
        self._watch = asyncio.create_task(self.watch(), name="volren acknowledgement watch")

    async def watch(self) -> None:
        """Park the viewers whose frame waits for its acknowledgement over PARK_AFTER_S, close those over
        ACK_TIMEOUT_S."""
        while True:
            await asyncio.sleep(WATCH_INTERVAL_S)
            now = time.monotonic()
            for v in list(self.viewers.viewers.values()):
                if v.unacked is None or v.closed:
                    continue
                age = now - v.unacked_since
                if age > ACK_TIMEOUT_S and v.close is not None:
                    self.viewers.remove(v)
                    v.texting = asyncio.create_task(v.close(CLOSE_NO_ACK, f"no frame acknowledged for "
                                                                          f"{ACK_TIMEOUT_S:g} s"))
                elif age > PARK_AFTER_S:
                    v.parked = True

    async def stop(self) -> None:
        if self._watch is not None:
            self._watch.cancel()
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

    @property
    def refine_budget(self) -> int:
        """Frames a still view is rendered for (`refine_frames`, or the ``refine`` given)."""
        return self.refine if self.refine is not None else refine_frames(self._config, len(self.scene.volumes))

    @property
    def _averages(self) -> bool:
        """The loop itself averages a still view's frames: VPT without a denoiser (whose frames share no history)."""
        return isinstance(self._config, VPTConfig) and self._config.denoise == "none"

    def _refining(self, v: Viewer) -> bool:
        """``v``'s still view has frames of refinement left, or a refined frame it has not been handed (dropped
        while it was busy)."""
        still = self._still.get(v.id)
        if still is None or still.key != self._still_key(v):
            return False
        return still.frames < self.refine_budget or self._sent.get(v.id) != still.frames

    def _still_key(self, v: Viewer) -> tuple:
        return (v.camera, self.version, self._step)

    def _urgent(self, v: Viewer) -> bool:
        """``v`` waits for a new view: its camera, size or the settings changed, or the scene plays."""
        return (self.playing and self.animated) or v.shown != (v.camera_id, self.version)

    def _calm_in(self) -> float:
        """[s] until the loop is calm (<= 0: it is)."""
        return self._last_urgent + CALM_AFTER_S - time.monotonic()

    def _due(self) -> bool:
        """Some viewer free to receive needs a frame (new camera, size or settings, the scene plays, its still view
        is refining, its still view was shrunk and the loop is calm, or bricks of a streamed volume it shows are still
        coming: the picture sharpens as they come, issue 41 item 3)."""
        streaming = self._streaming()
        return any(not v.busy and (self._urgent(v) or self._refining(v) or streaming
                                   or (v.scaled and self._calm_in() <= 0))
                   for v in self.viewers.render_order())

    def _streaming(self) -> bool:
        """Whether a streamed volume of the scene has bricks on their way (never waited for: a tick draws what is
        resident, `Renderer.stream_wait`)."""
        return any(getattr(v.density, "streamed", False) and v.density.streamer.pending() > 0
                   for v in getattr(self.scene, "volumes", ()))

    async def run(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._due():
                try:
                    await self.step()
                    self.settle()  # a viewer's settings waiting for the tick to pass
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # never let one bad tick end the loop: tell the viewers, carry on
                    log.exception("render tick failed")
                    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    self.broadcast(error_message(f"render failed: {text}"))
                    for v in self.viewers.render_order():
                        v.shown = (v.camera_id, self.version)
                    self._still.clear()  # no refining of a view that fails: wait for a change
                await asyncio.sleep(0)  # let the event loop read messages between ticks
            if not self.viewers and self._holding:
                await self.release()
            if self._calm_in() > 0 and any(v.scaled for v in self.viewers.render_order()):
                asyncio.get_running_loop().call_later(self._calm_in() + 0.01, self.wake)  # its whole frame, calm
            if self.viewers and self._streaming():  # the readers are threads: look again soon
                asyncio.get_running_loop().call_later(STREAM_POLL_S, self.wake)

    async def step(self) -> None:
        """One tick: render every ready viewer in one call (or one per viewer when not shared), send the frames."""
        self._build_renderer()
        order = self.viewers.render_order()
        if not order:
            return
        self._holding = True
        advance = self.playing and self.animated
        step = self._step + advance
        version, index = self.version, self.tick
        # per viewer: its camera id and views (within its fair share of the pixel budget), its still view so far and
        # its key after this tick's animation step
        if any(self._urgent(v) for v in order):
            self._last_urgent = time.monotonic()
        calm = self._calm_in() <= 0
        shares = self.time_shares.shares([v.width * v.height for v in order], calm=calm)
        jobs = [(v, v.camera_id, v.views(self.ipd, px), self._still.get(v.id), (v.camera, version, step))
                for v, px in zip(order, shares, strict=True)]
        start = time.perf_counter()
        try:  # the renderer part sees viewer ids, not viewers (sockets): it may run in another process
            frames = await self._render([(v.id, *job) for v, *job in jobs], index, advance, len(self.viewers))
        except VolrenError as exc:
            for v, cam_id, *_ in jobs:
                v.shown = (cam_id, version)
            self._still.clear()
            self.broadcast(error_message(str(exc)))
            return
        self.time_shares.took(sum(c.width * c.height for _, _, cams, *_ in jobs for c in cams),
                              time.perf_counter() - start)
        self._step = step
        self.tick += 1
        self._tick_times.append(time.perf_counter())
        # a connected viewer left out of this tick (parked) keeps its still view: once it acknowledges again it refines
        # on from the frame it holds (before: forgotten, so it got no frame more and kept a noisy image until it moved)
        kept = {i: s for i, s in self._still.items() if i in self.viewers.viewers}
        self._still = kept | {job[0].id: still for job, (_, still) in zip(jobs, frames, strict=True)}
        self._sent = {i: n for i, n in self._sent.items() if i in self._still}
        for (v, cam_id, *_), (payload, still), px in zip(jobs, frames, shares, strict=True):
            if v.closed:
                continue
            if v.busy:  # dropped: it still needs this state's frame once it is free (`_due`)
                v.dropped += 1
                continue
            v.shown, v.scaled = (cam_id, version), px < v.width * v.height and not calm  # calm: its best
            self._sent[v.id] = still.frames
            v.unacked, v.unacked_since = index, time.monotonic()
            v.sending = asyncio.create_task(self._send(v, payload))

    async def release(self) -> None:
        """The last viewer has left: forget the still views and drop the renderer part's view-sized state (a tick
        is never under way here: `run` calls this between them)."""
        self._holding = False
        self._still, self._sent = {}, {}
        await self._release_views()

    async def _release_views(self) -> None:
        await asyncio.to_thread(self.release_views)

    def release_views(self) -> None:
        """The renderer part of `release`: the renderers' render targets and per-view history
        (`Renderer.release_views`; the naive server's own renderers dropped), then the heap trimmed."""
        for r in filter(None, (self.renderer, *self._own.values())):
            r.release_views()
        self._own = {}
        self._pixels_high = 0
        trim_heap()

    async def _render(self, jobs: list[tuple[int, int, list[Camera], Still | None, tuple]], index: int,
                      advance: bool, viewers: int) -> list[tuple[bytes, Still]]:
        """The renderer part of a tick, `_render_encode`, in a worker thread (the event loop reads messages
        meanwhile)."""
        return await asyncio.to_thread(self._render_encode, jobs, index, advance, viewers)

    def _render_encode(self, jobs: list[tuple[int, int, list[Camera], Still | None, tuple]], index: int,
                       advance: bool, viewers: int) -> list[tuple[bytes, Still]]:
        """Advance the animation, render, refine, encode; per job (viewer id, camera id, views, still view so far,
        its key) its packed frame and still view."""
        if advance:
            self._frame_scene = self._animate()
            self.scene = with_light(self._frame_scene, self.light_dir)
        scene, renderer, averages = self.scene, self.renderer, self._averages
        start = time.perf_counter()
        if self.shared:
            frame = renderer.render(scene, [c for _, _, cams, *_ in jobs for c in cams], frame=index)
            self.renders += 1
            images, passes = frame.images, dict(frame.stats.times_ms)
        else:
            images, passes = [], {}
            self._own = {vid: self._own.get(vid) or self._make_renderer() for vid, *_ in jobs}
            for vid, _, cams, *_ in jobs:
                frame = self._own[vid].render(scene, cams, frame=index)
                self.renders += 1
                images += frame.images
                for k, ms in frame.stats.times_ms.items():
                    passes[k] = passes.get(k, 0.0) + ms
        self.render_ms = (time.perf_counter() - start) * 1e3
        self.pass_ms, self.views_last = passes, len(images)
        start = time.perf_counter()
        out, k = [], 0
        for _, cam_id, cams, old, key in jobs:
            own = images[k:k + len(cams)]
            k += len(cams)
            if old is not None and old.key == key and (old.mean is None or old.mean[0].shape == own[0].shape):
                n = old.frames + 1
                if averages and old.mean is not None:  # the running mean: mean += (x - mean) / n
                    own = [m + (x - m) / n for m, x in zip(old.mean, own, strict=True)]
                still = Still(key, n, own if averages else None)
            else:
                still = Still(key, 1, own if averages else None)
            rgb = display_image(own, scene.background)
            header = {"camera_id": cam_id, "tick": index, "width": rgb.shape[1], "height": rgb.shape[0],
                      "stereo": len(cams) == 2, "refine": still.frames, "render_ms": round(self.render_ms, 3),
                      "pass_ms": {p: round(ms, 3) for p, ms in passes.items()}, "viewers": viewers}
            data = encode_jpeg(rgb, self.jpeg_quality) if self.encode is None else self.encode(rgb)
            out.append((pack_frame(header, data), still))
        self.encode_ms = (time.perf_counter() - start) * 1e3
        pixels = sum(c.width * c.height for _, _, cams, *_ in jobs for c in cams)
        if pixels < self._pixels_high // 2:  # far fewer pixels than before: the larger targets were freed
            trim_heap()
            self._pixels_high = 0
        self._pixels_high = max(self._pixels_high, pixels)
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
        """A text message to every viewer but ``skip`` (`tell`)."""
        for v in list(self.viewers.viewers.values()):
            if v is not skip:
                self.tell(v, text)

    def tell(self, v: Viewer, text: str) -> None:
        """A text message to ``v``, never awaited: if its previous one is still on its way it misses this one (like
        frames: a stalled client stalls nobody)."""
        if v.text is not None and (v.texting is None or v.texting.done()):
            v.texting = asyncio.create_task(self._send_text(v, text))

    def announce_settings(self, skip: Viewer | None = None) -> None:
        """The shared settings to every viewer but ``skip``. A viewer whose previous text message is still on its way
        gets the settings as they are once it is through, so the last state always reaches every viewer (issue 20
        item 7: after a burst of 500 light changes a viewer's last message missed the final state)."""
        for v in list(self.viewers.viewers.values()):
            if v is skip or v.text is None:
                continue
            v.settings_due = True
            if v.texting is None or v.texting.done():
                v.texting = asyncio.create_task(self._send_text(v, None))

    def settings_message(self) -> str:
        return json.dumps({"type": "settings", **self.shared_settings()})

    async def _send_text(self, viewer: Viewer, text: str | None) -> None:
        """``text``, then the newest settings while they are due."""
        with contextlib.suppress(ConnectionError, RuntimeError):  # gone: its handler drops it
            if text is not None:
                await viewer.text(text)
            while viewer.settings_due and not viewer.closed:
                viewer.settings_due = False
                await viewer.text(self.settings_message())

    # ---- reporting ------------------------------------------------------------------------------------------

    def report(self) -> dict[str, Any]:
        """The loop's figures for /health."""
        return {"method": self.method, "quality": self.quality, "fps": round(self.fps, 3), "tick": self.tick,
                "renders": self.renders, "views": self.views_last, "shared": self.shared,
                "render_ms": round(self.render_ms, 3), "encode_ms": round(self.encode_ms, 3),
                "pass_ms": {k: round(v, 3) for k, v in self.pass_ms.items()}}

    @property
    def fps(self) -> float:
        """Ticks per second over the last FPS_WINDOW_S seconds (0 when idle)."""
        now = time.perf_counter()
        recent = [t for t in self._tick_times if now - t <= FPS_WINDOW_S]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)
