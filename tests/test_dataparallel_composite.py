"""`volren.dataparallel.composite` (issue 43 item 2): sort-last compositing equals one pass along the whole ray. A ray
through a piecewise-constant emission-absorption medium, cut at arbitrary planes into one segment per region, each
segment integrated on its own into premultiplied RGBA and the segments composited `over` in visibility order, gives
the whole ray's closed form; maxima composite exactly in any order; the nearest hit wins, ties to the earlier
region."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from volren.dataparallel import composite_max, composite_nearest, composite_over

pytestmark = pytest.mark.timeout(60)

VIEWS = (2, 7, 9)
"""(views, H, W): a stereo pair of small images, so leading axes composite too"""


def integrate(sigma: np.ndarray, colour: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Closed form, float64 (..., 4) premultiplied RGBA, of a ray through pieces of extinction ``sigma`` (..., K)
    [1/m] and emission sigma * colour (..., K, 3), of ``lengths`` (K,) [m], front first: radiance sum_i T_i c_i
    (1 - exp(-sigma_i l_i)), T_i the transmittance of the pieces before i; alpha 1 - prod_i exp(-sigma_i l_i)."""
    through = np.exp(-sigma * lengths)
    before = np.cumprod(np.concatenate([np.ones_like(through[..., :1]), through[..., :-1]], axis=-1), axis=-1)
    rgb = np.sum((before * (1 - through))[..., None] * colour, axis=-2)
    return np.concatenate([rgb, 1 - np.prod(through, axis=-1)[..., None]], axis=-1)


def overlap(a0: float, a1: float, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    return np.clip(np.minimum(a1, b1) - np.maximum(a0, b0), 0.0, None)


@pytest.mark.parametrize("regions", [2, 3, 5, 8])
def test_over_in_visibility_order_is_the_whole_rays_closed_form(regions):
    rng = np.random.default_rng(regions)
    pieces = 11
    edges = np.concatenate([[0.0], np.sort(rng.random(pieces - 1)), [1.0]])  # the medium's pieces along the ray
    sigma = rng.uniform(0.0, 4.0, (*VIEWS, pieces)) * (rng.random((*VIEWS, pieces)) < 0.8)  # some pieces empty
    colour = rng.random((*VIEWS, pieces, 3))
    whole = integrate(sigma, colour, np.diff(edges))
    cuts = np.concatenate([[0.0], np.sort(rng.random(regions - 1)), [1.0]])  # region planes, anywhere in a piece
    segments = [integrate(sigma, colour, overlap(cuts[j], cuts[j + 1], edges[:-1], edges[1:]))
                for j in range(regions)]
    owner = rng.permutation(regions)  # segment j (front first) is region owner[j]'s partial image
    partials = [None] * regions
    for j, region in enumerate(owner):
        partials[region] = segments[j].astype(np.float32)
    image = composite_over(partials, list(owner))
    assert image.dtype == np.float32
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-6)
    assert np.abs(whole[..., 3] - whole[..., 3].mean()).max() > 0.1  # the pixels differ: a real medium per pixel


def test_over_of_one_region_is_its_partial_and_refuses_a_wrong_order():
    rng = np.random.default_rng(0)
    partial = rng.random((*VIEWS, 4)).astype(np.float32)
    assert np.array_equal(composite_over([partial], [0]), partial)
    with pytest.raises(ValueError, match="not a permutation"):
        composite_over([partial, partial], [0, 0])
    with pytest.raises(ValueError, match="not a permutation"):
        composite_over([partial, partial], [1])
    with pytest.raises(ValueError, match="differ in shape"):
        composite_over([partial, partial[0]], [0, 1])


def test_max_of_the_segments_maxima_is_the_rays_maximum_exactly_in_any_order():
    rng = np.random.default_rng(1)
    samples = rng.normal(size=(*VIEWS, 64)).astype(np.float32)  # MIP samples along each ray
    cuts = [0, *sorted(rng.choice(np.arange(1, 64), 4, replace=False)), 64]
    partials = [samples[..., a:b].max(axis=-1) for a, b in itertools.pairwise(cuts)]
    for perm in (range(5), [4, 2, 0, 3, 1]):
        merged = composite_max([partials[i] for i in perm])
        assert merged.dtype == np.float32 and np.array_equal(merged, samples.max(axis=-1))


def test_nearest_hit_wins_ties_go_to_the_earlier_region_and_no_hit_is_inf():
    inf = np.inf
    depths = [np.array([[1.0, inf, 2.0, inf]]),
              np.array([[0.5, inf, 2.0, 3.0]]),
              np.array([[2.0, inf, 2.0, 3.0]])]
    rgba = [np.full((1, 4, 4), 0.1 * (i + 1), dtype=np.float32) for i in range(3)]
    winners = {(2, 0, 1): [1, 2, 2, 2], (0, 1, 2): [1, 0, 0, 1], (1, 2, 0): [1, 1, 1, 1]}
    for order, won in winners.items():
        image, depth = composite_nearest(rgba, depths, list(order))
        assert depth.tolist() == [[0.5, inf, 2.0, 3.0]]
        np.testing.assert_array_equal(image[0, :, 0], np.float32([0.1 * (i + 1) for i in won]))
    image, depth = composite_nearest(rgba, depths)  # the list's order by default
    np.testing.assert_array_equal(image[0, :, 0], np.float32([0.2, 0.1, 0.1, 0.2]))
