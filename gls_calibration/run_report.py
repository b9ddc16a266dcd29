"""The report of one calibrate request: its outcome and summary drawn as the report's files."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gls_calibration.outcome import CalibrationOutcome, RunSummary
from gls_calibration.report import ReportData, write_report


def measurement_lines(summary: RunSummary) -> tuple[str, ...]:
    """What the report says about the measurement: sweep plan, cell time, uncertainty, separation."""
    lines = [f"sweep plan of the marked plate: {summary.sweep_plan}; simulated cell time of the whole "
             f"calibration (sweeps at the configured speed, robot moves, marking): {summary.cell_time_s / 60.0:.1f} min",
             f"measurement uncertainty per fiducial (standard, per axis, first plate): median "
             f"{summary.fiducial_sigma_median_mm:.4f} mm, max {summary.fiducial_sigma_max_mm:.4f} mm"]
    if np.isfinite(summary.scanner_share):
        lines.append(f"attributed to the scanner and the robot's motion, not the galvo: "
                     f"{summary.scanner_error_rms_mm:.4f} mm RMS fixed to the scanner frame, "
                     f"{summary.motion_error_rms_mm:.4f} mm RMS of per-sweep motion "
                     f"({summary.scanner_share:.1%} of the measured deviation RMS)")
    return tuple(lines)


def write_outcome_report(out_dir: Path, outcome: CalibrationOutcome, summary: RunSummary) -> Path:
    """Write report.md, plots, fiducials.csv and summary.json for ``outcome``; the folder's path."""
    first, validation = outcome.runs[0], outcome.validation
    field = None
    correction = outcome.candidate.correction if outcome.candidate else None
    if correction is not None and correction.models:
        def field(points):
            dx, dy, _ = correction.deviation(points[:, 0], points[:, 1])
            return np.column_stack([dx, dy])

    def plain(metrics):
        return metrics.to_dict() if metrics is not None else None
    data = ReportData(
        targets_xy=first.paired_targets_xy, deviations_before=first.deviations,
        metrics_before=plain(first.metrics), summary=summary.to_dict(),
        targets_after=validation.paired_targets_xy if validation else None,
        deviations_after=validation.deviations if validation else None,
        metrics_after=plain(validation.metrics) if validation else None,
        true_before=first.true_deviations, true_after=validation.true_deviations if validation else None,
        true_metrics_before=plain(first.true_metrics),
        true_metrics_after=plain(validation.true_metrics) if validation else None,
        correction_field=field,
        extra_lines=tuple(f"iteration {index + 1}: measured RMS {rms:.4f} mm"
                          for index, rms in enumerate(summary.iteration_rms_mm)) + measurement_lines(summary)
        + (outcome.message,),
    )
    write_report(out_dir, data)
    return out_dir
