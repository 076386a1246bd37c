"""Pixel chunks of a compiled per-pixel kernel on a few threads.

The kernels of :mod:`polrig.solve._reduced_kernel` and :mod:`polrig.solve._diffuse_kernel`
release the GIL and treat each pixel on its own, so their callers split the pixels into
contiguous slices and run them side by side; the results do not depend on the split.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise

import numpy as np

__all__ = ["THREADS", "in_chunks"]

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
