"""The report's certificate: U over the field, its budget, method and conditions; validation.csv.

U is the candidate calibration's stored map (``calibration.uncertainty``): a 95 % coverage radius of
a corrected target's 2-D landing, relative to the best-fit rigid frame of the field. In simulation
the validation plate's TRUE landing errors (after the best rigid alignment, as every figure here)
are compared with U at their targets: the coverage.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from gls_calibration.common.files import atomic_write_text
from gls_calibration.report.files import report_figure, save_figure

MAP_FILE = "uncertainty_map.png"
VALIDATION_FILE = "validation.csv"


def validation_u(grid, targets_xy: np.ndarray) -> np.ndarray:
    """U at validation targets (N, 2); NaN without a grid."""
    if grid is None:
        return np.full(len(targets_xy), np.nan)
    return grid.at(targets_xy[:, 0], targets_xy[:, 1])


def coverage(u: np.ndarray, true_deviations: Optional[np.ndarray]) -> float:
    """Fraction of points whose TRUE landing error is within U; NaN without truth or U."""
    if true_deviations is None or not np.any(np.isfinite(u)):
        return math.nan
    return float(np.mean(np.hypot(*np.asarray(true_deviations).T) <= u))


def validation_csv_text(targets_xy: np.ndarray, u: np.ndarray, true_deviations: Optional[np.ndarray]) -> str:
    """One row per validation fiducial: ``x_mm,y_mm[,true_dx_mm,true_dy_mm],u_k2_mm`` (true only in simulation)."""
    handle = io.StringIO()
    writer = csv.writer(handle, lineterminator="\n")
    with_truth = true_deviations is not None
    writer.writerow(["x_mm", "y_mm"] + (["true_dx_mm", "true_dy_mm"] if with_truth else []) + ["u_k2_mm"])
    for index, (x, y) in enumerate(targets_xy):
        row = [repr(float(x)), repr(float(y))]
        if with_truth:
            row += [repr(float(true_deviations[index, 0])), repr(float(true_deviations[index, 1]))]
        writer.writerow(row + ["" if not math.isfinite(u[index]) else repr(float(u[index]))])
    return handle.getvalue()


def plot_u_map(path: Path, grid, targets_xy: Optional[np.ndarray]) -> Path:
    """U over the calibrated field (colour), the validation targets as dots."""
    figure = report_figure(6.0, 5.0, left_in=0.85, right_in=0.45, bottom_in=0.6)
    axes = figure.subplots()
    image = axes.pcolormesh(grid.x_mm, grid.y_mm, grid.u_k2_mm, shading="gouraud", cmap="magma")
    if targets_xy is not None:
        axes.plot(targets_xy[:, 0], targets_xy[:, 1], ".", color="cyan", markersize=2)
    figure.colorbar(image, ax=axes, label="U (mm, 95 % radius)")
    axes.set_aspect("equal")
    axes.set_xlabel("x (mm)")
    axes.set_ylabel("y (mm)")
    axes.set_title("expanded uncertainty of a corrected target", fontsize=10)
    return save_figure(figure, path)


def certificate_lines(stored: Optional[Mapping[str, Any]], summary: Any, map_name: Optional[str]) -> list[str]:
    """Return the certificate section of report.md from the calibration's ``uncertainty`` mapping and the summary."""
    if stored is None:
        return ["No uncertainty map: the calibration was not trained in this run, or its model admits none "
                "(the file then serves NaN)."]
    lines = [f"**A corrected target lands within U = {summary.certificate_u95_full_mm:.4f} mm of its target with "
             f"95 % probability over 190 x 190 mm; within "
             f"{summary.certificate_u95_central_mm:.4f} mm over the central 150 x 150 mm** (largest U of each; "
             f"median U {summary.certificate_u95_median_mm:.4f} mm). Position relative to the best-fit rigid frame "
             "of the field (a rigid motion of the whole field is not observable on one plate).", "",
             f"U is a 95 % coverage radius of the 2-D landing: the per-axis standard uncertainty (k = 1) of the "
             f"budget below, combined in quadrature, times {float(stored.get('coverage_factor', math.nan)):.3f} "
             "= sqrt(-2 ln 0.05) (an isotropic Gaussian's 95 % radius; served as `uncertainty_k2_mm`).", "",
             "| contribution | RMS over the field (k = 1, per axis) | max | basis |", "|---|---:|---:|---|"]
    for item in stored.get("budget", []):
        lines.append(f"| {item['name']} | {item['rms_mm']:.4f} | {item['max_mm']:.4f} | {item['basis']} |")
    lines += ["", "Method: the measurement's per-centre uncertainty carried exactly through the trained model "
              "(it is linear in its training data); the chain's correlated error from the reference check of the "
              "same sweep plan; the model's error between fiducials from spatially blocked cross-validation by the "
              "distance to the nearest fiducial; the plate height's scale error; where the validation plate's RMS in "
              "quadrature with the reference check is above the 2-D RMS the budget implies, the difference added "
              "uniformly (the `validation` line: the check is one draw of the chain's random error, the validation "
              "carries the calibration's own) (docs/method-and-results.md, Certificate).",
              f"Conditions: sweep plan {summary.sweep_plan}, chain map {summary.chain_map}, "
              f"{summary.fiducials_found} of {summary.fiducials_expected} fiducials, model {summary.method} "
              f"({summary.neurons} units).",
              f"Traceability of the scale: {summary.certificate_reference}."]
    if math.isfinite(summary.certificate_coverage):
        lines.append(f"**Simulation: {summary.certificate_coverage:.1%} of the validation fiducials' TRUE landing "
                     f"errors lie within U** (target 92-98.5 %; `validation.csv`).")
    if map_name:
        lines += ["", f"![U over the calibrated field]({map_name})"]
    return lines


def write_certificate_files(out_dir: Path, grid, validation) -> tuple[Optional[str], tuple[str, ...]]:
    """Write the U map PNG and validation.csv beside the report; return (its file name or None, Files lines)."""
    files: list[str] = []
    map_name = None
    if grid is not None:
        plot_u_map(out_dir / MAP_FILE, grid, validation.paired_targets_xy if validation is not None else None)
        map_name = MAP_FILE
        files.append(f"- `{MAP_FILE}`: the expanded uncertainty U over the calibrated field.")
    if validation is not None:
        u = validation_u(grid, validation.paired_targets_xy)
        atomic_write_text(out_dir / VALIDATION_FILE,
                          validation_csv_text(validation.paired_targets_xy, u, validation.true_deviations))
        files.append(f"- `{VALIDATION_FILE}`: one row per validation fiducial, `x_mm,y_mm,true_dx_mm,true_dy_mm,"
                     "u_k2_mm` (true columns in simulation only; U empty where the calibration has no map).")
    return map_name, tuple(files)
