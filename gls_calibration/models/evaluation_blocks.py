"""Evaluation of a model over a large batch of points in blocks: block sizes, scratch buffers, query checks."""
from __future__ import annotations

import threading
from typing import Any

import numpy as np

from gls_calibration.common.validation import as_points


# Rows per block when evaluating many points (bounds memory, stays in cache). A row's result depends
# only on the block it falls in: batches split at multiples of it give bit-identical results.
BLOCK_ROWS = 512
SMALL_BATCH = 64            # up to this many points, plain differences beat any set-up
# From this many points on, a thin-plate spline sums its kernels through its tiled evaluator
# (gls_calibration.models.tps_tiles; below, its fixed cost per tile outweighs the saving). The correction's
# worker threads never get fewer rows, so a target's value does not depend on how a request is shared.
TILED_MIN_ROWS = 8 * BLOCK_ROWS


_thread_scratch = threading.local()
# Serialises building splines' tiled evaluators (one module lock: a model stays picklable).
TILES_LOCK = threading.Lock()


def scratch(name: str, rows: int, columns: int) -> np.ndarray:
    """Return a (rows, columns) float work array of the calling thread, reused between calls.

    A fresh array of a few MB would be mapped and page-faulted anew each time (10 % of a large
    evaluation).
    """
    size = rows * columns
    buffer = getattr(_thread_scratch, name, None)
    if buffer is None or buffer.size < size:
        buffer = np.empty(size)
        setattr(_thread_scratch, name, buffer)
    return buffer[:size].reshape(rows, columns)


def query_points(points) -> np.ndarray:
    """``points`` as a finite (M, 2) float array; the full check (exact message) only when the quick one fails."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2 or not np.isfinite(points).all():
        points = as_points(points, "points", 2, min_length=0)
    return points


def rows_of_two(values: Any, name: str) -> np.ndarray:
    """(K, 2) points; an empty list (a network of the bias alone, as YAML writes it) gives (0, 2)."""
    if isinstance(values, (list, tuple)) and len(values) == 0:
        return np.empty((0, 2))
    return as_points(values, name, 2, min_length=0)
