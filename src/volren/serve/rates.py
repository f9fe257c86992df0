"""Per-client rate limits of `volren serve` (issue 44 item 4): token buckets for settings changes and connections,
a sliding count of a socket's refused messages. One neighbour's flood then costs the others a bounded share: before,
460 settings changes from one client cut four others to 0.78 fps, malformed JSON to 2.15 fps, 100 clients'
connect/disconnect churn to 3.5 fps."""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field

TICK_MS = 50.0
"""[ms] the tick time the server aims for when several viewers share it (`volren.serve.viewers.Limits.tick_ms`): 20
frames a second (here, not in viewers.py: the CLI's help shows it without importing numpy)"""
SETTINGS_PER_S, SETTINGS_BURST = 4.0, 4
"""a client's settings changes applied: a burst of 4, then 4 a second; the rest coalesce (the newest value of each
setting waits, `RenderLoop.offer`), so a dragged light still ends where the user let go"""
CONNECTS_PER_S, CONNECT_BURST = 2.0, 32
"""WebSocket upgrades per client address: a burst of 32 (every viewer slot twice over: a page reloaded in a few
tabs, a VR pair reconnecting), then 2 a second; past it the upgrade is answered 429 before any work"""
MESSAGES_PER_S, MESSAGE_BURST = 200.0, 400
"""messages a socket may send: a burst of 400, then 200 a second (a page sends a camera per pointer event, ~60-120 a
second, and an ack per frame); past it the socket is closed (1008) before the message is parsed: 1.6 million valid
settings messages in 6 s from one socket had cut four viewers from 10 to 2 fps by parsing alone"""
ERROR_LIMIT, ERROR_WINDOW_S = 50, 10.0
"""a socket with more than 50 refused messages within 10 s is closed (1008): a page makes none; each costs a parse
and a reply on the event loop every viewer shares"""
ADDRESSES_KEPT = 4096
"""connection buckets remembered at once (least recently used dropped first): memory stays bounded whatever the
number of addresses (IPv6 gives a client many)"""


@dataclass
class TokenBucket:
    """``burst`` tokens, refilled at ``rate`` a second; `take` spends one if there is one."""

    rate: float
    burst: int
    tokens: float = -1.0
    at: float = field(default_factory=time.monotonic)

    def __post_init__(self) -> None:
        if self.tokens < 0:
            self.tokens = float(self.burst)

    def _refill(self, now: float) -> None:
        self.tokens = min(float(self.burst), self.tokens + (now - self.at) * self.rate)
        self.at = now

    def take(self, now: float | None = None) -> bool:
        self._refill(time.monotonic() if now is None else now)
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    def wait(self, now: float | None = None) -> float:
        """[s] until a token is there (0: one is now)."""
        self._refill(time.monotonic() if now is None else now)
        return max(0.0, (1.0 - self.tokens) / self.rate)


class ErrorCount:
    """A socket's refused messages within the last ERROR_WINDOW_S; `add` says whether it is past ERROR_LIMIT."""

    def __init__(self, limit: int = ERROR_LIMIT, window: float = ERROR_WINDOW_S) -> None:
        self.limit, self.window = limit, window
        self.times: deque[float] = deque(maxlen=limit + 1)

    def add(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        self.times.append(now)
        return len(self.times) > self.limit and now - self.times[0] <= self.window


class ConnectRates:
    """One `TokenBucket` per client address, at most ADDRESSES_KEPT of them (least recently used forgotten: a
    forgotten address starts with a full bucket, so the bound costs no one a refusal they would not get)."""

    def __init__(self, rate: float = CONNECTS_PER_S, burst: int = CONNECT_BURST, kept: int = ADDRESSES_KEPT) -> None:
        self.rate, self.burst, self.kept = rate, burst, kept
        self.buckets: OrderedDict[str, TokenBucket] = OrderedDict()

    def take(self, address: str) -> bool:
        bucket = self.buckets.pop(address, None) or TokenBucket(self.rate, self.burst)
        self.buckets[address] = bucket
        while len(self.buckets) > self.kept:
            self.buckets.popitem(last=False)
        return bucket.take()
