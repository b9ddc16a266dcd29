"""Median time of the whole discrepancy workflow on a 19x19 grid (361 points), all candidate effects.

Target: <= 2 s per run. Data: the truth head with two hidden effects (and, in the second case,
thermal drift with a shuffled marking order), 0.015 mm noise, a random rigid motion of the measured frame.
Run: .venv/bin/python benchmarks/bench_discrepancy.py
"""
from __future__ import annotations

import math
import statistics
import time

import numpy as np

from gls_calibration.discrepancy import explain
from gls_calibration.kinematics import HeadGeometry, inverse
from gls_calibration.optics import PhysicalHead

REPEATS = 5


def measured(geometry: HeadGeometry, targets: np.ndarray, effects: dict, t, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    joints = inverse(geometry, targets[:, 0], targets[:, 1])
    landed = PhysicalHead(geometry, effects).land(joints.alpha_x, joints.alpha_y, t)[:, :2]
    landed += rng.normal(0.0, 0.015, landed.shape)
    angle = rng.uniform(-math.pi, math.pi)
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return landed @ rotation.T + rng.uniform(-50.0, 50.0, 2)


def main() -> None:
    """Print median wall time per case."""
    geometry = HeadGeometry()
    axis = np.linspace(-95.0, 95.0, 19)
    grid_x, grid_y = np.meshgrid(axis, axis)
    targets = np.column_stack([grid_x.ravel(), grid_y.ravel()])
    # shuffled marking order: with row-wise order a drift over time looks like a static field effect
    t = np.random.default_rng(0).permutation(np.arange(len(targets), dtype=float))
    cases = {
        "no defect": ({}, None),
        "1 defect (radial_distortion)": ({"radial_distortion": [2e-7]}, None),
        "2 defects (working_distance + plate_tilt)": ({"working_distance": [1.5], "plate_tilt": [0.01, 0.005]}, None),
        "3 defects with time (mirror_distance + axis_skew + thermal_drift)":
            ({"mirror_distance": [1.5], "axis_skew": [5e-3], "thermal_drift": [4e-6, 4e-6]}, t),
    }
    for label, (effects, times) in cases.items():
        data = measured(geometry, targets, effects, times, seed=1)
        durations = []
        for _ in range(REPEATS):
            start = time.perf_counter()
            result = explain(targets, data, geometry, t=times)
            durations.append(time.perf_counter() - start)
        print(f"{label:68s} median {statistics.median(durations):6.3f} s  "
              f"named {', '.join(result.named_effects) or 'none'}; "
              f"RMS {result.rms_before_mm:.4f} -> {result.rms_after_mm:.4f} mm (floor {result.noise_floor_mm:.4f})")


if __name__ == "__main__":
    main()
