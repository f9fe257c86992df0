"""Device selection: ``auto | cpu | cuda | cuda:N``, with a clear error when CUDA is asked for and absent."""

from __future__ import annotations

import functools
import os
import re
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from typing import Any

import warp as wp

from volren.errors import VolrenError

_DEVICE_RE = re.compile(r"^(auto|cpu|cuda|cuda:\d+)$")


# volren never differentiates its kernels: skipping adjoint code halves compile times. No banner on every CLI call.
wp.config.enable_backward = False
wp.config.log_level = wp.LOG_WARNING

_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"
_ready = False


def init_warp() -> None:
    """Initialise Warp once. Its native library prints a warning on every start on machines without a CUDA driver;
    that expected line is dropped (``resolve_device`` reports a missing GPU when one is asked for), anything else
    the native code writes to stderr is passed on."""
    global _ready
    if _ready:
        return
    _ready = True
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as capture:
        os.dup2(capture.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        lines = capture.read().decode(errors="replace").splitlines()
    for line in lines:
        if _NO_DRIVER not in line:
            print(line, file=sys.stderr)


def resolve_device(name: str = "auto") -> str:
    """Map a user's device string to a Warp device name; ``auto`` picks the first CUDA device when there is one."""
    name = (name or "auto").strip().lower()
    if not _DEVICE_RE.match(name):
        raise VolrenError(f"unknown device '{name}': use auto, cpu, cuda or cuda:N")
    init_warp()
    cuda = wp.get_cuda_device_count()
    if name == "auto":
        return "cuda:0" if cuda > 0 else "cpu"
    if name == "cpu":
        return "cpu"
    if cuda == 0:
        raise VolrenError(f"device '{name}' requested but no CUDA GPU is available (use --device cpu or auto)")
    index = int(name.split(":")[1]) if ":" in name else 0
    if index >= cuda:
        raise VolrenError(f"device '{name}' requested but only {cuda} CUDA device(s) exist")
    return f"cuda:{index}"


def check_allocation(nbytes: int, device: str, what: str) -> None:
    """Refuse an allocation that cannot fit (host RAM for the CPU, free memory for a GPU) with a clear error, rather
    than failing inside Warp or swapping the machine to a halt."""
    if device.startswith("cuda"):
        free = wp.get_device(device).free_memory
    else:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    if nbytes > free:
        raise VolrenError(f"{what} needs {nbytes / 2**30:.1f} GiB but only {free / 2**30:.1f} GiB is free on {device}")


def synchronize(device: str) -> None:
    """Wait for all work on ``device``, so that wall-clock pass timings are real."""
    wp.synchronize_device(device)


def cpu_threads() -> int:
    """Threads for CPU launches: ``VOLREN_CPU_THREADS`` if set (benchmarks use 1 to measure one thread), else all."""
    value = os.environ.get("VOLREN_CPU_THREADS", "")
    return max(1, int(value)) if value.isdigit() else (os.cpu_count() or 1)


MAX_BANDS = 64
"""Rows of a counters array: one per concurrent CPU band, because Warp's CPU atomics are not atomic across threads."""
CUDA_COUNTER_ROWS = 4096
"""Rows of a counters array on CUDA, over which `counter_row` spreads a launch's threads."""


def counter_rows_for(device: str) -> int:
    return MAX_BANDS if device.startswith("cpu") else CUDA_COUNTER_ROWS


def launch_rows(
    kernel: Any,
    rows: int,
    cols: int,
    inputs: list[Any],
    device: str,
    counters: wp.array,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Launch a 2D kernel over ``rows x cols`` whose last two inputs are ``counter_rows`` (2D int64, read through
    `counter_row`) and ``row0: int`` (the launch's first row); ``counters`` is the frame's ``(rows, n)`` array
    (`counter_rows_for`): each CPU band adds into a row of its own, a CUDA launch into all of them.

    Warp's CPU backend runs one launch on one thread, but launches from different Python threads run concurrently
    (the native call releases the GIL; see DESIGN.md, measured 1.9x on 2 cores). On the CPU the rows are split into
    bands run by one thread per core; on CUDA it is a single launch. ``progress``, if given, is called with the
    number of rows each launch covered once it has been issued (a CPU launch has then finished).

    A CPU launch cannot be interrupted, so each band is issued as launches of `_band_step` rows, short enough that
    Ctrl-C stops a render within about `STOP_SECONDS` (the bands not yet started then do nothing).
    """
    if rows <= 0 or cols <= 0:
        return
    if not device.startswith("cpu"):  # every counter row at once: `counter_row` spreads the threads over them
        wp.launch(kernel, dim=(rows, cols), inputs=[*inputs, counters, 0], device=device)
        if progress is not None:
            progress(rows)
        return
    threads = cpu_threads()
    stop = threading.Event()
    key = (kernel, cols)

    def run(band: int, start: int, end: int) -> None:
        step = end - start
        while start < end and not stop.is_set():
            step = min(_band_step(key, end - start), 2 * step)  # doubling at most: rows differ in cost
            began = time.perf_counter()
            wp.launch(kernel, dim=(step, cols), inputs=[*inputs, counters[band : band + 1], start], device=device)
            # a cheap stretch (sky) only halves an expensive one's estimate: the next band may be all volume
            _row_seconds[key] = max((time.perf_counter() - began) / step, 0.5 * _row_seconds.get(key, 0.0))
            start += step
            if progress is not None:
                progress(step)

    if threads == 1 or rows < 2 * threads:
        run(0, 0, rows)  # on this thread: Ctrl-C lands between its launches
        return
    # More bands than threads balances uneven per-row cost (a volume covers only part of the image).
    bands = min(rows, threads * 4, MAX_BANDS)
    edges = [rows * b // bands for b in range(bands + 1)]
    pool = _band_pool(threads)
    futures = [pool.submit(run, b, edges[b], edges[b + 1]) for b in range(bands)]
    try:
        wait(futures, return_when=FIRST_EXCEPTION)  # Ctrl-C lands here, between the bands' launches
        failed = [f.exception() for f in futures if f.done() and f.exception() is not None]
        if failed:
            raise failed[0]
    except BaseException:  # Ctrl-C or a failed band (a serve render abandoned): the others stop after their launch
        stop.set()
        # and are waited for (at most one launch, about STOP_SECONDS): a caller that went on while a launch ran
        # could free what it reads (a bricked volume's page table, reached only through its volume struct) and crash
        wait(futures)
        raise


STOP_SECONDS = 0.25
"""[s] the longest CPU launch `launch_rows` aims for, so that Ctrl-C stops a render within about this long."""
_row_seconds: dict[tuple[Any, int], float] = {}
"""[s] per image row of the last launch of each (kernel, width): sizes the next launch of that kernel."""


def _band_step(key: tuple[Any, int], left: int) -> int:
    """Rows for the next launch of a band: all that are left for a kernel known to be fast (one launch per band, as
    before, costing nothing), else as many as take about `STOP_SECONDS`; a kernel not yet timed starts with one
    row. A launch costs ~0.2 ms on the CPU, so short launches are kept to kernels that take far longer than that."""
    per_row = _row_seconds.get(key)
    if per_row is None:
        return 1
    return max(1, min(left, int(STOP_SECONDS / max(per_row, 1e-9))))


@functools.cache
def _band_pool(threads: int) -> ThreadPoolExecutor:
    """One long-lived pool per thread count (a frame issues many launches: a light map per volume, a march per view)."""
    return ThreadPoolExecutor(max_workers=threads, thread_name_prefix="volren-band")
