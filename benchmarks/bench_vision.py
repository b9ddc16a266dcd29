"""Speed of the vision stage: plate pose on 4 million points, 361 fiducials in a 2000x2000 scan.

Targets: plate pose <= 0.5 s, fiducial measurement <= 2 s (median wall time, this machine).
Also prints centre accuracy against the rendered truth and peak memory (numpy allocations traced by
tracemalloc per step; the process's peak resident set size from getrusage).

Run: .venv/bin/python benchmarks/bench_vision.py [--repeats 5]
"""
from __future__ import annotations

import argparse
from pathlib import Path
import resource
import statistics
import sys
import time
import tracemalloc

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from rendering import plate_to_scanner, render_plate_scan  # noqa: E402

from gls_calibration.fiducials import measure_fiducials  # noqa: E402
from gls_calibration.plate_pose import estimate_plate_pose  # noqa: E402

PER_SIDE = 19
PITCH_MM = 190.0 / 18
TILT = (0.01, -0.015)
OFFSET = (0.3, -0.2, 3.0)


def _timed(function, repeats: int):
    """Median and all wall times (s), peak traced allocation of one call (MB), last result."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    tracemalloc.start()
    function()
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return statistics.median(times), times, peak, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    rng = np.random.default_rng(2024)
    axis = (np.arange(PER_SIDE) - (PER_SIDE - 1) / 2) * PITCH_MM
    truth = np.array([(u, v) for v in axis for u in axis]) + rng.uniform(-0.05, 0.05, (PER_SIDE**2, 2))
    start = time.perf_counter()
    xyz, intensity = render_plate_scan(truth, tilt_rad=TILT, offset_mm=OFFSET, size_mm=(200.0, 200.0),
                                       noise=3.0, speckle=0.05, range_noise_mm=0.01,
                                       dropout_fraction=0.01, supersampling=4, seed=7)
    print(f"rendered {intensity.shape[0]}x{intensity.shape[1]} scan ({intensity.size / 1e6:.1f} M points) "
          f"with {len(truth)} fiducials in {time.perf_counter() - start:.1f} s")

    pose_median, pose_times, pose_peak, pose = _timed(lambda: estimate_plate_pose(xyz), args.repeats)
    print(f"plate pose, {intensity.size / 1e6:.1f} M points: median {pose_median:.3f} s "
          f"(runs {', '.join(f'{t:.3f}' for t in pose_times)}; target <= 0.5 s), "
          f"peak traced {pose_peak:.0f} MB, flatness {pose.flatness_rms_mm * 1000:.1f} um")

    fid_median, fid_times, fid_peak, measurement = _timed(
        lambda: measure_fiducials(xyz, intensity, pose, expected_count=len(truth)), args.repeats)
    distance, _ = cKDTree(measurement.centres).query(plate_to_scanner(truth, TILT, OFFSET))
    print(f"fiducials, {len(measurement.centres)} found (missing {measurement.missing}, merged "
          f"{measurement.merged}, rejected {measurement.rejected}): median {fid_median:.3f} s "
          f"(runs {', '.join(f'{t:.3f}' for t in fid_times)}; target <= 2 s), peak traced {fid_peak:.0f} MB")
    print(f"centre error vs truth: RMS {np.sqrt(np.mean(distance**2)) * 1000:.2f} um, "
          f"max {distance.max() * 1000:.2f} um (noise 3, speckle 5 %, 1 % dropouts)")
    print(f"process peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
