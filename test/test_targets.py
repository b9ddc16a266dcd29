"""Tests of the target grid and ring polylines."""
import numpy as np
import pytest

from gls_calibration.fiducials.targets import grid_targets, ring_polyline, ring_segment_count, rings_polylines


def test_default_grid_is_19_by_19_over_190_mm_row_major():
    grid = grid_targets()
    assert grid.shape == (361, 2)
    np.testing.assert_allclose(grid.min(axis=0), [-95.0, -95.0])
    np.testing.assert_allclose(grid.max(axis=0), [95.0, 95.0])
    np.testing.assert_allclose(grid[1] - grid[0], [190.0 / 18, 0.0])     # x is the inner index
    np.testing.assert_allclose(grid[19] - grid[0], [0.0, 190.0 / 18])    # y is the outer index
    np.testing.assert_allclose(grid.mean(axis=0), [0.0, 0.0], atol=1e-12)


def test_grid_is_centred_where_asked():
    grid = grid_targets(per_side=4, size_mm=30.0, centre_xy=(10.0, -5.0))
    assert grid.shape == (16, 2)
    np.testing.assert_allclose(grid.mean(axis=0), [10.0, -5.0])
    np.testing.assert_allclose(np.ptp(grid, axis=0), [30.0, 30.0])


@pytest.mark.parametrize("kwargs, message", [
    ({"per_side": 1}, "per_side must be an integer >= 2"),
    ({"per_side": 2.5}, "per_side must be an integer >= 2"),
    ({"size_mm": 0.0}, "size_mm must be a positive finite number"),
    ({"size_mm": float("nan")}, "size_mm must be a positive finite number"),
    ({"centre_xy": (1.0, 2.0, 3.0)}, "centre_xy must hold 2 numbers"),
])
def test_grid_rejects_bad_input(kwargs, message):
    with pytest.raises(ValueError, match=message):
        grid_targets(**kwargs)


@pytest.mark.parametrize("radius, error", [(2.5, 0.005), (2.7, 0.005), (2.5, 0.001), (50.0, 0.01)])
def test_ring_polyline_keeps_the_chord_error_with_the_fewest_segments(radius, error):
    centre = np.array([3.0, -4.0])
    polyline = ring_polyline(centre, radius, error)
    assert np.array_equal(polyline[0], polyline[-1])
    np.testing.assert_allclose(np.linalg.norm(polyline - centre, axis=1), radius, rtol=1e-12)
    # Sagitta of every chord: distance from the circle to the chord's midpoint.
    midpoints = 0.5 * (polyline[1:] + polyline[:-1])
    sagitta = radius - np.linalg.norm(midpoints - centre, axis=1)
    assert sagitta.max() <= error + 1e-12
    segments = polyline.shape[0] - 1
    assert radius * (1.0 - np.cos(np.pi / (segments - 1))) > error    # one fewer would not do


def test_ring_segment_count_has_a_floor_of_three():
    assert ring_segment_count(1.0, 5.0) == 3


@pytest.mark.parametrize("args, message", [
    (((0.0, 0.0), 0.0), "radius_mm must be a positive finite number"),
    (((0.0, 0.0), 2.5, -0.1), "max_chord_error_mm must be a positive finite number"),
    (((0.0,), 2.5), "centre_xy must hold 2 numbers"),
])
def test_ring_polyline_rejects_bad_input(args, message):
    with pytest.raises(ValueError, match=message):
        ring_polyline(*args)


def test_rings_polylines_are_in_marking_order():
    centres = grid_targets(per_side=2, size_mm=10.0)
    rings = rings_polylines(centres, radii=(2.5, 2.7))
    assert len(rings) == 8
    for index, ring in enumerate(rings):
        centre, radius = centres[index // 2], (2.5, 2.7)[index % 2]
        np.testing.assert_allclose(np.linalg.norm(ring - centre, axis=1), radius)


def test_rings_polylines_rejects_non_positive_radius():
    with pytest.raises(ValueError, match="radii must be a positive finite number"):
        rings_polylines(np.zeros((1, 2)), radii=(2.5, 0.0))
