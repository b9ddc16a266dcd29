"""The plate height at marking, from profiles taken with the robot standing still (issue 31 item 5).

A sweep's path is off by the robot's repeatability (+-0.05 mm per sweep), so the plate height from
the plain sweeps is off too and scales the marked field by dz/d. Standing at the marking pose, the
scanner measures the plate without travel, where the head held by the same robot marks it.
"""
from __future__ import annotations

import asyncio
import dataclasses

import numpy as np
import pytest

from gls_calibration.calibration import procedure
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.scan.plate_pose import MIN_HEIGHT_POINTS, estimate_plate_pose, pose_at_height
from gls_calibration.simulation.world import SimulatedCell

from test_procedure import FAST, new_cell, small_config


def test_the_height_comes_from_the_points_and_the_tilt_from_the_pose():
    rng = np.random.default_rng(4)
    xy = rng.uniform(-100.0, 100.0, (5000, 2))
    tilted = np.column_stack([xy, 300.0 + 1e-3 * xy[:, 0] - 2e-3 * xy[:, 1]])
    pose = estimate_plate_pose(tilted)
    # one line of the plate, 0.03 mm off the pose's plane, with noise and two stray points
    x = np.linspace(-90.0, 90.0, 1800)
    line = np.column_stack([x, np.full_like(x, 12.0), 300.0 + 1e-3 * x - 2e-3 * 12.0 + 0.03
                            + 0.015 * rng.standard_normal(x.size)])
    line = np.vstack([line, [[0.0, 12.0, 310.0], [5.0, 12.0, np.nan]]])
    moved = pose_at_height(pose, line)
    np.testing.assert_allclose(moved.normal, pose.normal)
    assert np.mean(moved.distance(line[:-2])) == pytest.approx(0.0, abs=1e-3)
    assert pose.distance(moved.centre[None])[0] == pytest.approx(0.03 * abs(pose.normal[2]), abs=1.5e-3)
    with pytest.raises(ValueError, match=f"the stand-still profiles hold 99 finite points; at least "
                                         f"{MIN_HEIGHT_POINTS} are needed for the plate height"):
        pose_at_height(pose, line[:99])


def gls_height(cell: SimulatedCell, points) -> float:
    """Mean height (mm, along gls z) of base-frame points above the true plate plane (CAD mounting;
    the default mounting error is zero)."""
    points = points.reshape(-1, 3)
    gls = cell.scanner.to_gls(points[np.all(np.isfinite(points), axis=1)])
    normal, origin = cell.plate.normal, cell.plate.origin
    plane_z = origin[2] - ((gls[:, 0] - origin[0]) * normal[0] + (gls[:, 1] - origin[1]) * normal[1]) / normal[2]
    return float(np.mean(gls[:, 2] - plane_z))


def with_repeatability(config, bound_mm: float):
    return dataclasses.replace(config, scanner=dataclasses.replace(config.scanner, path_repeatability_mm=bound_mm))


def test_standing_still_the_scanner_sees_the_plate_where_the_head_marks_it():
    # the plate as this scanner sees it from a path without error (its own range bias included)
    reference = SimulatedCell(with_repeatability(small_config(), 0.0))
    true_z = gls_height(reference, reference.sweep_data(step_mm=2.0, seed=0).placed_by_pose())
    cell = SimulatedCell(with_repeatability(small_config(), 0.2))
    sweeps = [gls_height(cell, cell.sweep_data(step_mm=2.0, seed=seed).placed_by_pose()) for seed in range(4)]
    still = [gls_height(cell, cell.standstill_data(20, seed=seed).placed_by_pose()) for seed in range(4)]
    # each sweep's height is off by its path error; standing still, by the sensor's noise only
    assert max(abs(z - true_z) for z in sweeps) > 0.02
    assert max(abs(z - true_z) for z in still) < 0.002
    # the robot-held head off by its marking-pose error: the scanner held with it sees the same
    cell.plate.marking_pose_error = (0.04, 0.0, 0.0)
    shifted = gls_height(cell, cell.standstill_data(20, seed=0).placed_by_pose())
    assert shifted - still[0] == pytest.approx(0.04, abs=0.001)
    with pytest.raises(ValueError, match="profiles must be a positive integer, got 0"):
        cell.standstill_data(0, seed=0)


def test_the_standstill_does_not_take_the_sweeps_random_draws(tmp_path):
    """An earlier attempt numbered the stand-still as a sweep: every later sweep changed."""
    plain, with_standstill = new_cell(tmp_path / "a"), new_cell(tmp_path / "b")
    asyncio.run(plain.acquire_sweep(2.0))
    asyncio.run(with_standstill.acquire_sweep(2.0))
    asyncio.run(with_standstill.acquire_standstill(5))
    expected = asyncio.run(plain.acquire_sweep(2.0))
    got = asyncio.run(with_standstill.acquire_sweep(2.0))
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    assert with_standstill.sweeps == 2 and with_standstill.standstills == 1


def marked_heights(tmp_path, repeatability_mm: float, standstill: bool) -> np.ndarray:
    """The heights (gls z) the targets of one plate are commanded at; one plain sweep."""
    cell = new_cell(tmp_path)
    cell.sim = SimulatedCell(with_repeatability(small_config(), repeatability_mm))
    settings = cell.settings(**FAST, standstill_height=standstill)
    run = asyncio.run(procedure.run_plate(cell, settings, grid_targets(5, 90.0), lambda *_: None, (0.0, 1.0), True))
    assert cell.standstills == (1 if standstill else 0) and cell.sweeps == 2   # one plain, one marked sweep
    return run.targets[:, 2]


def test_targets_are_commanded_at_the_height_the_plate_has_at_marking(tmp_path):
    exact = marked_heights(tmp_path / "exact", 0.0, False)     # a robot path without error
    assert np.abs(marked_heights(tmp_path / "still", 0.2, True) - exact).max() < 0.003
    # from the sweep alone: off by its path error (uniform within +-0.2 mm; well over 0.01 mm on this seed)
    assert np.abs(marked_heights(tmp_path / "swept", 0.2, False) - exact).max() > 0.01


def test_standstill_profiles_must_be_a_positive_integer():
    with pytest.raises(ValueError, match="standstill_profiles must be a positive integer, got 0"):
        procedure.ProcedureSettings(standstill_profiles=0)
