"""What is resident (issue 41 item 3): bricks by (level, bz, by, bx), least recently used first out, within a byte
budget (``--memory-budget``, host memory).

Two kinds of brick are never evicted: the **floor** (the coarsest level, loaded at open, so that every brick has a
resident ancestor: never a hole) and the **pinned** bricks (the current frame's admitted needs: the streamer admits
no more than fit beside the floor, so a frame's own loads never evict each other). A brick that cannot fit even after
every other brick is evicted is refused (`put` returns False), so the resident bytes never exceed the budget.

Counters (cumulative; the streamer reports them per frame as differences): bricks loaded (admitted by `put`),
evicted, refused; resident bytes.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterable

import numpy as np

from volren.stream.layout import BrickKey


class BrickCache:
    """An LRU of brick arrays within ``budget`` bytes (module docstring). Thread-safe."""

    def __init__(self, budget: int) -> None:
        if budget <= 0:
            raise ValueError(f"a cache budget must be a positive number of bytes, got {budget}")
        self.budget = int(budget)
        self._lock = threading.Lock()
        self._bricks: OrderedDict[BrickKey, np.ndarray] = OrderedDict()
        self._floor: set[BrickKey] = set()
        self._pinned: frozenset[BrickKey] = frozenset()
        self.resident_bytes = 0
        self.loaded = 0
        self.evicted = 0
        self.refused = 0

    def __contains__(self, key: BrickKey) -> bool:
        with self._lock:
            return key in self._bricks

    def __len__(self) -> int:
        with self._lock:
            return len(self._bricks)

    def get(self, key: BrickKey) -> np.ndarray | None:
        """The brick, marked as just used, or None."""
        with self._lock:
            array = self._bricks.get(key)
            if array is not None:
                self._bricks.move_to_end(key)
            return array

    def pin(self, keys: Iterable[BrickKey]) -> None:
        """Replace the pinned set (the current frame's admitted needs)."""
        with self._lock:
            self._pinned = frozenset(keys)

    def put(self, key: BrickKey, array: np.ndarray, *, floor: bool = False) -> bool:
        """Make ``key`` resident, evicting the least recently used bricks that are neither floor nor pinned until it
        fits; False (nothing changed) where it cannot."""
        with self._lock:
            if key in self._bricks:
                self._bricks.move_to_end(key)
                return True
            need = self.resident_bytes + array.nbytes - self.budget
            victims = []
            if need > 0:
                for k, a in self._bricks.items():  # least recently used first
                    if k in self._floor or k in self._pinned:
                        continue
                    victims.append(k)
                    need -= a.nbytes
                    if need <= 0:
                        break
                if need > 0:
                    self.refused += 1
                    return False
            for k in victims:
                self.resident_bytes -= self._bricks.pop(k).nbytes
                self.evicted += 1
            self._bricks[key] = array
            self.resident_bytes += array.nbytes
            self.loaded += 1
            if floor:
                self._floor.add(key)
            return True

    def resident_keys(self) -> list[BrickKey]:
        """The resident bricks, least recently used first."""
        with self._lock:
            return list(self._bricks)
