"""Data-parallel rendering on Ray (issue 43): a volume split into N convex regions (`volren.dataparallel`), each held
and rendered by its own Ray actor (`RegionWorker`), the partial images composited sort-last.

- **Regions.** The driver splits the volume's brick grid by its active bricks (`split_volume`: from the data it
  planned with; a streamed OME-Zarr pyramid's from its coarsest level, so the driver never reads the finest) and
  sends each actor the tree and its region's index. The actor builds the run from the same `RenderSpec` as the
  driver (`volren.plan.plan_render`), cuts the volume to its region's bricks (a pyramid's level-0 bricks read straight
  from the file or store, `volren.dataparallel.region_grid`), drops the rest and keeps its region resident across
  frames. With ``--memory-budget`` each region must fit it.
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
        self.renderer: Any = None
        self.scene: Any = None
        self.halo = -1

    def pid(self) -> int:
        return os.getpid()

    def open(self, source: Callable[[], Any], tree: Any, index: int, cls: type, config: Any,
             device: str) -> dict[str, Any]:
        """Build the whole scene by ``source()``, keep region ``index`` of ``tree`` of its volume, and a ``cls``
        renderer of ``config`` on ``device``; returns the region's report (`region_report`)."""
        from volren.dataparallel.render import region_report

        start = time.perf_counter()
        self.source, self.tree, self.index = source, tree, index
        self.renderer = cls(config, device=device)
        self._cut(config.mode)
        return region_report(tree, index, self.scene, load_seconds=time.perf_counter() - start)

    def _cut(self, mode: str) -> None:
        """The region of the whole scene as ``mode`` reads it (iso: a ring of bricks more), read afresh from the
        source when that changes."""
        from volren.dataparallel.render import check_data_parallel, region_scene

        halo = 1 if mode == "iso" else 0
        if halo == self.halo:
            return
        whole = self.source()
        check_data_parallel(self.renderer.name, self.renderer.config, whole)
        lights = self.scene.lights if self.scene is not None else whole.lights
        self.scene = dataclasses.replace(region_scene(whole, self.tree, self.index, mode), lights=lights)
        for v in whole.volumes:  # the whole pyramid's streamer is not needed: the region was read
            if getattr(v.density, "streamed", False):
                v.density.close()
        self.halo = halo

    def _sync(self, config: Any, lights: tuple) -> None:
        """Render with the driver's ``config`` and ``lights`` (`volren serve`'s settings and light drag)."""
        self.renderer.config = config
        self._cut(config.mode)
        if lights != self.scene.lights:
            self.scene = dataclasses.replace(self.scene, lights=lights)

    def light(self, frame: int, config: Any, lights: tuple) -> tuple[np.ndarray | None, tuple]:
        """This region's light map when its pass ran (`LightMapRenderer.region_light_map`), else None, and the
        pass's (times, counters)."""
        self._sync(config, lights)
        return self.renderer.region_light_map(self.scene, frame), self.renderer.region_light_stats

    def render(self, frame: int, views: list, total: np.ndarray | None, strips: int) -> tuple:
        """Render the region's partial images of ``views`` (``total``: the summed light map when it changed, else
        None) and return (its stats and seconds, then ``strips`` strips of rows, `cut_strips`)."""
        start = time.perf_counter()
        if total is not None:
            self.renderer.light_map_total = total
        f = self.renderer.render(self.scene, views, frame)
        meta = {"stats": f.stats, "seconds": time.perf_counter() - start}
        return (meta, *cut_strips(f.images, f.depths, strips))

    def composite(self, mode: str, orders: list, *parts: tuple[list, list]) -> tuple[list, list, float]:
        """Composite one strip of every region's partial images (``parts[r]``: region r's) in ``orders``."""
        from volren.dataparallel.render import composite_views

        start = time.perf_counter()
        images, depths = composite_views([p[0] for p in parts], [p[1] for p in parts], orders, mode)
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
        check_data_parallel(renderer.name, renderer.config, scene, flag)
        self.source, self.n, self.compositing, self.flag = source, n, compositing, flag
        self.cls, self.config, self.device, self.lights = type(renderer), renderer.config, renderer.device, scene.lights
        self.memory_budget = memory_budget
        self.tree = split_volume(scene, n)
        self.to_local = scene.volumes[0].to_local
        start = time.perf_counter()
        self.ray = ray = connect(flag, address, num_cpus=None if address else max(n, 1))
        have = ray.cluster_resources().get("CPU", 0)
        self._remote = ray.remote(max_restarts=0, max_task_retries=0)(RegionWorker).options(
            num_cpus=min(1.0, have / n) if have else 0)
        self.ray_start_seconds = time.perf_counter() - start
        self.actors: list[Any] = [None] * n
        self.reports: list[dict[str, Any]] = [{}] * n
        self._partials: list[np.ndarray | None] = [None] * n
        self._total: Any = None
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
        refs = {i: self.actors[i].open.remote(self.source, self.tree, i, self.cls, self.config, self.device)
                for i in which}
        for i, ref in refs.items():
            report = self.reports[i] = self._get(ref)
            if self.memory_budget is not None and report["bytes"] > self.memory_budget:
                raise VolrenError(f"region {i} of {self.n} holds {report['bytes'] / 2**20:.1f} MiB of bricks, above "
                                  f"--memory-budget {self.memory_budget / 2**30:g} GiB: give more {self.flag} regions")
            if self.on_region is not None:
                self.on_region(report)

    def _get(self, ref: Any) -> Any:
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
        from volren.dataparallel.render import composite_views, merged_stats, view_orders
        from volren.render.frame import Frame

        ray, n = self.ray, self.n
        start = time.perf_counter()
        received = 0
        lit = ray.get([a.light.remote(frame, self.config, self.lights) for a in self.actors])
        partials = [m for m, _ in lit]
        light_start = time.perf_counter()
        changed = [i for i, p in enumerate(partials) if p is not None]
        for i in changed:
            self._partials[i] = partials[i]
            received += partials[i].nbytes
        if changed and all(p is not None for p in self._partials):
            self._total = ray.put(np.sum(self._partials, axis=0, dtype=np.float32))
            self._version += 1
        light_ms = (time.perf_counter() - light_start) * 1e3
        totals = []
        for i in range(n):
            fresh = self._total is not None and self._sent[i] != self._version
            totals.append(self._total if fresh else None)
            self._sent[i] = self._version if fresh else self._sent[i]
        strips = n if self.compositing == "direct-send" else 1
        outs = [a.render.options(num_returns=strips + 1).remote(frame, views, totals[i], strips)
                for i, a in enumerate(self.actors)]
        orders = view_orders(self.tree, self._scene_stub(), views)
        t = time.perf_counter()
        if self.compositing == "direct-send":
            done = ray.get([self.actors[k].composite.remote(self.config.mode, orders, *[o[k + 1] for o in outs])
                            for k in range(n)])
            images = [np.concatenate([d[0][v] for d in done]) for v in range(len(views))]
            depths = [np.concatenate([d[1][v] for d in done]) for v in range(len(views))]
            received += _nbytes([d[:2] for d in done])
            composite_ms = max(d[2] for d in done)
        else:
            parts = ray.get([o[1] for o in outs])
            received += _nbytes(parts)
            c = time.perf_counter()
            images, depths = composite_views([p[0] for p in parts], [p[1] for p in parts], orders, self.config.mode)
            composite_ms = (time.perf_counter() - c) * 1e3
        metas = ray.get([o[0] for o in outs])
        exchange_ms = (time.perf_counter() - t) * 1e3
        reports = [{**r, "times_ms": {k: round(v, 3) for k, v in m["stats"].times_ms.items()},
                    "seconds": round(m["seconds"], 4)} for r, m in zip(self.reports, metas, strict=True)]
        stats = merged_stats([m["stats"] for m in metas], reports,
                             {"light_sum": light_ms, "composite": composite_ms, "render_and_composite": exchange_ms},
                             {"compositing": self.compositing, "driver_bytes": received,
                              "light_exchange_bytes": sum(self._partials[i].nbytes for i in changed),
                              "replaced": self.replaced, "orders": orders,
                              "wall_ms": (time.perf_counter() - start) * 1e3}, [s for _, s in lit])
        return Frame(images, depths, stats, frame)

    def _scene_stub(self) -> Any:
        """What `view_orders` reads of the scene: its volume's ``to_local``."""
        from types import SimpleNamespace

        return SimpleNamespace(volumes=(SimpleNamespace(to_local=self.to_local),))

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

    from volren.dataparallel.render import check_data_parallel
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
    check_data_parallel(method, plan.renderer.config, plan.scene, flag)
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
    return 0
