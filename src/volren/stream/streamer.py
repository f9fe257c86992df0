"""Bricks on demand (issue 41 item 3): a reader pool loads what a frame needs, in priority order, into the cache,
while the renderer draws what is resident; nothing a frame does waits on I/O.

- At open the coarsest level is read whole, synchronously, as the cache's floor: every brick has a resident ancestor
  from the first frame on, never a hole. Its bricks must fit the budget (else a one-line error).
- ``request(needs)`` (one call per frame, non-blocking) takes the frame's needs (`volren.stream.lod.frame_needs`),
  adds each one's not yet resident coarser ancestors (``progressive``: the picture sharpens a level at a time), and
  walks them in priority order (`volren.stream.lod`: visible, coarse before fine, near before far), admitting those
  that fit in the budget beside the floor; the admitted bricks are pinned, and those not resident replace the
  reader queue: a request of an older frame that this one still needs is reprioritised, one it no longer needs is
  dropped (a read already under way finishes and is cached unpinned). Needs past the budget are not read this frame:
  they are drawn from their ancestors, as a brick is that is still on its way.
- ``best_resident(level, brick)`` gives the finest resident brick among ``brick`` and its ancestors.
- ``wait(needs)`` (render, animate) requests and blocks until every admitted brick is resident or bad.
- A brick touching a bad chunk (`volren.stream.source`) is never read again; it is drawn from its ancestor. The
  warnings of bad chunks are emitted on the caller's thread (in `request`, `wait` and `stats`), one per chunk.

``stats()`` (call once per frame) says, since the previous call: bricks loaded and evicted, bytes read; and now:
bricks resident, pool bytes (resident brick bytes), and the levels used: how many of the last request's needs are
drawn from each level.
"""

from __future__ import annotations

import heapq
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from volren.data.grid import one_line
from volren.errors import VolrenError, VolrenWarning
from volren.stream.cache import BrickCache
from volren.stream.layout import BRICK, Brick, BrickKey
from volren.stream.lod import BrickNeed, need, need_keys
from volren.stream.source import PyramidSource

BRICK_BYTES = (BRICK + 1) ** 3 * 4
"""[bytes] of one resident brick: (B+1)^3 float32"""
WORKERS = 4
"""reader threads: I/O bound (a store's latency), so more than the cores help little and cost little"""


class BrickStreamer:
    """A reader pool, a priority queue and a brick cache over a `PyramidSource` (module docstring). Thread-safe; a
    context manager: `close` stops the readers (a read under way finishes first)."""

    def __init__(self, source: PyramidSource, *, memory_budget: float, workers: int = WORKERS,
                 progressive: bool = True) -> None:
        """``memory_budget`` [bytes] of resident bricks, the coarsest level's included; ``workers`` reader threads;
        ``progressive``: request the coarser ancestors of each need too (module docstring)."""
        self.source = source
        self.layout = source.layout
        self.progressive = progressive
        self.cache = BrickCache(int(memory_budget))
        floor = self.floor_keys()
        if len(floor) * BRICK_BYTES > self.cache.budget:
            raise VolrenError(f"{source.name}: the coarsest level's {len(floor)} bricks take "
                              f"{len(floor) * BRICK_BYTES / 2**20:.2f} MiB, over the memory budget of "
                              f"{self.cache.budget / 2**20:.2f} MiB; raise memory_budget (CLI: --memory-budget)")
        for key in floor:
            self.cache.put(key, source.read_brick(*key, warn=False), floor=True)  # the coarsest never reads None
        self._cond = threading.Condition()
        self._heap: list[tuple[tuple[int, int, float], int, BrickKey]] = []
        self._seq = 0
        self._in_flight: set[BrickKey] = set()
        self._bad: set[BrickKey] = set()
        self._admitted: list[BrickKey] = []
        self._needs = np.zeros((0, 4), np.int64)
        self._closed = False
        self._errors: list[str] = []
        self._last = {"loaded": 0, "evicted": 0, "bytes_read": 0}  # the first frame counts the floor's reads
        self.frame = 0
        # daemon threads: a streamer nobody closed (a volume dropped in a notebook) never holds the interpreter's exit
        self._readers = [threading.Thread(target=self._reader, name=f"volren-brick-reader-{i}", daemon=True)
                         for i in range(workers)]
        for thread in self._readers:
            thread.start()

    # ------------------------------------------------------------------ the readers

    def _reader(self) -> None:
        while True:
            with self._cond:
                while not self._heap and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                _, _, key = heapq.heappop(self._heap)
                self._in_flight.add(key)
            try:
                array = self.source.read_brick(*key, warn=False)
            except Exception as exc:  # the store went away, a timeout: drawn from the ancestor, said once
                array = None
                with self._cond:
                    self._errors.append(f"{self.source.name}: brick {key[1:]} of level {key[0]} cannot be read "
                                        f"({one_line(exc)}); it is drawn from level {key[0] + 1}")
            with self._cond:
                self._in_flight.discard(key)
                if array is None:
                    self._bad.add(key)
                elif not self.cache.put(key, array) and key in self._admitted:  # cannot happen: admitted bricks fit
                    self._admitted = [k for k in self._admitted if k != key]  # beside the floor; never wait on one
                self._cond.notify_all()

    def _warn(self) -> None:
        with self._cond:
            errors, self._errors = self._errors, []
        for message in self.source.pop_warnings() + errors:
            warnings.warn(message, VolrenWarning, stacklevel=3)

    # ------------------------------------------------------------------ the frame's side

    def request(self, needs: Iterable[BrickNeed]) -> None:
        """This frame's needs (module docstring); returns at once."""
        needs = list(needs)
        keys = need_keys(needs)
        bad = np.flatnonzero(~self._valid(keys))
        if len(bad):
            raise VolrenError(f"{self.source.name}: no brick {needs[bad[0]].brick} at level {needs[bad[0]].level}")
        wanted = self._wanted(needs, keys) if self.progressive else self._wanted_one_by_one(needs)
        room = self.room
        with self._cond:
            admitted = [w for w in wanted if w[1] not in self._bad][:room]
            self.frame += 1
            self._needs = keys
            self._admitted = [key for _, key in admitted]
            self.cache.pin(self._admitted)
            self._heap = []
            for priority, key in admitted:
                if key not in self._in_flight and key not in self.cache:
                    self._seq += 1
                    self._heap.append((priority, self._seq, key))
            heapq.heapify(self._heap)
            self._cond.notify_all()
        self._warn()

    def _valid(self, keys: np.ndarray) -> np.ndarray:
        """Whether each (level, bz, by, bx) row of ``keys`` is a brick of the pyramid."""
        ok = (keys[:, 0] >= 0) & (keys[:, 0] < self.layout.count)
        for level in np.unique(keys[ok, 0]):
            at = keys[:, 0] == level
            ok[at] = np.all((keys[at, 1:] >= 0) & (keys[at, 1:] < np.array(self.layout.bricks(int(level)))), axis=1)
        return ok

    def _parents(self, keys: np.ndarray) -> np.ndarray:
        """Each row's parent (`PyramidLayout.parent`), the rows all of one level below the coarsest."""
        level = int(keys[0, 0])
        out = np.empty_like(keys)
        out[:, 0] = level + 1
        out[:, 1:] = np.minimum(keys[:, 1:] // np.array(self.layout.factors[level]),
                                np.array(self.layout.bricks(level + 1)) - 1)
        return out

    def _wanted(self, needs: list[BrickNeed], keys: np.ndarray) -> list[tuple[tuple[int, int, float], BrickKey]]:
        """(priority, key) of every need and each of its ancestors below the coarsest, each key at the best priority
        of the needs under it (`need`: visible, then nearest), in priority order (then key, as `BrickNeed` sorts).
        At once (numpy): brick by brick, the 16 K ancestors of a 512^3 close-up's 8 K needs took 0.37 s a frame."""
        hidden = np.array([n.priority[0] for n in needs], np.int64)
        distance = np.array([n.priority[2] for n in needs], np.float64)
        parts: list[tuple[np.ndarray, np.ndarray]] = []  # (keys, index of their need) per level below the coarsest
        cur, at = keys, np.arange(len(keys))
        for level in range(self.layout.coarsest):  # finest first: the rows of a level climb to the next
            mine = cur[:, 0] == level
            if mine.any():
                parts.append((cur[mine], at[mine]))
                cur = np.concatenate([cur[~mine], self._parents(cur[mine])])
                at = np.concatenate([at[~mine], at[mine]])
        if not parts:
            return []
        key = np.concatenate([k for k, _ in parts])
        which = np.concatenate([i for _, i in parts])
        h, d = hidden[which], distance[which]
        order = np.lexsort((d, h, key[:, 3], key[:, 2], key[:, 1], key[:, 0]))  # per key, the best need first
        key, h, d = key[order], h[order], d[order]
        best = np.ones(len(key), bool)
        best[1:] = np.any(key[1:] != key[:-1], axis=1)
        key, h, d = key[best], h[best], d[best]
        order = np.lexsort((key[:, 3], key[:, 2], key[:, 1], key[:, 0], d, -key[:, 0], h))
        return [((hh, -k[0], dd), tuple(k)) for hh, dd, k in
                zip(h[order].tolist(), d[order].tolist(), key[order].tolist(), strict=True)]

    def _wanted_one_by_one(self, needs: list[BrickNeed]) -> list[tuple[tuple[int, int, float], BrickKey]]:
        """`_wanted` without ``progressive``: each need alone, or a bad one's nearest good ancestor."""
        wanted: dict[BrickKey, BrickNeed] = {}
        for n in needs:
            for level, brick in self.layout.ancestors(n.level, n.brick):
                if level == self.layout.coarsest:
                    break
                key = (level, *brick)
                candidate = need(key, n.visible, n.priority[2])  # type: ignore[arg-type]
                if key not in wanted or candidate < wanted[key]:
                    wanted[key] = candidate
                if key not in self._bad:
                    break
        return [(w.priority, w.key) for w in sorted(wanted.values())]

    @property
    def room(self) -> int:
        """Bricks the cache holds beside the floor: how many of a frame's needs can be admitted."""
        return max((self.cache.budget - len(self.floor_keys()) * BRICK_BYTES) // BRICK_BYTES, 0)

    def floor_keys(self) -> list[BrickKey]:
        """The coarsest level's bricks: resident from open on."""
        top = self.layout.coarsest
        return [(top, *b) for b in np.ndindex(*self.layout.bricks(top))]

    def resident(self, level: int, brick: Brick) -> bool:
        return (level, *brick) in self.cache

    def best_resident(self, level: int, brick: Brick) -> tuple[int, Brick, np.ndarray]:
        """(level, brick, voxels) of the finest resident brick among ``brick`` of ``level`` and its ancestors."""
        for lv, b in self.layout.ancestors(level, brick):
            array = self.cache.get((lv, *b))
            if array is not None:
                return lv, b, array
        raise AssertionError("the coarsest level is always resident")  # the floor is never evicted

    def best_resident_keys(self, keys: np.ndarray) -> np.ndarray:
        """`best_resident`'s key of each (level, bz, by, bx) row of ``keys`` (M, 4), at once (numpy), from a snapshot
        of the resident bricks: a reader may cache or evict one meanwhile."""
        resident = [np.zeros(self.layout.bricks(k), bool) for k in range(self.layout.count)]
        for key in self.cache.resident_keys():
            resident[key[0]][key[1:]] = True
        out = np.array(keys, np.int64).reshape(-1, 4)
        for level in range(self.layout.coarsest):  # finest first: a miss climbs to the next level
            at = np.flatnonzero(out[:, 0] == level)
            miss = at[~resident[level][out[at, 1], out[at, 2], out[at, 3]]]
            if len(miss):
                out[miss] = self._parents(out[miss])
        return out

    def resident_for(self, needs: Sequence[BrickNeed]) -> dict[BrickKey, np.ndarray]:
        """The finest resident brick for each of ``needs`` (`best_resident`) and its voxels, each brick once, in the
        order of the first need it serves; each marked used in the cache as `best_resident` marks it (the order of
        the last need it serves). At once (numpy): brick by brick, 8 K needs took 0.25 s a frame."""
        best = self.best_resident_keys(need_keys(needs))
        if not len(best):
            return {}
        _, first = np.unique(best, axis=0, return_index=True)
        _, last = np.unique(best[::-1], axis=0, return_index=True)
        arrays = {tuple(k): self.cache.get(tuple(k)) for k in best[np.sort(len(best) - 1 - last)].tolist()}
        if any(a is None for a in arrays.values()):  # evicted since the snapshot: brick by brick, as it was
            out: dict[BrickKey, np.ndarray] = {}
            for n in needs:
                level, brick, array = self.best_resident(n.level, n.brick)
                out.setdefault((level, *brick), array)
            return out
        return {k: arrays[k] for k in map(tuple, best[np.sort(first)].tolist())}  # type: ignore[misc]

    def queued(self) -> int:
        """Bricks waiting for a reader."""
        with self._cond:
            return len(self._heap)

    def reading(self) -> int:
        """Bricks a reader is reading now."""
        with self._cond:
            return len(self._in_flight)

    def pending(self) -> int:
        """Admitted bricks of the last request neither resident nor bad yet."""
        with self._cond:
            return sum(1 for k in self._admitted if k not in self._bad and k not in self.cache)

    def wait(self, needs: Iterable[BrickNeed] | None = None, *, progress: Callable[[int, int], Any] | None = None,
             timeout: float | None = None) -> bool:
        """Request ``needs`` (unless None: the last request's) and block until every admitted brick is resident or
        bad; ``progress(done, total)`` after each brick. True when all came, False at ``timeout`` [s]."""
        if needs is not None:
            self.request(needs)
        end = None if timeout is None else time.monotonic() + timeout
        total = len(self._admitted)
        last = -1
        with self._cond:
            while True:
                left = sum(1 for k in self._admitted if k not in self._bad and k not in self.cache)
                if progress is not None and total - left != last:
                    last = total - left
                    progress(last, total)
                if left == 0 or self._closed:
                    break
                remaining = None if end is None else end - time.monotonic()
                if remaining is not None and remaining <= 0:
                    break
                self._cond.wait(remaining)
        self._warn()
        return left == 0

    def stats(self) -> dict[str, Any]:
        """This frame's counters (module docstring)."""
        self._warn()
        levels = np.bincount(self.best_resident_keys(self._needs)[:, 0], minlength=self.layout.count).tolist()
        now = {"loaded": self.cache.loaded, "evicted": self.cache.evicted, "bytes_read": self.source.bytes_read}
        delta = {k: now[k] - self._last[k] for k in now}
        self._last = now
        return {"frame": self.frame, "bricks_resident": len(self.cache), "bricks_loaded": delta["loaded"],
                "bricks_evicted": delta["evicted"], "bytes_read": delta["bytes_read"], "levels_used": levels,
                "pool_bytes": self.cache.resident_bytes, "bricks_pending": self.pending(),
                "bricks_bad": len(self._bad)}

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._heap = []
            self._cond.notify_all()
        for thread in self._readers:
            thread.join()

    def __enter__(self) -> BrickStreamer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
