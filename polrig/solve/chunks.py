"""Where per-pixel work runs: pixel chunks of a compiled kernel on a few threads, and the box
that holds a mask's pixels.

The kernels of :mod:`polrig.solve._reduced_kernel` and :mod:`polrig.solve._diffuse_kernel`
release the GIL and treat each pixel on its own, so their callers split the pixels into
contiguous slices and run them side by side; the results do not depend on the split. Work that
is per pixel (or sums over neighbours that only the mask's pixels enter) can run within
:func:`mask_box` and leave the rest of the image alone.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise

import numpy as np

__all__ = ["THREADS", "in_chunks", "mask_box"]

#: The CPUs this process may use.
THREADS = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def in_chunks(p: int, work: Callable[[slice], None], *, min_pixels: int, per_thread: int = 1,
              name: str = "chunks") -> None:
    """``work(sl)`` for contiguous slices ``sl`` covering ``range(p)``: up to ``per_thread``
    slices a thread on up to :data:`THREADS` threads, each of at least ``min_pixels`` pixels
    (one slice, on the calling thread, where ``p`` is smaller); ``name`` prefixes the threads'
    names."""
    n_chunks = max(1, min(per_thread * THREADS, p // max(1, int(min_pixels))))
    if n_chunks == 1:
        work(slice(0, p))
        return
    bounds = np.linspace(0, p, n_chunks + 1).astype(int)
    with ThreadPoolExecutor(min(THREADS, n_chunks), thread_name_prefix=name) as pool:
        list(pool.map(work, [slice(a, b) for a, b in pairwise(bounds)]))


def mask_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """The smallest ``(rows, cols)`` slices of an ``(H, W)`` bool ``mask`` that hold every one of
    its True pixels; None where it has none."""
    mask = np.asarray(mask, bool)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)
