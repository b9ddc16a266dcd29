"""Fiducial measurement on rendered scans of real-plate conditions (issue 11), and its quality figures.

Every condition of ``rendering.vision_conditions`` is rendered (independently of the package's
simulator) as a 5x5 grid at the 19x19 plate's pitch, one as the full 19x19 plate. Targets at 0.1 mm
pitch: every fiducial found, per-axis centre RMS <= 10 um against the TRUE rendered centres, no
accepted centre off by more than 30 um or by more than 3x its stated standard uncertainty.
"""
from functools import lru_cache

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gls_calibration.fiducials.measure import measure_fiducials
from gls_calibration.scan.plate_pose import estimate_plate_pose
from rendering import BASE_SCAN, grid_truth, plate_to_scanner, render_condition, render_plate_scan

PER_SIDE = 5
# The conditions the issue names (the benchmark adds combinations beyond them).
ISSUE_CONDITIONS = ("clean", "speckle_0.3", "speckle_0.3_corr2", "marks_85pct", "marks_bright", "scratches",
                    "pitch_0.07", "pitch_0.15", "pitch_0.07x0.15", "unorganized", "rotation_15deg",
                    "rotation_-15deg", "tilt_3deg", "dropouts_1pct", "unorganized_irregular",
                    "unorganized_turned_20deg")


@lru_cache(maxsize=None)
def measured(name: str, per_side: int = PER_SIDE):
    """Measurement (polarity found by the measurement) and true centres of one rendered condition."""
    xyz, intensity, truth, _ = render_condition(name, per_side, seed=11)
    pose = estimate_plate_pose(xyz)
    return measure_fiducials(xyz, intensity, pose, expected_count=per_side**2, marks_darker=None), truth


def per_axis_errors(measurement, truth):
    """Per-axis errors (K, 2) of the accepted centres against their nearest true centre, and its index."""
    _, index = cKDTree(truth).query(measurement.centres)
    return measurement.centres[:, :2] - truth[index, :2], index


@pytest.mark.parametrize("name", ISSUE_CONDITIONS)
def test_every_fiducial_found_within_target(name):
    measurement, truth = measured(name)
    error, index = per_axis_errors(measurement, truth)
    assert len(measurement.centres) == len(truth) and len(np.unique(index)) == len(truth)
    assert np.all(np.sqrt(np.mean(error**2, axis=0)) <= 0.010)
    assert np.abs(error).max() <= 0.030


@pytest.mark.parametrize("name", ISSUE_CONDITIONS)
def test_accepted_centres_within_three_sigma(name):
    measurement, truth = measured(name)
    error, _ = per_axis_errors(measurement, truth)
    assert np.all(np.abs(error) <= 3 * measurement.sigma_xy_mm)


@pytest.mark.parametrize("name", ISSUE_CONDITIONS)
def test_quality_figures_are_reported_per_centre(name):
    measurement, _ = measured(name)
    count = len(measurement.centres)
    assert measurement.sigma_xy_mm.shape == (count, 2) and measurement.coverage.shape == (count,)
    assert np.all((measurement.sigma_xy_mm > 0) & (measurement.sigma_xy_mm <= 0.010))
    assert np.all((measurement.coverage >= 0.75) & (measurement.coverage <= 1.0))
    assert len(measurement.rejected_reasons) == measurement.rejected == len(measurement.rejected_centres)


def test_bright_marks_are_found_without_being_told():
    measurement, _ = measured("marks_bright")
    assert len(measurement.centres) == PER_SIDE**2


@pytest.mark.slow
def test_full_plate_19x19_with_speckle():
    measurement, truth = measured("speckle_0.3", 19)
    error, index = per_axis_errors(measurement, truth)
    assert len(measurement.centres) == 361 and len(np.unique(index)) == 361
    assert np.all(np.sqrt(np.mean(error**2, axis=0)) <= 0.010)
    assert np.abs(error).max() <= 0.030


def _render(truth_uv, **scan):
    xyz, intensity = render_plate_scan(truth_uv, size_mm=(60.0, 60.0), **dict(BASE_SCAN, **scan))
    return xyz, intensity, plate_to_scanner(truth_uv, BASE_SCAN["tilt_rad"], BASE_SCAN["offset_mm"])


@pytest.mark.parametrize("arc_rad", [np.pi, 0.35 * np.pi])
@pytest.mark.parametrize("speckle", [0.0, 0.1])
def test_half_erased_rings_are_rejected_or_accurate(arc_rad, speckle):
    truth_uv = grid_truth(PER_SIDE, seed=12)
    erased = {6: (0.3, 0.3 + arc_rad), 12: (2.0, 2.0 + arc_rad), 18: (-1.0, -1.0 + arc_rad)}
    xyz, intensity, truth = _render(truth_uv, erased=erased, speckle=speckle, speckle_corr_px=1.5)
    measurement = measure_fiducials(xyz, intensity, estimate_plate_pose(xyz), expected_count=PER_SIDE**2)
    error, index = per_axis_errors(measurement, truth)
    assert np.abs(error).max() <= 0.030
    # With 0.1 speckle this failed (3.3-3.4x) before the spectral uncertainty (2.97x now).
    assert np.all(np.abs(error) <= 3 * measurement.sigma_xy_mm)
    damaged = np.isin(index, list(erased))
    if arc_rad == np.pi:
        # Half a ring: listed as partial, never accepted.
        assert not damaged.any()
        _, rejected_index = cKDTree(truth).query(measurement.rejected_centres)
        reasons = [reason for reason, k in zip(measurement.rejected_reasons, rejected_index) if k in erased]
        assert reasons.count("partial") >= 3
    else:
        # A small gap (17 % of the circumference): accepted with the coverage that was seen.
        assert damaged.sum() == 3
        assert np.all(measurement.coverage[damaged] < 0.95)
    assert len(measurement.centres) == PER_SIDE**2 - (3 if arc_rad == np.pi else 0)


def test_overlapping_rings_are_not_accepted_off_target():
    # Two fiducials 0.3 mm apart (one merged detection) between two normal ones. Its mean radii
    # (+0.06/+0.09 mm) pass the 0.12 mm tolerance an uncalibrated head needs; its rings' semi-axes
    # (the envelope of two offset rings is elliptical, second harmonic about 0.09 mm) do not.
    truth_uv = np.array([[-15.0, 0.0], [0.0, 0.0], [0.3, 0.1], [15.0, 0.0]])
    xyz, intensity, truth = _render(truth_uv)
    measurement = measure_fiducials(xyz, intensity, estimate_plate_pose(xyz), allow_empty=True)
    error, index = per_axis_errors(measurement, truth)
    assert np.abs(error).max() <= 0.030
    assert set(index.tolist()) == {0, 3}
    # One candidate for the pair, turned down: its rings are neither whole nor of the nominal size.
    assert len(measurement.rejected_reasons) == 1 and measurement.rejected_reasons[0] in ("partial", "radius")


def test_bare_speckled_steel_gives_no_fiducial():
    xyz, intensity, _ = _render(np.empty((0, 2)), speckle=0.3, speckle_corr_px=1.5)
    measurement = measure_fiducials(xyz, intensity, estimate_plate_pose(xyz), allow_empty=True)
    assert len(measurement.centres) == 0
    assert all(reason != "ok" for reason in measurement.rejected_reasons)


@pytest.mark.parametrize("speckle", [0.0, 0.3])
@pytest.mark.parametrize("separation_mm", [0.11, 0.16, 0.21])
def test_close_pairs_are_rejected_as_merged(separation_mm, speckle):
    # Two fiducials s apart in the middle of a 5x5 plate: one detection whose ring radii and shape
    # pass the tolerances an uncalibrated head needs, about s / 2 from either true centre. Its lines
    # split along the offset and coincide across it: rejected as merged, also under 0.3 speckle
    # (accepted 55-105 um off there before the pair's signature was fitted on the prewhitened pixels).
    truth_uv = grid_truth(PER_SIDE, seed=12)
    pair = truth_uv[12] + separation_mm * np.array([0.3, 0.1]) / np.hypot(0.3, 0.1)
    truth_uv = np.vstack([truth_uv, pair])
    xyz, intensity, truth = _render(truth_uv, speckle=speckle, speckle_corr_px=1.5 if speckle else 0.0)
    measurement = measure_fiducials(xyz, intensity, estimate_plate_pose(xyz), expected_count=PER_SIDE**2)
    error, index = per_axis_errors(measurement, truth)
    assert np.all(np.abs(error) <= 3 * measurement.sigma_xy_mm) and np.abs(error).max() <= 0.030
    assert set(index.tolist()) == set(range(PER_SIDE**2)) - {12}
    _, rejected_index = cKDTree(truth).query(measurement.rejected_centres)
    reasons = [reason for reason, k in zip(measurement.rejected_reasons, rejected_index) if k in (12, 25)]
    assert "merged" in reasons


@pytest.mark.slow
def test_irregular_cloud_on_a_tilted_plate_is_not_stretched():
    # Points one per cell of the scanner's grid, jittered (no lattice to follow): a raster on the
    # plate's plane beat against the foreshortened cells and stretched the measured plate by 43 ppm
    # (4 um at its edge, beyond the centres' uncertainty); on the cloud's x-y it stays within 2 ppm.
    measurement, truth = measured("unorganized_irregular", 19)
    error, index = per_axis_errors(measurement, truth)
    design = np.column_stack([measurement.centres[:, :2], np.ones(len(index))])
    linear = np.linalg.lstsq(design, truth[index, :2], rcond=None)[0][:2].T
    stretch = np.linalg.eigvalsh(linear.T @ linear) ** 0.5 - 1.0
    assert len(measurement.centres) == 361 and np.abs(stretch).max() <= 10e-6
    assert np.all(np.sqrt(np.mean(error**2, axis=0)) <= 0.010) and np.abs(error).max() <= 0.030
