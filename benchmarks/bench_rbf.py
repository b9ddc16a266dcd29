"""Speed and memory of the deviation models: prints median figures.

Run: ``.venv/bin/python benchmarks/bench_rbf.py``. Goals (published figures in brackets):
OLS training on 361 points <= 50 ms (5.88 s), one prediction <= 20 us (55 us), 100 000 predictions
<= 20 ms. On a shared machine, ``OPENBLAS_NUM_THREADS=1`` avoids thread oversubscription.
"""
from __future__ import annotations

import math
import resource
import statistics
import time
import tracemalloc

import numpy as np

from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.models.rbf import OLSRBFNetwork, select_model
from timing import median_seconds


def synthetic_samples(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """19 x 19 grid with a smooth ~0.85 mm RMS distortion and 0.02 mm noise."""
    grid = grid_targets()
    s, t = grid[:, 0] / 95.0, grid[:, 1] / 95.0
    r2 = s * s + t * t
    field = np.column_stack([0.55 * s + 0.25 * s * t + 0.35 * s ** 3 + 0.30 * s * r2,
                             0.30 * t - 0.20 * s * s + 0.15 * t ** 3 + 0.18 * t * r2])
    field *= 0.85 / math.sqrt(np.mean(np.sum(field ** 2, axis=1)))
    return grid, field + np.random.default_rng(seed).normal(0.0, 0.02, grid.shape)


def per_call_seconds(action, calls: int, batches: int) -> float:
    """Median over batches of the mean time per call (hides the timer's own cost)."""
    def batch() -> None:
        for _ in range(calls):
            action()
    return median_seconds(batch, batches) / calls


def main() -> None:
    X, Y = synthetic_samples()
    queries = np.random.default_rng(1).uniform(-95.0, 95.0, (100_000, 2))
    one = queries[:1].copy()

    print("OLS RBF network, 361 training points (19 x 19 over 190 mm)")
    for spread, goal in ((35.0, 0.0005), (35.0, 0.0002), (20.0, 0.0002)):
        network = OLSRBFNetwork(X, Y, spread, goal)
        train = median_seconds(lambda: OLSRBFNetwork(X, Y, spread, goal), 11)
        single = per_call_seconds(lambda: network(one), 2000, 9)
        batch = median_seconds(lambda: network(queries), 11)
        form = "separable" if network._separable else "expanded"
        print(f"  spread {spread:4.0f} mm, goal {goal:.4f} mm^2: {network.neuron_count:3d} units ({form}); "
              f"train {train * 1e3:6.1f} ms, 1 point {single * 1e6:5.1f} us, "
              f"100 000 points {batch * 1e3:5.1f} ms")

    start = time.perf_counter()
    model, report = select_model(X, Y)
    selection = time.perf_counter() - start
    selection = statistics.median([selection] + [median_seconds(lambda: select_model(X, Y), 1) for _ in range(2)])
    print(f"select_model ({len(report.candidates)} candidates, {report.folds}-fold CV): "
          f"{selection:.2f} s, chose {report.method} {dict(report.chosen.parameters)} "
          f"(CV RMS {report.chosen.cv_rms_mm * 1e3:.1f} um)")

    tracemalloc.start()
    network = OLSRBFNetwork(X, Y)
    _, training_peak = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    network(queries)
    _, prediction_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(f"peak traced memory: training {training_peak / 2 ** 20:.1f} MiB, "
          f"100 000 predictions {prediction_peak / 2 ** 20:.1f} MiB (output alone 1.5 MiB); "
          f"process max RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
