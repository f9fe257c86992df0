"""Data-parallel rendering on Ray (issue 43): a volume split into N convex regions (`volren.dataparallel`), each held
and rendered by its own Ray actor (`RegionWorker`), the partial images composited sort-last.

- **Regions.** The driver splits the volume's brick grid by its active bricks (`split_volume`: from the data it
  planned with; a streamed OME-Zarr pyramid's from its coarsest level, so the driver never reads the finest) and
  sends each actor the tree and its region's index. The actor builds the whole scene itself (a picklable source:
  the same `RenderSpec` as the driver's plan, `PlannedScene`; serve's file; the Python API's path or scene), cuts the
  volume (each channel of a multi-channel file) to its region's bricks (a pyramid's level-0 bricks read straight
  from the file or store, `volren.dataparallel.region_grid`; a dense file is read whole, then cut), drops the rest
  and keeps its region resident across frames. With ``--memory-budget`` each region must fit it. The driver sends
  the renderer's config and the scene's lights with each frame (`volren serve`'s settings and light drag).
- **Light.** Each frame the actors run their light-map pass on their region; the maps that changed come to the
  driver, which sums them (optical depth adds: `volren.dataparallel.render`) and sends the sum back through Ray's
  object store, only to the actors that lack it (an orbit sends nothing after the first frame).
- **Compositing.** Direct-send by default: every actor renders its region's partial images for every view, cut into
  N strips of rows; actor k composites strip k of every region's partials in each view's visibility order (Ray hands
  it the other actors' strips through the object store) and returns it, so the driver receives one image's bytes
  whatever N. ``gather`` (for the benchmark): the driver fetches every partial and composites alone, N images' bytes.
- **Faults.** An actor that dies is replaced by a fresh one that loads its region again, and the frame in flight is
  redone: the output is the one-process output (``replaced`` in the stats).
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from volren.errors import VolrenError

COMPOSITING = ("direct-send", "gather")
MAX_REDOS = 2
"""times a frame is redone after actors died in it before the run is given up"""


def strip_rows(height: int, n: int) -> list[tuple[int, int]]:
    """Rows [r0, r1) of strip k of an image of ``height`` rows cut into ``n`` strips (the first ones one row taller
    where they do not divide)."""
    edges = np.linspace(0, height, n + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges)]


def cut_strips(images: Sequence[np.ndarray], depths: Sequence[np.ndarray], n: int) -> list[tuple[list, list]]:
    """Per strip k, (every view's image rows, every view's depth rows) of strip k."""
    out = []
    for k in range(n):
        rows = [strip_rows(im.shape[0], n)[k] for im in images]
        out.append(([im[a:b] for im, (a, b) in zip(images, rows, strict=True)],
                    [d[a:b] for d, (a, b) in zip(depths, rows, strict=True)]))
    return out


@dataclass(frozen=True)
class PlannedScene:
    """The scene ``spec`` (a `volren.plan.spec.RenderSpec`) plans, built where it is called: a region actor's whole
    volume, read there (a streamed pyramid: its metadata and coarsest level) before it keeps its region."""

    spec: Any
    cwd: str | None = None
    """the driver's folder, which relative paths name, where this machine has it"""

    def __call__(self) -> Any:
        from volren.plan import plan_render

        if self.cwd is not None and os.path.isdir(self.cwd):
            os.chdir(self.cwd)
        args = self.spec.namespace(max_minutes=0, data_parallel=None)
        return plan_render(args, args.method).scene


class RegionWorker:
    """One region's actor: its part of the volume and its renderer, kept across frames (module docstring). Imports
    no Ray: `RegionEngine` wraps it in ``ray.remote``."""

    def __init__(self, threads: int | None = None) -> None:
        if threads is not None:
            os.environ["VOLREN_CPU_THREADS"] = str(threads)
        self.renderers: list[Any] = []
        self.scenes: list[Any] = []
        self.halo = -1

    def pid(self) -> int:
        return os.getpid()

    def open(self, source: Callable[[], Any], tree: Any, index: int, cls: type, config: Any, device: str,
             channels: int = 0) -> dict[str, Any]:
        """Build the whole scene by ``source()``, keep region ``index`` of ``tree`` of its volume (of each of its
        ``channels``, 0: one volume), and a ``cls`` renderer of ``config`` on ``device`` per channel; returns the
        region's report (`region_report`)."""
        from volren.dataparallel.render import region_report

        start = time.perf_counter()
        self.source, self.tree, self.index, self.channels = source, tree, index, channels
        self.renderers = [cls(config, device=device) for _ in range(max(channels, 1))]
        self.parts: list[Any] = [None] * len(self.renderers)
        """per channel its light map's last `LightPart` (its layout, for the sums that come back)"""
        self._cut(config.mode)
        return region_report(tree, index, self.scenes, load_seconds=time.perf_counter() - start)

    def _cut(self, mode: str) -> None:
        """The region of the whole scene as ``mode`` reads it (iso: a ring of bricks more), read afresh from the
        source when that changes."""
        from volren.dataparallel.render import check_data_parallel, region_scenes

        halo = 1 if mode == "iso" else 0
        if halo == self.halo:
            return
        whole = self.source()
        first = self.renderers[0]
        check_data_parallel(first.name, first.config, whole, channels=self.channels > 0)
        lights = self.scenes[0].lights if self.scenes else whole.lights
        self.scenes = [dataclasses.replace(s, lights=lights)
                       for s in region_scenes(whole, self.tree, self.index, mode, self.channels > 0)]
        for v in whole.volumes:  # the whole pyramid's streamer is not needed: the region was read
            if getattr(v.density, "streamed", False):
                v.density.close()
        self.halo = halo

    def _sync(self, config: Any, lights: tuple) -> None:
        """Render with the driver's ``config`` and ``lights`` (`volren serve`'s settings and light drag)."""
        for r in self.renderers:
            r.config = config
        self._cut(config.mode)
        if lights != self.scenes[0].lights:
            self.scenes = [dataclasses.replace(s, lights=lights) for s in self.scenes]

    def light(self, frame: int, config: Any, lights: tuple) -> tuple[list, list]:
        """Per channel this region's light map where its pass ran (`LightMapRenderer.region_light_map`) as the
        exchange sends it (`volren.dataparallel.light.light_part`), else None, and the passes' (times, counters)."""
        from volren.dataparallel.light import light_part

        self._sync(config, lights)
        parts = []
        for c, (r, s) in enumerate(zip(self.renderers, self.scenes, strict=True)):
            m = r.region_light_map(s, frame)
            parts.append(None if m is None else light_part(m, s.volumes[0], config.light_grid))
            if parts[-1] is not None:
                self.parts[c] = parts[-1]
        return parts, [r.region_light_stats for r in self.renderers]

    def render(self, frame: int, views: list, patches: list | None, strips: int) -> tuple:
        """Render the region's partial images of ``views`` per channel (``patches``: the summed light maps over the
        nodes it reads when they changed, else None) and return (its stats and seconds, then ``strips`` strips of
        rows: per strip (images, depths), each per channel and view, `cut_strips`)."""
        from volren.dataparallel.light import light_map_of

        start = time.perf_counter()
        frames = []
        for c, (r, s) in enumerate(zip(self.renderers, self.scenes, strict=True)):
            if patches is not None and patches[c] is not None:
                r.light_map_total = light_map_of(patches[c], self.parts[c])
            frames.append(r.render(s, views, frame))
        meta = {"stats": [f.stats for f in frames], "seconds": time.perf_counter() - start}
        cut = [cut_strips(f.images, f.depths, strips) for f in frames]
        return (meta, *[([c[k][0] for c in cut], [c[k][1] for c in cut]) for k in range(strips)])

    def composite(self, mode: str, orders: list, colors: list | None, *parts: tuple[list, list]
                  ) -> tuple[list, list, float]:
        """Composite one strip of every region's partial images (``parts[r]``: region r's) in ``orders``, the
        channels added in ``colors`` (`composite_channels`)."""
        from volren.dataparallel.render import composite_channels

        start = time.perf_counter()
        images, depths = composite_channels([p[0] for p in parts], [p[1] for p in parts], orders, mode, colors)
        return images, depths, (time.perf_counter() - start) * 1e3


def _nbytes(value: Any) -> int:
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, list | tuple):
        return sum(_nbytes(v) for v in value)
    return 0


class RegionEngine:
    """N region actors rendering ``scene``'s volume as ``renderer`` (its class, config and device) would, each
    building the whole scene by ``source()`` (a picklable call: `PlannedScene`, `volren.serve`'s file) and keeping
    its region, on a local Ray (``address`` None) or a cluster (module docstring). ``memory_budget`` [bytes]: the
    most a region may hold. ``flag`` names the option in errors; ``on_region`` is called with each region's report
    as it is loaded."""

    def __init__(self, source: Callable[[], Any], scene: Any, n: int, renderer: Any, *, address: str | None = None,
                 compositing: str = "direct-send", flag: str = "--data-parallel", memory_budget: float | None = None,
                 on_region: Callable[[dict[str, Any]], None] | None = None) -> None:
        from volren.dataparallel.render import check_data_parallel, split_volume
        from volren.distributed.runtime import connect

        if compositing not in COMPOSITING:
            raise VolrenError(f"compositing must be one of {', '.join(COMPOSITING)}, got {compositing!r}")
        if n < 1:
            raise VolrenError(f"{flag} must be >= 1 regions, got {n}")
        from volren.dataparallel.render import channel_colors

        # a multi-channel file's renderer (`AdditiveChannels`) renders each channel by a renderer of its own
        self.channels = len(getattr(renderer, "renderers", ()))
        base = renderer.renderers[0] if self.channels else renderer
        check_data_parallel(base.name, base.config, scene, flag, channels=self.channels > 0)
        self.source, self.n, self.compositing, self.flag = source, n, compositing, flag
        self.cls, self.config, self.device, self.lights = type(base), base.config, base.device, scene.lights
        self.colors = channel_colors(scene, self.channels > 0)
        self.memory_budget = memory_budget
        try:
            self.tree = split_volume(scene, n)
        except VolrenError as exc:  # more regions than bricks
            raise VolrenError(f"{flag} {n}: {exc}") from None
        self.to_local = scene.volumes[0].to_local
        start = time.perf_counter()
        self.ray = ray = connect(flag, address, num_cpus=None if address else max(n, 1))
        have = ray.cluster_resources().get("CPU", 0)
        self._remote = ray.remote(max_restarts=0, max_task_retries=0)(RegionWorker).options(
            num_cpus=min(1.0, have / n) if have else 0)
        self.ray_start_seconds = time.perf_counter() - start
        self.actors: list[Any] = [None] * n
        self.reports: list[dict[str, Any]] = [{}] * n
        self._partials: list[list | None] = [None] * n
        """per region, per channel its last light map as it came (`volren.dataparallel.light.LightPart`)"""
        self._patches: list[list] = [[]] * n
        """per region, per channel the summed maps over the nodes it reads, as of ``_version``"""
        self._version, self._sent = 0, [-1] * n
        self.replaced = 0
        self.on_region = on_region
        try:
            self._open(list(range(n)))
        except BaseException:
            self.close()
            raise

    def _open(self, which: list[int]) -> None:
        for i in which:
            self.actors[i] = self._remote.remote(1)
            self._sent[i] = -1
            self._partials[i] = None
        refs = {i: self.actors[i].open.remote(self.source, self.tree, i, self.cls, self.config, self.device,
                                              self.channels) for i in which}
        for i, ref in refs.items():
            report = self.reports[i] = self._get(ref)
            if self.memory_budget is not None and report["bytes"] > self.memory_budget:
                raise VolrenError(f"region {i} of {self.n} holds {report['bytes'] / 2**20:.1f} MiB of bricks, above "
                                  f"--memory-budget {self.memory_budget / 2**30:g} GiB: give more {self.flag} regions")
            if self.on_region is not None:
                self.on_region(report)

    def _get(self, ref: Any) -> Any:
        """``ray.get(ref)``, an actor's `VolrenError` raised here as the one line it is."""
        try:
            return self.ray.get(ref)
        except self.ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, VolrenError):
                raise VolrenError(str(cause)) from None
            raise

    def pids(self) -> list[int]:
        """The actors' process ids, region by region (the tests' fault injection)."""
        return self.ray.get([a.pid.remote() for a in self.actors])

    def render(self, views: Sequence[Any], frame: int = 0, *, config: Any = None, lights: tuple | None = None) -> Any:
        """Frame ``frame`` of ``views``: every region rendered by its actor and composited (module docstring), with
        ``config`` and ``lights`` where given (else the last ones); an actor that died is replaced and the frame
        redone."""
        if config is not None:
            from volren.dataparallel.render import check_data_parallel

            check_data_parallel(self.cls.name, config, flag=self.flag)
            self.config = config
        self.lights = self.lights if lights is None else tuple(lights)
        for attempt in range(MAX_REDOS + 1):
            try:
                return self._render(list(views), frame)
            except self.ray.exceptions.RayActorError:
                if attempt == MAX_REDOS:
                    raise VolrenError(f"{self.flag}: region actors died {attempt + 1} times in frame {frame}") from None
                self._replace_dead()
        raise AssertionError("unreachable")

    def _replace_dead(self) -> None:
        dead = []
        for i, a in enumerate(self.actors):
            try:
                self.ray.get(a.pid.remote(), timeout=30)
            except (self.ray.exceptions.RayActorError, self.ray.exceptions.GetTimeoutError):
                dead.append(i)
        for i in dead:
            self.ray.kill(self.actors[i], no_restart=True)
        self.replaced += len(dead)
        self._open(dead)

    def _render(self, views: list, frame: int) -> Any:
        from volren.dataparallel.light import light_patch, light_sum
        from volren.dataparallel.render import composite_channels, merged_stats, view_orders
        from volren.render.frame import Frame

        n = self.n
        start = time.perf_counter()
        received = 0
        lit = self._get([a.light.remote(frame, self.config, self.lights) for a in self.actors])
        light_start = time.perf_counter()
        changed = [i for i, (parts, _) in enumerate(lit) if any(p is not None for p in parts)]
        for i in changed:
            parts, old = lit[i][0], self._partials[i] or [None] * len(lit[i][0])
            self._partials[i] = [p if p is not None else o for p, o in zip(parts, old, strict=True)]
            received += sum(p.nbytes for p in parts if p is not None)
        if changed and all(p is not None and all(m is not None for m in p) for p in self._partials):
            channels = range(len(self._partials[0]))
            sums = [light_sum([p[c] for p in self._partials]) for c in channels]
            self._patches = [[light_patch(sums[c], p[c]) for c in channels] for p in self._partials]
            self._version += 1
        patches = []
        for i in range(n):
            fresh = self._version > 0 and self._sent[i] != self._version
            patches.append(self._patches[i] if fresh else None)
            self._sent[i] = self._version if fresh else self._sent[i]
        light_ms = (time.perf_counter() - light_start) * 1e3
        light_bytes = received + sum(_nbytes(p) for p in patches if p is not None)
        strips = n if self.compositing == "direct-send" else 1
        outs = [a.render.options(num_returns=strips + 1).remote(frame, views, patches[i], strips)
                for i, a in enumerate(self.actors)]
        orders = view_orders(self.tree, self.to_local, views)
        t = time.perf_counter()
        if self.compositing == "direct-send":
            done = self._get([self.actors[k].composite.remote(self.config.mode, orders, self.colors,
                                                            *[o[k + 1] for o in outs]) for k in range(n)])
            images = [np.concatenate([d[0][v] for d in done]) for v in range(len(views))]
            depths = [np.concatenate([d[1][v] for d in done]) for v in range(len(views))]
            received += _nbytes([d[:2] for d in done])
            composite_ms = max(d[2] for d in done)
        else:
            parts = self._get([o[1] for o in outs])
            received += _nbytes(parts)
            c = time.perf_counter()
            images, depths = composite_channels([p[0] for p in parts], [p[1] for p in parts], orders,
                                                self.config.mode, self.colors)
            composite_ms = (time.perf_counter() - c) * 1e3
        metas = self._get([o[0] for o in outs])
        exchange_ms = (time.perf_counter() - t) * 1e3
        reports = [{**r, "times_ms": {k: round(v, 3) for k, v in m["stats"][0].times_ms.items()},
                    "seconds": round(m["seconds"], 4)} for r, m in zip(self.reports, metas, strict=True)]
        stats = merged_stats([s for m in metas for s in m["stats"]], reports,
                             {"light_sum": light_ms, "composite": composite_ms, "render_and_composite": exchange_ms},
                             {"compositing": self.compositing, "driver_bytes": received,
                              "light_exchange_bytes": light_bytes, "replaced": self.replaced, "orders": orders,
                              "wall_ms": (time.perf_counter() - start) * 1e3}, [s for _, ss in lit for s in ss])
        return Frame(images, depths, stats, frame)

    def close(self) -> None:
        for a in self.actors:
            if a is not None:
                self.ray.kill(a, no_restart=True)
        self.actors = [None] * self.n

    def __enter__(self) -> RegionEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DataParallelRenderer:
    """A `RegionEngine` where a plan's renderer stands (`volren.plan.RenderPlan.renderer`): ``render(scene, views,
    frame)`` composites the regions' images of the planned scene, so ``volren render`` and ``animate`` write its frames
    as they write an in-process renderer's."""

    def __init__(self, engine: RegionEngine, config: Any = None) -> None:
        self.engine = engine
        self.name, self.device = engine.cls.name, engine.device
        self.config = engine.config if config is None else config
        self.on_rows: Callable[[int], None] | None = None
        self.on_bricks: Callable[[int, int], None] | None = None
        self.stream_wait = True

    def release_views(self) -> None:
        """Nothing held per view here (`volren serve` calls it when its last viewer leaves)."""

    def render(self, scene: Any, views: Sequence[Any], frame: int = 0, *, occluder_depth: Any = None) -> Any:
        if occluder_depth is not None and any(z is not None for z in occluder_depth):
            raise VolrenError(f"{self.engine.flag} takes no depth images (--depth-image)")
        out = self.engine.render(views, frame, config=self.config, lights=scene.lights)
        out.background, out.scene_name = scene.background, scene.name
        if self.on_rows is not None:
            self.on_rows(sum(v.height for v in views))
        return out


def run_data_parallel(args: Any, method: str, command: str) -> int:
    """``volren render|animate ... --data-parallel N [--ray-address ADDR]``: the planned run with its renderer's work
    split into N regions on Ray (`RegionEngine`), written as the in-process run writes it."""
    import sys

    from volren.distributed.runtime import import_ray
    from volren.output import print_summary
    from volren.plan import plan_render, render_plan
    from volren.plan.spec import RenderSpec

    flag = "--data-parallel"
    n = args.data_parallel
    if n < 1:
        raise VolrenError(f"{flag} must be >= 1 regions, got {n}")
    if args.workers is not None:
        raise VolrenError(f"{flag} splits the volume and --workers the frames: give one of them")
    import_ray(flag, local=not args.ray_address)  # missing: one line before the plan's seconds of work
    args.max_minutes = 0  # the run-time probe would render the whole volume in this process
    plan = plan_render(args, method)
    if plan.played is not None or plan.animated:
        raise VolrenError(f"{flag} splits one volume: a sequence or an animated scene changes it every frame")
    if plan.sequence is not None:
        plan.frame(args.frames - 1)
        if plan.renderer.config != plan.base_config:
            raise VolrenError(f"{flag} keeps one renderer config per region: this animation switches it per frame")
        plan.renderer.config = plan.base_config

    def said(report: dict[str, Any]) -> None:
        print(f"  region {report['index']}: bricks {report['lo']}..{report['hi']}, {report['resident_bricks']} "
              f"resident, {report['bytes'] / 2**20:.1f} MiB, loaded in {report['load_seconds']:.1f} s", file=sys.stderr)

    plan.value_mapping["regions"] = n  # stats.json's, beside the scene and the command
    budget = getattr(args, "memory_budget", None)
    with RegionEngine(PlannedScene(RenderSpec.from_args(args, command), os.getcwd()), plan.scene, n, plan.renderer,
                      address=args.ray_address, memory_budget=None if budget is None else budget * 2**30,
                      on_region=said) as engine:
        plan.renderer = DataParallelRenderer(engine)
        done = render_plan(plan, command)
    print_summary(method, plan.scene.name, len(plan.views), args.frames, done.wall, done.frames[-1].stats,
                  done.files, done.stats)
    info = done.frames[-1].stats.info
    print("  regions (last frame): " + ", ".join(f"{r['index']} {r['seconds']:.2f} s" for r in info["region_stats"])
          + f"; the driver received {info['driver_bytes'] / 2**20:.1f} MiB ({info['compositing']})")
    return 0
