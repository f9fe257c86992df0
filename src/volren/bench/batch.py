"""Suite ``batch``: the batch engine (`volren.distributed.engine`, issue 23) on this machine: a 64-frame turntable of
the default scene (``volren animate --views mono``) in process against a local Ray with 1 and 2 workers.

Rows: in process with one CPU thread (what one CPU worker has: a worker launches on one thread) and with all threads,
after a warm-up run (kernels loaded); Ray with each worker count, one frame per unit (dssrm keeps no history). Per
row: wall time (Ray: `run_jobs` from its checks to its stats.json and animation.mp4, start-up aside), frames per
second, units and frames run. Ray rows also give the start-up (the local cluster started, then the most workers
started and warmed by a frame each: Python, Warp and the kernels loaded; the engine keeps them for the next run, so
the runs go from the most workers down and none starts cold; paid once per session), the actors a run itself started
[s], the mean unit wall time (dispatch to its files written, in the driver), the per-unit overhead: the unit's wall
time minus the in-process time of its frames (the same frames rendered and encoded by the worker's own code in this
process on one thread), mean and max, the engine's own measure (wall minus the worker's setup, warm-up and frame
time: scheduling, transfer, writing), the worker's setup (the job's scene built and uploaded, its renderer made:
once per actor and job, inside the wall time), the driver's serial share of a unit (`driver_seconds`: what bounds
the units per second however many workers), and whether every file equals the in-process run's. Goals (issue 23):
per-unit overhead < 50 ms; local Ray within 1.15x of the in-process time on the same cores (1 worker against one
thread, 2 workers against all threads), start-up aside.

Quick (CPU): 64^3 smoke at 320x180. Full (GPU): 128^3 smoke at 1280x720, the workers sharing the GPUs Ray finds.
"""

from __future__ import annotations

import contextlib
import io
import statistics
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from volren.bench import Suite, cpu_thread_limit
from volren.progress import case_done

if TYPE_CHECKING:
    from volren.plan.spec import RenderSpec

FULL = {"frames": 64, "size": (1280, 720), "resolution": 128, "workers": [1, 2], "overrides": []}
QUICK = {"frames": 64, "size": (320, 180), "resolution": 64, "workers": [1, 2], "overrides": []}
GOAL_OVERHEAD_MS, GOAL_RAY_RATIO = 50.0, 1.15


def turntable(cfg: dict[str, Any], device: str, out: Path) -> RenderSpec:
    """The job: ``volren animate`` of the turntable into ``out``."""
    from volren.plan.spec import RenderSpec

    width, height = cfg["size"]
    return RenderSpec.parse(["animate", "--frames", str(cfg["frames"]), "--orbit", "360", "--views", "mono",
                             "--width", str(width), "--height", str(height), "--resolution", str(cfg["resolution"]),
                             "--device", device, *cfg["overrides"], "--out", str(out)])


def _pngs(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.png"))}


def in_process(spec: RenderSpec, threads: int | None) -> float:
    """[s] ``spec`` run in this process with ``threads`` CPU threads (None: all)."""
    from volren.plan import plan_render, render_plan

    with cpu_thread_limit(threads), contextlib.redirect_stdout(io.StringIO()):  # not a line amid the table
        start = time.perf_counter()
        args = spec.namespace()
        render_plan(plan_render(args, args.method), spec.line)
        return time.perf_counter() - start


def frame_seconds(spec: RenderSpec, frames: int) -> float:
    """[s] one frame's in-process time: the worker's own code (`UnitWorker.run`: render, then encode the files) run
    here on one thread, setup excluded, averaged over the job's frames."""
    from volren.distributed.worker import Unit, UnitWorker

    with cpu_thread_limit(1):
        result = UnitWorker().run(spec, Unit(0, 0, frames))
    return result["render_seconds"] / frames


def driver_seconds(out: Path, repeats: int = 5) -> float:
    """[s] the driver's own share of one unit, serial however many workers there are: its files hashed and written
    (temporary name, then ``os.replace``) and the manifest serialised and written, as `JobState.commit` does, at the
    manifest's final size (it holds every unit of the job: it grows with the units)."""
    import hashlib
    import json

    from volren.distributed.engine import MANIFEST, write_atomically

    manifest = json.loads((out / MANIFEST).read_text())
    files = {name: (out / name).read_bytes() for name in next(iter(manifest["units"].values()))["files"]}
    start = time.perf_counter()
    for _ in range(repeats):
        for name, data in files.items():
            hashlib.sha256(data).hexdigest()
            write_atomically(out / name, data)
        write_atomically(out / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())
    return (time.perf_counter() - start) / repeats


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    from volren.distributed.engine import Job, release_workers, run_jobs
    from volren.distributed.runtime import connect, import_ray

    frames, rows = cfg["frames"], []
    with tempfile.TemporaryDirectory(prefix="volren-bench-batch-") as tmp:
        base = Path(tmp)
        ref = base / "in-process-1"
        spec = turntable(cfg, device, ref)
        in_process(spec, 1)  # warm-up: kernels compiled, the scene's first build
        walls = {1: in_process(spec, 1), None: in_process(turntable(cfg, device, base / "in-process-all"), None)}
        for threads, wall in walls.items():
            rows.append({"case": "in process", "threads": threads or "all", "workers": None, "frames": frames,
                         "units": None, "wall_s": wall, "fps": frames / wall})
            case_done(f"in process, {threads or 'all'} thread(s)")
        per_frame = frame_seconds(spec, frames)
        reference = _pngs(ref)
        was_up = import_ray("bench batch", local=True).is_initialized()  # a session's cluster (the tests') is kept
        started = time.perf_counter()
        ray = connect("bench batch", num_cpus=max(cfg["workers"]))
        gpus = ray.cluster_resources().get("GPU", 0)

        def on_ray(workers: int, out: Path, frames: int):
            share = min(1.0, gpus / workers) if device.startswith("cuda") and gpus else 1.0
            cfg_run = {**cfg, "frames": frames}
            return run_jobs([Job(turntable(cfg_run, device, out))], workers=workers, address=None,
                            flag="bench batch", gpus_per_worker=share, keep_workers=True)

        try:
            # start-up: the cluster, then the most workers started and warmed (Python, Warp, kernels loaded) on a
            # frame each; the engine keeps them for the runs below, the most workers first so that none starts cold
            most = max(cfg["workers"])
            on_ray(most, base / "ray-warm-up", most)
            start_up = time.perf_counter() - started
            for workers in sorted(cfg["workers"], reverse=True):
                out = base / f"ray-{workers}"
                report = on_ray(workers, out, frames)
                wall = report.wall_seconds - report.ray_start_seconds
                units = report.units
                overhead = [u.seconds - (u.stop - u.start) * per_frame for u in units]
                rows.append({
                    "case": "local Ray", "threads": 1 if not device.startswith("cuda") else "all", "workers": workers,
                    "frames": report.frames_rendered, "units": report.units_run, "wall_s": wall,
                    "fps": report.frames_rendered / wall, "ray_start_s": start_up, "actors_s": report.ray_start_seconds,
                    "unit_ms": 1e3 * statistics.mean(u.seconds for u in units),
                    "frame_in_process_ms": 1e3 * per_frame,
                    "overhead_ms": 1e3 * statistics.mean(overhead), "overhead_max_ms": 1e3 * max(overhead),
                    "engine_overhead_ms": 1e3 * statistics.mean(u.overhead_seconds for u in units),
                    "setup_ms": 1e3 * max(u.setup_seconds for u in units),
                    "retried": report.units_retried, "files": report.files_written,
                    "same_files": _pngs(out) == reference, "driver_ms": 1e3 * driver_seconds(out)})
                case_done(f"local Ray, {workers} worker(s)")
        finally:
            release_workers(ray)  # kept warm between the runs above only
        if not was_up:
            ray.shutdown()
    rows.sort(key=lambda r: (r["case"] == "local Ray", r["workers"] or 0))
    # on the same cores: one worker (one thread) against one thread in process, more against all threads
    in_proc = {r["threads"]: r["wall_s"] for r in rows if r["case"] == "in process"}
    summary = []
    for r in rows:
        if r["case"] == "local Ray":
            ratio = r["wall_s"] / in_proc[1 if r["workers"] == 1 else "all"]
            met = ratio <= GOAL_RAY_RATIO and r["overhead_ms"] < GOAL_OVERHEAD_MS and r["same_files"]
            summary.append({"workers": r["workers"], "against": f"in process, {1 if r['workers'] == 1 else 'all'} "
                            "thread(s)", "ratio": ratio, "overhead_ms": r["overhead_ms"],
                            "goals": "pass" if met else "fail"})
    columns = [
        ("case", "run", "s"), ("workers", "workers", ""), ("threads", "CPU threads", ""), ("frames", "frames", ""),
        ("units", "units", ""), ("wall_s", "wall [s]", ".2f"), ("fps", "frames/s", ".2f"),
        ("ray_start_s", "Ray start-up [s]", ".1f"), ("actors_s", "actors [s]", ".2f"), ("unit_ms", "unit [ms]", ".1f"),
        ("frame_in_process_ms", "its frame in process [ms]", ".1f"), ("overhead_ms", "overhead/unit [ms]", ".1f"),
        ("overhead_max_ms", "max overhead [ms]", ".1f"), ("engine_overhead_ms", "engine's overhead [ms]", ".1f"),
        ("setup_ms", "worker setup [ms]", ".0f"), ("driver_ms", "driver per unit [ms]", ".2f"),
        ("same_files", "files = in process", ""),
    ]
    summary_columns = [("workers", "Ray workers", ""), ("against", "against", "s"),
                       ("ratio", "wall / in-process wall", ".3f"), ("overhead_ms", "overhead/unit [ms]", ".1f"),
                       ("goals", f"goals (<= {GOAL_RAY_RATIO}x, < {GOAL_OVERHEAD_MS:g} ms, same files)", "s")]
    width, height = cfg["size"]
    settings = {"scene": "smoke", "command": "animate --views mono --orbit 360", "frames": frames,
                "size": f"{width}x{height}", "resolution": cfg["resolution"], "workers": cfg["workers"],
                "overrides": cfg["overrides"], "unit_frames": 1}
    return {"settings": settings, "rows": rows, "columns": columns, "summary": (summary, summary_columns)}


def run(quick: bool, device: str) -> dict[str, Any]:
    return run_config(QUICK if quick else FULL, device)


SUITE = Suite("batch", "volren batch's engine: a 64-frame turntable in process against local Ray, 1 and 2 workers",
              run)
