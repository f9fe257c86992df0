"""Sharded serving on Ray: ``volren serve --shards N [--ray-address ADDR]`` (issue 23 item 3).

The aiohttp front end stays the WebSocket end (`volren.serve.app`, its Host, Origin and token checks unchanged) and
keeps every socket. Behind it, N Ray actors (`ShardWorker`) each hold the renderer part of a `RenderLoop` (renderer,
light map, GI and fog history, majorants, the playing scene); the front end runs the socket part of one `RenderLoop`
per shard (`ShardLoop`: its viewers, their still views, its ticks) whose `_render` sends the tick's jobs (viewer ids,
cameras, still views) to its actor, which renders them in one multi-view call and returns the frames already JPEG
encoded. `ShardedLoop` is the app's loop: it holds the viewers and the shared settings (every shard adopts them), and
places each viewer on a shard once its first camera arrives (`volren.serve.placement`: a stereo pair whole, viewers
looking at the same part of the scene together, else where it adds the least work).

A shard whose actor dies (killed, its node lost) is marked down at its next tick: its viewers get a notice
(`notice_message`) and move to the shards still up, the others never stop. With no shard left the viewers are told
so and /health's ``shards_up`` is 0. Dead shards are not replaced (restart the server to get them back).

Each shard renders the whole scene with its own passes: N shards compute N light maps (shadow grids) per tick where
one loop computes one; /health's ``shards`` counts them per shard. Each animates the scene on its own clock (a tick
advances its own copy), so viewers on different shards may see different steps of a playing scene.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from volren.camera import Camera
from volren.errors import VolrenError
from volren.scene import Scene
from volren.serve.heap import one_arena
from volren.serve.jpeg import JPEG_QUALITY
from volren.serve.loop import SHARED_SETTINGS, RenderLoop, Still
from volren.serve.placement import Footprint, choose_shard, footprint
from volren.serve.viewers import Limits, Viewer, ViewerSet

log = logging.getLogger("volren.serve")

RENDER_SETTINGS = ("method", "quality", "tf", "light_dir", "mode", "iso_value")
"""the shared settings a shard's actor renders with (playing stays in the front end: it says whether to advance)"""
READY_TIMEOUT_S = 300.0
"""[s] for every shard actor to be up: placed on the cluster, volren and Warp imported, its scene received"""
FLAG = "--shards"


class ShardLost(Exception):
    """A shard's actor died during a tick (no `VolrenError`: `RenderLoop.step` lets it through to `ShardLoop.step`)."""


def notice_message(text: str) -> str:
    """A protocol notice: a server event the page shows (a shard lost), not an error of the viewer's."""
    return json.dumps({"type": "notice", "message": text})


@dataclass(frozen=True)
class ShardSpec:
    """What a shard actor builds its render loop from (pickled to it). ``animate`` is run in the actor and gives the
    loop's animation step (None: not animated): an advected smoke's simulation lives on the actor's device."""

    scene: Scene
    method: str
    quality: str
    limits: Limits
    device: str
    overrides: dict[str, Any] = field(default_factory=dict)
    animate: Callable[[], Callable[[], Scene] | None] | None = None
    shared: bool = True
    ipd: float = 0.063
    jpeg_quality: int = JPEG_QUALITY
    refine: int | None = None

    def loop(self, cls: type[RenderLoop] = RenderLoop, **kw: Any) -> RenderLoop:
        return cls(self.scene, self.method, self.quality, limits=self.limits, device=self.device, shared=self.shared,
                   ipd=self.ipd, jpeg_quality=self.jpeg_quality, overrides=self.overrides, refine=self.refine, **kw)


class ShardWorker:
    """A shard's Ray actor: the renderer part of a `RenderLoop` (never started: no sockets, no ticks of its own)."""

    def __init__(self, spec: ShardSpec) -> None:
        one_arena()  # as `volren serve` does (the threads Ray started already keep the arenas they have)
        self.loop = spec.loop(animate=spec.animate() if spec.animate is not None else None)

    def ready(self) -> bool:
        """Up (the caller waits for it); whether the scene is animated."""
        return self.loop.animated

    def tick(self, settings: dict[str, Any], jobs: list[tuple[int, int, list[Camera], Still | None, tuple]],
             index: int, advance: bool, viewers: int) -> tuple[list[tuple[bytes, Still]], dict[str, Any]]:
        """One tick of the front end's `ShardLoop`: adopt its settings, render and encode (`_render_encode`); the
        frames and the tick's counters."""
        loop = self.loop
        loop.adopt(settings)
        loop._build_renderer()
        renders = loop.renders
        frames = loop._render_encode(jobs, index, advance, viewers)
        return frames, {"renders": loop.renders - renders, "render_ms": loop.render_ms, "encode_ms": loop.encode_ms,
                        "pass_ms": loop.pass_ms, "views": loop.views_last}

    def release_views(self) -> None:
        """The front end's shard has no viewer left (`RenderLoop.release`)."""
        self.loop.release_views()


class ShardLoop(RenderLoop):
    """The socket part of shard ``index``'s render loop, in the front end: its viewers and ticks; each tick's render
    runs in its ``actor``. ``light_maps`` and ``shadow_grids``: its ticks that computed one."""

    local = False

    def __init__(self, index: int, actor: Any, front: ShardedLoop, spec: ShardSpec) -> None:
        super().__init__(spec.scene, spec.method, spec.quality, limits=spec.limits, device=spec.device,
                         shared=spec.shared, ipd=spec.ipd, jpeg_quality=spec.jpeg_quality, overrides=spec.overrides,
                         refine=spec.refine)
        self.index, self.actor, self.front = index, actor, front
        self.viewers = ViewerSet(spec.limits.max_viewers)  # the front end limits them per client
        """the viewers placed here (`ShardedLoop._place`), the same objects as the front end's"""
        self.up = True
        self.light_maps = self.shadow_grids = 0
        self.adopt({name: getattr(front, name) for name in SHARED_SETTINGS})

    @property
    def animated(self) -> bool:
        return self.front.animated

    async def _render(self, jobs: list[tuple[int, int, list[Camera], Still | None, tuple]], index: int,
                      advance: bool, viewers: int) -> list[tuple[bytes, Still]]:
        from ray.exceptions import RayActorError, RayTaskError

        settings = {name: getattr(self, name) for name in RENDER_SETTINGS}
        try:
            frames, stats = await self.actor.tick.remote(settings, jobs, index, advance, viewers)
        except RayActorError as exc:
            raise ShardLost(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
        except RayTaskError as exc:  # the tick's own failure: the loop reports it as it does in process
            raise exc.cause from None
        self.renders += stats["renders"]
        self.render_ms, self.encode_ms, self.pass_ms = stats["render_ms"], stats["encode_ms"], stats["pass_ms"]
        self.views_last = stats["views"]
        self.light_maps += "light_map" in self.pass_ms
        self.shadow_grids += "shadow_grid" in self.pass_ms
        return frames

    def settle(self) -> None:
        self.front.settle()  # the front end holds the shared settings

    async def step(self) -> None:
        try:
            await super().step()
        except ShardLost as exc:
            self.front.lost(self, str(exc))

    async def _release_views(self) -> None:
        """The actor's view-sized state, and the front end's heap."""
        from ray.exceptions import RayError

        await super()._release_views()
        if self.up:
            with contextlib.suppress(RayError):  # a dead actor: its next tick marks the shard down
                await self.actor.release_views.remote()

    def health(self) -> dict[str, Any]:
        fps = self.fps
        return {"shard": self.index, "state": "up" if self.up else "down", "viewers": sorted(self.viewers.viewers),
                "tick": self.tick, "tick_ms": round(1e3 / fps, 3) if fps else None, "fps": round(fps, 3),
                "renders": self.renders, "views": self.views_last, "render_ms": round(self.render_ms, 3),
                "encode_ms": round(self.encode_ms, 3), "light_maps": self.light_maps,
                "shadow_grids": self.shadow_grids}


def start_workers(spec: ShardSpec, shards: int, address: str | None) -> tuple[Any, bool, list[Any], bool]:
    """(ray, whether this call connected it, ``shards`` started `ShardWorker` actors, whether the scene is
    animated). Each actor asks one GPU on CUDA, one CPU otherwise; a local cluster holds at least ``shards`` CPUs."""
    import os

    from volren.distributed.runtime import connect, import_ray

    cuda = spec.device.startswith("cuda")
    connected = not import_ray(FLAG, local=not address).is_initialized()
    ray = connect(FLAG, address, num_cpus=None if address else max(os.cpu_count() or 1, shards))
    worker = ray.remote(num_gpus=1, num_cpus=0)(ShardWorker) if cuda else ray.remote(num_cpus=1)(ShardWorker)
    actors = [worker.remote(spec) for _ in range(shards)]
    try:
        animated = ray.get([a.ready.remote() for a in actors], timeout=READY_TIMEOUT_S)
    except ray.exceptions.GetTimeoutError:
        for a in actors:
            ray.kill(a)
        raise VolrenError(f"{FLAG} {shards}: the shards were not all up within {READY_TIMEOUT_S:g} s (each asks one "
                          f"{'GPU' if cuda else 'CPU'} of the cluster)") from None
    except ray.exceptions.RayError as exc:
        for a in actors:
            ray.kill(a)
        cause = getattr(exc, "cause", exc)
        raise VolrenError(f"{FLAG} {shards}: a shard failed to start: {str(cause).splitlines()[0]}") from None
    return ray, connected, actors, animated[0]


class ShardedLoop(RenderLoop):
    """The app's loop of a sharded server: the viewers, the shared settings, the acknowledgement watch; ``shards``
    `ShardLoop`s render them (module docstring). The other arguments are `RenderLoop`'s, ``animate`` a factory of
    its animation step run in each actor (`ShardSpec`). ``address``: an existing Ray cluster (None: a local one)."""

    local = False

    def __init__(self, scene: Scene, method: str, quality: str = "interactive", *, shards: int,
                 address: str | None = None, animate: Callable[[], Callable[[], Scene] | None] | None = None,
                 limits: Limits | None = None, camera: Camera | None = None, device: str = "cpu",
                 overrides: dict[str, Any] | None = None, refine: int | None = None,
                 lock_settings: bool = False) -> None:
        if shards < 1:
            raise VolrenError(f"{FLAG} must be at least 1, got {shards}")
        self.shards: list[ShardLoop] = []
        super().__init__(scene, method, quality, limits=limits, camera=camera, device=device,
                         overrides=overrides, refine=refine, lock_settings=lock_settings)
        spec = ShardSpec(scene, method, quality, self.limits, device, dict(overrides or {}), animate, refine=refine)
        self._ray, self._connected, actors, self._animated = start_workers(spec, shards, address)
        self.shards = [ShardLoop(i, actor, self, spec) for i, actor in enumerate(actors)]

    @property
    def animated(self) -> bool:
        return self._animated

    def adopt(self, values: dict[str, Any]) -> set[str]:
        changed = super().adopt(values)
        for s in self.shards:
            s.adopt(values)
        return changed

    @property
    def ticks_done(self) -> int:
        return sum(s.tick for s in self.shards)

    def start(self) -> None:
        for s in self.shards:  # settings set before the start (the bench's playing)
            s.adopt({name: getattr(self, name) for name in SHARED_SETTINGS})
            s._task = asyncio.create_task(s.run(), name=f"volren shard {s.index}")
        self._watch = asyncio.create_task(self.watch(), name="volren acknowledgement watch")

    async def stop(self) -> None:
        await super().stop()
        for s in self.shards:
            await s.stop()
            self._ray.kill(s.actor)
        if self._connected:  # the server's own Ray: `serve` ends the process without the atexit that stops it
            from volren.distributed.runtime import shutdown_local

            shutdown_local(self._ray)

    def wake(self) -> None:
        self._place()
        for s in self.shards:
            if s.up:
                s.wake()

    def _place(self) -> None:
        """Drop the viewers gone from the server from their shards; place those with a first camera on none yet."""
        here = self.viewers.viewers
        for s in self.shards:
            for vid in [vid for vid, v in s.viewers.viewers.items() if here.get(vid) is not v or v.closed]:
                del s.viewers.viewers[vid]
        placed = {vid for s in self.shards for vid in s.viewers.viewers}
        for v in here.values():
            if v.id not in placed and v.camera is not None and not v.closed and any(s.up for s in self.shards):
                self._assign(v)

    def _assign(self, v: Viewer) -> None:
        loads: list[list[Footprint] | None] = [[viewer_footprint(u) for u in s.viewers.viewers.values()]
                                               if s.up else None for s in self.shards]
        self.shards[choose_shard(loads, viewer_footprint(v))].viewers.viewers[v.id] = v

    def lost(self, shard: ShardLoop, why: str) -> None:
        """``shard``'s actor died: mark it down, tell its viewers, move them to the shards still up."""
        shard.up = False
        left = sum(s.up for s in self.shards)
        log.warning("volren serve: render shard %d lost (%s); %d shard(s) left", shard.index, why, left)
        if left:
            shard.broadcast(notice_message(f"render shard {shard.index} stopped ({why}); your view moved to another "
                                           "shard"))
        else:
            self.broadcast(notice_message(f"render shard {shard.index} stopped ({why}): no render shard is left, "
                                          "the server cannot show frames (restart it)"))
        moved = list(shard.viewers.viewers.values())
        shard.viewers.viewers.clear()
        for v in moved:
            v.shown = (-1, -1)  # its new shard owes it a frame
        self.wake()

    def report(self) -> dict[str, Any]:
        shards = [s.health() for s in self.shards]
        return {**super().report(), "fps": round(sum(s.fps for s in self.shards), 3),
                "tick": sum(s.tick for s in self.shards), "renders": sum(s.renders for s in self.shards),
                "views": sum(s.views_last for s in self.shards if s.up),
                "render_ms": max((h["render_ms"] for h in shards), default=0.0),
                "encode_ms": max((h["encode_ms"] for h in shards), default=0.0),
                "shards_up": sum(s.up for s in self.shards), "shards": shards}


def viewer_footprint(v: Viewer) -> Footprint:
    assert v.camera is not None
    return footprint(v.camera, v.width, v.height)
