"""The report of one calibrate request: its outcome and summary drawn as the report's files."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gls_calibration.calibration.outcome import CalibrationOutcome, RunSummary
from gls_calibration.calibration.stated_accuracy import SELF_CONSISTENCY
from gls_calibration.common.files import atomic_write_text
from gls_calibration.discrepancy import run_verdict_lines
from gls_calibration.correction.uncertainty_grid import UNCERTAINTY_KEY
from gls_calibration.report.certificate import certificate_lines, write_certificate_files
from gls_calibration.report.files import ReportData, write_report


def figure_kind_lines(summary: RunSummary) -> tuple[str, ...]:
    """Which figures are self-consistency and which independent, and what the candidate was judged against."""
    lines = []
    if summary.pre_kind:
        lines.append(f"first plate (`pre_rms_mm` {summary.pre_rms_mm:.4f} mm): {summary.pre_kind.upper()}"
                     + (" (the calibration in use re-measured at the positions it was trained on)"
                        if summary.pre_kind == SELF_CONSISTENCY else ""))
    if summary.post_kind:
        lines.append(f"candidate on the validation grid (`post_rms_mm` {summary.post_rms_mm:.4f} mm): "
                     f"{summary.post_kind.upper()}")
    if summary.active_post_kind:
        lines.append(f"calibration in use on the validation grid (`active_post_rms_mm` "
                     f"{summary.active_post_rms_mm:.4f} mm): {summary.active_post_kind.upper()}")
    if summary.accepted_against:
        lines.append(f"the candidate was judged against: {summary.accepted_against}")
    return tuple(lines)


def accuracy_lines(summary: RunSummary) -> tuple[str, ...]:
    """Return what the cell states as its accuracy, and which of its figures are self-consistency."""
    basis = ("Every measured figure is SELF-CONSISTENCY of the measuring chain: the chain that measured the "
             "training plate measures every plate, so errors of the chain that repeat (robot lines, scanner "
             "shapes) were learned and cancel in them; INDEPENDENT below means only at positions the "
             "calibration judged was not trained on.")
    if np.isfinite(summary.stated_rms_mm):
        return (f"**Stated accuracy: {summary.stated_rms_mm:.4f} mm RMS** (2-D, over the validation grid; basis: "
                f"{summary.stated_basis}): {summary.stated_explanation}.", basis)
    return (f"**No accuracy is stated** (basis: {summary.stated_basis}): {summary.stated_explanation}.", basis)


def measurement_lines(summary: RunSummary) -> tuple[str, ...]:
    """Return what the report says about the measurement: sweep plan, cell time, uncertainty, separation."""
    chain = ([f"Simulated cell, measurement chain preset **{summary.measurement_preset}**: `post_rms_mm` / "
              "`post_max_mm` are MEASURED (as a real cell sees them), `true_post_*` are TRUE (simulation ground "
              "truth)."] if summary.measurement_preset else [])
    lines = [*chain, *accuracy_lines(summary), *figure_kind_lines(summary),
             f"sweep plan of the marked plate: {summary.sweep_plan}; simulated cell time of the whole "
             f"calibration (sweeps at the configured speed, robot moves, marking): "
             f"{summary.cell_time_s / 60.0:.1f} min",
             f"measurement uncertainty per fiducial (standard, per axis, first plate): median "
             f"{summary.fiducial_sigma_median_mm:.4f} mm, max {summary.fiducial_sigma_max_mm:.4f} mm"]
    if np.isfinite(summary.scanner_share):
        lines.append(f"attributed to the scanner and the robot's motion, not the galvo: "
                     f"{summary.scanner_error_rms_mm:.4f} mm RMS fixed to the scanner frame, "
                     f"{summary.motion_error_rms_mm:.4f} mm RMS of per-sweep motion "
                     f"({summary.scanner_share:.1%} of the measured deviation RMS)")
    if summary.stage_wall_s:
        stages = ", ".join(f"{stage} {seconds:.1f} s" for stage, seconds in summary.stage_wall_s.items())
        last = summary.last_sweep_to_result_s
        lines.append(f"time budget (wall, this run): {stages}; from the end of the last sweep to the result "
                     f"{'n/a' if not np.isfinite(last) else f'{last:.1f} s'}")
    return tuple(lines)


def _deviation_field(correction):
    """Return the trained deviation (dx, dy) at (N, 2) points, for the plots; None without a trained model."""
    if correction is None or not correction.models:
        return None

    def field(points):
        dx, dy, _ = correction.deviation(points[:, 0], points[:, 1])
        return np.column_stack([dx, dy])
    return field


def write_outcome_report(out_dir: Path, outcome: CalibrationOutcome, summary: RunSummary) -> Path:
    """Write report.md, plots, fiducials.csv, summary.json and training.csv for ``outcome``.

    The certificate's files are added when the candidate holds a U map.

    Parameters
    ----------
    out_dir : pathlib.Path
        The report folder (created with its parents).
    outcome : CalibrationOutcome
        The calibration's plate runs, candidate and message.
    summary : RunSummary
        The run's summary, computed once (``outcome.summarise``).

    Returns
    -------
    pathlib.Path
        The report folder.

    Raises
    ------
    OSError
        If the folder cannot be created or written.
    """
    first, validation = outcome.runs[0], outcome.validation
    correction = outcome.candidate.correction if outcome.candidate else None
    field = _deviation_field(correction)

    def plain(metrics):
        return metrics.to_dict() if metrics is not None else None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    grid = getattr(correction, "uncertainty", None)
    map_name, certificate_files = write_certificate_files(out_dir, grid, validation)
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
        + (outcome.message,)
        + run_verdict_lines(first.paired_targets_xy, first.deviations,
                            correction.geometry if correction is not None else None),
        extra_files=("- `training.csv`: the first plate's fiducials as `gls-train` reads them "
                     "(`x_cmd,y_cmd,z_cmd,x_meas,y_meas`).",)
        + (("- `calibrations/`: the calibration store (history and the active calibration).",)
           if (Path(out_dir) / "calibrations").is_dir() else ()) + certificate_files,
        certificate_lines=tuple(certificate_lines(_stored_uncertainty(outcome), summary, map_name))
        if outcome.candidate is not None else (),
    )
    write_report(out_dir, data)
    atomic_write_text(out_dir / "training.csv", training_csv_text(first))
    return out_dir


def _stored_uncertainty(outcome: CalibrationOutcome):
    """Return the candidate record's ``uncertainty`` mapping (the budget), or None.

    From the record in hand, not its file read back.
    """
    record = outcome.candidate.record
    return None if record is None else record.get(UNCERTAINTY_KEY)


def training_csv_text(run) -> str:
    """Return the first plate's fiducials as gls-train reads them.

    Commanded targets, the height they were commanded at and the measured centres (gls frame, mm).
    Training from it reproduces the run's model when the plate was marked through the nominal model
    (the first calibration of a head).
    """
    height = {(float(x), float(y)): float(z) for x, y, z in run.targets}
    z_cmd = [height[(float(x), float(y))] for x, y in run.paired_targets_xy]
    rows = np.column_stack([run.paired_targets_xy, z_cmd, run.measured_gls[:, :2]]).tolist()
    return "x_cmd,y_cmd,z_cmd,x_meas,y_meas\n" + "".join(",".join(map(repr, row)) + "\n" for row in rows)
