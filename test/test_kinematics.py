"""Nominal kinematics: inverse and forward agree over the field, limits are flagged, never clipped."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gls_calibration.geometry.kinematics import HeadGeometry, forward, inverse

GEOMETRY = HeadGeometry()


def field_points(seed: int, count: int = 5000, half_mm: float = 120.0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return (rng.uniform(-half_mm, half_mm, count), rng.uniform(-half_mm, half_mm, count),
            rng.uniform(-20.0, 20.0, count))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_of_inverse_returns_the_target(seed):
    x, y, z = field_points(seed)
    joints = inverse(GEOMETRY, x, y, z)
    back_x, back_y = forward(GEOMETRY, joints.alpha_x, joints.alpha_y, z)
    assert np.max(np.abs(back_x - x)) < 1e-9
    assert np.max(np.abs(back_y - y)) < 1e-9


def test_focus_shift_is_the_extra_beam_path():
    x, y, z = field_points(3, count=200)
    joints = inverse(GEOMETRY, x, y, z)
    d, e = GEOMETRY.working_distance_mm, GEOMETRY.mirror_distance_mm
    expected = np.sqrt((e + np.sqrt((d - z) ** 2 + x ** 2)) ** 2 + y ** 2) - (e + d - z)
    assert np.allclose(joints.focus_shift, expected, atol=1e-12)
    centre = inverse(GEOMETRY, [0.0], [0.0])
    assert centre.alpha_x[0] == 0.0 and centre.alpha_y[0] == 0.0 and centre.focus_shift[0] == 0.0


def test_targets_beyond_the_limits_are_flagged_not_clipped():
    # On the work plane the focus range binds first: at x = 165 mm the mirrors are within 10.5 deg
    # but the beam path is 27 mm longer than at the centre.
    limit_x = GEOMETRY.working_distance_mm * math.tan(2.0 * GEOMETRY.mirror_limit_rad)
    x = np.array([0.0, 150.0, 1.01 * limit_x, 165.0])
    joints = inverse(GEOMETRY, x, np.zeros(4))
    assert joints.within_mirror_limits.tolist() == [True, True, False, True]
    assert joints.alpha_x[2] > GEOMETRY.mirror_limit_rad            # the real angle, not the limit
    assert joints.within_focus_range.tolist() == [True, True, False, False]
    assert joints.focus_shift[3] > GEOMETRY.focus_range_mm          # the real shift, not the limit
    assert joints.within_limits.tolist() == [True, True, False, False]


@pytest.mark.parametrize("args, message", [
    (([np.nan], [0.0]), r"x contains 1 NaN or infinite value\(s\)"),
    (([0.0], [np.inf]), r"y contains 1 NaN or infinite value\(s\)"),
    (([0.0, 1.0], [0.0]), r"x and y must have the same length, got 2 and 1"),
    (([0.0, 1.0], [0.0, 1.0], [0.0]), r"z must be empty or have the length of x \(2\), got 1"),
    (([], []), r"x must hold at least 1 point\(s\), got 0"),
])
def test_bad_targets_raise_exact_errors(args, message):
    with pytest.raises(ValueError, match=message):
        inverse(GEOMETRY, *args)


def test_bad_geometry_raises():
    with pytest.raises(ValueError, match=r"working_distance_mm must be a positive finite number, got -1.0"):
        HeadGeometry(working_distance_mm=-1.0)
    with pytest.raises(ValueError, match=r"mirror_distance_mm must be a non-negative finite number, got nan"):
        HeadGeometry(mirror_distance_mm=float("nan"))
