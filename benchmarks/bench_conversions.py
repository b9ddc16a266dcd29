"""Median times of PointCloud2 <-> numpy conversions for a 4,000,000-point x, y, z, intensity cloud.

Goal: message -> structured array (zero copy) well under 50 ms. Run:
    .venv/bin/python benchmarks/bench_conversions.py [--points N] [--repeats R]
"""
from __future__ import annotations

import argparse

import numpy as np

from gls_calibration.ros.conversions import (array_to_pointcloud2, cloud_arrays_from_msg, cloud_from_msg, cloud_to_msg,
                                             pointcloud2_to_array, xyz_intensity_arrays, xyzi_array)
from timing import median_seconds


def main() -> None:
    """Build a seeded cloud and print the median time of each conversion."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=4_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(12345)
    points = xyzi_array(rng.normal(size=(args.points, 3)), rng.random(args.points))
    points["z"][::97] = np.nan          # a few invalid points, as a scanner delivers them
    message = array_to_pointcloud2(points, "scanner")

    figures = {
        "array -> PointCloud2 (message build, little-endian)":
            lambda: array_to_pointcloud2(points, "scanner"),
        "array -> PointCloud2 (big-endian, byte swap)":
            lambda: array_to_pointcloud2(points, "scanner", big_endian=True),
        "PointCloud2 -> array (zero-copy view)":
            lambda: pointcloud2_to_array(message),
        "PointCloud2 -> array (skip_nans, copy)":
            lambda: pointcloud2_to_array(message, skip_nans=True),
        "structured -> float64 xyz, intensity":
            lambda: xyz_intensity_arrays(pointcloud2_to_array(message)),
        # The message boundary: clouds on the wire in metres, the core in mm.
        "mm array -> PointCloud2 in metres (cloud_to_msg)":
            lambda: cloud_to_msg(points, "scanner"),
        "PointCloud2 in metres -> mm array (cloud_from_msg)":
            lambda: cloud_from_msg(message),
        "PointCloud2 in metres -> float64 xyz mm (cloud_arrays_from_msg)":
            lambda: cloud_arrays_from_msg(message),
    }
    print(f"{args.points:,} points x, y, z, intensity (float32, {points.nbytes / 1e6:.0f} MB), "
          f"median of {args.repeats}:")
    for label, action in figures.items():
        print(f"  {label:<55s} {1e3 * median_seconds(action, args.repeats):9.3f} ms")


if __name__ == "__main__":
    main()
