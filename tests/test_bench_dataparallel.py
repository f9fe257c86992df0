"""The ``dataparallel`` bench suite's Ray-free parts (issue 43): its compositing timings composite what
`composite_over` composites, and its cluster model (`composite_model`) has the byte, message and time relations its
docstring derives. Tiny sizes, no rendering, no Ray."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from volren.bench.dataparallel import (
    ANCHORS,
    PARTIAL_BYTES_PER_PIXEL,
    anchor_rows,
    composite_model,
    compositing_rows,
    over_throughput,
    radix_factors,
    synthetic_partials,
    time_operator,
)
from volren.bench.runner import run_suite
from volren.dataparallel.composite import composite_over

pytestmark = pytest.mark.timeout(60)


def naive_over(partials: list[np.ndarray], order: list[int]) -> np.ndarray:
    """Front to back by the transmittance product: C = sum_i c_i prod_{j before i} (1 - a_j), in float64."""
    out = np.zeros(partials[0].shape, np.float64)
    transmittance = np.ones((*partials[0].shape[:-1], 1), np.float64)
    for i in order:
        p = partials[i].astype(np.float64)
        out += transmittance * p
        transmittance *= 1.0 - p[..., 3:4]
    return out


def test_synthetic_partials_are_premultiplied_rgba():
    images, depths = synthetic_partials(3, 8, 5, seed=1)
    assert len(images) == len(depths) == 3
    for im, d in zip(images, depths, strict=True):
        assert im.shape == (5, 8, 4) and im.dtype == np.float32 and d.shape == (5, 8)
        assert (im[..., 3] >= 0).all() and (im[..., 3] < 1).all() and (im[..., :3] <= im[..., 3:4] + 1e-7).all()


def test_timed_compositing_is_composite_over():
    images, _ = synthetic_partials(4, 12, 7, seed=2)
    order = [2, 0, 3, 1]
    ms, out = time_operator(composite_over, (images, order), 2)
    assert ms >= 0.0
    np.testing.assert_array_equal(out, composite_over(images, order))
    np.testing.assert_allclose(out, naive_over(images, order), rtol=1e-5, atol=1e-6)


def test_compositing_rows_measure_every_size_and_count():
    rows = compositing_rows([[16, 8], [32, 16]], [1, 2, 4], repeats=1)
    assert [(r["size"], r["n"]) for r in rows] == [(s, n) for s in ("16x8", "32x16") for n in (1, 2, 4)]
    for r in rows:
        assert r["partial_bytes"] == r["pixels"] * PARTIAL_BYTES_PER_PIXEL and r["depth_bytes"] == r["pixels"] * 4
        assert (r["over_mpix_per_s"] is None) == (r["n"] == 1)
        if r["n"] > 1:  # (N - 1) composites of each pixel per frame
            assert r["over_mpix_per_s"] == pytest.approx((r["n"] - 1) * r["pixels"] / r["over_ms"] / 1e3)
    assert over_throughput(rows) == pytest.approx(1e6 * float(np.median(
        [r["over_mpix_per_s"] for r in rows if r["size"] == "32x16" and r["n"] > 1])))


@pytest.mark.parametrize("scheme,nodes,factors", [
    ("direct-send", 16, [16]), ("binary-swap", 16, [2, 2, 2, 2]), ("radix-k", 64, [8, 8]), ("radix-k", 32, [8, 4]),
    ("radix-k", 12, [6, 2]), ("radix-k", 11, [11]), ("direct-send", 1, [])])
def test_radix_factors_multiply_to_the_nodes(scheme, nodes, factors):
    assert radix_factors(nodes, scheme) == factors
    assert math.prod(factors) == nodes


def test_binary_swap_needs_a_power_of_two():
    with pytest.raises(ValueError, match="power of two"):
        composite_model(100, 12, 1e8, 1e10, 1e-5, scheme="binary-swap")


def test_direct_send_bytes_messages_and_time():
    pixels, rate, bandwidth, latency = 1920 * 1080, 1e8, 1e10, 1e-5
    b = PARTIAL_BYTES_PER_PIXEL
    out = {n: composite_model(pixels, n, rate, bandwidth, latency) for n in (8, 16, 32, 64)}
    for n, m in out.items():
        share = (n - 1) / n
        assert m["bytes_per_node"] == pytest.approx(share * pixels * b)
        assert m["message_bytes"] == pytest.approx(pixels * b / n)  # each tile message falls as 1/N
        assert m["messages_per_node"] == n - 1
        assert m["latency_s"] == pytest.approx((n - 1) * latency)
        assert m["composite_s"] == pytest.approx((n - 1) * latency + share * pixels * b / bandwidth
                                                 + share * pixels / rate)
        assert m["composite_s"] == pytest.approx(m["latency_s"] + m["transfer_s"] + m["compute_s"])
    times = [out[n]["composite_s"] for n in sorted(out)]
    assert times == sorted(times) and times[-1] > times[0]  # grows with N
    assert out[16]["message_bytes"] == pytest.approx(out[8]["message_bytes"] / 2)


def test_schemes_move_the_same_bytes_and_differ_in_messages():
    pixels, rate, bandwidth, latency = 4096 * 1024, 1e8, 1e10, 1e-5
    for n in (8, 64):
        ds, bs, rk = (composite_model(pixels, n, rate, bandwidth, latency, scheme=s)
                      for s in ("direct-send", "binary-swap", "radix-k"))
        for m in (bs, rk):
            assert m["bytes_per_node"] == pytest.approx(ds["bytes_per_node"])
            assert m["compute_s"] == pytest.approx(ds["compute_s"])
        assert bs["messages_per_node"] == math.log2(n) and bs["latency_s"] == pytest.approx(math.log2(n) * latency)
        assert bs["composite_s"] <= ds["composite_s"]
    # without latency every dense scheme takes the same time
    same = {composite_model(pixels, 64, rate, bandwidth, 0.0, scheme=s)["composite_s"]
            for s in ("direct-send", "binary-swap", "radix-k")}
    assert max(same) == pytest.approx(min(same))


def test_sparse_partials_send_less():
    pixels = 8192 * 8192
    for scheme in ("direct-send", "binary-swap", "radix-k"):
        dense = composite_model(pixels, 64, 1e8, 1e10, 1e-5, scheme=scheme)
        sparse = composite_model(pixels, 64, 1e8, 1e10, 1e-5, scheme=scheme, sparse=2 / 3)
        assert sparse["bytes_per_node"] < dense["bytes_per_node"]
        assert sparse["messages_per_node"] == dense["messages_per_node"]
    # direct-send's one round: every tile covered 64^(-2/3) = 1/16
    ds = composite_model(pixels, 64, 1e8, 1e10, 1e-5, sparse=2 / 3)
    assert ds["bytes_per_node"] == pytest.approx(63 / 64 * pixels * PARTIAL_BYTES_PER_PIXEL / 16)


def test_anchor_rows_carry_the_published_figures():
    rows = anchor_rows(1e8)
    assert [r["published_ms"] for r in rows] == pytest.approx([1e3 * a[3] for a in ANCHORS])
    for r in rows:
        best = min(r["ds_ms"], r["bs_ms"], r["rk_ms"], r["rk_sparse_ms"])
        assert r["best_over_published"] == pytest.approx(best / r["published_ms"])


def test_suite_writes_the_model_section_without_rendering(tmp_path):
    json_path, md_path, _ = run_suite("dataparallel", quick=True, device="cpu", out=tmp_path, overrides={
        "sizes": [[16, 8]], "counts": [1, 2], "composite_repeats": 1, "regions": [], "ray": False, "nodes": [8, 16]})
    doc = json.loads(json_path.read_text())
    assert [r["n"] for r in doc["rows"]] == [1, 2]
    assert doc["regions"] == [] and doc["ray"][0]["compositing"] == "skipped"
    assert {r["nodes"] for r in doc["model"]} == {8, 16} and len(doc["anchors"]) == len(ANCHORS)
    md = md_path.read_text()
    section = md.index("a model, not a measurement")
    assert section < md.index("| image | network (model) |") and "direct-send: T = (N-1) a" in md
