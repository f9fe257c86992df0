"""`volren.Viewer`: a Jupyter widget showing a scene live, on `jupyter_rfb`'s remote frame buffer, rendered by the
render loop of `volren serve` (`volren.serve.loop.RenderLoop`) with the widget as its one viewer.

The widget is to the loop what a page is to the server: a mouse drag orbits its camera and the wheel zooms with the
page's own camera math (`Orbit`, the port of static/viewer.js), each new camera goes to the loop as a camera message
with an increasing id, and every frame drawn is acknowledged. So the loop's frame dropping holds unchanged: while a
frame waits to be drawn the loop renders nothing for the widget, and once it is drawn only the newest camera is
rendered (a burst of drags between two draws costs one render, the states in between are skipped). Methods with
temporal state refine a still view as in serve (VPT's running mean, fog's history, GI accumulation).

Threads: the loop runs on an asyncio event loop of its own in a daemon thread, and renders in that loop's worker
thread as serve does. The kernel's thread hands it events and settings and waits for the bookkeeping only
(microseconds), never for a render, so a notebook stays responsive while a frame renders (seconds at
``quality="high"``, a minute for the first frame when Warp compiles its kernels); a frame that arrives asks
jupyter_rfb to draw it (`request_draw` on the kernel's event loop) and jupyter_rfb's `get_frame` hands it over and
acknowledges it. Rendering inside `get_frame` instead would block the kernel for every frame, and every event queued
behind it. Outside a kernel (a script, a test) there is no event loop to draw on: `get_frame` then waits for the
frame of the current camera, size and settings, so ``Viewer(scene).get_frame()`` is an image anywhere.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import concurrent.futures.thread  # registers its exit hook first (`_close_all`)
import contextlib
import dataclasses
import io
import json
import math
import threading
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import ipywidgets
import numpy as np
from jupyter_rfb import RemoteFrameBuffer
from traitlets import Bool, Float, Unicode, validate

from volren.camera import Camera, StereoRig
from volren.device import resolve_device
from volren.errors import VolrenError
from volren.presets import QUALITIES
from volren.render import METHODS
from volren.render.base import LightMapMarchConfig
from volren.render.marching.modes import MODES
from volren.scene import Scene, Volume
from volren.serve.loop import DENSITY_TF, RenderLoop, scene_methods
from volren.serve.protocol import MAX_ISO, MIN_ISO, CameraMessage, ProtocolError, Settings, unpack_frame
from volren.serve.viewers import Limits

if TYPE_CHECKING:
    from volren.plan.volume import VolumeSequence

ORBIT_RAD_PER_PX = 0.01
"""[rad per CSS pixel] of a drag, as viewer.js"""
ZOOM_PER_WHEEL = 0.001
"""the orbit radius is multiplied by exp(ZOOM_PER_WHEEL * dy) per wheel step of dy pixels, as viewer.js"""
PITCH_LIMIT = 1.5
"""[rad] short of the poles, where looking at the target with up = +y degenerates (viewer.js)"""
RADIUS_RANGE = (0.05, 1e4)
"""[m] the orbit radius is kept within (viewer.js)"""
FRAME_TIMEOUT_S = 180.0
"""[s] `get_frame` outside a kernel waits this long for a frame: the first one compiles Warp's kernels when its cache
is cold (30-90 s a module on two CPU cores)"""
SETTINGS = {"method": "method", "preset": "quality", "tf": "tf", "mode": "mode", "iso_value": "iso_value",
            "stereo": "stereo", "playing": "playing"}
"""the viewer's setting traits -> the fields of serve's settings message they are applied as"""
DEFAULT_EYE = (0.0, 0.4, 3.2)
"""the default camera of `volren serve` and `volren render` for the unit box [-1, 1]^3, scaled to the scene's"""


@dataclasses.dataclass(frozen=True)
class Orbit:
    """A camera orbiting ``target`` at ``radius``: ``yaw`` about +y (0: on the +z side), ``pitch`` above the
    target's horizon. The serve page's camera (static/viewer.js `setCamera`, `cameraMessage`, the pointer and wheel
    handlers) in Python: the same drag and zoom give the same camera in the widget and in the browser."""

    target: tuple[float, float, float]
    radius: float
    yaw: float
    pitch: float

    @classmethod
    def of(cls, camera: Camera) -> Orbit:
        d = np.subtract(camera.position, camera.look_at)
        radius = max(float(np.linalg.norm(d)), 1e-3)
        return cls(tuple(camera.look_at), radius, math.atan2(d[0], d[2]),
                   math.asin(min(max(d[1] / radius, -1.0), 1.0)))

    @property
    def position(self) -> tuple[float, float, float]:
        """The eye: ``radius`` from the target, opposite the viewing direction."""
        c = math.cos(self.pitch)
        offset = (c * math.sin(self.yaw), math.sin(self.pitch), c * math.cos(self.yaw))
        return tuple(t + self.radius * o for t, o in zip(self.target, offset, strict=True))

    def dragged(self, dx: float, dy: float) -> Orbit:
        """The scene follows the hand: a drag right (``dx`` > 0) turns it right, a drag down shows its top."""
        pitch = min(max(self.pitch + dy * ORBIT_RAD_PER_PX, -PITCH_LIMIT), PITCH_LIMIT)
        return dataclasses.replace(self, yaw=self.yaw - dx * ORBIT_RAD_PER_PX, pitch=pitch)

    def zoomed(self, dy: float) -> Orbit:
        """The wheel turned by ``dy`` pixels: towards the user (dy > 0) moves the eye away."""
        radius = min(max(self.radius * math.exp(dy * ZOOM_PER_WHEEL), RADIUS_RANGE[0]), RADIUS_RANGE[1])
        return dataclasses.replace(self, radius=radius)


def default_camera(scene: Scene) -> Camera:
    """A fog scene's own viewpoint; else serve's default camera scaled and moved to the volumes' world box (the same
    camera for the unit box, a proportionally nearer one for a 20 cm CT), its near plane at most a thousandth of its
    distance (the default 1 cm would clip a specimen in micrometres away), its far plane beyond the box (the default
    1000 m would clip a simulation in kilometres away)."""
    from volren.data.fog_scenes import FOG_SCENES, fog_scene_camera

    if not scene.volumes and scene.name in FOG_SCENES:
        view = fog_scene_camera(scene.name)
        return Camera(position=view["position"], look_at=view["look_at"])
    lo, hi = scene.bounds
    centre, half = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    offset = np.asarray(DEFAULT_EYE) * half / math.sqrt(3.0)
    distance = float(np.linalg.norm(offset))
    return Camera(position=tuple(centre + offset), look_at=tuple(centre), near=min(Camera.near, distance / 1000),
                  far=max(Camera.far, 2.0 * (distance + half)))


@dataclasses.dataclass
class _Delivered:
    """A frame handed to the widget by the loop: its tick, its (camera id, settings version), its pixels."""

    tick: int
    key: tuple[int, int]
    rgb: np.ndarray
    acked: bool = False


def _raw_pixels(rgb: np.ndarray) -> bytes:
    """The loop's frame encoding for the widget: the uint8 pixels as they are (jupyter_rfb compresses them itself)."""
    return np.ascontiguousarray(rgb).tobytes()


_OPEN: weakref.WeakSet[Viewer] = weakref.WeakSet()


def _close_all() -> None:
    """Stop every viewer's render at the interpreter's exit, before `concurrent.futures` refuses new work (the loop's
    next tick would log a traceback) and before the teardown (a daemon thread inside a kernel launch then)."""
    for viewer in list(_OPEN):
        viewer.stop()


# threading's exit hooks run before `atexit`'s, the last registered first: concurrent.futures.thread (imported above)
# has registered its shutdown, so this runs before it
threading._register_atexit(_close_all)  # type: ignore[attr-defined]


class Viewer(RemoteFrameBuffer):
    """A live view of ``scene`` in a notebook: drag to orbit, wheel to zoom. ``width`` x ``height`` is the image
    (both eyes side by side when ``stereo``); the widget's size in the page replaces it once it is shown. ``quality``
    is the preset the render starts with (the `preset` trait; jupyter_rfb's own ``quality`` is the JPEG quality of
    the frames it streams); ``settings`` are config fields on top of it (``samples=64``, ``light_grid=16``) for
    whichever method is on. `method`, `preset`, `tf`, `mode`, `iso_value`, `stereo` and `playing` are traits: set
    them (``viewer.method = "cmsrm"``) or show `controls` beside the widget. ``camera``: the start view (default:
    `default_camera`). ``scene``: a Scene, a Volume, or a `VolumeSequence` (from `volren.load`), shown at frame 0
    and stepped through while ``playing`` is True, as ``volren serve --volume PATTERN`` plays it."""

    method = Unicode("dssrm")
    preset = Unicode("interactive")
    """the quality preset (`volren.presets`): interactive, default or high"""
    tf = Unicode(DENSITY_TF)
    """transfer function: a `volren.transfer` preset, or "density" (extinction proportional to density)"""
    stereo = Bool(False)
    mode = Unicode("dvr")
    """the light-map marchers' sci-vis mode: dvr, mip, mida or iso (`volren.render.marching.modes`)"""
    iso_value = Float(LightMapMarchConfig.iso_value)
    """[density] of mode iso"""
    playing = Bool(False)
    """a `VolumeSequence` plays: its next frame each tick, looping (the serve page's play control)"""

    def __init__(self, scene: Scene | Volume | VolumeSequence, method: str = "dssrm", quality: str = "interactive",
                 stereo: bool = False, width: int = 480, height: int = 270, *, camera: Camera | None = None,
                 device: str = "auto", ipd: float = 0.063, tf: str = DENSITY_TF, mode: str = "dvr",
                 iso_value: float = LightMapMarchConfig.iso_value, **settings: Any) -> None:
        scene, animate = _shown(scene)
        self._limits = Limits(max_viewers=1)
        self._loop: RenderLoop | None = None
        methods = scene_methods(scene)
        _check_choice("method", method, methods)
        _check_choice("quality", quality, QUALITIES)
        _check_choice("tf", tf, self._choices("tf"))
        _check_choice("mode", mode, MODES)
        (min_w, min_h), max_w, max_h = self._limits.clamp(0, 0), self._limits.max_width, self._limits.max_height
        for name, side, lo, hi in (("width", width, min_w, max_w), ("height", height, min_h, max_h)):
            if isinstance(side, bool) or not isinstance(side, int) or not lo <= side <= hi:
                raise VolrenError(f"Viewer: {name} must be an integer in [{lo}, {hi}] pixels, got {side!r}")
        known = {f.name for m in methods for f in dataclasses.fields(METHODS[m][1])}
        unknown = sorted(set(settings) - known)
        if unknown:
            raise VolrenError(f"Viewer: unknown setting(s) {', '.join(unknown)}: config fields of "
                              f"{', '.join(methods)} only")
        device = resolve_device(device)
        camera = camera if camera is not None else default_camera(scene)
        StereoRig(camera, ipd)  # checks ipd now, not at the first stereo frame
        self._orbit = Orbit.of(camera)
        self._up, self._fov, self._near, self._far = camera.up, camera.fov_y, camera.near, camera.far
        self._camera_id = 0
        self._drag: tuple[float, float] | None = None
        self._frame: _Delivered | None = None
        self._error: tuple[tuple[int, int], str] | None = None
        self._cond = threading.Condition()
        try:  # the kernel's event loop, where jupyter_rfb draws; None outside a kernel
            self._kernel: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            self._kernel = None
        quiet = contextlib.nullcontext() if _in_ipython() else contextlib.redirect_stdout(io.StringIO())
        with quiet:  # outside IPython jupyter_rfb's display() of its output area would print the area's repr
            super().__init__(css_width=f"{width}px", css_height=f"{height}px", method=method, preset=quality,
                             tf=tf, stereo=stereo, mode=mode, iso_value=iso_value)
        self._aio = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._aio.run_forever, name="volren viewer", daemon=True)
        self._thread.start()
        try:
            self._call(self._start, scene, method, quality, Settings(tf=tf, mode=mode, iso_value=iso_value), camera,
                       (width, height, stereo), device, ipd, settings, animate)
        except BaseException:
            self.close()
            raise
        _OPEN.add(self)

    # ---- the loop's thread -----------------------------------------------------------------------------------

    def _call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` on the loop's thread, its result or exception here. ``fn`` wakes the loop before the result
        is set, so the loop starts on a change before this thread can post the next one."""
        if not self._thread.is_alive():
            raise VolrenError("Viewer: stopped (closed): make a new one")
        done: concurrent.futures.Future = concurrent.futures.Future()

        def run() -> None:
            try:
                done.set_result(fn(*args))
            except BaseException as exc:
                done.set_exception(exc)

        self._aio.call_soon_threadsafe(run)
        return done.result()

    def _start(self, scene: Scene, method: str, quality: str, shared: Settings, camera: Camera,
               size: tuple[int, int, bool], device: str, ipd: float, settings: dict[str, Any],
               animate: Callable[[], Scene] | None) -> None:
        loop = RenderLoop(scene, method, quality, limits=self._limits, camera=camera, device=device, ipd=ipd,
                          overrides=settings, encode=_raw_pixels, animate=animate)
        self._client = loop.viewers.add(self._deliver, self._text)
        self._loop = loop
        self._client.resize(*size, self._limits)
        self._apply(shared)  # and the first camera
        loop.start()

    def _send_camera(self) -> None:
        """The orbit's camera as the page sends it: a camera message with the next id (any change of the view, size
        or stereo gets a new id, so a frame's camera id and settings version tell whether it shows the current
        state)."""
        self._camera_id += 1
        o = self._orbit
        self._client.set_camera(CameraMessage(self._camera_id, o.position, o.target, self._up, self._fov))
        self._loop.wake()

    async def _deliver(self, payload: bytes) -> None:
        """The loop's send: keep the newest frame, ask jupyter_rfb to draw it."""
        header, data = unpack_frame(payload)
        rgb = np.frombuffer(data, np.uint8).reshape(header["height"], header["width"], 3)
        with self._cond:  # the frame's state: `RenderLoop.step` marks the viewer shown before it sends
            self._frame = _Delivered(header["tick"], self._client.shown, rgb)
            self._cond.notify_all()
        if self._kernel is not None and not self._kernel.is_closed():
            self._kernel.call_soon_threadsafe(self.request_draw)

    async def _text(self, text: str) -> None:
        """The loop's text messages to a viewer are errors (a render that failed): kept for `get_frame`, shown
        under the widget."""
        message = json.loads(text).get("message", text)
        with self._cond:
            self._error = (self._client.shown, message)
            self._cond.notify_all()
        if self._kernel is not None and not self._kernel.is_closed():
            self._kernel.call_soon_threadsafe(self.print, f"volren: {message}")

    def _ack(self, tick: int) -> None:
        if self._client.unacked == tick:
            self._client.ack(tick)
            self._loop.wake()

    # ---- jupyter_rfb --------------------------------------------------------------------------------------------

    def get_frame(self) -> np.ndarray | None:
        """The newest frame, (H, W, 3) uint8 sRGB, acknowledged (the loop may render the next). On the kernel's
        thread it never waits (None before the first frame); elsewhere it first waits for the frame of the current
        camera, size and settings (a render error is raised)."""
        if self._loop is None:
            return None
        if self._thread.is_alive() and not _on_event_loop():
            return self._wait_current()
        with self._cond:
            frame = self._take()
        return None if frame is None else frame.rgb

    def _take(self) -> _Delivered | None:
        """(with the lock) The newest frame, acknowledged to the loop once, so it may render the next."""
        frame = self._frame
        if frame is not None and not frame.acked and self._thread.is_alive():
            frame.acked = True
            self._aio.call_soon_threadsafe(self._ack, frame.tick)
        return frame

    def _wait_current(self) -> np.ndarray:
        want = (self._client.camera_id, self._loop.version)
        with self._cond:
            ok = self._cond.wait_for(lambda: self._current(want), FRAME_TIMEOUT_S)
            error = self._error
            frame = self._frame
        if not ok:
            raise VolrenError(f"Viewer: no frame within {FRAME_TIMEOUT_S:g} s")
        if frame is None or frame.key != want:
            raise VolrenError(error[1] if error is not None else "Viewer: no frame")
        return frame.rgb

    def _current(self, want: tuple[int, int]) -> bool:
        """(with the lock) The frame of state ``want`` or its error is here; an older frame is taken (`_take`) so the
        loop renders the current one."""
        frame = self._take()
        return (frame is not None and frame.key == want) or (self._error is not None and self._error[0] == want)

    def handle_event(self, event: dict[str, Any]) -> None:
        """jupyter_rfb's events: a drag with the primary button orbits, the wheel zooms, a resize sets the image
        size (its logical pixels, clamped as serve clamps a page's), close stops the render."""
        kind = event.get("type", event.get("event_type"))
        if kind == "pointer_down" and event.get("button") == 1:
            self._drag = (event["x"], event["y"])
        elif kind in ("pointer_move", "pointer_up") and self._drag is not None:
            # the release counts too: jupyter_rfb throttles moves, so the last ones may reach us only as the up
            x, y = event["x"], event["y"]
            if (x, y) != self._drag:
                self._orbit = self._orbit.dragged(x - self._drag[0], y - self._drag[1])
                self._call(self._send_camera)
            self._drag = None if kind == "pointer_up" else (x, y)
        elif kind == "wheel":
            self._orbit = self._orbit.zoomed(event["dy"])
            self._call(self._send_camera)
        elif kind == "resize":
            self._call(self._resize, round(event["width"]), round(event["height"]))
        elif kind == "close":
            self.stop()

    def _resize(self, width: int, height: int) -> None:
        c = self._client
        if self._limits.clamp(width, height) != (c.width, c.height):
            c.resize(width, height, c.stereo, self._limits)
            self._send_camera()

    # ---- settings -----------------------------------------------------------------------------------------------

    @property
    def camera(self) -> Camera:
        """The current camera (one eye's size: the image's, or half its width when stereo)."""
        o = self._orbit
        if self._loop is None:
            return Camera(position=o.position, look_at=o.target, up=self._up, fov_y=self._fov, near=self._near,
                          far=self._far)
        return self._client.camera

    @property
    def render_loop(self) -> RenderLoop:
        """The render loop behind the widget (its counters: ``renders``, ``tick``, ``fps``, ``render_ms``)."""
        assert self._loop is not None
        return self._loop

    def _choices(self, trait: str) -> tuple[str, ...]:
        from volren.transfer import PRESETS

        return {"method": self._loop.methods if self._loop else tuple(METHODS), "preset": QUALITIES,
                "tf": (DENSITY_TF, *PRESETS), "mode": MODES}[trait]

    @validate(*SETTINGS)
    def _apply_setting(self, proposal: Any) -> Any:
        """Check a setting and hand it to the loop before the trait takes it: a value the loop refuses (mode mip
        with vpt) leaves the trait as it was. The constructor's values reach the loop when it starts."""
        name, value = proposal["trait"].name, proposal["value"]
        if name == "iso_value":
            if not (math.isfinite(value) and MIN_ISO <= value <= MAX_ISO):
                raise VolrenError(f"Viewer: iso_value must be a finite density in [{MIN_ISO:g}, {MAX_ISO:g}], got "
                                  f"{value}")
        elif name not in ("stereo", "playing"):
            _check_choice(name, value, self._choices(name))
        if self._loop is not None and value != getattr(self, name):
            self._call(self._apply, Settings(**{SETTINGS[name]: value}))
        return value

    def _apply(self, settings: Settings) -> None:
        try:
            self._loop.apply(settings, self._client)
        except ProtocolError as exc:  # serve's words for it: settings.mode ... needs method ...
            raise VolrenError(f"Viewer: {exc}") from None
        self._send_camera()

    def controls(self) -> ipywidgets.HBox:
        """Menus for method, quality preset, transfer function and mode, the iso value and a stereo box, linked to
        this viewer's traits: ``display(ipywidgets.VBox([viewer.controls(), viewer]))``."""
        layout = ipywidgets.Layout(width="max-content")
        controls = {name: ipywidgets.Dropdown(options=self._choices(name), description=SETTINGS[name],
                                              layout=layout)
                    for name in ("method", "preset", "tf", "mode")}
        controls["iso_value"] = ipywidgets.BoundedFloatText(min=MIN_ISO, max=MAX_ISO, step=0.05,
                                                            description="iso value", layout=layout)
        controls["stereo"] = ipywidgets.Checkbox(description="stereo", layout=layout)
        for name, control in controls.items():
            ipywidgets.link((self, name), (control, "value"))
        return ipywidgets.HBox(list(controls.values()))

    def close(self) -> None:
        """Close the widget's views and stop the render (`stop`)."""
        if getattr(self, "_output_context", None) is None:  # refused arguments: jupyter_rfb never initialised
            return
        super().close()

    def stop(self) -> None:
        """Stop rendering (the render in flight ends after its current pass) and the loop's thread; the widget keeps
        its last frame. Closing the widget stops it too."""
        if not self._thread.is_alive():
            return
        if self._loop is not None:
            loop = self._loop
            loop.abandon()

            async def shut() -> None:
                await loop.stop()
                await self._aio.shutdown_default_executor()

            with contextlib.suppress(TimeoutError):  # a pass longer than that: the daemon thread is left to it
                asyncio.run_coroutine_threadsafe(shut(), self._aio).result(FRAME_TIMEOUT_S)
        self._aio.call_soon_threadsafe(self._aio.stop)
        self._thread.join(FRAME_TIMEOUT_S)
        if not self._thread.is_alive():
            self._aio.close()
        _OPEN.discard(self)


def _shown(value: Any) -> tuple[Scene, Callable[[], Scene] | None]:
    """The Viewer's scene and what plays (`RenderLoop`'s ``animate``): a Scene as it is; a Volume in a Scene with
    the default light, as `volren.render` shows it; a `VolumeSequence`'s frame 0, then its frames in turn while
    ``playing`` (as ``volren serve --volume PATTERN``)."""
    from volren.plan.volume import VolumeSequence
    from volren.render.compositing.channels import Channels
    from volren.serve.loop import sequence_player

    if isinstance(value, Scene):
        return value, None
    if isinstance(value, Volume):
        return Scene((value,), name=value.name), None
    if isinstance(value, VolumeSequence):
        first = value[0]
        if isinstance(first, Volume):
            scene = Scene((first,), name=value.path.stem)
            return scene, sequence_player(len(value), lambda i: dataclasses.replace(scene, volumes=(value[i],)))
    if isinstance(value, Channels | VolumeSequence):  # a sequence of channels too
        raise VolrenError("Viewer: a multi-channel volume renders each channel by a renderer of its own, which the "
                          "live loop does not (as volren serve): render it with volren.render")
    raise VolrenError(f"Viewer: scene must be a volren Scene, Volume or VolumeSequence, got {type(value).__name__}")


def _check_choice(name: str, value: Any, choices: Any) -> str:
    if not isinstance(value, str) or value not in choices:
        shown = repr(value) if isinstance(value, str) and len(value) <= 40 else type(value).__name__
        raise VolrenError(f"Viewer: {name} must be one of {', '.join(choices)}, got {shown}")
    return value


def _on_event_loop() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


def _in_ipython() -> bool:
    from IPython.core.interactiveshell import InteractiveShell

    return InteractiveShell.initialized()
