"""gls-export: a calibration as tables a galvo controller can load without Python.

Writes into ``--out``:

- ``table.csv`` / ``table.npz``: a regular grid at ``--pitch`` mm over the calibrated region at each
  height ``--z`` (gls frame): target x, y, z, corrected target k_x, k_y (mm), mechanical mirror
  angles (rad), focus shift (mm), the flags and ``uncertainty_k2_mm`` (the calibration's expanded
  uncertainty U, mm, 95 % radius; nan outside the field or for a file without a U map); the NPZ
  holds the same as arrays (z, y, x).
- ``interpolation_error.json``: the worst error of bilinear interpolation in that table, found by
  evaluating the calibration exactly at 3 x 3 points inside every cell: of the corrected target
  (mm), of the angles (rad), of the landing those interpolated angles give (mm) and of the focus
  shift (mm), in the cells whose four corners lie in the calibrated field and over the whole table
  (with the taper beyond the field).
- ``deviations.txt``: the measured deviations of the calibration's first plate, ``x,y,dx,dy`` (mm,
  target and target - measured), the text table vendor correction tools import.

Exit 0, or 2 with a message and nothing written on bad input.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
from pathlib import Path
import sys
from typing import Optional, Sequence

import numpy as np

from gls_calibration.calibration.record import correction_from_record
from gls_calibration.calibration.record_file import head_geometry, load_record
from gls_calibration.common.files import atomic_write_bytes
from gls_calibration.correction.setpoints import Correction
from gls_calibration.geometry.kinematics import forward

TABLE_COLUMNS = ("x", "y", "z", "k_x", "k_y", "alpha_x_rad", "alpha_y_rad", "focus_shift_mm",
                 "inside_calibrated_field", "within_limits")
UNCERTAINTY_COLUMN = "uncertainty_k2_mm"   # last column: U (mm, 95 % radius), nan outside the field or without a map
_SUBCELL_FRACTIONS = (0.25, 0.5, 0.75)
MAX_TABLE_POINTS = 1_000_000
"""Most table points (over every height) an export computes: each costs about 2.5 kB of memory while
the table and its 3 x 3 interpolation check per cell are evaluated (measured: 1.4 GB for 580 000
points), so the limit keeps an export near 2.5 GB; it allows a 0.2 mm pitch over a 190 mm field."""


def axis_points(low: float, high: float, pitch_mm: float) -> float:
    """Count the table points along one axis from ``low`` to ``high`` at ``pitch_mm``.

    Table points along one axis from ``low`` to ``high`` at ``pitch_mm`` (inf when absurdly many:
    counted as a float first, so a tiny pitch never reaches an allocation).
    """
    ratio = (high - low) / pitch_mm
    return math.ceil(ratio - 1e-9) + 1 if math.isfinite(ratio) and ratio < 1e12 else math.inf


def table_axes(correction: Correction, pitch_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid axes from the region's low corner at ``pitch_mm``, covering the whole region."""
    region = correction.calibrated_region
    if region is None:
        raise ValueError("the calibration holds no model: there is nothing to tabulate")

    def axis(low: float, high: float) -> np.ndarray:
        return low + pitch_mm * np.arange(axis_points(low, high, pitch_mm))
    return axis(region.x_min, region.x_max), axis(region.y_min, region.y_max)


def table_size_problem(correction: Correction, pitch_mm: float, heights: int) -> str:
    """Say why a table at ``pitch_mm`` cannot be exported (empty when it can).

    Decided before anything is allocated: more than MAX_TABLE_POINTS points, or no cell inside the
    calibrated field, where the interpolation error would be checked.
    """
    region = correction.calibrated_region
    if region is None:
        return ""   # table_axes names that problem
    width, height = region.x_max - region.x_min, region.y_max - region.y_min
    points = (axis_points(region.x_min, region.x_max, pitch_mm) * axis_points(region.y_min, region.y_max, pitch_mm)
              * heights)
    count = f"{points:,}" if math.isfinite(points) else "more than 10^24"
    if points > MAX_TABLE_POINTS:
        return (f"table would have {count} points (limit {MAX_TABLE_POINTS:,}: about 2.5 kB of memory each "
                f"while computed); choose a larger --pitch (or fewer --z heights)")
    if pitch_mm > min(width, height) + 1e-9:
        return (f"--pitch {pitch_mm:g} mm leaves no table cell inside the calibrated field "
                f"({width:g} x {height:g} mm), where the interpolation error is checked: "
                "the pitch must not exceed the field's smaller side")
    return ""


def cell_of(axis_x: np.ndarray, axis_y: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column and row index of the table cell holding each point (the cell's low corner)."""
    i = np.clip(((x - axis_x[0]) / (axis_x[1] - axis_x[0])).astype(int), 0, axis_x.size - 2)
    j = np.clip(((y - axis_y[0]) / (axis_y[1] - axis_y[0])).astype(int), 0, axis_y.size - 2)
    return i, j


def bilinear(table: np.ndarray, axis_x: np.ndarray, axis_y: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``table`` (ny, nx) on a regular grid at points inside it."""
    i, j = cell_of(axis_x, axis_y, x, y)
    u, v = (x - axis_x[i]) / (axis_x[1] - axis_x[0]), (y - axis_y[j]) / (axis_y[1] - axis_y[0])
    return ((1 - u) * (1 - v) * table[j, i] + u * (1 - v) * table[j, i + 1]
            + (1 - u) * v * table[j + 1, i] + u * v * table[j + 1, i + 1])


def interpolation_errors(correction: Correction, axis_x, axis_y, z: float, tables: dict) -> dict:
    """Worst differences between bilinear interpolation of ``tables`` and the exact correction."""
    fractions = np.asarray(_SUBCELL_FRACTIONS)
    x = (axis_x[:-1, None] + fractions * (axis_x[1] - axis_x[0])).ravel()
    y = (axis_y[:-1, None] + fractions * (axis_y[1] - axis_y[0])).ravel()
    grid_x, grid_y = (values.ravel() for values in np.meshgrid(x, y))
    exact = correction.correct(grid_x, grid_y, np.full(grid_x.size, z))
    guess = {name: bilinear(tables[name], axis_x, axis_y, grid_x, grid_y)
             for name in ("k_x", "k_y", "alpha_x_rad", "alpha_y_rad", "focus_shift_mm")}
    landed = np.column_stack(forward(correction.geometry, guess["alpha_x_rad"], guess["alpha_y_rad"], z))
    wanted = np.column_stack(forward(correction.geometry, exact.alpha_x, exact.alpha_y, z))
    errors = {"corrected_target_mm": np.hypot(guess["k_x"] - exact.x, guess["k_y"] - exact.y),
              "angle_rad": np.maximum(np.abs(guess["alpha_x_rad"] - exact.alpha_x),
                                      np.abs(guess["alpha_y_rad"] - exact.alpha_y)),
              "landing_from_interpolated_angles_mm": np.linalg.norm(landed - wanted, axis=1),
              "focus_shift_mm": np.abs(guess["focus_shift_mm"] - exact.focus_shift)}
    # Beyond the region the correction fades out (raised cosine over taper_mm): a steep change the
    # table samples coarsely, so cells with a corner outside the calibrated field are reported apart.
    i, j = cell_of(axis_x, axis_y, grid_x, grid_y)
    corners = tables["inside_calibrated_field"]
    inside = corners[j, i] & corners[j, i + 1] & corners[j + 1, i] & corners[j + 1, i + 1]
    return {"z_mm": z, "points_checked": int(grid_x.size), "points_in_cells_inside_calibrated_field": int(inside.sum()),
            "cells_inside_calibrated_field": {name: float(np.max(values[inside], initial=0.0))
                                              for name, values in errors.items()},
            "whole_table": {name: float(np.max(values)) for name, values in errors.items()}}


def export(calibration: Path, pitch_mm: float, heights_mm: Sequence[float]) -> dict[str, bytes]:
    """File name -> content of every output (computed before anything is written)."""
    record = load_record(calibration)
    try:
        correction = correction_from_record(record, head_geometry(record))
    except ValueError as error:
        raise ValueError(f"calibration file {calibration}: {error}") from None
    problem = table_size_problem(correction, pitch_mm, len(heights_mm))
    if problem:
        raise ValueError(problem)
    axis_x, axis_y = table_axes(correction, pitch_mm)
    grid_x, grid_y = np.meshgrid(axis_x, axis_y)
    arrays = {name: [] for name in TABLE_COLUMNS}
    uncertainty = []
    errors = []
    for z in heights_mm:
        result = correction.correct(grid_x.ravel(), grid_y.ravel(), np.full(grid_x.size, z))
        values = {"x": grid_x.ravel(), "y": grid_y.ravel(), "z": np.full(grid_x.size, z), "k_x": result.x,
                  "k_y": result.y, "alpha_x_rad": result.alpha_x, "alpha_y_rad": result.alpha_y,
                  "focus_shift_mm": result.focus_shift, "inside_calibrated_field": result.inside_calibrated_field,
                  "within_limits": result.within_limits}
        for name in TABLE_COLUMNS:
            arrays[name].append(values[name].reshape(grid_x.shape))
        uncertainty.append(result.uncertainty_k2_mm.reshape(grid_x.shape))
        errors.append(interpolation_errors(correction, axis_x, axis_y, z,
                                           {name: arrays[name][-1] for name in TABLE_COLUMNS}))
    stacked = {name: np.stack(arrays[name]) for name in TABLE_COLUMNS}
    stacked_u = np.stack(uncertainty)
    lines = [",".join(TABLE_COLUMNS + (UNCERTAINTY_COLUMN,))]
    floats = np.column_stack([stacked[name].ravel() for name in TABLE_COLUMNS[:8]]).tolist()
    flags = np.column_stack([stacked[name].ravel() for name in TABLE_COLUMNS[8:]]).astype(int).tolist()
    lines += [",".join(map(repr, row)) + f",{flag[0]},{flag[1]},{u!r}"
              for row, flag, u in zip(floats, flags, stacked_u.ravel().tolist())]
    archive = io.BytesIO()
    np.savez(archive, axis_x_mm=axis_x, axis_y_mm=axis_y, z_mm=np.asarray(heights_mm, float),
             **{name: stacked[name] for name in TABLE_COLUMNS[3:]}, **{UNCERTAINTY_COLUMN: stacked_u})
    fiducials = record["fiducials"]
    deviations = ["x,y,dx,dy"] + [f"{x!r},{y!r},{dx!r},{dy!r}" for x, y, dx, dy in zip(
        fiducials["target_x"], fiducials["target_y"], fiducials["dx"], fiducials["dy"])]
    summary = {"calibration": str(calibration), "pitch_mm": pitch_mm, "grid": [axis_x.size, axis_y.size],
               "region": correction.calibrated_region.to_dict(), "interpolation": "bilinear",
               "worst_interpolation_error": errors}
    return {"table.csv": ("\n".join(lines) + "\n").encode(), "table.npz": archive.getvalue(),
            "interpolation_error.json": (json.dumps(summary, indent=2) + "\n").encode(),
            "deviations.txt": ("\n".join(deviations) + "\n").encode()}


def write_all(folder: Path, files: dict[str, bytes]) -> None:
    """Write every file atomically; on a failure remove the ones this call created (no half export)."""
    created_folder = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    created = []
    try:
        for name, content in files.items():
            existed = (folder / name).exists()
            atomic_write_bytes(folder / name, content)
            if not existed:
                created.append(folder / name)
    except OSError:
        for path in created:
            path.unlink(missing_ok=True)
        if created_folder:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def main(argv: Optional[list[str]] = None) -> int:
    """Exit 0 on success, 2 on bad input or an unwritable folder (nothing written)."""
    parser = argparse.ArgumentParser(prog="gls-export", description=__doc__.split("\n\n")[0])
    parser.add_argument("--calibration", type=Path, required=True, help="calibration file (YAML)")
    parser.add_argument("--out", type=Path, required=True, help="folder to write the tables into")
    parser.add_argument("--pitch", type=float, default=2.0, help="table pitch (mm, default 2)")
    parser.add_argument("--z", type=float, nargs="+", default=[0.0], help="heights (mm, gls frame; default 0)")
    args = parser.parse_args(argv)
    try:
        if not (math.isfinite(args.pitch) and args.pitch > 0.0):
            raise ValueError(f"--pitch must be a positive number of mm, got {args.pitch}")
        if not all(math.isfinite(z) for z in args.z):
            raise ValueError(f"--z must be finite heights in mm, got {args.z}")
        files = export(args.calibration, args.pitch, args.z)
    except (OSError, ValueError) as error:
        print(error, file=sys.stderr)
        return 2
    try:
        write_all(args.out, files)
    except OSError as error:
        print(f"cannot write {args.out}: {error.strerror or error}", file=sys.stderr)
        return 2
    summary = json.loads(files["interpolation_error.json"])
    entries = summary["worst_interpolation_error"]
    inside = max(entry["cells_inside_calibrated_field"]["landing_from_interpolated_angles_mm"] for entry in entries)
    whole = max(entry["whole_table"]["landing_from_interpolated_angles_mm"] for entry in entries)
    print(f"table {summary['grid'][0]}x{summary['grid'][1]} at {args.pitch} mm for z = {args.z} mm written to "
          f"{args.out}; worst bilinear interpolation error of the landing {1e3 * inside:.3f} um inside the "
          f"calibrated field, {1e3 * whole:.3f} um with the taper beyond it")
    return 0


if __name__ == "__main__":
    sys.exit(main())
