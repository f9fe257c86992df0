"""Benchmarks: one suite per table of the papers. Each writes JSON (machine, device, settings, figures) and a
Markdown table. ``--quick`` sizes run on a CPU in seconds; full sizes are for a GPU."""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import warp as wp

from volren.camera import Camera
from volren.device import cpu_threads, resolve_device
from volren.errors import VolrenError
from volren.progress import case_done, cases
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


def all_suites() -> dict[str, Suite]:
    """Every suite by name (imported here, so importing volren.bench stays cheap)."""
    from volren.bench.batch import SUITE as BATCH_SUITE
    from volren.bench.binocular import SUITE as BINOCULAR_SUITE
    from volren.bench.dssrm import SUITE as DSSRM_SUITE
    from volren.bench.gi import SUITE as GI_SUITE
    from volren.bench.integrated import SUITE as INTEGRATED_SUITE
    from volren.bench.interactive import SUITE as INTERACTIVE_SUITE
    from volren.bench.load import SUITE as LOAD_SUITE
    from volren.bench.oit import SUITE as OIT_SUITE
    from volren.bench.peers import SUITE as PEERS_SUITE
    from volren.bench.resolution import SUITE as RESOLUTION_SUITE
    from volren.bench.serve import SUITE as SERVE_SUITE
    from volren.bench.viewers import SUITE as VIEWERS_SUITE
    from volren.bench.vpt import SUITE as VPT_SUITE

    return {s.name: s for s in (DSSRM_SUITE, RESOLUTION_SUITE, BINOCULAR_SUITE, VIEWERS_SUITE, VPT_SUITE, GI_SUITE,
                                OIT_SUITE, INTEGRATED_SUITE, SERVE_SUITE, INTERACTIVE_SUITE, LOAD_SUITE, PEERS_SUITE,
                                BATCH_SUITE)}


REPEATS: ContextVar[int | None] = ContextVar("bench_repeats", default=None)
"""timed frames per case for every `measure` of a run (``volren bench --repeats``), None: each suite's own: a full
size run on a CPU cuts repeats, not sizes"""

OVERRIDES: ContextVar[dict[str, Any] | None] = ContextVar("bench_overrides", default=None)
"""``volren bench --set KEY=VALUE``: entries of a suite's configuration replaced for a run (a full-size run on a CPU
cuts the frames of a camera path, not the sizes)"""


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


def run_suite(name: str, *, quick: bool, device: str, out: Path | None = None,
              suite: Suite | None = None, repeats: int | None = None,
              overrides: dict[str, Any] | None = None) -> tuple[Path, Path, str]:
    """Run suite ``name`` and write ``<name>-<cpu|cuda>-<quick|full>.{json,md}`` into ``out`` (default
    :data:`DEFAULT_OUT`); each file is written beside its name and renamed over it, so a failure leaves the old one.
    ``suite``: run that one under ``name`` (a suite with options bound: ``bench serve --shards``). ``repeats``: timed
    frames per case instead of the suite's own (suites timed by `measure` only; recorded in the JSON's settings).
    ``overrides``: configuration entries replaced (`sized`; recorded as the settings' "overridden" keys)."""
    out = DEFAULT_OUT if out is None else out
    suites = all_suites() if suite is None else {name: suite}
    if name not in suites:
        raise VolrenError(f"unknown bench suite '{name}': choose from {', '.join(suites)}")
    if repeats is not None:
        takes = [n for n, s in all_suites().items() if s.repeats]
        if not suites[name].repeats:
            raise VolrenError(f"--repeats: bench {name} times its work its own way; it applies to "
                              f"{', '.join(takes)}")
        if repeats < 1:
            raise VolrenError(f"--repeats must be at least 1, got {repeats}")
    if overrides and not suites[name].settable:
        takes = [n for n, s in all_suites().items() if s.settable]
        raise VolrenError(f"--set: bench {name} has no settings to change; it applies to {', '.join(takes)}")
    device = resolve_device(device)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VolrenError(f"cannot create '{out}': {exc.strerror}") from exc
    start = time.perf_counter()
    token, changed = REPEATS.set(repeats), OVERRIDES.set(dict(overrides or {}))
    try:
        with cases(f"bench {name}"):  # a line per measured case on stderr: a suite takes minutes
            result = suites[name].run(quick, device)
    finally:
        REPEATS.reset(token)
        OVERRIDES.reset(changed)
    elapsed = time.perf_counter() - start
    if repeats is not None:
        result["settings"] = {**result.get("settings", {}), "repeats": repeats, "repeats_cut_from_suite": True}
    if overrides:
        result["settings"] = {**result.get("settings", {}), "overridden": sorted(overrides)}
    table = markdown_table(result["rows"], result["columns"])
    summary_rows, summary_columns = result.pop("summary", ([], []))
    if summary_rows:
        table += "\n\n" + markdown_table(summary_rows, summary_columns)
    doc = {"suite": name, "quick": quick, "machine": machine_info(device), "elapsed_s": round(elapsed, 1), **result,
           "summary": summary_rows}
    tag = f"{name}-{'cpu' if device == 'cpu' else 'cuda'}-{'quick' if quick else 'full'}"
    json_path, md_path = out / f"{tag}.json", out / f"{tag}.md"
    m = doc["machine"]
    from volren.imageio import save_srgb8

    for file, pixels in doc.pop("figures", {}).items():  # images a suite shows beside its table (uint8 sRGB)
        save_srgb8(out / f"{tag}-{file}", pixels)
        table += f"\n\n![{file}]({tag}-{file})"
    _write_replace(json_path, json.dumps(doc, indent=2, default=str) + "\n")
    _write_replace(md_path, f"### {name} ({'quick' if quick else 'full'}) on {m['device_name']} ({m['cpu']}, "
                            f"{m['cpu_threads_used']} CPU threads), warp {m['warp']}, {m['date']}, "
                            f"{elapsed / 60:.1f} min"
                            f"{f', {repeats} timed frame(s) per case' if repeats else ''}"
                            f"{''.join(f', {k} = {v}' for k, v in (overrides or {}).items())}\n\n{table}\n")
    return json_path, md_path, table


def _write_replace(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
