"""Per-viewer state of `volren serve`: image size, stereo, the newest camera, whether a frame is on its way or waits
for the page's acknowledgement."""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass, field, replace
from typing import Any

from volren.camera import Camera, StereoRig
from volren.errors import VolrenError
from volren.serve.protocol import MIN_SIDE, CameraMessage, ProtocolError
from volren.serve.rates import (
    CONNECT_BURST,
    MESSAGE_BURST,
    MESSAGES_PER_S,
    SETTINGS_BURST,
    SETTINGS_PER_S,
    TICK_MS,
    ErrorCount,
    TokenBucket,
)

MIN_SHARE = 160 * 90
"""[px] every viewer is owed min(its size, this) whatever the tick costs: the time share never shrinks a frame below
160x90 (a big viewer's floor then costs about 11 ms a tick on the 2-core CPU, dssrm at interactive)"""
SHARE_STEPS = 2
"""a shrunk frame's pixels are its size / 2^(k / SHARE_STEPS) for a whole k: sizes on a ladder, so the tick-to-tick
jitter of the estimate does not change a still view's size (which would restart its refinement)"""


@dataclass(frozen=True)
class Limits:
    max_viewers: int = 16
    max_width: int = 1920
    """[px] of a viewer's image (both eyes together when stereo)"""
    max_height: int = 1080
    pixel_budget: int = 1920 * 1080
    """[px] rendered per tick for all viewers together, at most: one viewer at the clamp alone gets all of it"""
    max_per_client: int = 4
    """viewers connected at once from one client address, at most max_viewers (issue 44 item 2: 16 sockets of one
    neighbour held every slot); on loopback every 127.x.y.z address counts as its own: local users are told apart
    by --token only"""
    tick_ms: float | None = TICK_MS
    """[ms] with two or more viewers, the tick time aimed at: each viewer gets an equal share of it (`TimeShares`),
    a viewer whose frame costs more gets a smaller one (the page upscales it); None: the pixel budget alone"""
    connect_burst: int = CONNECT_BURST
    """WebSocket upgrades one address may make at once before the rate limit (`volren.serve.rates`)"""

    def __post_init__(self) -> None:
        if not 1 <= self.max_viewers <= 1024:
            raise VolrenError(f"--max-viewers must lie in [1, 1024], got {self.max_viewers}")
        if not 1 <= self.max_per_client <= 1024:
            raise VolrenError(f"--max-viewers-per-client must lie in [1, 1024], got {self.max_per_client}")
        if self.tick_ms is not None and not 1.0 <= self.tick_ms <= 10_000.0:
            raise VolrenError(f"--tick-ms must lie in [1, 10000] ms, got {self.tick_ms:g}")
        if not MIN_SIDE * MIN_SIDE <= self.pixel_budget <= 1 << 26:
            raise VolrenError(f"--pixel-budget must lie in [{MIN_SIDE * MIN_SIDE}, {1 << 26}] pixels, got "
                              f"{self.pixel_budget}")
        for flag, side in (("--max-width", self.max_width), ("--max-height", self.max_height)):
            if not 2 * MIN_SIDE <= side <= 8192:
                raise VolrenError(f"{flag} must lie in [{2 * MIN_SIDE}, 8192] pixels, got {side}")

    def clamp(self, width: int, height: int) -> tuple[int, int]:
        return (min(max(width, 2 * MIN_SIDE), self.max_width), min(max(height, MIN_SIDE), self.max_height))


@dataclass(eq=False)
class Viewer:
    """One connected page. ``send`` delivers a packed frame (the WebSocket's send_bytes); ``sending`` is the task of
    the frame still on its way, if any, and ``unacked`` the tick of the frame sent that the page has not acknowledged
    drawing: while either holds, the viewer gets no new frame (dropped, never queued), so no frame waits in a socket
    buffer behind another (issue 20 item 5)."""

    id: int
    send: Any
    """coroutine function sending a binary frame"""
    text: Any = None
    """coroutine function sending a text message (errors, settings)"""
    width: int = 0
    height: int = 0
    stereo: bool = False
    camera: Camera | None = None
    camera_id: int = -1
    near: float = Camera.near
    """[m] the near plane of the cameras this viewer sends (the served camera's: a thousandth of the distance that
    frames a specimen in micrometres, which the default 1 cm would clip away)"""
    far: float = Camera.far
    """[m] their far plane (the served camera's: twice the farthest corner of a volume beyond 1000 m)"""
    shown: tuple[int, int] = (-1, -1)
    """(camera id, scene version) of the last frame rendered for this viewer"""
    sending: asyncio.Task | None = None
    unacked: int | None = None
    """tick of the frame handed to the socket and not yet acknowledged"""
    unacked_since: float = 0.0
    """[s, time.monotonic] when that frame was handed over"""
    parked: bool = False
    """no acknowledgement for PARK_AFTER_S: not rendered until one comes"""
    texting: asyncio.Task | None = None
    """the text message (settings, error) still on its way, if any"""
    settings_due: bool = False
    """the shared settings changed while a text message was on its way: send the newest once it is through"""
    close: Any = None
    """coroutine function closing the socket: (code, reason)"""
    frames: int = 0
    dropped: int = 0
    closed: bool = False
    scaled: bool = False
    """its last frame was smaller than its size (its time share, `TimeShares`)"""
    client: str = ""
    """the address it connected from (`Limits.max_per_client`)"""
    pending: dict[str, Any] = field(default_factory=dict)
    """shared settings it asked for that wait for their turn (`RenderLoop.offer`): the newest value of each"""
    settings_rate: TokenBucket = field(default_factory=lambda: TokenBucket(SETTINGS_PER_S, SETTINGS_BURST))
    errors: ErrorCount = field(default_factory=ErrorCount)
    messages: TokenBucket = field(default_factory=lambda: TokenBucket(MESSAGES_PER_S, MESSAGE_BURST))
    """its socket's message rate (from its upgrade on: `volren.serve.app.greet` hands its bucket over)"""

    @property
    def ready(self) -> bool:
        return self.width > 0 and self.camera is not None and not self.closed and not self.parked

    @property
    def busy(self) -> bool:
        return self.unacked is not None or (self.sending is not None and not self.sending.done())

    def ack(self, tick: int) -> None:
        if tick != self.unacked:
            shown = "none" if self.unacked is None else f"tick {self.unacked}"
            raise ProtocolError(f"ack.tick {tick} is not the frame awaiting acknowledgement ({shown})")
        self.unacked, self.parked = None, False

    def eye_size(self) -> tuple[int, int]:
        return (self.width // 2, self.height) if self.stereo else (self.width, self.height)

    def set_camera(self, msg: CameraMessage) -> None:
        if msg.id <= self.camera_id:  # one socket keeps the order: a repeated id is a client's bug, say so
            raise ProtocolError(f"camera.id must increase: got {msg.id} after {self.camera_id}")
        w, h = self.eye_size()
        try:
            self.camera = Camera(position=msg.position, look_at=msg.look_at, up=msg.up, fov_y=msg.fov, width=w,
                                 height=h, near=self.near, far=self.far)
        except VolrenError as exc:
            raise ProtocolError(f"camera: {exc}") from None
        self.camera_id = msg.id

    def resize(self, width: int, height: int, stereo: bool, limits: Limits) -> None:
        self.width, self.height = limits.clamp(width, height)
        self.stereo = stereo
        if self.camera is not None:
            w, h = self.eye_size()
            self.camera = replace(self.camera, width=w, height=h)
            self.shown = (-1, -1)

    def views(self, ipd: float, pixels: int | None = None) -> list[Camera]:
        """This viewer's views: one camera, or a stereo viewer's two eyes (left first, a coupled CACRM pair); with
        ``pixels`` below its size, scaled down (same aspect, at least MIN_SIDE a side) to fit them."""
        assert self.camera is not None
        cam = self.camera
        if pixels is not None and pixels < self.width * self.height:
            s = math.sqrt(pixels / (self.width * self.height))
            cam = replace(cam, width=max(MIN_SIDE, int(cam.width * s)), height=max(MIN_SIDE, int(cam.height * s)))
        return StereoRig(cam, ipd).eyes() if self.stereo else [cam]


class TimeShares:
    """Fair by time, not by pixels (issue 44 item 3): with two or more viewers each gets an equal share of the tick
    time ``tick_ms``, as pixels. After each tick the pixels that fit in ``tick_ms`` are estimated from what it
    rendered and how long it took (render and encode), ``pixels * tick_ms / took``: the dynamic resolution of games,
    which converges to the fitting size from either side, since a tick's time is a fixed part plus a part per pixel
    (the estimate grows at most 2x a tick, so one lucky tick cannot bring a big viewer back whole). The estimate is
    water-filled among the viewers (`fair_shares`), each owed at least min(its size, MIN_SHARE); a lone viewer has
    the whole tick (up to the pixel budget). Before: one 1920x1080 viewer beside four 64x48 ones cut them from 16
    fps / 52 ms median frame age to 0.64 fps / 1.55 s."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.budget = limits.pixel_budget
        """[px] a tick may render, all viewers together"""

    def shares(self, wants: list[int], calm: bool = False) -> list[int]:
        """Each viewer's pixels this tick; ``calm`` (no viewer moved for a while): the pixel budget alone, so still
        views get their whole size once nobody waits for a frame."""
        if self.limits.tick_ms is None or len(wants) < 2 or calm:
            return fair_shares(wants, self.limits.pixel_budget)
        owed = sum(min(w, MIN_SHARE) for w in wants)
        fair = fair_shares(wants, min(self.limits.pixel_budget, max(self.budget, owed)))
        # a rung of the ladder, never under what a viewer is owed (unless the operator's pixel budget gives less)
        return [w if s >= w else max(min(w, MIN_SHARE, s), int(w / 2 ** (math.ceil(SHARE_STEPS * math.log2(w / s))
                                                                        / SHARE_STEPS)))
                for w, s in zip(wants, fair, strict=True)]

    def took(self, pixels: int, seconds: float) -> None:
        """A tick rendered ``pixels`` in ``seconds``: the next one's budget."""
        if self.limits.tick_ms is None or pixels <= 0 or seconds <= 0:
            return
        fits = pixels * self.limits.tick_ms * 1e-3 / seconds
        self.budget = int(min(self.limits.pixel_budget, fits, 2 * max(self.budget, pixels)))


def fair_shares(wants: list[int], budget: int) -> list[int]:
    """Max-min fair split of ``budget`` pixels (water filling): smallest request first, each gets what it asks or an
    equal part of what is left, whichever is less; what a small viewer leaves goes to the larger ones."""
    out, left = [0] * len(wants), budget
    order = sorted(range(len(wants)), key=wants.__getitem__)
    for k, i in enumerate(order):
        out[i] = min(wants[i], left // (len(wants) - k))
        left -= out[i]
    return out


@dataclass
class ViewerSet:
    """The connected viewers, at most ``limit``; ids count up from 1."""

    limit: int
    viewers: dict[int, Viewer] = field(default_factory=dict)
    next_id: int = 1

    per_client: int | None = None
    """viewers one address may hold (None: no limit of its own)"""
    near: float = Camera.near
    """[m] each viewer's `Viewer.near`: the served camera's"""
    far: float = Camera.far
    """[m] each viewer's `Viewer.far`: the served camera's"""

    def add(self, send: Any, text: Any = None, client: str = "") -> Viewer:
        if len(self.viewers) >= self.limit:
            raise ProtocolError(f"server full: {self.limit} viewers connected (--max-viewers)")
        if self.per_client is not None and sum(v.client == client for v in self.viewers.values()) >= self.per_client:
            raise ProtocolError(f"server full for {client}: {self.per_client} viewers connected from that address "
                                "(--max-viewers-per-client)")
        v = Viewer(self.next_id, send, text, client=client, near=self.near, far=self.far)
        self.viewers[v.id] = v
        self.next_id += 1
        return v

    def remove(self, viewer: Viewer) -> None:
        viewer.closed = True
        self.viewers.pop(viewer.id, None)

    def __len__(self) -> int:
        return len(self.viewers)

    def render_order(self) -> list[Viewer]:
        """Viewers with a camera, stereo ones first, so every stereo pair sits at views (2k, 2k + 1) (CACRM couples
        views in those pairs), then the mono ones; join order within each."""
        ready = [v for v in self.viewers.values() if v.ready]
        return [v for v in ready if v.stereo] + [v for v in ready if not v.stereo]
