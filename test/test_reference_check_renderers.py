"""The reference check's measurement on plates from two independent renderers.

``measure_reference_plate`` (detection, combination, pairing) and ``chain_sigma_mm`` take a plate
scanned by ``test/rendering.py`` (a regular scan, handed over flattened as a ``.pcd`` export carries
it) and by ``test/rendering_independent.py`` (jittered scan lines, no lattice). A chain error is put
into the points' coordinates, as a robot that reports its pose wrongly puts it there: the check
must report it, not the renderer's lattice (found with this test: the regular scan's points were
binned on their lattice, which erased a smooth displacement below half a pixel, 0.0137 mm RMS
reported as 0.0079 mm).
"""
from __future__ import annotations

import numpy as np
import pytest

from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.calibration.reference_check import chain_sigma_mm, measure_reference_plate
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.registration.sweep_plan import parse_plan

from plate_renderers import RENDERERS, render

PER_SIDE = 5
CLEAN_LIMIT_MM = 0.004          # the bag tool's ideal-chain limit (test_reference_check_tool.py)
AMPLITUDE_MM = 0.03             # a robot's repeating path error (issue 32: 0.05 mm, 20 mm correlation)


def _chain_error(points: np.ndarray) -> np.ndarray:
    """A smooth non-rigid displacement (N, 3) of scanner-frame points, mm: no rigid motion takes it out."""
    displacement = np.zeros_like(points)
    displacement[:, 0] = AMPLITUDE_MM * np.sin(2 * np.pi * points[:, 1] / 60.0)
    displacement[:, 1] = AMPLITUDE_MM * np.cos(2 * np.pi * points[:, 0] / 45.0)
    return displacement


def _ring_mean_error(centres: np.ndarray) -> np.ndarray:
    """The displacement a ring's centre takes: the field's mean over its two circles (N, 3), mm."""
    angle = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    circles = [centres[:, None, :2] + radius * np.stack([np.cos(angle), np.sin(angle)], -1)
               for radius in RING_RADII_MM]
    on_circles = np.concatenate(circles, axis=1)                     # (N, 1440, 2)
    flat = np.column_stack([on_circles.reshape(-1, 2), np.zeros(on_circles.shape[0] * on_circles.shape[1])])
    return _chain_error(flat).reshape(on_circles.shape[0], -1, 3).mean(axis=1)


def _check(points: np.ndarray, intensity: np.ndarray, known: np.ndarray) -> tuple[float, float]:
    settings = ProcedureSettings(grid_per_side=PER_SIDE, grid_size_mm=50.0, sweep_plan=parse_plan("0+"),
                                 plain_sweeps=1, standstill_height=False, profiles_placed_by_pose=True,
                                 scanner_to_gls=RigidTransform(np.eye(3), np.zeros(3)))
    measured, paired = measure_reference_plate([points], [(points, intensity)], settings, known)
    assert len(measured) == PER_SIDE ** 2
    sigma, _ = chain_sigma_mm([measured], [paired])
    return sigma


@pytest.mark.parametrize("renderer", RENDERERS)
def test_the_check_reports_the_chain_error_in_the_points_not_the_scan_lattice(renderer):
    cloud, truth = render(renderer, "pitch_0.1", PER_SIDE, seed=0)
    points, intensity = cloud[:, :3], cloud[:, 3]
    assert max(_check(points, intensity, truth)) < CLEAN_LIMIT_MM
    # rigid motions of the whole plate are not the chain's error: the check takes them out
    turn = np.deg2rad(0.3)
    rotation = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]])
    moved = (points - truth.mean(axis=0)) @ rotation.T + truth.mean(axis=0) + [0.4, -0.25, 0.0]
    assert max(_check(moved, intensity, truth)) < CLEAN_LIMIT_MM
    # a smooth chain error of 0.03 mm comes out as its RMS after the best rigid motion (within 5 %:
    # the detector's own few micrometres add in quadrature)
    expected, _ = chain_sigma_mm([truth + _ring_mean_error(truth)], [truth])
    assert min(expected) > 5 * CLEAN_LIMIT_MM / 2
    measured = _check(points + _chain_error(points), intensity, truth)
    np.testing.assert_allclose(measured, expected, rtol=0.05)
