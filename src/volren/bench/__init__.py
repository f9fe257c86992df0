"""Benchmarks: one suite per table of the papers. Each writes JSON (machine, device, settings, figures) and a
Markdown table. ``--quick`` sizes run on a CPU in seconds; full sizes are for a GPU."""

from __future__ import annotations

import os
import platform
import statistics
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import warp as wp

from volren.camera import Camera
from volren.device import cpu_threads
from volren.errors import VolrenError
from volren.progress import case_done
from volren.render import Renderer
from volren.render.base import LightMapMarchConfig
from volren.scene import Scene

# Untracked by default: `--out docs/bench` is the deliberate step that updates the committed tables.
DEFAULT_OUT = Path("out/bench")


@dataclass(frozen=True)
class Suite:
    name: str
    description: str
    run: Callable[[bool, str], dict[str, Any]]
    """(quick, device) -> {"settings": ..., "rows": [dict, ...], "columns": [(key, header, format), ...]}, plus
    optionally "summary": (rows, columns) for a second table (ratios against a paper's goals)"""
    repeats: bool = False
    """its frames are timed by `measure` (so ``--repeats`` can cut their count)"""
    settable: bool = False
    """it takes its sizes and counts through `sized` (so ``--set KEY=VALUE`` can change them)"""


REPEATS: ContextVar[int | None] = ContextVar("bench_repeats", default=None)
"""timed frames per case for every `measure` of a run (``volren bench --repeats``), None: each suite's own: a full
size run on a CPU cuts repeats, not sizes"""

OVERRIDES: ContextVar[dict[str, Any] | None] = ContextVar("bench_overrides", default=None)
"""``volren bench --set KEY=VALUE``: entries of a suite's configuration replaced for a run (a full-size run on a CPU
cuts the frames of a camera path, not the sizes)"""


def bench_scene(name: str, resolution: int, **options: Any) -> Scene:
    """`volren.data.builtin_scene` with the light, sky and phantom opacity the suites recorded their figures under
    (`volren.data.classic_look`): the scenes' key light of issue 45.6 is for first pictures, and would change what
    the suites measure (light-map work, PSNR against the reference)."""
    from volren.data import builtin_scene, classic_look

    return classic_look(builtin_scene(name, resolution, **options))


def sized(quick_cfg: dict[str, Any], full_cfg: dict[str, Any], quick: bool) -> dict[str, Any]:
    """The suite configuration a run uses: ``quick_cfg`` or ``full_cfg`` with `OVERRIDES` applied; an override of a
    key the configuration does not have is refused, naming the keys it has."""
    cfg, overrides = dict(quick_cfg if quick else full_cfg), OVERRIDES.get() or {}
    unknown = sorted(set(overrides) - set(cfg))
    if unknown:
        raise VolrenError(f"--set {unknown[0]}: not a setting of this suite; it has {', '.join(cfg)}")
    return cfg | overrides


NOT_PASSES = ("upload", "readback", "fog_bake")
"""Times that are not the method's per-frame work (one-off upload, copying images to the host)."""


def measure(renderer: Renderer, scene: Scene, views: list[Camera], repeats: int) -> dict[str, Any]:
    """Median pass times [ms] over ``repeats`` frames after a warm-up frame (kernel compilation, upload), the
    frame time (sum of the median passes), the fastest frame (``frame_min_ms``: on a shared machine the least
    disturbed run, the one ratios are taken from), the last frame's counters, and the last frame itself. Every pass
    runs in every frame, as in the papers' tables (whose scenes move): a light-map renderer recomputes its map though
    the scene stands still here (no light-map cache)."""
    repeats = REPEATS.get() or repeats
    if isinstance(renderer.config, LightMapMarchConfig):
        renderer.config = replace(renderer.config, reuse_light_map=False)
    renderer.render(scene, views)
    frames = [renderer.render(scene, views, frame=i) for i in range(repeats)]
    passes = sorted({k for f in frames for k in f.stats.times_ms if k not in NOT_PASSES})
    times = {f"{k}_ms": statistics.median(f.stats.times_ms.get(k, 0.0) for f in frames) for k in passes}
    fastest = min(sum(f.stats.times_ms.get(k, 0.0) for k in passes) for f in frames)
    case_done(f"{renderer.name}, {len(views)} view(s) of {views[0].width}x{views[0].height}")
    return {"frame_ms": sum(times.values()), "frame_min_ms": fastest, **times, **frames[-1].stats.counters,
            "frame": frames[-1]}


@contextmanager
def cpu_thread_limit(threads: int | None) -> Iterator[None]:
    """Run with ``VOLREN_CPU_THREADS`` set (None: leave it as it is)."""
    old = os.environ.get("VOLREN_CPU_THREADS")
    if threads is not None:
        os.environ["VOLREN_CPU_THREADS"] = str(threads)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("VOLREN_CPU_THREADS", None)
        else:
            os.environ["VOLREN_CPU_THREADS"] = old


def machine_info(device: str) -> dict[str, Any]:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {
        "hostname": platform.node(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "cpu_threads_used": cpu_threads(),
        "device": device,
        "device_name": wp.get_device(device).name,
        "python": platform.python_version(),
        "warp": wp.__version__,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def markdown_table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "| " + " | ".join("---" for _ in columns) + " |"
    body = ["| " + " | ".join(format(r[k], f) if r.get(k) is not None else "" for k, _, f in columns) + " |"
            for r in rows]
    return "\n".join([head, rule, *body])
