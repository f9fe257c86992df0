"""Sort-last compositing of the regions' partial images (issue 43 item 2), numpy, vectorised over pixels: each region
renders only its own box, so each pixel's ray is cut into one segment per region, and the segments' results combine
per pixel into what one pass along the whole ray gives.

- ``over`` (DVR, DESIGN.md images: premultiplied RGBA, alpha = 1 - transmittance): front to back, C = C_front +
  (1 - A_front) C_back. Emission and absorption of a segment attenuate by the transmittance of everything in front
  of it, which is the product of the segments' transmittances: the same integral as one pass, regrouped.
- ``max`` (MIP, MIDA's running maximum): the maximum over the ray is the maximum of the segments' maxima, in any
  order, bit-exact.
- ``nearest`` (iso): the first hit along the ray is the segment hit with the smallest depth (+inf: no hit); equal
  depths go to the region earlier in the view's order.

Partial images may carry leading axes (views: stereo's ``(2, H, W, 4)``); they composite pixel by pixel alike.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def composite_over(partials: Sequence[np.ndarray], order: Sequence[int]) -> np.ndarray:
    """float32 (..., 4): the premultiplied RGBA ``partials`` (one per region, ``partials[i]`` region i's)
    composited front to back in ``order`` (region indices, front first; `volren.dataparallel.order`)."""
    _check_order(len(partials), order)
    out = np.array(partials[order[0]], dtype=np.float32)
    _check_shape(out, partials, rgba=True)
    for i in order[1:]:
        out += (1.0 - out[..., 3:4]) * np.asarray(partials[i], dtype=np.float32)
    return out


def composite_max(partials: Sequence[np.ndarray]) -> np.ndarray:
    """The elementwise maximum of the regions' running maxima (MIP/MIDA): exact and order-free."""
    if not partials:
        raise ValueError("no partial images to composite")
    _check_shape(np.asarray(partials[0]), partials, rgba=False)
    return np.maximum.reduce([np.asarray(p) for p in partials])


def composite_nearest(partials_rgba: Sequence[np.ndarray], depths: Sequence[np.ndarray],
                      order: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(RGBA float32 (..., 4), depth float32 (...)): per pixel the partial with the smallest depth (iso; ``depths[i]``
    region i's, +inf where it has no hit), equal depths going to the region earlier in ``order`` (by default the
    list's). Where no region hits, the depth is +inf and the pixel the first region's (what its render wrote for a
    miss)."""
    order = list(range(len(partials_rgba))) if order is None else list(order)
    _check_order(len(partials_rgba), order)
    if len(depths) != len(partials_rgba):
        raise ValueError(f"{len(depths)} depth images for {len(partials_rgba)} partial images")
    rgba = np.array(partials_rgba[order[0]], dtype=np.float32)
    _check_shape(rgba, partials_rgba, rgba=True)
    depth = np.array(depths[order[0]], dtype=np.float32)
    _check_shape(depth, depths, rgba=False)
    if depth.shape != rgba.shape[:-1]:
        raise ValueError(f"depth images {list(depth.shape)} do not match RGBA images {list(rgba.shape)}")
    for i in order[1:]:
        nearer = np.asarray(depths[i], dtype=np.float32) < depth  # strict: a tie keeps the earlier region
        depth[nearer] = np.asarray(depths[i], dtype=np.float32)[nearer]
        rgba[nearer] = np.asarray(partials_rgba[i], dtype=np.float32)[nearer]
    return rgba, depth


def _check_order(count: int, order: Sequence[int]) -> None:
    # a region left out or composited twice is a wrong image, not a slow one: refuse it
    if count == 0 or sorted(order) != list(range(count)):
        raise ValueError(f"the order {list(order)} is not a permutation of the {count} regions")


def _check_shape(first: np.ndarray, images: Sequence[np.ndarray], *, rgba: bool) -> None:
    if rgba and first.shape[-1:] != (4,):
        raise ValueError(f"partial images must be RGBA (..., 4), got {list(first.shape)}")
    for image in images:
        if np.shape(image) != first.shape:
            raise ValueError(f"partial images differ in shape: {list(np.shape(image))} and {list(first.shape)}")
