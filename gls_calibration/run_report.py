"""The report of one calibrate request: its outcome turned into the report's data and summary."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from gls_calibration.correction import Correction
from gls_calibration.discrepancy import run_verdict_lines
from gls_calibration.procedure import CalibrationOutcome
from gls_calibration.report import ReportData, write_report


def _full(metrics: Optional[dict], key: str) -> float:
    return float(metrics["full"][key]) if metrics else math.nan


def summary(outcome: CalibrationOutcome) -> dict:
    """The figures of ``summary.json`` (NaN where a figure does not apply)."""
    first, validation = outcome.runs[0], outcome.validation
    last_model = outcome.models[-1] if outcome.models else None
    return {
        "success": outcome.success,
        "message": outcome.message,
        "pre_rms_mm": _full(first.metrics, "rms_abs_mm"),
        "pre_max_mm": _full(first.metrics, "max_abs_mm"),
        "post_rms_mm": _full(validation.metrics if validation else None, "rms_abs_mm"),
        "post_max_mm": _full(validation.metrics if validation else None, "max_abs_mm"),
        "true_pre_rms_mm": _full(first.true_metrics, "rms_abs_mm"),
        "true_pre_max_mm": _full(first.true_metrics, "max_abs_mm"),
        "true_post_rms_mm": _full(validation.true_metrics if validation else None, "rms_abs_mm"),
        "true_post_max_mm": _full(validation.true_metrics if validation else None, "max_abs_mm"),
        "true_post_rms_150_mm": (float(validation.true_metrics["150x150"]["rms_abs_mm"])
                                 if validation and validation.true_metrics else math.nan),
        "fiducials_expected": len(first.targets),
        "fiducials_found": first.fiducials_found,
        "iterations": len(outcome.runs),
        "neurons": last_model.neurons if last_model else 0,
        "method": last_model.method if last_model else "",
        "cv_rms_mm": last_model.cv_rms_mm if last_model else math.nan,
        "duration_s": outcome.duration_s,
        "calibration_file": outcome.calibration_file,
        "iteration_rms_mm": [_full(run.metrics, "rms_abs_mm") for run in outcome.runs],
    }


def write_outcome_report(out_dir: Path, outcome: CalibrationOutcome, correction: Optional[Correction]) -> Path:
    """Write report.md, plots, fiducials.csv and summary.json for ``outcome``; the folder's path."""
    first, validation = outcome.runs[0], outcome.validation
    field = None
    if correction is not None and correction.models:
        def field(points):
            dx, dy, _ = correction.deviation(points[:, 0], points[:, 1])
            return np.column_stack([dx, dy])
    data = ReportData(
        targets_xy=first.paired_targets_xy, deviations_before=first.deviations, metrics_before=first.metrics,
        summary=summary(outcome),
        targets_after=validation.paired_targets_xy if validation else None,
        deviations_after=validation.deviations if validation else None,
        metrics_after=validation.metrics if validation else None,
        true_before=first.true_deviations, true_after=validation.true_deviations if validation else None,
        true_metrics_before=first.true_metrics, true_metrics_after=validation.true_metrics if validation else None,
        correction_field=field,
        extra_lines=tuple(f"iteration {index + 1}: measured RMS {_full(run.metrics, 'rms_abs_mm'):.4f} mm"
                          for index, run in enumerate(outcome.runs)) + (outcome.message,)
        + run_verdict_lines(first.paired_targets_xy, first.deviations,
                            correction.geometry if correction is not None else None),
    )
    write_report(out_dir, data)
    return out_dir
