"""The batch engine: ``volren render|animate ... --workers N`` (or ``--ray-address ADDR``), and `run_jobs` for
``volren batch``. Each job is a render or animate run as plain data (`volren.plan.spec.RenderSpec`); the driver
runs all its checks first (the plan's `plan_render`, once, before Ray starts), splits its frames into work units
(`Unit`: contiguous frames, every view of them: a stereo pair's eyes and a CACRM pair are never split), and hands the
units to Ray actors, each holding one renderer (`volren.distributed.worker.UnitWorker`: the plan's functions build
the job from the spec it receives, so the frames come from the same `RenderPlan.render` as in process). CUDA workers
ask ``num_gpus`` = ``--gpus-per-worker``, CPU workers one CPU (and launch on one thread).

Output: the files ``render``/``animate`` write, each written by the driver under a temporary name and moved in with
``os.replace``; ``batch.json`` (the manifest: the command, its settings, every complete unit with its files' SHA-256
and frames' stats) after each unit; ``stats.json`` (the frames' stats as ``render`` writes them, plus ``batch``: the
units, their times and workers) and animate's ``animation.mp4`` (from the frames' PNGs) when all units are done.
Re-running the same command resumes: a unit in the manifest whose files are all there, unchanged, is skipped. A
different command into that folder starts clean (the earlier run's files removed, as a plain ``render`` replaces
them; ``batch.json`` is one of them, so a plain render there later removes it too).

Faults: a worker that dies mid-unit (killed, out of memory) costs a retry of that unit only, on a fresh actor
(`MAX_RETRIES`); a unit failing with a `VolrenError` fails the job with that line, no retry; Ctrl-C kills the actors
and leaves only complete units and the manifest, and so does SIGTERM (`runtime.terminate_like_ctrl_c`). A unit is
written once: a result for a unit already complete is dropped. An address where nothing answers is refused before
--out is touched (`runtime.check_address`).

Temporal methods keep history across frames (`warmup_frames`): a unit starting at frame s renders the W frames
before s first, not written, unless its worker's renderer has just rendered frame s - 1 (then it continues, exactly
as in process); by default each worker gets one contiguous range. W is the smallest warm-up after which every frame
is within 60 dB PSNR of one in-process run (far under one 8-bit step), measured at 64x48 on a 48-frame animate
(orbit 30 degrees), frames 24-31 after W frames on a fresh renderer, worst frame [dB]
(``scripts/batch_warmup.py``):

* fog (``--scene dynamic``; the temporal blend weighs the new frame 0.1, and rejects stale history):
  W = 0: 56.2, 1: 56.4, 2: 58.4, 4: 62.6, 8: 82.0, 16: 91.0, so `FOG_WARMUP` = 4; the shadow grid's parity re-trace
  alone (``--no-temporal``) needs 1 frame, then it is exact.
* vpt ``--denoise ours --spp 2`` (Eq. 12 counts a class for at most 4 frames): W = 0: 40.3, 1: 51.1, 2: 57.7,
  4: 66.3, 8: 77.2, 16: 98.7, so `DENOISE_WARMUP` = 4 (svgf and wrls take the same).
* ``--gi sresir`` (lambda(n) = 1 / min(n + 1, 32); its seeds follow the frames a renderer has rendered, so after
  any warm-up the noise differs, not its level): W = 0: 43.3, 4: 53.1, 8: 56.2, 16: 61.1, so `GI_WARMUP` = 16
  (restir too; major only cycles its volumes, prt and brute precompute per scene: none).

Deterministic methods (dssrm, cmsrm, cacrm, reference without GI) are bit-identical to ``volren render`` in process;
stochastic ones (jitter, vpt) use the same per-frame seeds (``frame=i``), so they are too.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from volren.distributed.runtime import check_address, terminate_like_ctrl_c
from volren.distributed.worker import Unit, UnitWorker
from volren.errors import VolrenError
from volren.plan.spec import RenderSpec

MANIFEST = "batch.json"
"""the manifest's name in --out (`volren.output.RUN_FILE` matches it: a new run replaces it)"""
MANIFEST_VERSION = 2
"""2: the command is the run's `RenderSpec` (1 held its command line)"""
MAX_RETRIES = 3
"""retries of one unit whose worker died, before the job fails"""
PART = ".volren-part-"
"""the temporary names files are written under before ``os.replace`` moves them in"""
FOG_WARMUP = 4
DENOISE_WARMUP = 4
GI_WARMUP = 16
MANIFEST_EVERY_S = 1.0
"""[s] the manifest is written at most this often while units complete, and always at the end or on a stop"""
_POOL: list[tuple[Any, int, tuple[bool, float, str]]] = []
"""idle actors of this process's Ray connection (actor, pid, (resources, Ray job)), kept warm after a run for the
next one (a bench's repeats, the tests); killed with the connection, on a failure, or when the next run needs fewer"""
IGNORED_SETTINGS = ("workers", "ray_address", "gpus_per_worker", "max_minutes")
"""what may differ between a run and the run it resumes: where and how long, not what is rendered"""


@dataclass(frozen=True)
class Job:
    spec: RenderSpec
    """a ``volren render|animate`` run, its --out incl. (`RenderSpec.parse` makes one of a command line)"""

    @property
    def out(self) -> Path:
        return Path(self.spec.out)


@dataclass(frozen=True)
class UnitReport:
    job: int
    unit: str
    start: int
    stop: int
    warmup: int
    worker: str
    """host:pid of the actor that completed it"""
    attempts: int
    """1, plus one per worker that died running it"""
    seconds: float
    """dispatch to its files written, in the driver"""
    setup_seconds: float
    """the worker building the job's scene and renderer (0 when it held them)"""
    warmup_seconds: float
    render_seconds: float
    """its frames rendered and encoded, in the worker"""

    @property
    def overhead_seconds(self) -> float:
        """what the unit cost beyond the worker's setup, warm-up and frames: scheduling, transfer, writing"""
        return self.seconds - self.setup_seconds - self.warmup_seconds - self.render_seconds


@dataclass(frozen=True)
class BatchReport:
    units: tuple[UnitReport, ...]
    """the units run by this call, in completion order (skipped ones are not here)"""
    units_skipped: int
    """complete in the manifest of an earlier run, files unchanged"""
    units_retried: int
    """retries after a worker died"""
    files_written: int
    """unit files moved into --out (each unit's once)"""
    workers: int
    ray_start_seconds: float
    """connecting to (or starting) Ray and starting the actors"""
    wall_seconds: float

    @property
    def units_run(self) -> int:
        return len(self.units)

    @property
    def frames_rendered(self) -> int:
        return sum(u.stop - u.start for u in self.units)


def warmup_frames(config: Any, volumes: int) -> int:
    """Frames a unit starting mid-sequence renders before its first (module docstring); 0: the method keeps no
    history across frames."""
    if hasattr(config, "temporal_weight"):  # fog
        return FOG_WARMUP if config.temporal else int(config.sharing == "grid")
    if getattr(config, "denoise", "none") != "none":
        return DENOISE_WARMUP
    gi = getattr(config, "gi", None)
    if gi is not None and gi.method in ("sresir", "restir", "major"):
        # major keeps nothing but the volumes' round-robin updates (--gi-volumes under the count)
        return GI_WARMUP if gi.method != "major" else int(min(gi.volumes_per_frame, volumes) < volumes) * volumes
    return 0


def settings_of(args: argparse.Namespace) -> dict[str, str]:
    """What a run renders, as the manifest compares it (not `IGNORED_SETTINGS`)."""
    return {k: str(v) for k, v in sorted(vars(args).items()) if k not in IGNORED_SETTINGS}


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_atomically(path: Path, data: bytes) -> None:
    """``data`` at ``path``, under a temporary name first: a reader (or a Ctrl-C) never meets half a file."""
    fd, tmp = tempfile.mkstemp(prefix=f"{PART}{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@dataclass
class JobState:
    """One job in the driver: its plan (checks done), units, and manifest."""

    job: Job
    plan: Any
    units: list[Unit]
    settings: dict[str, str]
    manifest: dict[str, Any] = field(default_factory=dict)
    saved: float = -math.inf
    """[s, perf_counter] when the manifest was last written"""

    @property
    def out(self) -> Path:
        return self.plan.args.out

    def complete(self, unit: Unit) -> bool:
        entry = self.manifest["units"].get(unit.key)
        return entry is not None and all((self.out / n).is_file() and sha256(self.out / n) == h
                                         for n, h in entry["files"].items())

    def save_manifest(self, *, every: float = 0.0) -> None:
        """Write the manifest, or with ``every`` only if the last write is that many seconds old: it is rewritten
        whole, so writing it after each of F units would cost O(F^2) (0.24 ms per recorded unit). A driver killed
        outright loses at most ``every`` seconds of records: those units render again, their files replaced."""
        if every and time.perf_counter() - self.saved < every:
            return
        write_atomically(self.out / MANIFEST, (json.dumps(self.manifest, indent=1) + "\n").encode())
        self.saved = time.perf_counter()

    def open_output(self) -> None:
        """Resume the manifest of the same command, or start clean: the earlier run's files removed."""
        from volren.output import is_run_file

        out = self.out
        if out.exists() and not out.is_dir():
            raise VolrenError(f"--out '{out}' is a file, not a folder")
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise VolrenError(f"cannot create output folder '{out}': {exc.strerror}") from exc
        for p in out.glob(f"{PART}*"):  # left by a driver killed mid-write
            p.unlink()
        try:
            old = json.loads((out / MANIFEST).read_text())
        except (OSError, ValueError):
            old = None
        if old is not None and old.get("version") == MANIFEST_VERSION and old.get("settings") == self.settings:
            self.manifest = old
            return
        if old is not None:
            print(f"volren: --out {out}: its {MANIFEST} is of another command: starting clean", file=sys.stderr)
        for p in out.iterdir():
            if is_run_file(p):
                p.unlink()
        self.manifest = {"version": MANIFEST_VERSION, "command": self.job.spec.line,
                         "spec": self.job.spec.to_json(), "settings": self.settings, "units": {}}

    def commit(self, unit: Unit, result: dict[str, Any], report: UnitReport) -> int:
        """Write a finished unit's files and record it; returns the files written (none for a unit already
        complete: a retried unit is written once)."""
        if unit.key in self.manifest["units"]:
            return 0
        for name, data in result["files"].items():
            write_atomically(self.out / name, data)
        self.manifest["units"][unit.key] = {
            "frames": [unit.start, unit.stop], "warmup": unit.warmup, "worker": report.worker,
            "attempts": report.attempts, "seconds": round(report.seconds, 4),
            "render_seconds": round(report.render_seconds, 4), "scene": result["scene"],
            "files": {name: hashlib.sha256(data).hexdigest() for name, data in result["files"].items()},
            "stats": result["stats"]}
        self.save_manifest(every=MANIFEST_EVERY_S)
        return len(result["files"])

    def prune(self) -> None:
        """After a Ctrl-C or a failure: only complete units' files stay (and the manifest)."""
        from volren.output import is_run_file

        if self.manifest:
            self.save_manifest()
        kept = {n for entry in self.manifest.get("units", {}).values() for n in entry["files"]} | {MANIFEST}
        for p in self.out.iterdir():
            if p.name.startswith(PART) or (is_run_file(p) and p.name not in kept):
                p.unlink(missing_ok=True)

    def finish(self, extra: dict[str, Any]) -> list[Path]:
        """stats.json (and animate's animation.mp4) once every unit is complete; returns the files of the run."""
        from volren.plan import frame_prefix

        entries = sorted(self.manifest["units"].values(), key=lambda e: e["frames"][0])
        frames = [s for e in entries for s in e["stats"]]
        plan, out = self.plan, self.out
        files = [out / n for e in entries for n in e["files"]]
        if plan.sequence is not None:
            import imageio.v3 as iio

            from volren.animate import write_mp4

            shown = ["view0.png", "stereo.png"][len(plan.views) - 1] if len(plan.views) <= 2 else "contact.png"
            movie = [iio.imread(out / f"{frame_prefix(plan.args, i)}{shown}") for i in range(plan.args.frames)]
            with tempfile.TemporaryDirectory(prefix=PART, dir=out) as tmp:
                os.replace(write_mp4(Path(tmp) / "animation.mp4", movie, plan.sequence.fps), out / "animation.mp4")
            files.append(out / "animation.mp4")
        batch = {"units": [{"unit": k, **{n: e[n] for n in ("frames", "warmup", "worker", "attempts", "seconds",
                                                           "render_seconds")}}
                           for k, e in sorted(self.manifest["units"].items(), key=lambda kv: kv[1]["frames"][0])]}
        doc = {"scene": entries[0]["scene"], "command": self.manifest["command"], **plan.value_mapping,
               "frames": frames, "batch": batch | extra}
        write_atomically(out / "stats.json", (json.dumps(doc, indent=2, default=str) + "\n").encode())
        return files


def plan_job(index: int, job: Job, workers: int | None, unit_frames: int | None) -> JobState:
    """A job's checks (the plan's, in the driver, before any work) and its units."""
    from volren.plan import plan_render

    if job.spec.command not in ("render", "animate"):
        raise VolrenError(f"a batch job is a render or animate run, got '{job.spec.command}'")
    args = job.spec.namespace()
    plan = plan_render(args, args.method)
    volumes = len(plan.scene.volumes)
    warmup = warmup_frames(plan.renderer.config, volumes)
    frames = args.frames
    # temporal methods: one contiguous range per worker by default (each warm-up paid once)
    size = unit_frames or (math.ceil(frames / max(workers or 1, 1)) if warmup else 1)
    if size < 1:
        raise VolrenError(f"unit frames must be >= 1, got {size}")
    units = [Unit(index, s, min(s + size, frames), min(warmup, s), warmup > 0) for s in range(0, frames, size)]
    return JobState(job, plan, units, settings_of(args))


def _actor_options(cuda: bool, gpus_per_worker: float) -> dict[str, Any]:
    return {"num_cpus": 0, "num_gpus": gpus_per_worker} if cuda else {"num_cpus": 1, "num_gpus": 0}


def release_workers(ray: Any) -> None:
    """Stop the idle workers that ``keep_workers`` kept: they hold their share of the cluster meanwhile."""
    for actor, _, _ in _POOL:
        ray.kill(actor, no_restart=True)
    _POOL.clear()


def run_jobs(jobs: Sequence[Job], *, workers: int | None, address: str | None, flag: str,
             gpus_per_worker: float = 1.0, unit_frames: int | None = None,
             on_dispatch: Callable[[Unit, int], None] | None = None, keep_workers: bool = False,
             planned: Sequence[JobState] | None = None) -> BatchReport:
    """Run ``jobs`` on ``workers`` Ray actors (a local Ray when ``address`` is None; default on a cluster: one per
    GPU or CPU it has); ``flag`` names the option in errors. ``unit_frames``: frames per unit (default: 1, or for a
    temporal method one range per worker). ``on_dispatch(unit, pid)`` is called as a unit goes to the actor with
    that process id (the tests' fault injection). ``keep_workers``: keep the idle actors, warm, for the next call in
    this process (`volren bench batch`); otherwise they are stopped at the end. ``planned``: the jobs' `plan_job`
    states when the caller has them (`volren batch` planned them checking the job file). Returns what ran
    (`BatchReport`)."""
    if workers is not None and workers < 1:
        raise VolrenError(f"{flag}: the workers must be >= 1, got {workers}")
    if not 0 < gpus_per_worker <= 1:
        raise VolrenError(f"--gpus-per-worker must lie in (0, 1], got {gpus_per_worker:g}")
    if planned is not None and [s.job for s in planned] != list(jobs):  # else ``jobs`` would be silently ignored
        raise ValueError(f"run_jobs: the {len(planned)} planned state(s) are not those of the {len(jobs)} job(s)")
    start = time.perf_counter()
    states = list(planned) if planned is not None else [plan_job(i, job, workers, unit_frames)
                                                          for i, job in enumerate(jobs)]
    cuda = any(s.plan.renderer.device.startswith("cuda") for s in states)
    terminate_like_ctrl_c()  # from here SIGTERM stops the run as Ctrl-C does: complete units kept
    if address is not None:  # an address where nothing answers is refused before --out is touched
        check_address(address)
    for s in states:
        s.open_output()
    queue = deque(u for s in states for u in s.units if not s.complete(u))
    for u in queue:  # a unit whose files changed since is no longer complete
        states[u.job].manifest["units"].pop(u.key, None)
    skipped = sum(len(s.units) for s in states) - len(queue)
    reports: list[UnitReport] = []
    counts = {"retried": 0, "files": 0, "workers": 0}
    ray_start = 0.0
    try:
        if queue:
            ray_start = _run_units(states, queue, reports, counts, workers, address, flag, cuda, gpus_per_worker,
                                   on_dispatch, keep_workers)
    except BaseException:
        for s in states:
            s.prune()
        raise
    for s in states:
        s.save_manifest()
        s.finish({"workers": counts["workers"], "ray_start_seconds": round(ray_start, 3)})
    return BatchReport(tuple(reports), skipped, counts["retried"], counts["files"], counts["workers"], ray_start,
                       time.perf_counter() - start)


def _run_units(states: list[JobState], queue: deque[Unit], reports: list[UnitReport], counts: dict[str, int],
               workers: int | None, address: str | None, flag: str, cuda: bool, gpus_per_worker: float,
               on_dispatch: Callable[[Unit, int], None] | None, keep_workers: bool) -> float:
    """Hand the queued units to the actors until all are written; returns Ray's start-up seconds."""
    from volren.distributed.runtime import connect
    from volren.progress import progress

    t0 = time.perf_counter()
    ray = connect(flag, address, num_cpus=None if address or cuda else workers)
    kind = "GPU" if cuda else "CPU"
    have = ray.cluster_resources().get(kind, 0)
    share = gpus_per_worker if cuda else 1
    if workers is None:
        workers = max(1, int(have / share + 1e-9))
    elif workers * share > have + 1e-9:  # the actors past it would wait for resources that never come
        raise VolrenError(f"{flag}: {workers} worker(s) need {workers * share:g} {kind}(s), Ray has {have:g}: give "
                          f"fewer --workers{' or a smaller --gpus-per-worker' if cuda else ''}")
    workers = min(workers, len(queue))
    remote = ray.remote(max_restarts=0, max_task_retries=0)(UnitWorker).options(
        **_actor_options(cuda, gpus_per_worker))
    threads = None if cuda else 1

    def spawn() -> tuple[Any, int]:
        actor = remote.remote(threads)
        return actor, ray.get(actor.pid.remote())

    context = ray.get_runtime_context()  # the job id alone repeats (01000000) in each new connection's cluster
    key = (cuda, gpus_per_worker, (context.get_node_id(), context.get_job_id()))
    kept = [(a, pid) for a, pid, k in _POOL if k == key][:workers]
    for a, _, k in _POOL:  # the rest would hold resources a new actor may need
        if k[2] == key[2] and a not in dict(kept):
            ray.kill(a, no_restart=True)
    _POOL.clear()
    started = [remote.remote(threads) for _ in range(workers - len(kept))]
    pids = dict(kept) | dict(zip(started, ray.get([a.pid.remote() for a in started]), strict=True))
    actors = list(pids)
    counts["workers"] = workers
    ray_start = time.perf_counter() - t0
    idle = list(actors)
    last: dict[Any, tuple[int, int]] = {}  # actor -> (job, next frame) its renderer leads up to
    pending: dict[Any, tuple[Any, Unit, float, int]] = {}
    attempts: dict[tuple[int, str], int] = {}
    per_worker: dict[str, list[float]] = {}
    total = sum(u.frames for u in queue)
    label = f"{len(queue)} unit(s) on {workers} worker(s)"
    try:
        with progress(label, total, "frames", always=True) as advance:
            while queue or pending:
                while idle and queue:
                    actor = idle.pop()
                    # a temporal unit that continues where this actor's renderer stopped skips its warm-up
                    unit = next((u for u in queue if (u.job, u.start) == last.get(actor)), queue[0])
                    queue.remove(unit)
                    ref = actor.run.remote(states[unit.job].job.spec, unit, os.getcwd())
                    pending[ref] = (actor, unit, time.perf_counter(), attempts.get((unit.job, unit.key), 0) + 1)
                    if on_dispatch is not None:
                        on_dispatch(unit, pids[actor])
                done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                for ref in done:
                    actor, unit, sent, attempt = pending.pop(ref)
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayActorError:  # the worker died: a fresh one retries this unit only
                        if attempt > MAX_RETRIES:
                            raise VolrenError(f"{unit.key} of job {unit.job}: {attempt} workers died running "
                                              "it") from None
                        attempts[(unit.job, unit.key)] = attempt
                        counts["retried"] += 1
                        queue.appendleft(unit)
                        fresh, pid = spawn()
                        pids[fresh] = pid
                        idle.append(fresh)
                        continue
                    except ray.exceptions.RayTaskError as exc:
                        cause = getattr(exc, "cause", None)
                        if isinstance(cause, VolrenError):
                            raise VolrenError(str(cause)) from None
                        raise
                    report = UnitReport(unit.job, unit.key, unit.start, unit.stop, unit.warmup, result["worker"],
                                        attempt, time.perf_counter() - sent, result["setup_seconds"],
                                        result["warmup_seconds"], result["render_seconds"])
                    written = states[unit.job].commit(unit, result, report)
                    report = replace(report, seconds=time.perf_counter() - sent)  # its files written too
                    counts["files"] += written
                    reports.append(report)
                    per_worker.setdefault(report.worker, []).extend([unit.frames, result["busy_seconds"]])
                    last[actor] = (unit.job, unit.stop)
                    idle.append(actor)
                    advance(unit.frames)
    except BaseException:
        for actor in pids:
            ray.kill(actor, no_restart=True)
        raise
    if keep_workers:  # warm for the next call in this process; meanwhile they hold their CPUs or GPUs of the cluster
        _POOL.extend((actor, pids[actor], key) for actor in idle)
    else:  # released: an idle actor's resources would keep another user's actors (a shard, say) waiting
        for actor in idle:
            ray.kill(actor, no_restart=True)
    rates = [f"{w} {sum(v[::2]) / max(sum(v[1::2]), 1e-9):.2f} frames/s" for w, v in per_worker.items()]
    print(f"  per worker: {', '.join(rates)}", file=sys.stderr)
    return ray_start


def run_command_on_ray(args: argparse.Namespace, command: str) -> int:
    """``volren render|animate ... --workers N | --ray-address ADDR``: the same run on Ray (`run_jobs`); ``command``
    the command line as given, for stats.json."""
    from volren.distributed.runtime import import_ray

    flag = "--workers" if args.workers is not None else "--ray-address"
    if args.gpus_per_worker is not None:
        from volren.device import resolve_device

        if not resolve_device(args.device).startswith("cuda"):
            raise VolrenError("--gpus-per-worker shares a GPU among workers: the workers render on the CPU here")
    import_ray(flag, local=not args.ray_address)  # missing: one line before the checks' seconds of work
    report = run_jobs([Job(RenderSpec.from_args(args, command))], workers=args.workers, address=args.ray_address,
                      flag=flag, gpus_per_worker=args.gpus_per_worker or 1.0)
    doc = json.loads((Path(args.out) / "stats.json").read_text())
    last = doc["frames"][-1]
    print(f"{args.method} on {last['device']}: {len(doc['frames'])} frame(s) of '{doc['scene']}' in "
          f"{report.wall_seconds:.2f} s on {report.workers} worker(s) (Ray start-up {report.ray_start_seconds:.1f} "
          f"s): {report.units_run} unit(s) run, {report.units_skipped} skipped, {report.units_retried} retried")
    print("  work (last frame): " + ", ".join(f"{k} {v:,}" for k, v in last["counters"].items()))
    print(f"  wrote {args.out}: {len(list(Path(args.out).iterdir()))} files ({MANIFEST}, stats.json)")
    return 0

