"""The one-target U lookup (``UncertaintyGrid.at_point``) against the vector lookups it must equal."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gls_calibration.correction.uncertainty_grid import UncertaintyGrid


def _grid(x_mm, y_mm, seed: int = 0) -> UncertaintyGrid:
    rng = np.random.default_rng(seed)
    return UncertaintyGrid(x_mm, y_mm, rng.uniform(0.01, 0.05, (len(y_mm), len(x_mm))))


def _points(grid: UncertaintyGrid, seed: int = 1) -> np.ndarray:
    """Random points, every node, the box's corners and edges, and points just inside/outside the 1e-9 mm tolerance."""
    rng = np.random.default_rng(seed)
    xs, ys = grid.x_mm, grid.y_mm
    inside = np.column_stack([rng.uniform(xs[0], xs[-1], 2000), rng.uniform(ys[0], ys[-1], 2000)])
    nodes = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    edges = np.array([[xs[0], rng.uniform(ys[0], ys[-1])], [xs[-1], rng.uniform(ys[0], ys[-1])],
                      [rng.uniform(xs[0], xs[-1]), ys[0]], [rng.uniform(xs[0], xs[-1]), ys[-1]],
                      [xs[0] - 5e-10, ys[0] - 5e-10], [xs[-1] + 5e-10, ys[-1] + 5e-10]])
    return np.vstack([inside, nodes, edges])


@pytest.mark.parametrize("x_mm, y_mm", [
    (np.linspace(-97.7, 97.7, 80), np.linspace(-97.7, 97.7, 80)),     # equally spaced, as the package writes
    (np.linspace(-50.0, 70.0, 7), np.linspace(10.0, 20.0, 3)),         # few nodes, different steps per axis
    (np.linspace(0.0, 1.0, 2), np.linspace(-3.0, 3.0, 2)),             # one cell
    ([-90.0, -60.0, -5.0, 0.0, 42.0, 97.0], [-80.0, -79.0, 0.0, 30.0]),  # not equally spaced: the bisecting path
])
def test_one_point_lookup_equals_the_vector_lookups(x_mm, y_mm):
    grid = _grid(x_mm, y_mm)
    points = _points(grid)
    one = np.array([grid.at_point(px, py) for px, py in points.tolist()])
    assert np.isfinite(one).all()
    # equally spaced: bit for bit the vector path a batch uses; always the documented bilinear within rounding
    if grid._uniform:
        np.testing.assert_array_equal(one, grid.inside_at(points[:, 0], points[:, 1]))
    np.testing.assert_allclose(one, grid.inside_at(points[:, 0], points[:, 1]), rtol=1e-12, atol=0.0)
    np.testing.assert_allclose(one, grid.at(points[:, 0], points[:, 1]), rtol=1e-12, atol=0.0)
    # on a node the value stored there
    assert grid.at_point(float(grid.x_mm[1]), float(grid.y_mm[-1])) == grid.u_k2_mm[-1, 1]


def test_one_point_lookup_is_nan_outside_the_grid():
    grid = _grid(np.linspace(-10.0, 10.0, 5), np.linspace(0.0, 4.0, 3))
    for x, y in [(-10.0 - 2e-9, 1.0), (10.0 + 2e-9, 1.0), (0.0, -2e-9), (0.0, 4.0 + 2e-9), (1e9, -1e9)]:
        assert math.isnan(grid.at_point(x, y))
        assert math.isnan(grid.at(np.array([x]), np.array([y]))[0])
