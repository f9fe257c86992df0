"""Bricks on demand (issue 41 item 3, `volren.stream.cache` and `volren.stream.streamer`): the LRU under a byte
budget, the coarsest level resident from open, coarse-first admission under a tiny budget with every brick still
drawn at some level, a slow store that never makes a tick wait, superseded requests dropped, a missing chunk drawn
from its ancestor with one warning, per-frame stats, and readers that stop."""

from __future__ import annotations

import threading
import time
import warnings

import numpy as np
import pytest

pytest.importorskip("zarr")
pytest.importorskip("ome_zarr.writer")

from test_stream_source import expected_brick, serve_folder, write_pyramid
from volren.errors import VolrenError, VolrenWarning
from volren.stream import BrickCache, BrickStreamer, PyramidSource
from volren.stream.lod import need
from volren.stream.streamer import BRICK_BYTES

LEVEL0 = list(np.ndindex(3, 3, 3))
"""the level-0 bricks of a 40^3 pyramid (40, 20, 10 voxels: 27, 8 and 1 bricks)"""


def all_level0(distance=lambda b: float(sum(b))):
    return [need((0, *b), True, distance(b)) for b in LEVEL0]


def readers_alive() -> int:
    return sum(t.name.startswith("volren-brick-reader") for t in threading.enumerate())


@pytest.mark.timeout(30)
def test_lru_cache_evicts_the_least_recent_unpinned():
    one = np.zeros(10, np.float32)  # 40 bytes
    cache = BrickCache(3 * one.nbytes)
    assert cache.put((2, 0, 0, 0), one, floor=True)
    assert cache.put((1, 0, 0, 0), one.copy()) and cache.put((1, 0, 0, 1), one.copy())
    assert cache.get((1, 0, 0, 0)) is not None  # now (1, 0, 0, 1) is the least recent
    assert cache.put((0, 0, 0, 0), one.copy())
    assert cache.resident_keys() == [(2, 0, 0, 0), (1, 0, 0, 0), (0, 0, 0, 0)]  # the floor stays, though least recent
    assert (cache.loaded, cache.evicted, cache.resident_bytes) == (4, 1, 120)
    cache.pin([(1, 0, 0, 0)])
    assert cache.put((0, 0, 0, 1), one.copy())  # evicts (0, 0, 0, 0): (1, 0, 0, 0) is pinned
    assert cache.resident_keys() == [(2, 0, 0, 0), (1, 0, 0, 0), (0, 0, 0, 1)]
    cache.pin([(1, 0, 0, 0), (0, 0, 0, 1)])
    assert not cache.put((0, 0, 0, 2), one.copy())  # nothing may go: refused, nothing changed
    assert (cache.loaded, cache.evicted, cache.refused, cache.resident_bytes, len(cache)) == (5, 2, 1, 120, 3)


@pytest.mark.timeout(60)
def test_coarsest_level_resident_at_open_and_everything_after_wait(tmp_path):
    levels = write_pyramid(tmp_path / "p.zarr")
    before = readers_alive()  # other tests' streamers (volumes nobody closed) may still hold theirs
    with PyramidSource(tmp_path / "p.zarr") as source, BrickStreamer(source, memory_budget=1 << 26) as streamer:
        assert readers_alive() == before + 4
        assert streamer.resident(2, (0, 0, 0)) and not streamer.resident(1, (0, 0, 0))
        level, brick, voxels = streamer.best_resident(0, (2, 1, 2))
        assert (level, brick) == (2, (0, 0, 0))
        np.testing.assert_array_equal(voxels, expected_brick(levels[2], (0, 0, 0)))
        seen = []
        assert streamer.wait(all_level0(), progress=lambda done, total: seen.append((done, total)), timeout=30)
        assert seen[0] == (0, 35) and seen[-1] == (35, 35)  # 27 bricks and their 8 level-1 ancestors
        for b in LEVEL0:
            level, brick, voxels = streamer.best_resident(0, b)
            assert (level, brick) == (0, b)
            np.testing.assert_array_equal(voxels, expected_brick(levels[0], b))
        stats = streamer.stats()
        # the whole pyramid read once: 40^3 + 20^3 + 10^3 uint16
        assert stats == {"frame": 1, "bricks_resident": 36, "bricks_loaded": 36, "bricks_evicted": 0,
                         "bytes_read": 2 * (40**3 + 20**3 + 10**3), "levels_used": [27, 0, 0],
                         "pool_bytes": 36 * BRICK_BYTES, "bricks_pending": 0, "bricks_bad": 0}
        assert streamer.stats()["bricks_loaded"] == 0  # per frame: since the last call
    assert readers_alive() == before


@pytest.mark.timeout(60)
def test_tiny_budget_admits_coarse_first_and_every_brick_has_a_level(tmp_path):
    """Room for the floor and 3 bricks. The 27 level-0 needs (distance bz + by + bx) bring their 8 level-1
    ancestors, which come first (coarse before fine); the 3 nearest: level 1's (0,0,0) (distance 0), then of the
    three at distance 2, (0,0,1) and (0,1,0) by key. They cover 8 + 4 + 4 level-0 bricks; the other 11 are drawn
    from the coarsest level."""
    levels = write_pyramid(tmp_path / "p.zarr")
    with PyramidSource(tmp_path / "p.zarr") as source, \
            BrickStreamer(source, memory_budget=4 * BRICK_BYTES) as streamer:
        assert streamer.wait(all_level0(), timeout=30)
        finer = sorted(k for k in streamer.cache.resident_keys() if k[0] < 2)
        assert finer == [(1, 0, 0, 0), (1, 0, 0, 1), (1, 0, 1, 0)]
        stats = streamer.stats()
        assert stats["levels_used"] == [0, 16, 11]
        assert (stats["bricks_loaded"], stats["bricks_evicted"], stats["pool_bytes"]) == (4, 0, 4 * BRICK_BYTES)
        assert stats["bytes_read"] == 2 * (20**3 + 10**3)  # level 1's eight chunks serve its three bricks
        # the next frame wants one far corner: its brick and ancestor come in, two older bricks go out
        assert streamer.wait([need((0, 2, 2, 2), True, 0.0)], timeout=30)
        stats = streamer.stats()
        assert (stats["bricks_loaded"], stats["bricks_evicted"], stats["levels_used"]) == (2, 2, [1, 0, 0])
        assert stats["bytes_read"] == 2 * 8**3 and stats["pool_bytes"] == 4 * BRICK_BYTES
        assert streamer.cache.resident_bytes <= streamer.cache.budget
        for b in LEVEL0:  # every brick drawn at some level, with that level's voxels
            level, brick, voxels = streamer.best_resident(0, b)
            assert brick == tuple(x >> level for x in b)
            np.testing.assert_array_equal(voxels, expected_brick(levels[level], brick))
    with PyramidSource(tmp_path / "p.zarr") as source, pytest.raises(VolrenError, match="coarsest level's 1 bricks"):
        BrickStreamer(source, memory_budget=BRICK_BYTES - 1)


@pytest.mark.timeout(60)
def test_a_slow_store_never_makes_a_tick_wait(tmp_path):
    """Level 0's chunks take 2 s to come: each tick (request and drawing) returns at once (well under the delay),
    drawing the coarser levels, and the finest arrives later."""
    levels = write_pyramid(tmp_path / "p.zarr", chunks=32)
    with serve_folder(tmp_path, slow="/p.zarr/s0/", delay=2.0) as url, \
            PyramidSource(f"{url}/p.zarr") as source, BrickStreamer(source, memory_budget=1 << 26) as streamer:
        needs = [need((0, 0, 0, 0), True, 0.0), need((0, 0, 0, 1), True, 1.0)]
        drawn = []
        for _ in range(3):
            start = time.monotonic()
            streamer.request(needs)
            drawn.append([streamer.best_resident(n.level, n.brick)[0] for n in needs])
            assert time.monotonic() - start < 0.25
            time.sleep(0.05)
        assert all(level > 0 for tick in drawn for level in tick)  # never the finest before the delay
        assert streamer.wait(timeout=20)
        for n in needs:
            level, _, voxels = streamer.best_resident(n.level, n.brick)
            assert level == 0
            np.testing.assert_array_equal(voxels, expected_brick(levels[0], n.brick))


@pytest.mark.timeout(60)
def test_a_newer_frame_drops_what_it_no_longer_needs(tmp_path):
    write_pyramid(tmp_path / "p.zarr", chunks=32)
    with serve_folder(tmp_path, slow="/p.zarr/s0/", delay=1.0) as url, \
            PyramidSource(f"{url}/p.zarr") as source, \
            BrickStreamer(source, memory_budget=1 << 26, workers=1, progressive=False) as streamer:
        old = [need((0, 0, 0, 0), True, 0.0), need((0, 0, 2, 0), True, 1.0), need((0, 2, 0, 0), True, 2.0)]
        streamer.request(old)
        deadline = time.monotonic() + 5
        while streamer.reading() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert (streamer.reading(), streamer.queued()) == (1, 2)  # the nearest is being read
        streamer.request([need((0, 2, 2, 2), True, 0.0)])
        assert streamer.queued() == 1  # the old frame's two queued bricks dropped
        assert streamer.wait(timeout=20)
        time.sleep(0.2)
        assert streamer.resident(0, (0, 0, 0))  # finished in flight: kept
        assert not streamer.resident(0, (0, 2, 0)) and not streamer.resident(0, (2, 0, 0))
        assert streamer.resident(0, (2, 2, 2)) and streamer.stats()["bricks_loaded"] == 3  # floor + 2


@pytest.mark.timeout(60)
def test_a_missing_chunk_is_drawn_from_its_ancestor_with_one_warning(tmp_path):
    levels = write_pyramid(tmp_path / "p.zarr")
    (tmp_path / "p.zarr" / "s0" / "c" / "1" / "1" / "1").unlink()  # voxels 16..31: level-0 bricks 0 and 1 per axis
    with PyramidSource(tmp_path / "p.zarr") as source, BrickStreamer(source, memory_budget=1 << 26) as streamer:
        with pytest.warns(VolrenWarning) as record:
            assert streamer.wait(all_level0(), timeout=30)
        assert len(record) == 1 and "chunk 's0/c/1/1/1' of level 0" in str(record[0].message)
        stats = streamer.stats()
        assert stats["bricks_bad"] == 8 and stats["levels_used"] == [19, 8, 0]
        level, brick, voxels = streamer.best_resident(0, (1, 0, 1))
        assert (level, brick) == (1, (0, 0, 0))
        np.testing.assert_array_equal(voxels, expected_brick(levels[1], (0, 0, 0)))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the next frames: no second warning, no second read
            assert streamer.wait(all_level0(), timeout=30)
            assert streamer.stats()["bricks_loaded"] == 0
    with PyramidSource(tmp_path / "p.zarr") as source, \
            BrickStreamer(source, memory_budget=1 << 26, progressive=False) as streamer:
        one = [need((0, 1, 0, 1), True, 0.0)]
        with pytest.warns(VolrenWarning, match="s0/c/1/1/1"):
            assert streamer.wait(one, timeout=30)
        assert streamer.best_resident(0, (1, 0, 1))[0] == 2  # no ancestor asked for: the coarsest
        assert streamer.wait(one, timeout=30)  # now known bad: its parent stands in
        assert streamer.best_resident(0, (1, 0, 1))[:2] == (1, (0, 0, 0))


@pytest.mark.timeout(60)
def test_the_frame_side_at_once_is_the_brick_by_brick_one(tmp_path):
    """`request` (numpy) queues and admits what the brick-by-brick walk of each need's ancestors would (each key at
    its best need's priority, sorted as `BrickNeed`s), and `resident_for` and the stats' levels give each need's
    `best_resident`, each brick once in the order of its first need, touched in the cache in the order of its last."""
    write_pyramid(tmp_path / "p.zarr")
    rng = np.random.default_rng(3)
    needs = [need((0, *b), bool(rng.integers(2)), float(rng.integers(4))) for b in LEVEL0[::2]]
    needs += [need((1, 1, 0, 1), False, 0.5), need((2, 0, 0, 0), True, 9.0)]
    with PyramidSource(tmp_path / "p.zarr") as source, \
            BrickStreamer(source, memory_budget=1 << 26, workers=0) as streamer:  # no readers: nothing moves
        streamer.request(needs)
        by_hand: dict = {}
        for n in needs:
            for level, brick in streamer.layout.ancestors(n.level, n.brick):
                if level < 2:
                    w = need((level, *brick), n.visible, n.priority[2])
                    by_hand[w.key] = min(w, by_hand.get(w.key, w))
        want = sorted(by_hand.values())
        assert streamer._admitted == [w.key for w in want]
        assert sorted(streamer._heap) == [(w.priority, i + 1, w.key) for i, w in enumerate(want)]
        for key in want[1::3]:  # some of each level resident
            streamer.cache.put(key.key, np.full((17, 17, 17), key.key[0], np.float32))
        first: dict = {}
        for n in needs:
            level, brick, array = streamer.best_resident(n.level, n.brick)
            first.setdefault((level, *brick), array)
        last = [k for k in dict.fromkeys(reversed([(lv, *b) for lv, b, _ in
                                                   (streamer.best_resident(n.level, n.brick) for n in needs)]))][::-1]
        streamer.cache.get((2, 0, 0, 0))  # not the last any more
        got = streamer.resident_for(needs)
        assert list(got) == list(first) and all(got[k] is first[k] for k in first)
        assert streamer.cache.resident_keys()[-len(last):] == last
        levels = [0, 0, 0]
        for key in first:
            levels[key[0]] += sum(1 for n in needs if streamer.best_resident(n.level, n.brick)[:2] == (key[0], key[1:]))
        assert streamer.stats()["levels_used"] == levels
