"""The report of one calibrate request: its outcome and summary drawn as the report's files."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gls_calibration.outcome import CalibrationOutcome, RunSummary
from gls_calibration.report import ReportData, write_report


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
                          for index, rms in enumerate(summary.iteration_rms_mm)) + (outcome.message,),
    )
    write_report(out_dir, data)
    return out_dir
