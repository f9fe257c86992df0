"""The batch engine's worker: one per Ray actor, holding one renderer (scene uploaded once, kernels loaded, light
maps cached) for the job it last ran. It builds everything from the job's `RenderSpec` (plain data: no command
line is parsed here) with the plan's functions (`volren.plan.plan_render`), renders a unit's warm-up frames and then
its frames through the same `RenderPlan.render` as ``volren render``, and returns each file's bytes: the driver
alone writes into ``--out`` (`volren.distributed.engine`), so a worker killed mid-unit leaves nothing behind and
needs no shared file system.
Imports no Ray: the engine wraps this class in ``ray.remote``."""

from __future__ import annotations

import json
import os
import socket
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class Unit:
    """A work unit: frames ``start``..``stop - 1`` of job ``job``, every view (a stereo pair's eyes, a CACRM pair, a
    rig's views stay together), after ``warmup`` frames before ``start`` rendered and not written (temporal
    methods' history, `volren.distributed.engine.warmup_frames`)."""

    job: int
    start: int
    stop: int
    warmup: int = 0
    temporal: bool = False
    """the method keeps history across frames: a renderer whose history leads elsewhere is built afresh"""

    @property
    def key(self) -> str:
        """The unit's name in the manifest: its frame range, so a re-run with other chunks still finds its own."""
        return f"frames {self.start}-{self.stop - 1}"

    @property
    def frames(self) -> int:
        return self.stop - self.start


class UnitWorker:
    """Renders units. ``threads``: CPU threads of its launches (``VOLREN_CPU_THREADS``; the one CPU it asked)."""

    def __init__(self, threads: int | None = None) -> None:
        if threads is not None:
            os.environ["VOLREN_CPU_THREADS"] = str(threads)
        self._spec: Any = None
        self._plan: Any = None
        self._next = -1
        """the frame the renderer's history leads up to: a unit starting there needs no warm-up"""

    def pid(self) -> int:
        return os.getpid()

    def _planned(self, spec: Any, fresh: bool) -> tuple[Any, float]:
        """The job's `RenderPlan` (kept while the job stays the same, unless ``fresh``) and the seconds it took."""
        start = time.perf_counter()
        if fresh or spec != self._spec:
            from volren.plan import plan_render

            args = spec.namespace(max_minutes=0)  # the driver ran the estimate
            self._plan, self._spec, self._next = plan_render(args, args.method), spec, -1
        return self._plan, time.perf_counter() - start

    def run(self, spec: Any, unit: Unit, cwd: str | None = None) -> dict[str, Any]:
        """Render ``unit`` of the job ``spec`` (a `volren.plan.spec.RenderSpec`): its files' bytes, its frames'
        stats and where the time went. ``cwd``: the driver's folder, which relative paths (``--volume``, ``--mesh``)
        name, where this machine has it."""
        from volren.plan import write_plan_frame

        start = time.perf_counter()
        if cwd is not None and os.path.isdir(cwd):
            os.chdir(cwd)
        continues = spec == self._spec and self._next == unit.start
        # a temporal renderer whose history belongs elsewhere starts afresh, as the single-machine run did
        plan, setup = self._planned(spec, fresh=unit.temporal and not continues)
        first = unit.start if continues else unit.start - unit.warmup
        for i in range(first, unit.start):
            plan.render(i)
        warm = time.perf_counter() - start - setup
        files: dict[str, bytes] = {}
        stats: list[dict[str, Any]] = []
        with tempfile.TemporaryDirectory(prefix="volren-unit-") as tmp:
            for i in range(unit.start, unit.stop):
                frame = plan.render(i)
                for path in write_plan_frame(plan, frame, Path(tmp)):
                    files[path.name] = path.read_bytes()
                # as stats.json stores it (numbers numpy gave as text)
                stats.append(json.loads(json.dumps({"index": frame.index, **frame.stats.to_dict()}, default=str)))
        self._next = unit.stop
        busy = time.perf_counter() - start
        return {"files": files, "stats": stats, "scene": plan.scene.name, "worker": f"{socket.gethostname()}:"
                f"{os.getpid()}", "setup_seconds": setup, "warmup_seconds": warm,
                "render_seconds": busy - setup - warm, "busy_seconds": busy}
