"""Time of the whole discrepancy workflow on a 19x19 grid (361 points), every candidate effect, and of the CLI.

Targets: <= 1 s per run in-process; ``gls-discrepancy`` <= 3 s per run including start-up.
Data: the truth head with hidden effects (and, in one case, thermal drift with a shuffled marking
order, in others structure from outside the library or gross outliers), 0.015 mm noise, a random
rigid motion of the measured frame; the noise floor is stated (``sigma_mm``) except in the first
cases, which estimate it from the residual as before issue 13.
Run: .venv/bin/python benchmarks/bench_discrepancy.py
"""
from __future__ import annotations

import math
from pathlib import Path
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from gls_calibration.discrepancy import explain
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import PhysicalHead

REPEATS = 5
CLI_REPEATS = 3
NOISE_MM = 0.015


def measured(geometry: HeadGeometry, targets: np.ndarray, effects: dict, t, seed: int, extra=None) -> np.ndarray:
    rng = np.random.default_rng(seed)
    joints = inverse(geometry, targets[:, 0], targets[:, 1])
    landed = PhysicalHead(geometry, effects).land(joints.alpha_x, joints.alpha_y, t)[:, :2]
    if extra is not None:
        landed = landed + extra
    landed += rng.normal(0.0, NOISE_MM, landed.shape)
    angle = rng.uniform(-math.pi, math.pi)
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return landed @ rotation.T + rng.uniform(-50.0, 50.0, 2)


def main() -> None:
    """Print the median wall time per case, then the CLI's."""
    geometry = HeadGeometry()
    axis = np.linspace(-95.0, 95.0, 19)
    grid_x, grid_y = np.meshgrid(axis, axis)
    targets = np.column_stack([grid_x.ravel(), grid_y.ravel()])
    # shuffled marking order: with row-wise order a drift over time looks like a static field effect
    t = np.random.default_rng(0).permutation(np.arange(len(targets), dtype=float))
    periodic = np.column_stack([0.1 * np.sin(2 * np.pi * targets[:, 0] / 40.0), np.zeros(len(targets))])
    outliers = np.zeros_like(targets)
    outliers[[20, 200, 333]] = [[1.5, 0.0], [0.0, -2.0], [1.0, 1.0]]
    cases = {
        "no defect (residual floor)": ({}, None, None, None),
        "1 defect (radial_distortion, residual floor)": ({"radial_distortion": [2e-7]}, None, None, None),
        "2 defects (working_distance + plate_tilt)": ({"working_distance": [1.5], "plate_tilt": [0.01, 0.005]},
                                                      None, None, NOISE_MM),
        "3 defects with time (mirror_distance + axis_skew + thermal_drift)":
            ({"mirror_distance": [1.5], "axis_skew": [5e-3], "thermal_drift": [4e-6, 4e-6]}, t, None, NOISE_MM),
        "realistic (gains + skew + barrel)": ({"galvo_gain_x": [2.5e-3], "galvo_gain_y": [-1.5e-3], "axis_skew": [4e-3],
                                               "radial_distortion": [-2e-7]}, None, None, NOISE_MM),
        "out of library (periodic 0.1 mm) + gain": ({"galvo_gain_x": [3e-3]}, None, periodic, NOISE_MM),
        "3 gross outliers + gain": ({"galvo_gain_x": [3e-3]}, None, outliers, NOISE_MM),
    }
    for label, (effects, times, extra, sigma) in cases.items():
        data = measured(geometry, targets, effects, times, seed=1, extra=extra)
        durations, cpu = [], []
        for _ in range(REPEATS):
            start, start_cpu = time.perf_counter(), time.process_time()
            result = explain(targets, data, geometry, t=times, sigma_mm=sigma)
            durations.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
        print(f"{label:66s} median {statistics.median(durations):6.3f} s wall, {statistics.median(cpu):6.3f} s CPU  "
              f"named {', '.join(result.named_effects) or 'none'}; "
              f"RMS {result.rms_before_mm:.4f} -> {result.rms_after_mm:.4f} mm ({result.floor.source} floor "
              f"{result.noise_floor_mm:.4f}); {result.verdict.verdict}; {len(result.outliers)} outlier(s)")
    # the command-line tool, start-up included, on the realistic case
    data = measured(geometry, targets, cases["realistic (gains + skew + barrel)"][0], None, seed=1)
    executable = Path(sys.executable).with_name("gls-discrepancy")
    with tempfile.TemporaryDirectory() as folder:
        csv_path = Path(folder) / "marks.csv"
        csv_path.write_text("x_cmd,y_cmd,x_meas,y_meas\n" + "\n".join(
            f"{q[0]:.6f},{q[1]:.6f},{m[0]:.6f},{m[1]:.6f}" for q, m in zip(targets, data)) + "\n")
        durations, cpu = [], []
        for index in range(CLI_REPEATS):
            start = time.perf_counter()
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run([str(executable), "--measured", str(csv_path), "--out", str(Path(folder) / f"out{index}"),
                            "--sigma", str(NOISE_MM)], check=True, capture_output=True)
            durations.append(time.perf_counter() - start)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import gls_calibration.cli.discrepancy"], check=True)
        startup = time.perf_counter() - start
    print(f"{'gls-discrepancy CLI, realistic case, start-up and plots included':66s} median "
          f"{statistics.median(durations):6.3f} s wall, {statistics.median(cpu):6.3f} s CPU "
          f"(import of the CLI module alone {startup:.3f} s wall)")
    print(f"load average (2 cores shared): {', '.join(f'{v:.1f}' for v in __import__('os').getloadavg())}")


if __name__ == "__main__":
    main()
