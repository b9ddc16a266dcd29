"""Speed of the simulated cell: ray trace, marking a 19x19 ring grid, a full 200x200 mm sweep at 0.1 mm.

Prints median wall times and the peak memory of the sweep. Goals: a full sweep (about 4 M points)
in at most 5 s; 1e5 ray traces well under 50 ms.
"""
from __future__ import annotations

import tracemalloc

import numpy as np

from gls_calibration.geometry.optics import PhysicalHead
from gls_calibration.simulation.world import SimulatedCell, load_sim_config
from timing import median_seconds


def main() -> None:
    config = load_sim_config()
    rng = np.random.default_rng(0)
    limit = config.geometry.mirror_limit_rad
    alpha_x, alpha_y = rng.uniform(-limit, limit, (2, 100_000))
    head = PhysicalHead(config.geometry, config.effects)
    print("ray trace, 1e5 points, all effects: "
          f"{1e3 * median_seconds(lambda: head.land(alpha_x, alpha_y, 1.0), 9):.1f} ms")

    offsets = np.linspace(-95.0, 95.0, 19)
    angles = np.linspace(0.0, 2.0 * np.pi, 721)
    rings = [np.column_stack([cx + r * np.cos(angles), cy + r * np.sin(angles)])
             for cy in offsets for cx in offsets for r in (2.5, 2.7)]

    def mark_grid() -> SimulatedCell:
        cell = SimulatedCell(config)
        cell.mark_cartesian(rings)
        return cell

    print(f"mark 19x19 double rings (722 polylines, 721 vertices): {median_seconds(mark_grid, 3):.2f} s")
    cell = mark_grid()
    sweep = median_seconds(lambda: cell.sweep_cloud(seed=1), 3)
    tracemalloc.start()
    xyz, intensity = cell.sweep_cloud(seed=1)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    points = xyz.shape[0] * xyz.shape[1]
    print(f"full sweep {config.sweep_length_mm:.0f} mm x {config.scanner.line_length_mm:.0f} mm at "
          f"{config.scanner.step_mm} mm: {xyz.shape[0]} x {xyz.shape[1]} = {points / 1e6:.2f} M points, "
          f"{sweep:.2f} s (goal <= 5 s), peak memory {peak / 2**20:.0f} MiB, "
          f"result {(xyz.nbytes + intensity.nbytes) / 2**20:.0f} MiB")


if __name__ == "__main__":
    main()
