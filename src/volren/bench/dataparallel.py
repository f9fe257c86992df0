"""Suite ``dataparallel``: sort-last data-parallel rendering (issue 43) on this machine, and a model of compositing on
a cluster built from what it measures.

1. **Compositing** (numpy, no Ray): per image size and region count N, the time per frame of
   `volren.dataparallel.composite_over`, ``composite_max`` and ``composite_nearest`` on N synthetic partial images
   (RGBA float32, premultiplied; depth float32 for ``nearest``), the bytes of one partial image, and the measured
   throughput of ``over`` in pixel-composites per second (one pixel of one partial composited onto the running
   result: N - 1 per pixel per frame).
2. **Regions in process** (`volren.dataparallel.render.RegionSet`): a noisy smoke ball built here, DSSRM dvr with a
   slanted directional light (its light map recomputed every frame), N = 1, 2, 4 regions rendered one after another
   in this process: per region its march time (median over the timed frames; the light-map passes are in the wall
   time) and the bytes it holds, the light-map exchange bytes, the compositing time, the wall time and the PSNR of
   the N-region image against N = 1's (goal: >= 50 dB).
3. **Regions on Ray** (`volren.distributed.regions.RegionEngine`): the same kind of volume written to a ``.npy``
   file, N region actors on a local Ray, compositing ``direct-send`` and ``gather``: seconds per frame of a still view
   after a warm-up frame (the summed light map exchanged in the warm-up frame and kept), the bytes the driver received
   per frame, the light exchange bytes, and each actor's resident bytes against the whole volume's and a nominal
   actor budget the volume is several times (each actor holds about 1/N of the bricks). Skipped (a row saying why)
   where the engine is not in this build.
4. **A model** (`composite_model`, not a measurement): per-frame compositing time on 8-64 nodes from the measured
   single-node ``over`` throughput and a network's bandwidth and latency, for direct-send, binary-swap and radix-k
   (dense partials, and radix-k with sparse ones), set
   against two published anchors (radix-k, Kendall et al. EGPGV 2010; OSPRay's distributed frame buffer, Usher et
   al. EuroVis 2019).

Quick (CPU): compositing at 256x144 to 1920x1080 with N = 1, 2, 4, 8; a 128^3 ball at 256x144; Ray with a 192^3
file. Full: a 256^3 ball in process, a 384^3 file on Ray, more timed frames.
"""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from volren.bench import Suite, sized
from volren.progress import case_done

QUICK: dict[str, Any] = {
    "sizes": [[256, 144], [640, 360], [1280, 720], [1920, 1080]], "counts": [1, 2, 4, 8], "composite_repeats": 3,
    "resolution": 128, "view": [256, 144], "regions": [1, 2, 4], "repeats": 3, "light_grid": 64,
    "ray_resolution": 192, "ray_regions": [1, 2, 4], "ray_repeats": 3, "actor_budget_mib": 9,
    "ray_compositing": ["direct-send", "gather"],
    "ray": True, "nodes": [8, 16, 32, 64], "seed": 0,
}
FULL: dict[str, Any] = {
    **QUICK, "composite_repeats": 5, "resolution": 256, "view": [640, 360], "regions": [1, 2, 4, 8], "repeats": 5,
    "light_grid": 128, "ray_resolution": 384, "ray_regions": [1, 2, 4, 8], "ray_repeats": 5,
    "actor_budget_mib": 64,
}
GOAL_PSNR = 50.0
LIGHT_DIR = (-0.6, -1.0, -0.35)
"""slanted: the light crosses region boundaries (the summed light maps are what is exchanged)"""
CAMERA = (0.35, 0.4, 3.2)

NETWORKS: dict[str, tuple[float, float]] = {
    "10 GB/s, 10 us": (10e9, 10e-6),
    "100 Gb/s InfiniBand (12.5 GB/s, 1 us)": (12.5e9, 1e-6),
}
"""the model's networks: name -> (bandwidth [bytes/s] per node link, latency [s] per message)"""

ANCHORS = [
    # (name, pixels, nodes, published seconds per frame, what the published time covers)
    ("radix-k, 64 Mpixel on 32K processes (Kendall et al., EGPGV 2010)", 8192 * 8192, 32768, 0.08,
     "compositing only (BG/P; sparse partials, active pixels only)"),
    ("OSPRay distributed frame buffer, 4096x1024 on 64 nodes, 5 fps (Usher et al., EuroVis 2019)", 4096 * 1024, 64,
     0.2, "whole frame: rendering + compositing + final image"),
]
PARTIAL_BYTES_PER_PIXEL = 16
"""RGBA float32, what `composite_over` takes (depth, 4 more, only for iso)"""
FINAL_BYTES_PER_PIXEL = 4
"""the finished image gathered to the display node as RGBA8"""


# --- 1. compositing ---------------------------------------------------------------------------------------------

def synthetic_partials(n: int, width: int, height: int, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``n`` premultiplied RGBA float32 partial images (colour <= alpha, alpha in [0, 1)) and float32 depth images
    (+inf on a quarter of the pixels: no hit), random: what ``n`` regions' renders hand the compositor."""
    rng = np.random.default_rng(seed)
    images, depths = [], []
    for _ in range(n):
        alpha = rng.random((height, width, 1), dtype=np.float32) * 0.9
        rgb = rng.random((height, width, 3), dtype=np.float32) * alpha
        images.append(np.concatenate([rgb, alpha], axis=-1))
        depth = rng.random((height, width), dtype=np.float32) * 4.0
        depth[rng.random((height, width)) < 0.25] = np.inf
        depths.append(depth)
    return images, depths


def time_operator(fn: Any, args: tuple[Any, ...], repeats: int) -> tuple[float, Any]:
    """(the fastest of ``repeats`` calls ``fn(*args)`` [ms], the last call's result)."""
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn(*args)
        times.append((time.perf_counter() - start) * 1e3)
    return min(times), out


def compositing_rows(sizes: list[list[int]], counts: list[int], repeats: int, seed: int = 0) -> list[dict[str, Any]]:
    """Part 1: per (size, N) the fastest of ``repeats`` frames of each compositing operator [ms], the bytes of one
    partial image, and ``over``'s throughput [pixel-composites/s] (N - 1 per pixel; None for N = 1)."""
    from volren.dataparallel.composite import composite_max, composite_nearest, composite_over

    rows = []
    for width, height in sizes:
        for n in counts:
            images, depths = synthetic_partials(n, width, height, seed)
            order = list(range(n))[::-1]  # any permutation: the work is the same
            over_ms = time_operator(composite_over, (images, order), repeats)[0]
            max_ms = time_operator(composite_max, (images,), repeats)[0]
            nearest_ms = time_operator(composite_nearest, (images, depths, order), repeats)[0]
            pixels = width * height
            rows.append({"size": f"{width}x{height}", "pixels": pixels, "n": n,
                         "partial_bytes": images[0].nbytes, "depth_bytes": depths[0].nbytes,
                         "over_ms": over_ms, "max_ms": max_ms, "nearest_ms": nearest_ms,
                         "over_mpix_per_s": (n - 1) * pixels / over_ms / 1e3 if n > 1 and over_ms > 0 else None})
            case_done(f"compositing {width}x{height}, N = {n}")
    return rows


def over_throughput(rows: list[dict[str, Any]]) -> float:
    """[pixel-composites/s] of ``over`` at the largest image measured with N > 1: the median over its counts (the
    model's compositing rate; the largest image is the one least dominated by per-call overheads)."""
    largest = max(r["pixels"] for r in rows if r["n"] > 1)
    rates = [r["over_mpix_per_s"] for r in rows if r["pixels"] == largest and r["n"] > 1]
    return statistics.median(rates) * 1e6


# --- 4. the model -----------------------------------------------------------------------------------------------

def radix_factors(nodes: int, scheme: str, k: int = 8) -> list[int]:
    """The group size of each round: direct-send one round of all ``nodes``; binary-swap log2 N rounds of 2 (N a
    power of two); radix-k rounds of the largest divisor <= ``k`` of what is left (Peterka et al. 2009)."""
    if scheme == "direct-send":
        return [nodes] if nodes > 1 else []
    if scheme == "binary-swap":
        rounds = math.log2(nodes)
        if rounds != int(rounds):
            raise ValueError(f"binary-swap needs a power of two nodes, got {nodes}")
        return [2] * int(rounds)
    if scheme == "radix-k":
        factors, left = [], nodes
        while left > 1:
            divisors = [d for d in range(2, min(k, left) + 1) if left % d == 0]
            f = max(divisors) if divisors else left  # a prime above k: one round of it
            factors.append(f)
            left //= f
        return factors
    raise ValueError(f"unknown compositing scheme {scheme!r}: direct-send, binary-swap or radix-k")


def composite_model(pixels: int, nodes: int, rate: float, bandwidth: float, latency: float, *,
                    scheme: str = "direct-send", k: int = 8, sparse: float | None = None,
                    bytes_per_pixel: int = PARTIAL_BYTES_PER_PIXEL,
                    final_bytes_per_pixel: int = FINAL_BYTES_PER_PIXEL) -> dict[str, float]:
    """A model, not a measurement: the per-frame time of sort-last compositing of ``pixels`` = P on ``nodes`` = N
    nodes from the single-node compositing rate ``rate`` = R [pixel-composites/s: one partial pixel composited onto
    the running one] measured here, a link ``bandwidth`` = B [bytes/s] per node and a per-message ``latency`` = a [s],
    b = ``bytes_per_pixel``. Sending, receiving and compositing are not overlapped; every node's link runs at full
    bandwidth at once (a non-blocking network); the nodes are alike, so one node's time is the frame's.

    A scheme is rounds of groups (`radix_factors`): in a round of group size k_i each node cuts the piece of the image
    it holds (P / (k_1 ... k_{i-1}) pixels) into k_i parts, keeps one, sends the k_i - 1 others to its group and
    receives the group's k_i - 1 copies of the part it keeps, then composites them: k_i - 1 messages, (k_i - 1) / k_i
    of its piece received and composited. Dense partials (``sparse`` None: every node's partial covers the whole
    image, the worst case) telescope to

    - **direct-send** (one round, k = N: each node owns 1/N of the image and receives that tile, P/N pixels, from each
      of the N - 1 others): ``T = (N - 1) a + (N - 1)/N P b / B + (N - 1)/N P / R``
    - **binary-swap** (log2 N rounds of 2, halves exchanged): ``T = log2(N) a + (1 - 1/N) P b / B + (1 - 1/N) P / R``
    - **radix-k**: ``T = sum_i (k_i - 1) a + (1 - 1/N) P b / B + (1 - 1/N) P / R``

    so every scheme receives the same bytes per node, (1 - 1/N) P b, tending to one whole partial image (bandwidth
    does not fall with N), and they differ in messages: direct-send's N - 1 make its time grow with N. ``sparse`` = e:
    a partial that merges m of the N regions covers min(1, (m / N)^e) of its piece (e = 2/3: N equal cubes of a
    volume that fills the image each cover N^(-2/3) of it); only covered pixels are sent and composited, round by
    round (m = k_1 ... k_{i-1} before round i). ``gather_s``: the finished image (``final_bytes_per_pixel``) sent from
    the N owners of 1/N of it to one display node, (N - 1) a + (N - 1)/N P f / B, not in ``composite_s``. Returned:
    ``composite_s`` and its parts ``latency_s``, ``transfer_s``, ``compute_s``; ``bytes_per_node`` received,
    ``messages_per_node``, ``message_bytes`` (the first round's message), ``rounds``, ``gather_s``."""
    if nodes < 1 or pixels < 1 or rate <= 0 or bandwidth <= 0 or latency < 0:
        raise ValueError("composite_model needs nodes >= 1, pixels >= 1, rate > 0, bandwidth > 0, latency >= 0")
    factors = radix_factors(nodes, scheme, k)
    piece, merged, messages, received, composites, first_message = float(pixels), 1, 0, 0.0, 0.0, 0.0
    for f in factors:
        cover = 1.0 if sparse is None else min(1.0, (merged / nodes) ** sparse)
        part = piece / f
        messages += f - 1
        composites += (f - 1) * part * cover
        received += (f - 1) * part * cover * bytes_per_pixel
        first_message = first_message or part * cover * bytes_per_pixel
        piece, merged = part, merged * f
    latency_s, transfer_s, compute_s = messages * latency, received / bandwidth, composites / rate
    share = (nodes - 1) / nodes
    gather_s = (nodes - 1) * latency + share * pixels * final_bytes_per_pixel / bandwidth
    return {"composite_s": latency_s + transfer_s + compute_s, "latency_s": latency_s, "transfer_s": transfer_s,
            "compute_s": compute_s, "bytes_per_node": received, "messages_per_node": float(messages),
            "message_bytes": first_message, "rounds": float(len(factors)), "gather_s": gather_s}


def model_rows(rate: float, nodes: list[int], images: list[tuple[str, int]],
               networks: dict[str, tuple[float, float]] = NETWORKS) -> list[dict[str, Any]]:
    """Part 4's table: per image, network and node count the modelled direct-send and binary-swap times [ms]."""
    rows = []
    for image, pixels in images:
        for network, (bandwidth, latency) in networks.items():
            for n in nodes:
                ds = composite_model(pixels, n, rate, bandwidth, latency, scheme="direct-send")
                bs = composite_model(pixels, n, rate, bandwidth, latency, scheme="binary-swap")
                rk = composite_model(pixels, n, rate, bandwidth, latency, scheme="radix-k")
                sp = composite_model(pixels, n, rate, bandwidth, latency, scheme="radix-k", sparse=2 / 3)
                rows.append({"image": image, "network": network, "nodes": n,
                             "bytes_per_node_mb": ds["bytes_per_node"] / 1e6,
                             "tile_kb": ds["message_bytes"] / 1e3, "ds_ms": 1e3 * ds["composite_s"],
                             "ds_latency_ms": 1e3 * ds["latency_s"], "bs_ms": 1e3 * bs["composite_s"],
                             "rk_ms": 1e3 * rk["composite_s"], "rk_sparse_ms": 1e3 * sp["composite_s"],
                             "compute_ms": 1e3 * ds["compute_s"], "transfer_ms": 1e3 * ds["transfer_s"],
                             "gather_ms": 1e3 * ds["gather_s"]})
    return rows


def anchor_rows(rate: float, networks: dict[str, tuple[float, float]] = NETWORKS) -> list[dict[str, Any]]:
    """The published anchors against the model on the first network (the default), dense partials."""
    network, (bandwidth, latency) = next(iter(networks.items()))
    rows = []
    for name, pixels, n, published, covers in ANCHORS:
        ds = composite_model(pixels, n, rate, bandwidth, latency, scheme="direct-send")
        bs = composite_model(pixels, n, rate, bandwidth, latency, scheme="binary-swap")
        rk = composite_model(pixels, n, rate, bandwidth, latency, scheme="radix-k")
        sp = composite_model(pixels, n, rate, bandwidth, latency, scheme="radix-k", sparse=2 / 3)
        rows.append({"anchor": name, "covers": covers, "network": network, "published_ms": 1e3 * published,
                     "ds_ms": 1e3 * ds["composite_s"], "bs_ms": 1e3 * bs["composite_s"],
                     "rk_ms": 1e3 * rk["composite_s"], "rk_sparse_ms": 1e3 * sp["composite_s"],
                     "best_over_published": min(ds["composite_s"], bs["composite_s"], rk["composite_s"],
                                                sp["composite_s"]) / published})
    return rows


def model_notes(rate: float) -> str:
    return "\n".join([
        "#### Compositing on a cluster: a model, not a measurement",
        "",
        "The tables above are measured on this machine; the two below are computed "
        "(`volren.bench.dataparallel.composite_model`) from this machine's single-thread numpy `over` rate, "
        f"R = {rate / 1e6:.0f} M pixel-composites/s (the 1920x1080 rows' median), and a network's bandwidth B per "
        "node and latency a per message, for P pixels of b = "
        f"{PARTIAL_BYTES_PER_PIXEL} bytes (RGBA float32) on N nodes, sending and compositing not overlapped, "
        "every partial covering the whole image (dense: the worst case) unless marked sparse:",
        "",
        "- direct-send: T = (N-1) a + (N-1)/N P b / B + (N-1)/N P / R (each node owns 1/N of the image and receives "
        "that tile from each of the N-1 others)",
        "- binary-swap: T = log2(N) a + (1-1/N) P b / B + (1-1/N) P / R (log2 N rounds, halves exchanged)",
        "- radix-k (k = 8): T = sum_i (k_i - 1) a + (1-1/N) P b / B + (1-1/N) P / R (rounds of groups of k_i <= 8)",
        "- sparse: a partial merging m of the N regions covers (m/N)^(2/3) of its piece (N cubes of a volume that "
        "fills the image); only covered pixels are sent and composited",
        "",
        "Dense, every scheme receives the same bytes per node, tending to one whole partial image however many "
        "nodes; direct-send's N-1 messages are what grows with N. The final image's gather to one node (RGBA8) is "
        "a column of its own, not in T. The anchors ran on other machines than the model assumes (radix-k on BG/P "
        "ranks, their own compositing code; OSPRay's 200 ms covers rendering too): a model time above an anchor's "
        "says this machine's single-thread numpy rate and these assumptions would not reach it, not that the "
        "published figure is wrong; one far below it says what the model leaves out (slower cores, link "
        "contention and topology, load imbalance, the sparse partials' bookkeeping), not that it would be beaten.",
    ])


# --- 2. regions in process --------------------------------------------------------------------------------------

def smoke_ball(resolution: int, seed: int = 0) -> np.ndarray:
    """float32 [z, y, x]: a ball of radius 0.8 (local units) with a soft edge, its density noisy (uniform noise in
    [0.5, 1.5) times a falloff to the edge): active bricks near the centre, empty corners."""
    rng = np.random.default_rng(seed)
    axis = np.linspace(-1.0, 1.0, resolution, dtype=np.float32)
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij", sparse=True)
    r = np.sqrt(x * x + y * y + z * z)
    falloff = np.clip(1.0 - r / 0.8, 0.0, 1.0)
    return (falloff * (0.5 + rng.random((resolution,) * 3, dtype=np.float32))).astype(np.float32)


def region_rows(cfg: dict[str, Any], device: str) -> list[dict[str, Any]]:
    """Part 2: `RegionSet` with each region count on the ball, one warm-up frame then ``repeats`` timed frames."""
    from volren.camera import Camera
    from volren.dataparallel.render import RegionSet
    from volren.metrics import psnr
    from volren.render import DSSRM, DSSRMConfig
    from volren.scene import DirectionalLight, Scene, Volume

    if not cfg["regions"]:
        return []
    density = smoke_ball(cfg["resolution"], cfg["seed"])
    scene = Scene((Volume(density, name="smoke ball"),), lights=(DirectionalLight(LIGHT_DIR),), name="smoke ball")
    width, height = cfg["view"]
    views = [Camera(position=CAMERA, width=width, height=height)]
    config = DSSRMConfig(light_grid=cfg["light_grid"], reuse_light_map=False)
    rows, reference = [], None
    for n in cfg["regions"]:
        regions = RegionSet(scene, n, lambda: DSSRM(config, device))
        regions.render(views, 0)  # warm-up: kernels loaded, uploads
        frames, walls = [], []
        for i in range(cfg["repeats"]):
            start = time.perf_counter()
            frames.append(regions.render(views, i + 1))
            walls.append((time.perf_counter() - start) * 1e3)
        per_region = [[sum(v for k, v in report["times_ms"].items() if k != "readback")
                       for report in f.stats.info["region_stats"]] for f in frames]
        region_ms = [statistics.median(f[r] for f in per_region) for r in range(n)]
        reports = frames[-1].stats.info["region_stats"]
        image = frames[-1].images[0]
        if reference is None:
            reference = image
        quality = None if n == 1 else psnr(reference, image)
        rows.append({
            "n": n, "wall_ms": statistics.median(walls), "region_ms_max": max(region_ms),
            "region_ms_sum": sum(region_ms), "region_ms": [round(t, 2) for t in region_ms],
            "composite_ms": statistics.median(f.stats.times_ms["composite"] for f in frames),
            "light_exchange_bytes": frames[-1].stats.info["light_exchange_bytes"],
            "region_bytes_max": max(r["bytes"] for r in reports), "region_bytes": [r["bytes"] for r in reports],
            "volume_bytes": density.nbytes, "bricks": [r["resident_bricks"] for r in reports],
            "psnr_db": quality, "psnr_goal": None if quality is None else (
                "pass" if quality >= GOAL_PSNR else "fail")})
        case_done(f"regions in process, N = {n}")
    return rows


REGIONS_NOTE = (
    "Regions in process (`RegionSet`, one after another in this process): DSSRM dvr of the noisy smoke ball, light "
    "map recomputed every frame; a region's time is its march passes (its light-map pass is in the wall time only), "
    "the light exchange the bytes of the N regions' maps summed each frame, the PSNR the composited image's against "
    "N = 1's.")
RAY_NOTE = (
    "Regions on a local Ray (`RegionEngine`, one actor per region, sharing this machine's cores): frames of one still "
    "view after a warm-up frame, so the summed light map is exchanged in the warm-up frame only (an unchanged map is "
    "not sent again) and the frame times hold no light-map pass, unlike the in-process rows. Driver bytes: what the "
    "driver received per frame (direct-send: the composited strips, one image's RGBA and depth; gather: every "
    "partial). Resident: the bytes of bricks an actor holds against the whole volume's; the budget is a nominal "
    "actor budget the volume is several times.")


# --- 3. regions on Ray ------------------------------------------------------------------------------------------

def ray_spec(path: Path, cfg: dict[str, Any], device: str) -> Any:
    """The `RenderSpec` the region actors run: ``volren render`` of the ``.npy`` ball, DSSRM dvr, one view (mono, as
    part 2), the slanted light."""
    from volren.plan.spec import RenderSpec

    width, height = cfg["view"]
    return RenderSpec.parse([
        "render", "--volume", str(path), "--method", "dssrm", "--views", "mono",
        "--width", str(width), "--height", str(height),
        "--light-dir", ",".join(str(v) for v in LIGHT_DIR), "--light-grid", str(cfg["light_grid"]),
        "--device", device, "--out", str(path.with_suffix(".png"))])


def ray_rows(cfg: dict[str, Any], device: str) -> list[dict[str, Any]]:
    """Part 3: `volren.distributed.regions.RegionEngine` with each compositing and region count on a ``.npy`` ball
    (``ray_resolution``^3 float32, several times ``actor_budget_mib``), one warm-up frame (actors started, regions
    loaded, kernels loaded, the light maps exchanged) then ``ray_repeats`` timed frames of the same view (the summed
    light map kept: no exchange after the warm-up unless a map changes). The local Ray's start-up is its own row."""
    from volren.distributed.regions import PlannedScene, RegionEngine
    from volren.distributed.runtime import connect, import_ray
    from volren.plan import plan_render

    budget = cfg["actor_budget_mib"] * 2**20
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="volren-bench-dataparallel-") as tmp:
        path = Path(tmp) / "smoke-ball.npy"
        density = smoke_ball(cfg["ray_resolution"], cfg["seed"])
        np.save(path, density)
        volume_bytes = density.nbytes
        del density
        spec = ray_spec(path, cfg, device)
        args = spec.namespace(max_minutes=0)
        plan = plan_render(args, args.method)  # the driver's plan: the scene the regions split, the views
        was_up = import_ray("bench dataparallel", local=True).is_initialized()
        started = time.perf_counter()
        ray = connect("bench dataparallel", num_cpus=max(cfg["ray_regions"]))
        rows.append({"compositing": "local Ray start-up", "seconds": time.perf_counter() - started,
                     "volume_bytes": volume_bytes, "note": f"actor budget {cfg['actor_budget_mib']} MiB: the volume "
                     f"is {volume_bytes / budget:.1f}x it"})
        case_done("local Ray started")
        try:
            for compositing in cfg["ray_compositing"]:
                for n in cfg["ray_regions"]:
                    started = time.perf_counter()
                    with RegionEngine(PlannedScene(spec), plan.scene, n, plan.renderer, compositing=compositing,
                                      flag="bench dataparallel") as engine:
                        first = engine.render(plan.views, 0)
                        setup = time.perf_counter() - started
                        seconds, frames = [], []
                        for i in range(cfg["ray_repeats"]):
                            start = time.perf_counter()
                            frames.append(engine.render(plan.views, i + 1))
                            seconds.append(time.perf_counter() - start)
                    info = frames[-1].stats.info
                    resident = [r["bytes"] for r in info["region_stats"]]
                    rows.append({
                        "compositing": compositing, "n": n, "setup_s": setup,
                        "frame_s": statistics.median(seconds), "frame_min_s": min(seconds),
                        "driver_bytes": statistics.median(f.stats.info["driver_bytes"] for f in frames),
                        "driver_bytes_first": first.stats.info["driver_bytes"],
                        "light_exchange_first": first.stats.info["light_exchange_bytes"],
                        "light_exchange_bytes": statistics.median(f.stats.info["light_exchange_bytes"]
                                                                  for f in frames),
                        "composite_ms": statistics.median(f.stats.times_ms["composite"] for f in frames),
                        "region_bytes_max": max(resident), "region_bytes": resident, "volume_bytes": volume_bytes,
                        "resident_share": max(resident) / volume_bytes,
                        "fits_budget": "yes" if max(resident) <= budget else "no"})
                    case_done(f"regions on Ray, {compositing}, N = {n}")
        finally:
            if not was_up:
                ray.shutdown()
    return rows


# --- the suite --------------------------------------------------------------------------------------------------

def run(quick: bool, device: str) -> dict[str, Any]:
    cfg = sized(QUICK, FULL, quick)
    composite = compositing_rows(cfg["sizes"], cfg["counts"], cfg["composite_repeats"], cfg["seed"])
    rate = over_throughput(composite)
    regions = region_rows(cfg, device)
    ray = ray_rows(cfg, device) if cfg["ray"] else [{"compositing": "skipped", "note": "--set ray=false"}]
    images = [("1920x1080", 1920 * 1080), ("4096x1024", 4096 * 1024)]
    model = model_rows(rate, cfg["nodes"], images)
    anchors = anchor_rows(rate)
    columns = [
        ("size", "image", "s"), ("n", "N", ""), ("partial_bytes", "bytes/partial (RGBA f32)", ","),
        ("over_ms", "over [ms]", ".2f"), ("max_ms", "max [ms]", ".2f"), ("nearest_ms", "nearest [ms]", ".2f"),
        ("over_mpix_per_s", "over M pixel-composites/s", ".0f"),
    ]
    region_columns = [
        ("n", "regions in process", ""), ("wall_ms", "wall [ms]", ".1f"),
        ("region_ms_max", "slowest region march [ms]", ".1f"),
        ("region_ms_sum", "regions' marches summed [ms]", ".1f"),
        ("composite_ms", "composite [ms]", ".2f"), ("light_exchange_bytes", "light exchange [B]", ","),
        ("region_bytes_max", "largest region [B]", ","), ("volume_bytes", "volume [B]", ","),
        ("psnr_db", "PSNR vs N=1 [dB]", ".1f"), ("psnr_goal", f">= {GOAL_PSNR:g} dB", "s"),
    ]
    ray_columns = [
        ("compositing", "Ray compositing", "s"), ("n", "region actors", ""), ("seconds", "start-up [s]", ".1f"),
        ("setup_s", "actors + warm-up frame [s]", ".1f"), ("frame_s", "frame [s]", ".3f"),
        ("driver_bytes", "driver received/frame [B]", ",.0f"),
        ("light_exchange_first", "light exchange, 1st frame [B]", ","),
        ("light_exchange_bytes", "light exchange/frame after [B]", ",.0f"),
        ("composite_ms", "composite [ms]", ".2f"), ("region_bytes_max", "largest actor resident [B]", ","),
        ("volume_bytes", "volume [B]", ","), ("resident_share", "largest / volume", ".2f"),
        ("fits_budget", "fits actor budget", "s"), ("note", "note", "s"),
    ]
    model_columns = [
        ("image", "image", "s"), ("network", "network (model)", "s"), ("nodes", "nodes", ""),
        ("bytes_per_node_mb", "MB received/node", ".1f"), ("tile_kb", "direct-send tile [kB]", ".0f"),
        ("ds_ms", "direct-send [ms]", ".2f"), ("ds_latency_ms", "of it latency [ms]", ".3f"),
        ("bs_ms", "binary-swap [ms]", ".2f"), ("rk_ms", "radix-8 [ms]", ".2f"),
        ("rk_sparse_ms", "radix-8, sparse N^-2/3 [ms]", ".2f"), ("compute_ms", "direct-send compositing [ms]", ".2f"),
        ("gather_ms", "final gather RGBA8 [ms]", ".2f"),
    ]
    anchor_columns = [
        ("anchor", "published anchor", "s"), ("covers", "its time covers", "s"), ("network", "model network", "s"),
        ("published_ms", "published [ms]", ".0f"), ("ds_ms", "model direct-send [ms]", ".0f"),
        ("bs_ms", "model binary-swap [ms]", ".0f"), ("rk_ms", "model radix-8 [ms]", ".0f"),
        ("rk_sparse_ms", "model radix-8, sparse [ms]", ".1f"),
        ("best_over_published", "best model / published", ".2f"),
    ]
    settings = {**cfg, "over_rate_pix_per_s": rate, "light_dir": list(LIGHT_DIR), "camera": list(CAMERA),
                "method": "dssrm dvr", "networks": {k: {"bandwidth_bytes_per_s": b, "latency_s": a}
                                                    for k, (b, a) in NETWORKS.items()},
                "partial_bytes_per_pixel": PARTIAL_BYTES_PER_PIXEL, "final_bytes_per_pixel": FINAL_BYTES_PER_PIXEL}
    return {"settings": settings, "rows": composite, "columns": columns, "regions": regions, "ray": ray,
            "model": model, "anchors": anchors,
            "more_tables": {"regions": region_columns, "ray": ray_columns, "model": model_columns,
                            "anchors": anchor_columns},
            "notes": {"regions": REGIONS_NOTE, "ray": RAY_NOTE, "model": model_notes(rate)}}


SUITE = Suite("dataparallel", "sort-last data-parallel regions: compositing cost, regions in process and on Ray, "
              "a model of compositing on 8-64 nodes", run, settable=True)
