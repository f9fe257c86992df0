"""The C heap of a long-running server (issue 44 item 6: the resident set stayed 214 MB up once 16 full-HD viewers
had left). glibc keeps freed memory for reuse: the render targets, images and JPEG buffers of a tick went back to
malloc, not to the system. `trim_heap` gives the free pages back once the viewers have gone (`RenderLoop.release`);
`one_arena` makes every thread allocate where the trim reaches. Elsewhere than glibc both do nothing."""

from __future__ import annotations

import ctypes
import functools
from typing import Any

M_ARENA_MAX = -8
"""mallopt's parameter: the most malloc arenas (glibc's malloc.h)"""


@functools.cache
def _libc() -> Any:
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt, libc.malloc_trim  # noqa: B018 - glibc's, not musl's or macOS's
    except (OSError, AttributeError):
        return None
    return libc


def one_arena() -> None:
    """One malloc arena for every thread, as MALLOC_ARENA_MAX=1 would give; call it before other threads allocate.
    A render thread otherwise gets an arena of its own, and what it frees at that arena's top (up to glibc's trim
    threshold, which grows to 64 MB) stays resident: `malloc_trim` trims only the main arena's top (+40 to +75 MB
    after the viewers had left, one run in three). The render's threads take the arena's lock rarely: their large
    buffers are few, the kernels allocate nothing."""
    libc = _libc()
    if libc is not None:
        libc.mallopt(M_ARENA_MAX, 1)


def trim_heap() -> None:
    """Give the heap's free pages back to the system (``malloc_trim(0)``: every arena's free chunks and the main
    arena's top)."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)
