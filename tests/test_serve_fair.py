"""`volren serve` under a hostile neighbour (issue 44 items 2-4): the tick shared by time, not by pixels; viewers per
client address; settings coalesced per viewer; a socket's refused messages and an address's connections limited.
Against real servers on loopback (aiohttp's test server); other client addresses are other 127.x.y.z addresses. The
frame-age tests give the renderer a cost model (a sleep per pixel, on top of the real 16^3 render) so the ratios do
not depend on how busy this machine is."""

from __future__ import annotations

import asyncio
import json
import math
import statistics
import time

import aiohttp
import pytest
from aiohttp.test_utils import TestClient, TestServer

from test_serve import SCENE, SMALL, TIMEOUT, H, W, cam_msg, connect, frame_for, next_frame, until
from volren.serve import loop as serve_loop
from volren.serve import viewers as serve_viewers
from volren.serve.app import make_app
from volren.serve.loop import RenderLoop
from volren.serve.protocol import unpack_frame
from volren.serve.rates import SETTINGS_BURST, SETTINGS_PER_S, ConnectRates, ErrorCount, TokenBucket
from volren.serve.viewers import MIN_SHARE, Limits, TimeShares

FULL_HD = 1920 * 1080


def run(test, limits: Limits, cost_per_px: float = 0.0) -> None:
    """``test(client, loop)`` against a fresh server; ``cost_per_px`` [s]: each render call also sleeps that much per
    pixel it renders (in the worker thread, as a slow renderer would take)."""
    async def main() -> None:
        loop = RenderLoop(SCENE, "dssrm", "interactive", limits=limits, device="cpu", overrides=SMALL)
        if cost_per_px:
            render = loop.renderer.render

            def slow(scene, views, frame=0):
                out = render(scene, views, frame)
                time.sleep(cost_per_px * sum(c.width * c.height for c in views))
                return out

            loop.renderer.render = slow
        async with TestClient(TestServer(make_app(loop, "smoke16"), shutdown_timeout=1.0)) as client:
            await test(client, loop)
    asyncio.run(main())


class Sessions:
    """aiohttp sessions whose sockets come from other loopback addresses (other clients), closed together."""

    def __init__(self) -> None:
        self.open: list[aiohttp.ClientSession] = []

    async def ws(self, client, address: str, path: str = "/ws") -> aiohttp.ClientWebSocketResponse:
        session = aiohttp.ClientSession(connector=aiohttp.TCPConnector(local_addr=(address, 0)))
        self.open.append(session)
        return await session.ws_connect(client.make_url(path))

    async def viewer(self, client, address: str, width: int = W, height: int = H):
        ws = await self.ws(client, address)
        await ws.send_json({"type": "hello", "width": width, "height": height})
        return ws, await ws.receive_json(timeout=TIMEOUT)

    async def close(self) -> None:
        for s in self.open:
            await s.close()


async def closed_with(ws) -> tuple[int, str]:
    """The close code and reason the server sent (text messages before it skipped)."""
    while True:
        msg = await ws.receive(timeout=TIMEOUT)
        if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING):
            return ws.close_code, str(msg.extra or "")


# ---- item 3: fair by time ---------------------------------------------------------------------------------------

def test_time_shares_reach_the_tick_time_keep_floors_and_a_ladder():
    """`TimeShares` against a tick cost of 20 ms + 1 us a pixel (the 2-core CPU's order): four 64x48 viewers and a
    1920x1080 one converge within a few ticks to a tick near the 50 ms aimed at, the small ones whole, the big one
    shrunk but never below MIN_SHARE and on the sqrt(2) ladder; a fast device (1 ns a pixel) gives the big one all
    of it (the ladder's rung under the rest of the pixel budget). A lone viewer and a calm loop get the pixel budget
    whatever the estimate; tick_ms None is the pixel budget alone (the schedule before)."""
    wants = [64 * 48] * 4 + [FULL_HD]
    for per_px, settled_ms in ((1e-6, 50.0), (1e-9, None)):
        shares = TimeShares(Limits(8))
        for _ in range(12):
            got = shares.shares(wants)
            shares.took(sum(got), 0.020 + per_px * sum(got))
        assert got[:4] == wants[:4], "the small viewers whole"
        if settled_ms is None:
            # fast: the big one gets the rung of the ladder under the rest of the pixel budget
            assert got[4] == int(FULL_HD / math.sqrt(2)), got
            continue
        tick_ms = 1e3 * (0.020 + per_px * sum(got))
        assert settled_ms / math.sqrt(2) - 5 <= tick_ms <= settled_ms + 1, tick_ms
        k = 2 * math.log2(FULL_HD / got[4])
        assert MIN_SHARE <= got[4] < FULL_HD and abs(k - round(k)) < 1e-3, (got[4], k)
    slow = TimeShares(Limits(8))
    for _ in range(6):
        slow.took(sum(got := slow.shares(wants)), 0.5 + 1e-6 * sum(got))  # the fixed part alone is over the aim
    assert got == [64 * 48] * 4 + [MIN_SHARE], "everyone owed min(size, MIN_SHARE) whatever a tick costs"
    assert slow.shares([FULL_HD]) == [FULL_HD], "a lone viewer has the whole tick"
    assert slow.shares(wants, calm=True) == [*wants[:4], FULL_HD - 4 * 64 * 48], "calm: the pixel budget"
    capped = TimeShares(Limits(4, 128, 96, pixel_budget=2 * 64 * 48))
    assert capped.shares([128 * 96, 64 * 48]) == [64 * 48, 64 * 48], "the operator's pixel budget binds below floors"
    pixels_only = TimeShares(Limits(8, tick_ms=None))
    pixels_only.took(10_000, 10.0)
    assert pixels_only.shares(wants) == [*wants[:4], FULL_HD - 4 * 64 * 48]


async def small_viewer_ages(client, count: int, seconds: float, hz: float = 10.0) -> list[float]:
    """``count`` 64x48 viewers sending a camera every 1/hz s and acknowledging every frame for ``seconds``; each
    one's median frame age [s] (arrival minus the send time of the camera the frame shows) after its first frame."""
    async def one(i: int) -> float:
        ws, _ = await connect(client)
        sent, ages, cam_id = {}, [], 0

        async def cameras() -> None:
            nonlocal cam_id
            while True:
                cam_id += 1
                sent[cam_id] = time.perf_counter()
                await ws.send_json(cam_msg(cam_id, 0.05 * math.sin(cam_id + i)))
                await asyncio.sleep(1.0 / hz)

        sender = asyncio.create_task(cameras())
        try:
            await frame_for(ws, 1)
            end = time.perf_counter() + seconds
            while time.perf_counter() < end:
                header, _ = await next_frame(ws)
                ages.append(time.perf_counter() - sent[header["camera_id"]])
        finally:
            sender.cancel()
            await ws.close()
        return statistics.median(ages)

    return list(await asyncio.gather(*(one(i) for i in range(count))))


@pytest.mark.parametrize("tick_ms", [serve_viewers.TICK_MS, None], ids=["by-time", "by-pixels"])
def test_small_viewers_keep_their_frame_age_beside_a_full_hd_viewer(tick_ms):
    """Item 3, the attack's measurement on a real server at the default limits (a full-HD pixel budget): four 64x48
    viewers (a camera every 0.1 s, every frame acknowledged), alone and beside a viewer asking 1920x1080, with a
    renderer costing 1 us a pixel beyond the real render (the 2-core CPU's order). Sharing the tick by time their
    median frame age stays within 3x of alone (measured 1.2x) and the big viewer gets smaller frames, at least
    MIN_SHARE; sharing the pixel budget alone (the schedule before) the big viewer's 2 s ticks push it past 3x
    (measured ~10x)."""
    async def test(client, loop):
        alone = statistics.median(await small_viewer_ages(client, 4, 1.5))
        big, _ = await connect(client, 1920, 1080)
        await big.send_json(cam_msg(1))
        sizes = []

        async def big_reads() -> None:
            while True:
                header, _ = await next_frame(big)
                sizes.append(header["width"] * header["height"])

        reader = asyncio.create_task(big_reads())
        try:
            await until(lambda: sizes, "the big viewer's first frame")
            beside = statistics.median(await small_viewer_ages(client, 4, 2.5))
        finally:
            reader.cancel()
        ratio = beside / alone
        if tick_ms is None:
            assert ratio > 3.0 and sizes[-1] > 0.99 * (FULL_HD - 4 * 64 * 48), (alone, beside, sizes)
        else:
            assert ratio <= 3.0, (alone, beside, sizes)
            assert MIN_SHARE <= sizes[-1] < FULL_HD // 4, sizes
        await big.close()

    run(test, Limits(8, 1920, 1080, max_per_client=8, tick_ms=tick_ms), cost_per_px=1e-6)


def test_a_still_view_shrunk_by_its_share_gets_its_whole_size_once_calm(monkeypatch):
    """Item 3: a viewer shrunk to its time share while viewers move gets one frame of its whole size, of the same
    camera, once no viewer has moved for CALM_AFTER_S (its still view sharp); while another viewer keeps moving it
    stays shrunk."""
    monkeypatch.setattr(serve_viewers, "MIN_SHARE", 16 * 16)
    monkeypatch.setattr(serve_loop, "CALM_AFTER_S", 0.4)
    monkeypatch.setattr(serve_loop, "PARK_AFTER_S", 60.0)  # the small one, not acknowledging, stays in the tick

    async def test(client, loop):
        big, _ = await connect(client, 128, 96)
        small, _ = await connect(client)
        await big.send_json(cam_msg(1, 0.1))
        header, _ = await frame_for(big, 1)
        for i in range(2, 12):  # the small one moves: ticks at the time shares
            await small.send_json(cam_msg(i))
            await frame_for(small, i)
            if i == 6:
                header, _ = await next_frame(big)  # the big one's newest frame of camera 1
                assert header["camera_id"] == 1 and header["width"] * header["height"] < 128 * 96 // 2, header
        async def whole() -> dict:
            while (header := (await next_frame(big))[0])["width"] != 128:
                pass
            return header

        header = await asyncio.wait_for(whole(), 3.0)
        assert (header["camera_id"], header["height"]) == (1, 96), header
        for w in (big, small):
            await w.close()

    # 1 ms a pixel: the big viewer's whole frame would take 12 s, its share a few ms
    run(test, Limits(4, 128, 96, tick_ms=50.0), cost_per_px=1e-5)


# ---- item 2: slots per client address -------------------------------------------------------------------------

def test_one_address_cannot_take_every_slot(monkeypatch):
    """Item 2: a neighbour at 127.0.0.2 holds at most --max-viewers-per-client slots: its next hello is refused
    (1013, naming the flag), while viewers from 127.0.0.1 get in and get frames. Its sockets that send a camera,
    never acknowledge and reconnect after the close (the attack: 72 of 72 real viewers refused over 40 s) keep
    at most that many slots all along."""
    monkeypatch.setattr(serve_loop, "ACK_TIMEOUT_S", 0.8)
    monkeypatch.setattr(serve_loop, "PARK_AFTER_S", 0.2)

    async def test(client, loop):
        sessions = Sessions()
        try:
            async def squat() -> None:
                """Hello, a camera, never an ack; reconnect once closed."""
                while True:
                    ws, welcome = await sessions.viewer(client, "127.0.0.2")
                    if welcome["type"] == "welcome":
                        await ws.send_json(cam_msg(1))
                    async for _ in ws:
                        pass

            squatters = [asyncio.create_task(squat()) for _ in range(6)]
            await until(lambda: sum(v.client == "127.0.0.2" for v in loop.viewers.viewers.values()) == 2,
                        "the neighbour's two slots")
            extra, reply = await sessions.viewer(client, "127.0.0.2")
            assert reply["type"] == "error" and "--max-viewers-per-client" in reply["message"], reply
            assert (await closed_with(extra))[0] == 1013
            held = []
            for i in range(2):  # two real viewers, across several squatter reconnects
                ws, _ = await connect(client)
                await ws.send_json(cam_msg(1 + i))
                await frame_for(ws, 1 + i)
                held.append(ws)
                for _ in range(40):
                    held_now = sum(v.client == "127.0.0.2" for v in loop.viewers.viewers.values())
                    assert held_now <= 2, held_now
                    await asyncio.sleep(0.05)
            assert all(v.client in ("127.0.0.1", "127.0.0.2") for v in loop.viewers.viewers.values())
            for t in squatters:
                t.cancel()
            for ws in held:
                await ws.close()
        finally:
            await sessions.close()

    run(test, Limits(4, 128, 96, max_per_client=2))


# ---- item 4: per-client rate limits ---------------------------------------------------------------------------

def test_a_settings_flood_applies_one_change_a_tick_and_ends_on_the_newest():
    """Item 4: 400 settings from one viewer (quality flipped, the light moved) while another moves its camera: at
    most one applied change a tick and SETTINGS_BURST + SETTINGS_PER_S a second from that viewer (renderer
    rebuilds likewise), the other viewer keeps getting frames, and the flood ends on its newest values (coalesced,
    not dropped); two messages of different settings waiting together both apply."""
    async def test(client, loop):
        flood, _ = await connect(client)
        other, _ = await connect(client)
        await other.send_json(cam_msg(1))
        await frame_for(other, 1)
        builds, versions, make = [], [], loop._make_renderer
        loop._make_renderer = lambda: builds.append(1) or make()
        adopt = loop.adopt

        def counted(values):
            changed = adopt(values)
            if changed:
                versions.append(loop.tick)
            return changed

        loop.adopt = counted
        tick0, start = loop.tick, time.perf_counter()
        for i in range(400):
            await flood.send_str(json.dumps({"type": "settings", "quality": ("default", "interactive")[i % 2],
                                             "light_dir": [0.001 * i - 0.3, -1.0, 0.2]}))
        frames = 0
        for i in range(2, 10):
            await other.send_json(cam_msg(i))
            while True:  # the flood's settings messages come between the frames
                msg = await other.receive(timeout=TIMEOUT)
                if msg.type == aiohttp.WSMsgType.TEXT:
                    assert json.loads(msg.data)["type"] == "settings"
                    continue
                header, _ = unpack_frame(msg.data)
                await other.send_json({"type": "ack", "tick": header["tick"]})
                if header["camera_id"] == i:
                    break
            frames += 1
        await until(lambda: loop.light_dir == (0.399 - 0.3, -1.0, 0.2) and loop.quality == "interactive",
                    "the newest values")
        elapsed = time.perf_counter() - start
        assert frames == 8
        assert len(versions) <= SETTINGS_BURST + SETTINGS_PER_S * elapsed + 1, (len(versions), elapsed)
        assert len(versions) == len(set(versions)), f"two changes applied in one tick: {versions}"
        assert len(builds) <= len(versions), builds
        assert loop.tick - tick0 >= len(versions) - 1
        # after a change that applies, two messages of different settings wait together: both apply (merged while
        # they wait, not the last alone)
        await flood.send_str(json.dumps({"type": "settings", "light_dir": [0.1, -1.0, 0.0]}))
        await flood.send_str(json.dumps({"type": "settings", "quality": "default"}))
        await flood.send_str(json.dumps({"type": "settings", "light_dir": [0.25, -1.0, 0.0]}))
        await other.send_json(cam_msg(99))
        await until(lambda: loop.light_dir == (0.25, -1.0, 0.0), "the light")
        await asyncio.sleep(1.0)  # past the rate: whatever waited has applied
        assert loop.quality == "default", loop.quality
        for w in (flood, other):
            await w.close()

    run(test, Limits(4, 128, 96))


def test_a_socket_past_the_refused_message_limit_is_closed():
    """Item 4: a socket sending malformed JSON is answered with errors up to ERROR_LIMIT within ERROR_WINDOW_S,
    then closed (1008, saying why); before its hello as after it; another viewer's frames go on."""
    from volren.serve.rates import ERROR_LIMIT

    async def test(client, loop):
        good, _ = await connect(client)
        await good.send_json(cam_msg(1))
        await frame_for(good, 1)
        for hello_first in (False, True):
            bad = await client.ws_connect("/ws")
            if hello_first:
                await bad.send_json({"type": "hello", "width": W, "height": H})
                assert (await bad.receive_json(timeout=TIMEOUT))["type"] == "welcome"
            for _ in range(ERROR_LIMIT + 5):
                await bad.send_str("{not json")
            errors = 0
            while (msg := await bad.receive(timeout=TIMEOUT)).type == aiohttp.WSMsgType.TEXT:
                errors += 1
            assert errors == ERROR_LIMIT and bad.close_code == 1008 and "refused messages" in msg.extra, msg
        await good.send_json(cam_msg(2))
        await frame_for(good, 2)
        await good.close()

    run(test, Limits(4, 128, 96))


def test_a_socket_past_the_message_rate_is_closed():
    """Item 4: a socket sending valid messages faster than MESSAGES_PER_S after a burst of MESSAGE_BURST is closed
    (1008, saying why) before they are parsed; a page's rate (a camera every 10 ms, acks) never is; another viewer's
    frames go on."""
    from volren.serve.rates import MESSAGE_BURST

    async def test(client, loop):
        good, _ = await connect(client)
        for i in range(1, 40):  # 100 cameras a second for 0.4 s, each frame acknowledged
            await good.send_json(cam_msg(i, 0.001 * i))
            await asyncio.sleep(0.01)
        await frame_for(good, 39)
        flood, _ = await connect(client)
        for i in range(1, MESSAGE_BURST + 50):
            await flood.send_json(cam_msg(i, 0.001 * i))
        code, why = await closed_with(flood)
        assert code == 1008 and "messages a second" in why, (code, why)
        assert not good.closed
        await good.send_json(cam_msg(40))
        await frame_for(good, 40)
        await good.close()

    run(test, Limits(4, 128, 96))

def test_connections_are_rate_limited_per_address():
    """Item 4: WebSocket upgrades from one address past its burst are answered 429 before any work; another
    address connects meanwhile; a token comes back after 1 / CONNECTS_PER_S s. The buckets stay bounded (least
    recently used forgotten) and refill at their rate; the refused-message count forgets what left its window."""
    rates = ConnectRates(rate=2.0, burst=2, kept=3)
    assert [rates.take("a"), rates.take("a"), rates.take("a")] == [True, True, False]
    for name in "bcd":
        rates.take(name)
    assert list(rates.buckets) == ["b", "c", "d"] and rates.take("a"), "a forgotten address starts full"
    bucket = TokenBucket(2.0, 1, at=100.0)
    assert bucket.take(100.0) and not bucket.take(100.1) and bucket.wait(100.1) == pytest.approx(0.4)
    assert bucket.take(100.6)
    errors = ErrorCount(limit=2, window=1.0)
    assert [errors.add(0.0), errors.add(0.5), errors.add(2.0), errors.add(2.1), errors.add(2.2)] == \
        [False, False, False, False, True]

    async def test(client, loop):
        sessions = Sessions()
        try:
            for _ in range(5):
                await (await client.ws_connect("/ws")).close()
            with pytest.raises(aiohttp.WSServerHandshakeError) as exc:
                await client.ws_connect("/ws")
            assert exc.value.status == 429
            await (await sessions.ws(client, "127.0.0.3")).close()
            await asyncio.sleep(0.6)
            ws, _ = await connect(client)
            await ws.send_json(cam_msg(1))
            await frame_for(ws, 1)
            await ws.close()
        finally:
            await sessions.close()

    run(test, Limits(4, 128, 96, connect_burst=5))



def test_bench_fair_and_neighbour_runs():
    """`volren bench serve`'s fair run (small viewers alone and beside a big one, sharing by time and by pixels) and
    neighbour run (the viewers beside a neighbour at 127.0.0.2 in a process of its own): rows in order, the ratios
    and goal follow from them, the big viewer shrunk only sharing by time, and the neighbour's tallies show the
    server's answers (malformed JSON: closed past ERROR_LIMIT; churn: 429s past the connection burst)."""
    from volren.bench.serve import GOAL_FAIR_AGE, run_fair, run_neighbour
    from volren.serve.rates import CONNECT_BURST, ERROR_LIMIT

    cfg = {"cases": [("dssrm", "smoke")], "resolution": 64, "size": (48, 32), "min_ticks": 3, "camera_hz": 20.0,
           "overrides": {"samples": 32, "light_samples": 8, "light_grid": 8},
           "fair": {"small": 2, "small_size": (48, 32), "big_size": (640, 360), "camera_hz": 10.0, "seconds": 1.0},
           "neighbour": {"viewers": 2, "size": (48, 32), "camera_hz": 10.0, "seconds": 1.5,
                         "attacks": ("none", "malformed", "churn")}}
    r = asyncio.run(run_fair(cfg, "cpu"))
    rows = {(row["schedule"], row["run"]): row for row in r["rows"]}
    assert list(rows) == [("time", "alone"), ("time", "beside big"), ("pixels", "beside big")]
    alone = rows["time", "alone"]["small_age_median_ms"]
    assert r["age_ratio"] == rows["time", "beside big"]["small_age_median_ms"] / alone
    assert r["age_ratio_pixels"] == rows["pixels", "beside big"]["small_age_median_ms"] / alone
    assert r["goals"] == ("pass" if r["age_ratio"] <= GOAL_FAIR_AGE else "fail")
    assert rows["time", "beside big"]["big_pixels"] < 640 * 360 == rows["pixels", "beside big"]["big_pixels"]
    assert all(row["big_frames"] > 0 for (_, run), row in rows.items() if run != "alone")
    n = asyncio.run(run_neighbour(cfg, "cpu"))
    rows = {row["attack"]: row for row in n["rows"]}
    assert list(rows) == ["none", "malformed", "churn"] and rows["none"]["neighbour"]["messages"] == 0
    assert all(row["fps"] > 0 for row in rows.values())
    bad = rows["malformed"]["neighbour"]
    assert bad["closed"] >= 1 and bad["messages"] >= ERROR_LIMIT * bad["closed"]
    churn = rows["churn"]["neighbour"]
    assert churn["refused"] > 0 and churn["connections"] <= CONNECT_BURST + 2 * 3 * 2.0, churn
