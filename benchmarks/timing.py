"""The one timing helper of the benchmarks (imported by the scripts, which run from this folder)."""
from __future__ import annotations

from collections.abc import Callable
import statistics
import time


def median_seconds(action: Callable[[], object], repeats: int) -> float:
    """Median wall time (s) of ``repeats`` calls of ``action``."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return statistics.median(times)
