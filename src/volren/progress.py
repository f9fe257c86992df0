"""Progress of long runs on stderr (renders, ``animate``, bench suites, scripts), so slow can be told from stuck.

On an interactive terminal a rich bar with an ETA; otherwise (CI, pipes, logs) a plain line at every 10% of the
work. A run that may be short (one frame) prints nothing for its first `QUIET_SECONDS` of work, then a line saying
where it is and one at every 10%; a run of many frames prints the ten lines whatever its length. Light to
import: rich only when a bar is drawn.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

QUIET_SECONDS = 2.0
"""[s] a run that may be short prints no plain progress line before this: a quick render stays one line of output"""
STEPS = 10
"""plain lines per run: one at every 10% of the work"""


def _line(label: str, done: int, total: int, unit: str, elapsed: float) -> str:
    left = elapsed * (total - done) / done if done else float("nan")
    return f"volren: {label}: {100 * done // total}% ({done}/{total} {unit}), {elapsed:.0f} s, about {left:.0f} s left"


@contextmanager
def progress(label: str, total: int, unit: str = "rows", *, always: bool = False) -> Iterator[Callable[[int], None]]:
    """Yield ``advance(n)``: ``n`` more of ``total`` units of work are done (thread-safe: render bands call it).
    ``always``: print the plain lines even in a run shorter than `QUIET_SECONDS` (a run of several frames)."""
    total = max(total, 1)
    if sys.stderr.isatty() and not os.environ.get("CI"):
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        columns = (TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), TimeRemainingColumn())
        with Progress(*columns, transient=True) as bar:
            task = bar.add_task(label, total=total)
            yield lambda n: bar.advance(task, n)
        return
    start = time.perf_counter()
    lock = threading.Lock()
    state = {"done": 0, "shown": -1 if not always else 0, "first": 0.0}  # units done; the last step (of STEPS)
    # printed, -1: none yet (a single render says it is running once the quiet time is over, then every 10%)

    def advance(n: int) -> None:
        with lock:
            now = time.perf_counter()
            state["first"] = state["first"] or now  # quiet counted from here: a cold kernel compile is no work
            done = state["done"] = min(total, state["done"] + n)  # a channel's renderers each report the rows
            step = done * STEPS // total
            if step > state["shown"] and (always or now - state["first"] >= QUIET_SECONDS):
                state["shown"] = step
                print(_line(label, done, total, unit, now - start), file=sys.stderr, flush=True)

    yield advance


def reporter(label: str, unit: str) -> Callable[[int, int], None]:
    """A ``report(done, total)`` for work whose total is known only when it starts (a streamed volume's bricks,
    `volren.render.streaming`): plain lines at every 10% once it has run `QUIET_SECONDS`, as `progress` prints."""
    state = {"start": 0.0, "shown": -1}

    def report(done: int, total: int) -> None:
        now = time.perf_counter()
        if done == 0 or not state["start"]:
            state["start"], state["shown"] = state["start"] or now, -1
        step = done * STEPS // max(total, 1)
        if total and step > state["shown"] and now - state["start"] >= QUIET_SECONDS:
            state["shown"] = step
            print(_line(label, done, total, unit, now - state["start"]), file=sys.stderr, flush=True)

    return report


_case_hook: list[Callable[[str], None]] = []
"""the innermost `cases` context's report function (bench suites report each measured case through `case_done`)"""


@contextmanager
def cases(label: str) -> Iterator[None]:
    """Steps whose number is not known up front (a bench suite's cases): a plain line on stderr as each ends, saying
    how many are done and the time so far; `case_done` reports one."""
    start = time.perf_counter()
    done = [0]

    def report(what: str) -> None:
        done[0] += 1
        print(f"volren: {label}: case {done[0]} done ({what}), {time.perf_counter() - start:.0f} s", file=sys.stderr,
              flush=True)

    _case_hook.append(report)
    try:
        yield
    finally:
        _case_hook.pop()


def case_done(what: str) -> None:
    """One case of the running `cases` is done (nothing outside one)."""
    if _case_hook:
        _case_hook[-1](what)
