"""Suite ``serve``: `volren serve` under 1, 2, 4, 8 and 16 simulated clients, the shared render loop against a
naive server (issue 15: papers 000, 002 and 003 as live many-viewer systems).

Each client is an aiohttp WebSocket client on a rig: volume scenes orbit the scene's centre (phases spread evenly,
alternate directions), fog scenes stand at the scene's viewpoint and look around; every fourth client is a stereo
pair (one viewer, two eyes side by side: a coupled pair for CACRM). Clients send their camera open-loop at
``camera_hz`` like a page during a drag, and the scene plays (the advected smoke, the fog scene's moving geometry),
so every tick renders every viewer and recomputes the passes that depend on the scene (light map, shadow grid).
The shared server renders all viewers in one multi-view call per tick (`RenderLoop(shared=True)`); the naive one
renders each viewer with a renderer of its own (`shared=False`: as if each viewer had a server). Server and clients
share one event loop (one process), frames cross a real TCP socket on 127.0.0.1.

Each point alternates ``repeats`` windows between the two servers (both up, one idle while the other serves) and
keeps each server's window with the most frames per second (on a shared machine the least disturbed one; all are
listed). Per row: tick time (wall time per tick over the measured window), the render call(s) per tick, total frames per
second over all clients and the slowest client's, round-trip latency (camera sent -> first frame answering its id:
median and 95th percentile over all clients, and the worst client's p95), bytes per second received.
Goals (issue 15), measured in one run: at 8 clients the shared server delivers >= 1.5x the naive server's total
frames per second, and no client's p95 latency exceeds 3 frame times (the shared run's tick time).
Issue 44's fair run (`run_fair`): four 64x48 clients alone and beside a 1920x1080 one, on servers of the default
limits sharing the tick by time and by pixels; goal: their median frame age beside it within 3x of alone.
Full (GPU): 256^3 smoke, 480x270 per eye, 3 windows of 10 s per point and server.
Quick (CPU): 64^3 smoke, 160x90 per eye, 2 windows of 3 s per point and server.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import statistics
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from volren.bench import Suite
from volren.camera import Camera
from volren.errors import VolrenError
from volren.scene import Scene

FULL = {"cases": [("fog", "dynamic"), ("cacrm", "smoke")], "resolution": 256, "size": (480, 270),
        "counts": [1, 2, 4, 8, 16], "seconds": 10.0, "min_ticks": 10, "repeats": 3, "camera_hz": 60.0,
        "overrides": {}, "mixed": {"small": 8, "small_size": (480, 270), "big_size": (1920, 1080), "read_every": 1.0,
                                   "budget_factor": 1.5},
        "fair": {"small": 4, "small_size": (64, 48), "big_size": (1920, 1080), "camera_hz": 10.0, "seconds": 10.0},
        "neighbour": {"viewers": 4, "size": (64, 48), "camera_hz": 10.0, "seconds": 10.0}}
QUICK = {"cases": [("fog", "dynamic"), ("cacrm", "smoke")], "resolution": 64, "size": (160, 90),
         "counts": [1, 2, 4, 8, 16], "seconds": 3.0, "min_ticks": 4, "repeats": 2, "camera_hz": 30.0,
         "overrides": {}, "mixed": {"small": 8, "small_size": (320, 180), "big_size": (1920, 1080),
                                    "read_every": 1.0, "budget_factor": 1.5},
         "fair": {"small": 4, "small_size": (64, 48), "big_size": (1920, 1080), "camera_hz": 10.0, "seconds": 4.0},
         "neighbour": {"viewers": 4, "size": (64, 48), "camera_hz": 10.0, "seconds": 4.0}}
MODES = ("shared", "naive")
STEREO_EVERY = 4
"""client i is a stereo pair when i % STEREO_EVERY == STEREO_EVERY - 1 (2 of 8 clients, 4 of 16)"""
ORBIT_RAD_S = 0.5
"""[rad/s] of a client's orbit (volume scenes) or look-around swing (fog scenes)"""
LOOK_SWING = 0.6
"""[rad] half-angle of a fog client's look-around"""
GOAL_CLIENTS, GOAL_SPEEDUP, GOAL_LATENCY_FRAMES = 8, 1.5, 3.0
GOAL_MIXED_P95, GOAL_MIXED_AGE = 1.5, 2.0
"""issue 20's mixed run: the small clients' p95 latency with the big client at most 1.5x of without it; no frame
older than 2 tick times when it arrives"""
GOAL_FAIR_AGE = 3.0
"""issue 44's fair run: four small viewers' median frame age beside a full-HD viewer within 3x of theirs alone"""
WARMUP_FRAMES = 2
"""frames every client receives before the window opens (kernel compilation, the naive renderers' first upload)"""
WARMUP_TIMEOUT_S = 600.0


def rig_camera(base: Camera, walk: bool, index: int, count: int, t: float) -> dict[str, Any]:
    """Client ``index`` of ``count``'s camera message fields at time ``t`` [s]."""
    phase = 2 * math.pi * index / count + (1 if index % 2 == 0 else -1) * ORBIT_RAD_S * t
    eye, target = np.asarray(base.position, float), np.asarray(base.look_at, float)
    if walk:  # stand at the viewpoint, swing the gaze about +y
        a = LOOK_SWING * math.sin(phase)
        d = target - eye
        d = np.array([d[0] * math.cos(a) + d[2] * math.sin(a), d[1], -d[0] * math.sin(a) + d[2] * math.cos(a)])
        position, look_at = eye, eye + d
    else:  # orbit the target at the base camera's distance and height
        offset = eye - target
        radius = math.hypot(offset[0], offset[2])
        position = target + np.array([radius * math.sin(phase), offset[1], radius * math.cos(phase)])
        look_at = target
    return {"position": [float(x) for x in position], "look_at": [float(x) for x in look_at],
            "up": [float(x) for x in base.up], "fov": float(base.fov_y)}


@dataclass
class ClientRecord:
    """What one simulated client saw while the window was open."""

    stereo: bool
    frames: int = 0
    bytes: int = 0
    latencies_ms: list[float] = field(default_factory=list)
    """camera sent -> the first frame answering it"""
    ages_ms: list[float] = field(default_factory=list)
    """per frame: its arrival minus the send time of the camera it shows (issue 44's frame age)"""
    render_ms: dict[int, float] = field(default_factory=dict)
    """tick -> render time of that tick (frame headers)"""
    pixels: int = 0
    """the largest frame's width x height (smaller than asked when over its share of the pixel budget)"""
    opened: float = math.inf
    """[s, perf_counter] when the window opened: a frame answering a camera sent before it is warm-up left over (a
    first tick that compiled kernels for minutes answers the cameras it was started with), not latency"""
    warm: asyncio.Event = field(default_factory=asyncio.Event)
    viewer: int = 0
    """its viewer id (the welcome's): which shard serves it"""


async def run_client(session: Any, url: str, rec: ClientRecord, index: int, count: int, size: tuple[int, int],
                     base: Camera, walk: bool, hz: float, measuring: asyncio.Event, read_every: float = 0.0) -> None:
    """Connect, send hello, then cameras at ``hz`` while receiving frames until cancelled; a slow reader
    (``read_every`` > 0 s) takes one frame that often (it waits, then acknowledges the one it holds)."""
    from aiohttp import WSMsgType

    from volren.serve.protocol import unpack_frame

    width = size[0] * (2 if rec.stereo else 1)
    async with session.ws_connect(url, max_msg_size=0) as ws:
        await ws.send_json({"type": "hello", "width": width, "height": size[1], "stereo": rec.stereo})
        sent: dict[int, float] = {}
        sent_at: dict[int, float] = {}
        """every camera's send time until a frame shows a later one (frame ages)"""
        start = time.perf_counter()

        async def cameras() -> None:
            cam_id = 0
            while True:
                cam_id += 1
                sent[cam_id] = sent_at[cam_id] = time.perf_counter()
                msg = rig_camera(base, walk, index, count, sent[cam_id] - start)
                await ws.send_json({"type": "camera", "id": cam_id, **msg})
                await asyncio.sleep(1.0 / hz)

        sender: asyncio.Task | None = None
        seen = 0
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    data = msg.json()
                    if data["type"] == "error":
                        raise VolrenError(f"bench serve: the server refused client {index}: {data['message']}")
                    if data["type"] == "welcome":
                        rec.viewer = data["viewer"]
                        sender = asyncio.create_task(cameras())
                    continue
                if msg.type != WSMsgType.BINARY:
                    break
                now = time.perf_counter()
                header, _ = unpack_frame(msg.data)
                if read_every > 0:
                    await asyncio.sleep(read_every)
                await ws.send_json({"type": "ack", "tick": header["tick"]})  # as the page does once it drew it
                answered = header["camera_id"]
                t = sent.get(answered)
                for k in [k for k in sent if k <= answered]:
                    del sent[k]
                shown_at = sent_at.get(answered)
                for k in [k for k in sent_at if k < answered]:
                    del sent_at[k]
                seen += 1
                if seen >= WARMUP_FRAMES:
                    rec.warm.set()
                if measuring.is_set():
                    rec.frames += 1
                    rec.bytes += len(msg.data)
                    rec.render_ms[header["tick"]] = header["render_ms"]
                    rec.pixels = max(rec.pixels, header["width"] * header["height"])
                    if t is not None and t >= rec.opened:
                        rec.latencies_ms.append((now - t) * 1e3)
                    if shown_at is not None and shown_at >= rec.opened:
                        rec.ages_ms.append((now - shown_at) * 1e3)
        finally:
            if sender is not None:
                sender.cancel()


@dataclass
class Served:
    """A render loop served on 127.0.0.1: its WebSocket URL and the render calls of each tick."""

    loop: Any
    url: str
    calls: dict[int, int] = field(default_factory=dict)
    """tick -> render calls it made (counted around the worker-thread job, so a window edge cannot split a tick)"""
    busy: bool = False
    """a tick's render is running"""


@asynccontextmanager
async def served(loop: Any) -> AsyncIterator[Served]:
    from aiohttp import web

    from volren.serve.app import make_app

    runner = web.AppRunner(make_app(loop, "bench"), shutdown_timeout=1.0)  # not the refusals still queued
    await runner.setup()
    try:
        await web.TCPSite(runner, "127.0.0.1", 0).start()
        out = Served(loop, f"http://127.0.0.1:{runner.addresses[0][1]}/ws")
        if loop.local:  # a sharded loop renders in its actors: `measure_window` counts their renders
            render_encode = loop._render_encode

            def counted(jobs: list, index: int, advance: bool, viewers: int) -> list[bytes]:
                before, out.busy = loop.renders, True
                try:
                    return render_encode(jobs, index, advance, viewers)
                finally:
                    out.calls[index], out.busy = loop.renders - before, False

            loop._render_encode = counted
        yield out
    finally:
        await runner.cleanup()


def shard_counts(loop: Any) -> list[tuple[int, int, int]]:
    """Per shard of a sharded loop (none for one in process): its ticks, light maps and shadow grids so far."""
    return [(s.tick, s.light_maps, s.shadow_grids) for s in getattr(loop, "shards", ())]


async def measure_window(srv: Served, count: int, cfg: dict[str, Any], base: Camera, walk: bool,
                         clients: list[tuple[tuple[int, int], float]] | None = None,
                         bases: list[Camera] | None = None) -> dict[str, Any]:
    """Connect ``count`` clients to ``srv`` (or ``clients``: per client its size and read interval, all mono),
    wait until each has its first frames, measure one window, disconnect and let the loop finish its tick.
    ``bases``: each client's own rig (default: all on ``base``'s). A sharded loop's row has ``shards``: per shard its
    viewers, ticks, tick time, shared passes per tick, and each client's p95 latency in its shard's tick times."""
    import aiohttp

    loop = srv.loop
    measuring = asyncio.Event()
    if clients is None:
        recs = [ClientRecord(stereo=i % STEREO_EVERY == STEREO_EVERY - 1) for i in range(count)]
        clients = [(cfg["size"], 0.0)] * count
    else:
        recs, count = [ClientRecord(stereo=False) for _ in clients], len(clients)
    async with aiohttp.ClientSession() as session:
        bases = bases or [base] * count
        tasks = [asyncio.create_task(run_client(session, srv.url, rec, i, count, size, bases[i], walk,
                                                cfg["camera_hz"], measuring, read_every))
                 for i, (rec, (size, read_every)) in enumerate(zip(recs, clients, strict=True))]
        try:
            warm = asyncio.ensure_future(asyncio.gather(*(r.warm.wait() for r in recs)))
            done, _ = await asyncio.wait([*tasks, warm], timeout=WARMUP_TIMEOUT_S,
                                         return_when=asyncio.FIRST_COMPLETED)
            if warm not in done:
                warm.cancel()
                for t in done:
                    t.result()  # a client failed: raise its error
                raise VolrenError(f"bench serve: {count} clients not all served within {WARMUP_TIMEOUT_S:.0f} s")

            async def next_tick() -> float:
                """Wait for the loop (any shard) to finish a tick (5 ms resolution); the time it did."""
                k = loop.report()["tick"]
                while loop.report()["tick"] == k:
                    await asyncio.sleep(0.005)
                    for t in tasks:
                        if t.done():
                            t.result()
                return time.perf_counter()

            # the window opens and closes as ticks end: a whole number of ticks, not a time cut mid-tick
            t0 = await next_tick()
            tick0, renders0, shards0 = loop.report()["tick"], loop.report()["renders"], shard_counts(loop)
            for r in recs:
                r.opened = time.perf_counter()
            measuring.set()
            t1 = t0
            while t1 - t0 < cfg["seconds"] or loop.report()["tick"] - tick0 < cfg["min_ticks"]:
                t1 = await next_tick()
            measuring.clear()
            elapsed, ticks = t1 - t0, loop.report()["tick"] - tick0
            shards1, placed = shard_counts(loop), [sorted(s.viewers.viewers) for s in getattr(loop, "shards", ())]
            renders = (sum(srv.calls[k] for k in range(tick0, tick0 + ticks)) if loop.local
                       else loop.report()["renders"] - renders0)
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
    row = summarize(recs, elapsed, ticks, renders)
    row["clients_detail"] = [{"size": list(size), "read_every_s": every, "frames": r.frames, "pixels": r.pixels,
                              "fps": r.frames / elapsed,
                              "age_median_ms": float(np.median(r.ages_ms)) if r.ages_ms else None,
                              "latency_p95_ms": float(np.percentile(r.latencies_ms, 95)) if r.latencies_ms else None,
                              "latency_max_ms": max(r.latencies_ms, default=None)}
                             for r, (size, every) in zip(recs, clients, strict=True)]
    if shards0:
        row["shards"] = [{"shard": i, "viewers": ids, "ticks": b[0] - a[0],
                          "tick_ms": 1e3 * elapsed / max(b[0] - a[0], 1),
                          "light_maps_per_tick": (b[1] - a[1]) / max(b[0] - a[0], 1),
                          "shadow_grids_per_tick": (b[2] - a[2]) / max(b[0] - a[0], 1)}
                         for i, (a, b, ids) in enumerate(zip(shards0, shards1, placed, strict=True))]
        shard_of = {vid: entry for entry in row["shards"] for vid in entry["viewers"]}
        row["latency_worst_p95_tick_times"] = max(
            (float(np.percentile(r.latencies_ms, 95)) / shard_of[r.viewer]["tick_ms"] for r in recs
             if r.latencies_ms and r.viewer in shard_of), default=math.inf)
    while len(loop.viewers) or srv.busy:  # the last tick still running: the next window waits for it
        await asyncio.sleep(0.01)
    return row


def summarize(recs: list[ClientRecord], elapsed: float, ticks: int, renders: int) -> dict[str, Any]:
    lat = [x for r in recs for x in r.latencies_ms]
    render_ms = {k: v for r in recs for k, v in r.render_ms.items()}
    fps = [r.frames / elapsed for r in recs]
    return {
        "clients": len(recs), "stereo_clients": sum(r.stereo for r in recs), "seconds": elapsed, "ticks": ticks,
        "renders": renders, "renders_per_tick": renders / max(ticks, 1), "tick_ms": 1e3 * elapsed / max(ticks, 1),
        "render_ms": statistics.median(render_ms.values()) if render_ms else None,
        "frames": sum(r.frames for r in recs), "fps_total": sum(fps), "fps_client_min": min(fps),
        "latency_median_ms": float(np.median(lat)) if lat else None,
        "latency_p95_ms": float(np.percentile(lat, 95)) if lat else None,
        "latency_worst_p95_ms": max((float(np.percentile(r.latencies_ms, 95)) for r in recs if r.latencies_ms),
                                    default=None),
        "latency_samples": len(lat), "bytes_per_s": sum(r.bytes for r in recs) / elapsed,
    }


def make_loop(method: str, scene_name: str, cfg: dict[str, Any], shared: bool, device: str,
              limits: Any = None) -> tuple[Any, Camera, bool]:
    """A playing render loop of a built-in scene at the interactive quality, its start camera and whether its
    clients walk (fog) rather than orbit."""
    from volren.bench import bench_scene
    from volren.data.fog_scenes import FOG_SCENES, fog_scene, fog_scene_camera
    from volren.serve.loop import RenderLoop, animator
    from volren.serve.viewers import Limits

    if scene_name in FOG_SCENES:
        scene = fog_scene(scene_name)
        spot = fog_scene_camera(scene_name)
        base = Camera(position=spot["position"], look_at=spot["look_at"])
    else:
        scene = bench_scene(scene_name, cfg["resolution"])
        base = Camera(position=(0.0, 0.4, 3.2))
    w, h = cfg["size"]
    # the shared/naive comparison renders the same pixels in both: the pixel budget only, no time shares
    limits = limits or Limits(max_viewers=max(cfg["counts"]), max_width=2 * w, max_height=h,
                              max_per_client=max(cfg["counts"]), tick_ms=None, connect_burst=1 << 20)
    loop = RenderLoop(scene, method, "interactive", limits=limits, camera=base, device=device, shared=shared,
                      animate=animator(scene, scene_name, device), overrides=cfg["overrides"])
    loop.playing = loop.animated
    return loop, base, scene.fog is not None


async def run_mixed(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    """Issue 20's mixed run on the first volume case: ``small`` clients at ``small_size``, one slow reader (a frame
    every ``read_every`` s) of that size, with and without one client at ``big_size``; the pixel budget is
    ``budget_factor`` x the pixels of the run without the big client (the operator's --pixel-budget). The best of
    ``repeats`` windows each. Goals: the small clients' p95 latency with the big client within GOAL_MIXED_P95 x of
    the run without it, and no frame older than GOAL_MIXED_AGE tick times when it arrives (the slow reader's
    included: with acknowledgements nothing waits in a socket buffer)."""
    from volren.serve.viewers import Limits

    mixed = cfg["mixed"]
    method, scene_name = next((m, s) for m, s in cfg["cases"] if m != "fog")
    small = [(tuple(mixed["small_size"]), 0.0)] * mixed["small"] + [(tuple(mixed["small_size"]), mixed["read_every"])]
    budget = int(mixed["budget_factor"] * sum(w * h for (w, h), _ in small))
    big_w, big_h = mixed["big_size"]
    limits = Limits(max_viewers=len(small) + 1, max_width=big_w, max_height=big_h, pixel_budget=budget,
                    max_per_client=len(small) + 1, tick_ms=None, connect_burst=1 << 20)
    loop, base, walk = make_loop(method, scene_name, cfg, True, device, limits)
    out: dict[str, dict[str, Any]] = {}
    async with served(loop) as srv:
        for name, clients in (("without big", small), ("with big", [*small, ((big_w, big_h), 0.0)])):
            windows = [await measure_window(srv, 0, cfg, base, walk, clients) for _ in range(cfg["repeats"])]
            out[name] = max(windows, key=lambda w: w["fps_total"])
    rows = []
    for name, row in out.items():
        fast = row["clients_detail"][:mixed["small"]]
        rows.append({"run": name, "tick_ms": row["tick_ms"], "clients": row["clients"],
                     "small_p95_ms": max(c["latency_p95_ms"] for c in fast),
                     "slow_reader_max_ms": row["clients_detail"][mixed["small"]]["latency_max_ms"],
                     "max_age_ms": max(c["latency_max_ms"] for c in row["clients_detail"]),
                     "big_frames": row["clients_detail"][-1]["frames"] if name == "with big" else 0,
                     "big_pixels": row["clients_detail"][-1]["pixels"] if name == "with big" else 0})
    without, with_big = rows
    ratio = with_big["small_p95_ms"] / without["small_p95_ms"]
    age = with_big["max_age_ms"] / with_big["tick_ms"]
    return {"scene": scene_name, "method": method, "pixel_budget": budget, "rows": rows, "p95_ratio": ratio,
            "p95_goal": GOAL_MIXED_P95, "age_tick_times": age, "age_goal": GOAL_MIXED_AGE,
            "goals": "pass" if ratio <= GOAL_MIXED_P95 and age <= GOAL_MIXED_AGE else "fail"}


def median_age(clients: list[dict[str, Any]]) -> float:
    """[ms] the median of ``clients``' (`measure_window`'s clients_detail) median frame ages; inf when none got a
    frame."""
    ages = [a for c in clients if (a := c["age_median_ms"]) is not None]
    return statistics.median(ages) if ages else math.inf


async def run_fair(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    """Issue 44's fair run on the first volume case, as the attack measured it: ``small`` clients at ``small_size``
    sending a camera at ``camera_hz`` and acknowledging every frame, alone, then beside one client at ``big_size``,
    on a server of the default limits (one full-HD pixel budget) sharing by time (`TimeShares`, the default
    --tick-ms) and on one sharing the pixel budget alone (--tick-ms 0, the schedule before). Per run the small
    clients' frames per second and median frame age (arrival minus the send time of the camera a frame shows), the
    big client's frames and largest frame. Goal: the small clients' median age beside the big one within
    GOAL_FAIR_AGE x of theirs alone, sharing by time."""
    from volren.serve.viewers import Limits

    fair = cfg["fair"]
    method, scene_name = next((m, s) for m, s in cfg["cases"] if m != "fog")
    small = [(tuple(fair["small_size"]), 0.0)] * fair["small"]
    run_cfg = {**cfg, "camera_hz": fair["camera_hz"], "seconds": fair["seconds"], "repeats": 1}
    rows = []
    for schedule, tick_ms in (("time", Limits.tick_ms), ("pixels", None)):
        limits = Limits(max_viewers=len(small) + 1, max_per_client=len(small) + 1, tick_ms=tick_ms,
                        connect_burst=1 << 20)
        loop, base, walk = make_loop(method, scene_name, cfg, True, device, limits)
        async with served(loop) as srv:
            for name, clients in (("alone", small), ("beside big", [*small, (tuple(fair["big_size"]), 0.0)])):
                if schedule == "pixels" and name == "alone":
                    continue  # the same schedule as sharing by time: a tick under the target shrinks nobody
                row = await measure_window(srv, 0, run_cfg, base, walk, clients)
                detail = row["clients_detail"]
                rows.append({"schedule": schedule, "run": name, "tick_ms": row["tick_ms"],
                             "small_fps": statistics.mean(c["fps"] for c in detail[:fair["small"]]),
                             "small_age_median_ms": median_age(detail[:fair["small"]]),
                             "big_frames": detail[-1]["frames"] if name != "alone" else 0,
                             "big_pixels": detail[-1]["pixels"] if name != "alone" else 0})
    alone = rows[0]["small_age_median_ms"]
    ratios = {f"{r['schedule']} {r['run']}": r["small_age_median_ms"] / alone for r in rows[1:]}
    return {"scene": scene_name, "method": method, "rows": rows, "age_ratio": ratios["time beside big"],
            "age_ratio_pixels": ratios["pixels beside big"], "age_goal": GOAL_FAIR_AGE,
            "goals": "pass" if ratios["time beside big"] <= GOAL_FAIR_AGE else "fail"}


NEIGHBOUR = "127.0.0.2"
"""the hostile neighbour's address: another client than the viewers (127.0.0.1)"""
ATTACKS = ("none", "spin", "settings", "malformed", "churn")
"""`run_neighbour`'s runs, in order (`attack`; none: the viewers alone)"""
TALLY = ("messages", "closed", "connections", "refused")
"""what a neighbour counts (`attack`)"""


async def attack(kind: str, url: str, tally: Any) -> None:
    """A neighbour's attack on the server at ``url`` until cancelled, from NEIGHBOUR, counting in ``tally`` (indexed
    as TALLY) what it sent and how the server answered: ``settings`` (a viewer changing quality and light as fast as
    its socket takes them, reconnecting when closed), ``malformed`` (the same with invalid JSON), ``churn`` (100
    clients connecting, saying hello, sending a camera and leaving, each over and over); ``spin`` only keeps its
    process busy (the CPU an attacker on this machine takes whatever the server does)."""
    import aiohttp

    def count(what: str) -> None:
        tally[TALLY.index(what)] += 1

    if kind == "spin":  # the neighbour's process busy on its own core, sending nothing: the machine's share
        while True:
            sum(range(100_000))
            await asyncio.sleep(0)

    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(local_addr=(NEIGHBOUR, 0), limit=0)) as session:
        async def viewer() -> Any:
            while True:
                try:
                    ws = await session.ws_connect(url, max_msg_size=0)
                except aiohttp.WSServerHandshakeError:
                    count("refused")
                    await asyncio.sleep(0.05)
                    continue
                count("connections")
                await ws.send_json({"type": "hello", "width": 64, "height": 48})
                return ws

        async def churner() -> None:
            while True:
                ws = await viewer()
                await ws.send_json({"type": "camera", "id": 1, "position": [0, 0.4, 3.2], "look_at": [0, 0, 0]})
                await ws.close()

        if kind == "churn":
            await asyncio.gather(*(churner() for _ in range(100)))
        while True:
            ws = await viewer()

            async def drain(ws: Any = ws) -> None:
                async for _ in ws:  # until the server closes it
                    pass

            reader = asyncio.create_task(drain())
            i = 0
            while not reader.done():
                i += 1
                if kind == "settings":
                    await ws.send_json({"type": "settings", "quality": ("default", "interactive")[i % 2],
                                        "light_dir": [0.3 * math.sin(i), -1.0, 0.2]})
                else:
                    await ws.send_str("{not json")
                count("messages")
                await asyncio.sleep(0)
            count("closed")
            await ws.close()


def attack_process(kind: str, url: str, tally: Any, ready: Any) -> None:
    """`attack` in a process of its own (a neighbour's CPU is not the server's, nor its GIL); ``ready`` is set once
    it is imported and starts."""
    import aiohttp  # noqa: F401  (imported before the start is announced)

    ready.set()
    asyncio.run(attack(kind, url, tally))


async def run_neighbour(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    """Issue 44 item 4's attacks on the first volume case at the default limits: ``viewers`` clients (a camera at
    ``camera_hz``, every frame acknowledged) alone, then beside a neighbour (`attack`, in its own process) flooding
    settings, sending malformed JSON, or churning 100 connections, or only spinning its process (on a 2-core machine
    the attacker's own core is half the machine: the attacks compare with ``spin``). Per run their frames per
    second and median frame age, and what the neighbour sent and how it was answered."""
    import multiprocessing

    from volren.serve.viewers import Limits

    nb = cfg["neighbour"]
    method, scene_name = next((m, s) for m, s in cfg["cases"] if m != "fog")
    clients = [(tuple(nb["size"]), 0.0)] * nb["viewers"]
    run_cfg = {**cfg, "camera_hz": nb["camera_hz"], "seconds": nb["seconds"], "repeats": 1}
    loop, base, walk = make_loop(method, scene_name, cfg, True, device, Limits())
    ctx = multiprocessing.get_context("spawn")
    rows = []
    async with served(loop) as srv:
        for kind in nb.get("attacks", ATTACKS):
            tally, ready = ctx.Array("q", len(TALLY)), ctx.Event()
            attacker = ctx.Process(target=attack_process, args=(kind, srv.url, tally, ready), daemon=True)
            if kind != "none":
                attacker.start()
                if not await asyncio.to_thread(ready.wait, WARMUP_TIMEOUT_S):
                    raise VolrenError(f"bench serve: the neighbour's process did not start within "
                                      f"{WARMUP_TIMEOUT_S:.0f} s")
            try:
                row = await measure_window(srv, 0, run_cfg, base, walk, clients)
            finally:
                if attacker.is_alive():
                    attacker.kill()
                    attacker.join()
            while len(loop.viewers):  # the neighbour's sockets closing
                await asyncio.sleep(0.01)
            detail = row["clients_detail"]
            rows.append({"attack": kind, "tick_ms": row["tick_ms"], "fps": statistics.mean(c["fps"] for c in detail),
                         "age_median_ms": median_age(detail),
                         "neighbour": dict(zip(TALLY, tally[:], strict=True))})
            await asyncio.sleep(1.0)  # the connection rate's bucket refills a little between attacks
    return {"scene": scene_name, "method": method, "rows": rows}


async def run_async(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    rows, summary = [], []
    for method, scene_name in cfg["cases"]:
        at: dict[tuple[str, int], dict[str, Any]] = {}
        for count in cfg["counts"]:
            (shared, base, walk), (naive, _, _) = (make_loop(method, scene_name, cfg, mode == "shared", device)
                                                   for mode in MODES)
            windows: dict[str, list[dict[str, Any]]] = {mode: [] for mode in MODES}
            async with served(shared) as srv_shared, served(naive) as srv_naive:
                for _ in range(cfg["repeats"]):  # alternate, so a burst of load elsewhere hits both servers alike
                    for mode, srv in zip(MODES, (srv_shared, srv_naive), strict=True):
                        windows[mode].append(await measure_window(srv, count, cfg, base, walk))
            for mode in MODES:
                best = max(windows[mode], key=lambda w: w["fps_total"])
                row = {"scene": scene_name, "method": method, "mode": mode, **best,
                       "fps_total_windows": [w["fps_total"] for w in windows[mode]]}
                at[mode, count] = row
                rows.append(row)
        goal_n = GOAL_CLIENTS if GOAL_CLIENTS in cfg["counts"] else cfg["counts"][-1]
        shared, naive = at["shared", goal_n], at["naive", goal_n]
        speedup = shared["fps_total"] / naive["fps_total"]
        latency_frames = (shared["latency_worst_p95_ms"] or math.inf) / shared["tick_ms"]
        summary.append({"scene": scene_name, "method": method, "clients": goal_n, "speedup": speedup,
                        "speedup_goal": GOAL_SPEEDUP, "latency_frames": latency_frames,
                        "latency_goal": GOAL_LATENCY_FRAMES,
                        "goals": "pass" if speedup >= GOAL_SPEEDUP and latency_frames <= GOAL_LATENCY_FRAMES
                        else "fail"})
    columns = [
        ("scene", "scene", "s"), ("method", "method", "s"), ("mode", "server", "s"), ("clients", "clients", "d"),
        ("stereo_clients", "stereo", "d"), ("tick_ms", "tick [ms]", ".1f"), ("render_ms", "render [ms]", ".1f"),
        ("renders_per_tick", "render calls/tick", ".2f"), ("fps_total", "fps total", ".1f"),
        ("fps_client_min", "fps slowest client", ".2f"), ("latency_median_ms", "latency median [ms]", ".0f"),
        ("latency_p95_ms", "latency p95 [ms]", ".0f"), ("latency_worst_p95_ms", "worst client p95 [ms]", ".0f"),
        ("bytes_per_s", "bytes/s", ".3g"),
    ]
    summary_columns = [
        ("scene", "scene", "s"), ("method", "method", "s"), ("clients", "clients", "d"),
        ("speedup", "shared/naive fps", ".2f"), ("speedup_goal", "goal >=", ".1f"),
        ("latency_frames", "worst p95 latency [tick times]", ".2f"), ("latency_goal", "goal <=", ".0f"),
        ("p95_ratio", f"mixed: small p95 with/without big (goal <= {GOAL_MIXED_P95:g})", ".2f"),
        ("age_tick_times", f"mixed: oldest frame [tick times] (goal <= {GOAL_MIXED_AGE:g})", ".2f"),
        ("age_ratio", f"fair: small age beside/without big (goal <= {GOAL_FAIR_AGE:g})", ".2f"),
        ("age_ratio_pixels", "fair: same, pixel budget only", ".2f"),
        ("fps", "neighbour: viewers' fps", ".1f"), ("age_ms", "neighbour: median age [ms]", ".0f"),
        ("goals", "goals", "s"),
    ]
    if cfg.get("mixed"):
        mixed = await run_mixed(cfg, device)
        summary.append({"scene": f"{mixed['scene']} (mixed)", "method": mixed["method"],
                        "clients": mixed["rows"][1]["clients"], "p95_ratio": mixed["p95_ratio"],
                        "age_tick_times": mixed["age_tick_times"], "goals": mixed["goals"], "mixed": mixed})
    if cfg.get("neighbour"):
        neighbour = await run_neighbour(cfg, device)
        for r in neighbour["rows"]:
            summary.append({"scene": f"{neighbour['scene']} (neighbour: {r['attack']})", "method": neighbour["method"],
                            "clients": cfg["neighbour"]["viewers"], "fps": r["fps"], "age_ms": r["age_median_ms"],
                            "goals": "-", "neighbour": r})
    if cfg.get("fair"):
        fair = await run_fair(cfg, device)
        summary.append({"scene": f"{fair['scene']} (fair)", "method": fair["method"],
                        "clients": cfg["fair"]["small"] + 1, "age_ratio": fair["age_ratio"],
                        "age_ratio_pixels": fair["age_ratio_pixels"], "goals": fair["goals"], "fair": fair})
    settings = {k: v for k, v in cfg.items() if k != "overrides"} | {
        "quality": "interactive", "stereo_every": STEREO_EVERY, "orbit_rad_s": ORBIT_RAD_S,
        "timing": "CPU, 2 cores, shared with other jobs" if device == "cpu" else device}
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    return asyncio.run(run_async(cfg, device))


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(QUICK if quick else FULL, device)


SUITE = Suite("serve", "volren serve: 1-16 clients, shared render loop vs one renderer per viewer (issue 15)", run)


# ---- serve --shards (issue 23) ----------------------------------------------------------------------------------

SHARDS_FULL = {"method": "cacrm", "resolution": 256, "size": (480, 270), "clients": 16, "seconds": 10.0,
               "min_ticks": 10, "repeats": 3, "camera_hz": 60.0, "overrides": {}, "apart": 3.0}
SHARDS_QUICK = {"method": "cacrm", "resolution": 64, "size": (160, 90), "clients": 16, "seconds": 3.0,
                "min_ticks": 4, "repeats": 2, "camera_hz": 30.0, "overrides": {}, "apart": 3.0}
GOAL_SHARD_FPS = 0.85
"""2 shards on this 2-core machine add no compute: their total frames per second at least 0.85x one shard's"""


def two_rig_scene(resolution: int, apart: float) -> tuple[Scene, list[Camera]]:
    """The smoke twice, at x = -``apart`` and +``apart`` [m] (two rigs far apart: their footprints do not overlap),
    and each rig's base camera (the CLI's default view, moved to its smoke)."""
    from volren.bench import bench_scene

    scene = bench_scene("smoke", resolution)
    vol = scene.volumes[0]
    moved = []
    for x in (-apart, apart):
        shift = np.eye(4)
        shift[0, 3] = x
        moved.append(dataclasses.replace(vol, to_world=shift @ np.asarray(vol.to_world), name=f"smoke{x:+g}"))
    bases = [Camera(position=(x, 0.4, 3.2), look_at=(x, 0.0, 0.0)) for x in (-apart, apart)]
    return dataclasses.replace(scene, volumes=tuple(moved)), bases


async def run_shards_async(cfg: dict[str, Any], device: str, counts: list[int]) -> dict[str, Any]:
    """``clients`` clients (every fourth stereo), client i on rig i % 2, against the loop in process and against
    ``counts`` shards on a local Ray (started once, its start-up timed apart); the best of ``repeats`` windows each.
    Goals: the most shards' total fps >= GOAL_SHARD_FPS x one shard's; no client's p95 latency above
    GOAL_LATENCY_FRAMES tick times of its shard; the shared passes per shard and tick reported."""
    import os
    from functools import partial

    from volren.distributed.runtime import connect
    from volren.serve.loop import RenderLoop, animator
    from volren.serve.shards import ShardedLoop
    from volren.serve.viewers import Limits

    scene, rigs = two_rig_scene(cfg["resolution"], cfg["apart"])
    n = cfg["clients"]
    bases = [rigs[i % 2] for i in range(n)]
    w, h = cfg["size"]
    limits = Limits(max_viewers=n, max_width=2 * w, max_height=h)
    start = time.perf_counter()
    ray = connect("--shards", None, num_cpus=max(os.cpu_count() or 1, *counts))
    ray_start_s = time.perf_counter() - start
    rows = []
    try:
        for shards in [0, *counts]:  # 0: the render loop in process, for reference
            start = time.perf_counter()
            if shards:
                loop: Any = ShardedLoop(scene, cfg["method"], "interactive", shards=shards,
                                        animate=partial(animator, scene, "smoke", device), limits=limits,
                                        camera=rigs[0], device=device, overrides=cfg["overrides"])
            else:
                loop = RenderLoop(scene, cfg["method"], "interactive", limits=limits, camera=rigs[0], device=device,
                                  animate=animator(scene, "smoke", device), overrides=cfg["overrides"])
            loop.playing = loop.animated
            up_s = time.perf_counter() - start
            async with served(loop) as srv:
                windows = [await measure_window(srv, n, cfg, rigs[0], False, bases=bases)
                           for _ in range(cfg["repeats"])]
            best = max(windows, key=lambda row: row["fps_total"])
            per = best.get("shards", [])
            rows.append({**best, "server": f"{shards} shard(s)" if shards else "in process", "shard_count": shards,
                         "up_s": up_s, "fps_total_windows": [row["fps_total"] for row in windows],
                         "shard_tick_ms": " / ".join(f"{s['tick_ms']:.1f}" for s in per) or f"{best['tick_ms']:.1f}",
                         "shard_viewers": " / ".join(str(len(s["viewers"])) for s in per),
                         "light_maps_per_tick": " / ".join(f"{s['light_maps_per_tick']:.2f}" for s in per)})
            case_line(rows[-1])
    finally:
        ray.shutdown()
    one = next(r for r in rows if r["shard_count"] == 1) if 1 in counts else rows[1]
    most = rows[-1]
    ratio = most["fps_total"] / one["fps_total"]
    latency = max(r["latency_worst_p95_tick_times"] for r in rows if r["shard_count"])
    summary = [{"shards": most["shard_count"], "fps_ratio": ratio, "fps_goal": GOAL_SHARD_FPS,
                "latency_tick_times": latency, "latency_goal": GOAL_LATENCY_FRAMES, "ray_start_s": ray_start_s,
                "goals": "pass" if ratio >= GOAL_SHARD_FPS and latency <= GOAL_LATENCY_FRAMES else "fail"}]
    columns = [
        ("server", "server", "s"), ("clients", "clients", "d"), ("stereo_clients", "stereo", "d"),
        ("shard_viewers", "viewers per shard", "s"), ("shard_tick_ms", "tick [ms] per shard", "s"),
        ("light_maps_per_tick", "light maps/tick per shard", "s"),
        ("renders_per_tick", "render calls/tick", ".2f"), ("fps_total", "fps total", ".1f"),
        ("fps_client_min", "fps slowest client", ".2f"), ("latency_median_ms", "latency median [ms]", ".0f"),
        ("latency_worst_p95_ms", "worst client p95 [ms]", ".0f"),
        ("latency_worst_p95_tick_times", "worst p95 [own shard's tick times]", ".2f"), ("up_s", "start [s]", ".1f"),
    ]
    summary_columns = [
        ("shards", "shards", "d"), ("fps_ratio", f"fps total vs 1 shard (goal >= {GOAL_SHARD_FPS:g})", ".2f"),
        ("latency_tick_times", f"worst p95 latency [tick times] (goal <= {GOAL_LATENCY_FRAMES:g})", ".2f"),
        ("ray_start_s", "local Ray start-up [s]", ".1f"), ("goals", "goals", "s"),
    ]
    settings = {k: v for k, v in cfg.items() if k != "overrides"} | {
        "shard_counts": counts, "quality": "interactive", "stereo_every": STEREO_EVERY, "rigs": 2,
        "timing": "CPU, 2 cores, shared with other jobs" if device == "cpu" else device}
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}


def case_line(row: dict[str, Any]) -> None:
    from volren.progress import case_done

    case_done(f"{row['server']}: {row['fps_total']:.1f} fps total, tick per shard {row['shard_tick_ms']} ms")


def shard_suite(counts: list[int]) -> Suite:
    """``bench serve --shards COUNTS``: the sharded server against one shard and the loop in process."""
    if not counts or min(counts) < 1:
        raise VolrenError(f"--shards must list shard counts >= 1, got {counts}")
    return Suite("serve-shards", "volren serve --shards: 16 clients on two rigs far apart, in process and on 1-N "
                 "Ray shards (issue 23)",
                 lambda quick, device: asyncio.run(run_shards_async(SHARDS_QUICK if quick else SHARDS_FULL, device,
                                                                   sorted(set(counts)))))
