"""Core checks behind the fault handling: profile validation, deadlines, focus range, settings."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.correction.setpoints import Correction
from gls_calibration.geometry import kinematics
from gls_calibration.ros.conversions import xyzi_array
from gls_calibration.ros.deadlines import Deadlines
from gls_calibration.scan.sweep import SweepCollector, profile_problem

GEOMETRY = kinematics.HeadGeometry()


def good_profile(points: int = 5) -> np.ndarray:
    rng = np.random.default_rng(0)
    return xyzi_array(np.column_stack([np.linspace(-1, 1, points), np.zeros(points), 300 + rng.random(points)]),
                      rng.random(points))


def test_a_good_profile_passes_and_one_nan_point_is_a_missing_return():
    profile = good_profile()
    assert profile_problem(0.0, profile) == ""
    profile["z"][2] = np.nan
    assert profile_problem(1.5, profile) == ""


@pytest.mark.parametrize("stamp", [-1.0, math.nan, math.inf])
def test_bad_stamps_are_refused(stamp):
    assert "not a finite non-negative time" in profile_problem(stamp, good_profile())


def test_bad_profiles_are_refused_with_the_reason():
    nan_only = good_profile()
    for name in ("x", "y", "z"):
        nan_only[name] = np.nan
    assert profile_problem(0.0, nan_only) == "profile has no finite point"
    infinite = good_profile()
    infinite["x"][0] = np.inf
    assert profile_problem(0.0, infinite) == "profile has infinite coordinates"
    missing = np.zeros(3, dtype=[("x", np.float32), ("y", np.float32), ("z", np.float32)])
    assert profile_problem(0.0, missing) == "profile has no field intensity (fields: x, y, z)"
    pairs = np.zeros(3, dtype=[("x", np.float32, (2,)), ("y", np.float32), ("z", np.float32),
                               ("intensity", np.float32)])
    assert profile_problem(0.0, pairs) == "profile field x has count 2; 1 is expected"
    assert profile_problem(0.0, good_profile(0)) == "profile has no points"


def test_the_collector_refuses_a_bad_profile_and_keeps_nothing():
    collector = SweepCollector(10, 10)
    with pytest.raises(ValueError, match="not a finite non-negative time"):
        collector.add(-1.0, good_profile())
    assert len(collector) == 0 and collector.dropped == 0
    assert collector.add(0.0, good_profile())
    assert len(collector) == 1


def test_deadlines_follow_the_work():
    deadlines = Deadlines(sweep_length_mm=200.0, sweep_speed_mm_s=20.0, marking_speed_mm_s=500.0,
                          jump_time_s=0.01, factor=2.0, margin_s=5.0)
    assert deadlines.sweep_s() == pytest.approx(2.0 * 10.0 + 5.0)
    # two polylines: a 100 mm line and a 50 mm line, with a jump of 1000 mm between them (not marked)
    xy = np.array([[0.0, 0.0], [100.0, 0.0], [1100.0, 0.0], [1150.0, 0.0]])
    assert deadlines.marking_s(xy, [0, 2]) == pytest.approx(2.0 * (150.0 / 500.0 + 2 * 0.01) + 5.0)
    longer = Deadlines(sweep_length_mm=400.0, sweep_speed_mm_s=20.0, marking_speed_mm_s=250.0,
                       jump_time_s=0.01, factor=2.0, margin_s=5.0)
    assert longer.sweep_s() > deadlines.sweep_s()
    assert longer.marking_s(xy, [0, 2]) > deadlines.marking_s(xy, [0, 2])


@pytest.mark.parametrize("name, value", [("sweep_speed_mm_s", 0.0), ("margin_s", math.nan), ("factor", 0.5),
                                         ("jump_time_s", -1.0), ("sweep_length_mm", math.inf)])
def test_deadlines_refuse_nonsense(name, value):
    values = dict(sweep_length_mm=200.0, sweep_speed_mm_s=20.0, marking_speed_mm_s=500.0, jump_time_s=0.01,
                  factor=2.0, margin_s=5.0)
    values[name] = value
    with pytest.raises(ValueError, match=name):
        Deadlines(**values)


def test_a_target_height_beyond_the_focus_range_is_flagged():
    correction = Correction(GEOMETRY)
    limit = GEOMETRY.focus_range_mm
    result = correction.correct([0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, limit, limit + 0.01, 4 * limit])
    assert result.within_limits.tolist() == [True, True, False, False]
    assert result.within_limits[-1] == False  # noqa: E712  (the issue's case: z = +100 mm)


@pytest.mark.parametrize("radii", [(), (-2.5, 2.7), (2.7, 2.5), (2.5, math.nan), (0.0, 1.0)])
def test_settings_refuse_bad_ring_radii(radii):
    with pytest.raises(ValueError, match="ring_radii_mm must be one or more positive finite radii"):
        ProcedureSettings(ring_radii_mm=radii)


def test_iterations_are_bounded():
    settings = ProcedureSettings(max_iterations=3)
    assert settings.iterations_problem(0) == settings.iterations_problem(3) == ""
    assert settings.iterations_problem(255) == "iterations must be 0 (the default, 1) or 1 to 3, got 255"
    with pytest.raises(ValueError, match="default_iterations must be between 1 and max_iterations"):
        ProcedureSettings(default_iterations=4, max_iterations=3)
