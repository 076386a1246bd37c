"""Timing helpers the benchmarks share: medians of interleaved rounds after a warm-up, and the
peak of numpy's and Python's allocations during one call."""

from __future__ import annotations

import statistics
import time
import tracemalloc
from collections.abc import Callable, Mapping
from typing import Any


def interleaved_medians(runs: Mapping[str, Callable[[], Any]], rounds: int) -> tuple[dict[str, float], dict[str, Any]]:
    """Each of ``runs`` called once untimed (the warm-up: kernels compiled, caches filled; its
    answer kept), then ``rounds`` rounds calling each in turn: the median seconds of each and
    the warm-up's answers, by name."""
    answers = {k: f() for k, f in runs.items()}
    times: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(rounds):
        for k, f in runs.items():
            t = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t)
    return {k: statistics.median(v) for k, v in times.items()}, answers


def peak_mib(run: Callable[[], Any]) -> float:
    """The peak of the allocations ``tracemalloc`` traces (numpy's and Python's; not native
    arenas such as onnxruntime's) during one call of ``run``, MiB."""
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def sampled_against_every_band(sampled: Callable[[], Any], every_band: Callable[[], Any], solve: Callable[[], Any],
                               rounds: int) -> tuple[dict[str, float], dict[str, Any], dict[str, float]]:
    """A scale estimated on a sample of the row bands, the same on every band, and the banded
    solve it precedes (``prior_scale``, ``open_scale``): :func:`interleaved_medians` of the three
    (keys ``sampled``, ``every band``, ``hybrid solve``), the two estimates' answers, and
    :func:`peak_mib` of the sampled one and of the solve."""
    runs = {"sampled": sampled, "every band": every_band, "hybrid solve": solve}
    med, answers = interleaved_medians(runs, rounds)
    answers.pop("hybrid solve")  # the solve's result is not kept
    return med, answers, {k: peak_mib(runs[k]) for k in ("sampled", "hybrid solve")}
