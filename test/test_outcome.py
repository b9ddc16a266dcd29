"""Tests of the typed deviation metrics and of the run summary of an outcome."""
import math

import numpy as np
import pytest

from gls_calibration.calibration.outcome import (CalibrationOutcome, DeviationMetrics, FieldMetrics, deviation_metrics,
                                                 summarise)
from gls_calibration.fiducials.targets import grid_targets


def test_metrics_of_a_constant_field_and_sub_field_counts():
    targets = grid_targets()
    metrics = deviation_metrics(targets, np.tile([0.3, -0.4], (361, 1)))
    assert list(metrics.fields) == ["full", "150x150", "50x50"]
    assert [metrics.field(size).count for size in (None, 150.0, 50.0)] == [361, 225, 25]
    for entry in metrics.fields.values():
        assert entry.max_ux_mm == pytest.approx(0.3)
        assert entry.rms_uy_mm == pytest.approx(0.4)
        assert entry.max_abs_mm == pytest.approx(0.5)
        assert entry.rms_abs_mm == pytest.approx(0.5)


def test_metrics_of_a_linear_field():
    targets = grid_targets(per_side=5, size_mm=100.0, centre_xy=(20.0, 30.0))
    field = np.column_stack([(targets[:, 0] - 20.0) * 0.01, -(targets[:, 1] - 30.0) * 0.002])
    metrics = deviation_metrics(targets, field, subfields_mm=(None, 50.0, 1.0))
    full = metrics.full
    assert full.max_ux_mm == pytest.approx(0.5)
    assert full.max_uy_mm == pytest.approx(0.1)
    assert full.rms_ux_mm == pytest.approx(math.sqrt(np.mean(field[:, 0] ** 2)))
    assert full.max_abs_mm == pytest.approx(math.hypot(0.5, 0.1))
    assert metrics.field(50.0).count == 9 and metrics.field(50.0).max_ux_mm == pytest.approx(0.25)
    assert metrics.field(1.0).count == 1 and metrics.field(1.0).max_abs_mm == 0.0


def test_metrics_of_an_empty_sub_field_are_nan():
    targets = grid_targets(per_side=2, size_mm=10.0)
    entry = deviation_metrics(targets, np.zeros((4, 2)), subfields_mm=(1.0,)).field(1.0)
    assert entry.count == 0 and math.isnan(entry.rms_abs_mm)


def test_metrics_reject_mismatched_lengths():
    with pytest.raises(ValueError, match="targets_xy and deviations must have the same number of points"):
        deviation_metrics(np.zeros((3, 2)), np.zeros((2, 2)))


def test_metrics_as_a_plain_dict_keep_the_field_and_key_order():
    metrics = deviation_metrics(grid_targets(3, 10.0), np.full((9, 2), 0.1), subfields_mm=(None, 5.0))
    plain = metrics.to_dict()
    assert list(plain) == ["full", "5x5"]
    assert list(plain["full"]) == ["count", "max_ux_mm", "rms_ux_mm", "max_uy_mm", "rms_uy_mm",
                                   "max_abs_mm", "rms_abs_mm"]
    assert plain["full"]["count"] == 9 and plain["5x5"]["count"] == 1


class _Run:
    """The parts of a PlateRun the summary reads."""

    def __init__(self, rms, count=9, true_rms=None):
        targets = grid_targets(3, 10.0)
        self.targets = np.zeros((count, 3))
        self.fiducials_found = count - 1
        self.metrics = deviation_metrics(targets, np.tile([rms, 0.0], (9, 1)))
        self.true_metrics = (None if true_rms is None
                             else deviation_metrics(targets, np.tile([0.0, true_rms], (9, 1)), (None, 150.0)))
        self.sweep_plan, self.cell_time_s = "0+,90+", 150.0
        self.chain_map = "none"
        self.sigma_mm = np.array([0.002, 0.004, np.nan, 0.003])
        self.scanner_error_rms_mm, self.motion_error_rms_mm = 0.03 * rms, 0.04 * rms


def test_summary_states_the_plan_the_cell_time_the_uncertainty_and_the_scanners_share():
    outcome = CalibrationOutcome("calibrated", (_Run(0.5), _Run(0.1)), _Run(0.02), (), None, 1.5)
    summary = summarise(outcome)
    assert summary.sweep_plan == "0+,90+" and summary.cell_time_s == pytest.approx(450.0)
    assert summary.fiducial_sigma_median_mm == pytest.approx(0.003)
    assert summary.fiducial_sigma_max_mm == pytest.approx(0.004)
    assert summary.scanner_share == pytest.approx(0.05)      # hypot(0.03, 0.04) of the first plate's RMS


def test_summary_of_a_run_without_training_has_nan_after_and_no_file():
    outcome = CalibrationOutcome("within tolerance", (_Run(0.01),), None, (), None, 1.5)
    summary = summarise(outcome)
    assert summary.pre_rms_mm == pytest.approx(0.01) and math.isnan(summary.post_rms_mm)
    assert math.isnan(summary.true_pre_rms_mm) and math.isnan(summary.true_post_rms_150_mm)
    assert (summary.calibration_file, summary.neurons, summary.method) == ("", 0, "")
    assert (summary.fiducials_expected, summary.fiducials_found, summary.iterations) == (9, 8, 1)
    assert summary.to_dict()["iteration_rms_mm"] == [pytest.approx(0.01)]


def test_summary_takes_after_figures_from_the_validation_plate():
    outcome = CalibrationOutcome("calibrated", (_Run(0.9, true_rms=0.8), _Run(0.2)), _Run(0.03, true_rms=0.02),
                                 (), None, 2.0)
    summary = summarise(outcome)
    assert summary.post_rms_mm == pytest.approx(0.03) and summary.true_post_rms_mm == pytest.approx(0.02)
    assert summary.true_post_rms_150_mm == pytest.approx(0.02)
    assert summary.true_pre_max_mm == pytest.approx(0.8)
    assert summary.iteration_rms_mm == (pytest.approx(0.9), pytest.approx(0.2))
    assert isinstance(outcome.runs[0].metrics, DeviationMetrics)
    assert isinstance(outcome.runs[0].metrics.full, FieldMetrics)
