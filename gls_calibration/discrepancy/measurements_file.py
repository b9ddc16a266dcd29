"""The measurements the discrepancy workflow reads, checked row by row.

The measurements the discrepancy workflow reads: a table of commanded and measured marks, or a
calibration run's ``fiducials.csv``, checked row by row (exact messages, lines named).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
import math
from pathlib import Path

import numpy as np

from gls_calibration.discrepancy.residual_statistics import MIN_POINTS


REQUIRED_COLUMNS = ("x_cmd", "y_cmd", "x_meas", "y_meas")
TIME_COLUMN = "t"
SIGMA_COLUMNS = ("sigma", "sigma_mm")
REPEAT_COLUMN = "repeat"
FIDUCIALS_COLUMNS = ("stage", "target_x_mm", "target_y_mm", "dx_mm", "dy_mm")


class InputError(ValueError):
    """Bad command-line input: reported on stderr with exit code 2.

    Parameters
    ----------
    message : str
        What is wrong, naming the file and line or column.
    """


@dataclass(frozen=True)
class Measurements:
    """Validated rows of the measurement CSV.

    Parameters
    ----------
    commanded_xy : numpy.ndarray, shape (N, 2)
        Commanded targets, gls frame, mm.
    measured_xy : numpy.ndarray, shape (N, 2) or (R, N, 2)
        Measured marks, mm; (R, N, 2) for R repeats.
    t : numpy.ndarray, shape (N,), or None
        Marking time, s, when the file has the time column.
    dropped_lines : tuple of int
        File line numbers of rows dropped for NaN or empty values.
    sigma_mm : numpy.ndarray, shape (N,), optional
        Per-axis uncertainty from the sigma column, mm.
    data_rows : tuple, optional
        Per point: its 0-based data row (header excluded); with repeats a tuple of rows.
    source_format : str, default "measurements"
        ``"measurements"`` or ``"fiducials"`` (a run's fiducials.csv).
    """

    commanded_xy: np.ndarray
    measured_xy: np.ndarray            # (N, 2), or (R, N, 2) for R repeats
    t: np.ndarray | None
    dropped_lines: tuple[int, ...]     # file line numbers of rows dropped for NaN or empty values
    sigma_mm: np.ndarray | None = None  # (N,) per-axis uncertainty from the sigma column
    data_rows: tuple = ()              # per point: 0-based data row (header excluded); with repeats a tuple of rows
    source_format: str = "measurements"   # measurements | fiducials


def _parse_value(text: str, line: int, column: str) -> float:
    text = text.strip()
    if text == "":
        return math.nan
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"line {line}, column {column!r}: {text!r} is not a number") from None
    if math.isinf(value):
        raise InputError(f"line {line}, column {column!r}: {text!r} is not finite")
    return value


def _read_rows(path: Path) -> tuple[list[str], list[tuple[int, int, list[str]]]]:
    """Header and (file line, 0-based data row, cells) of every non-empty row."""
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            lines = list(csv.reader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise InputError(f"cannot read {path}: {getattr(error, 'strerror', None) or error}") from None
    numbered = [(number, row) for number, row in enumerate(lines, start=1) if any(cell.strip() for cell in row)]
    if not numbered:
        raise InputError(f"{path} is empty; expected the header {','.join(REQUIRED_COLUMNS)}[,{TIME_COLUMN}]")
    header = [cell.strip() for cell in numbered[0][1]]
    rows = []
    for data_row, (number, row) in enumerate(numbered[1:]):
        if len(row) != len(header):
            raise InputError(f"{path}: line {number} has {len(row)} field(s), the header has {len(header)}")
        rows.append((number, data_row, row))
    return header, rows


def read_measurements(path: str | Path) -> Measurements:
    """Read and validate the measurement CSV (or a run's fiducials.csv).

    Rows with NaN or empty values are dropped and listed; a fiducials.csv gives its ``before``
    rows, the mark at ``P = Q - d``.

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV file.

    Returns
    -------
    Measurements
        The validated points.

    Raises
    ------
    InputError
        Naming the problem: an unreadable or empty file, a row of the wrong length, a missing column,
        a value that is not a number, a sigma not above 0 mm, too few valid points, duplicate targets
        or inconsistent repeats.
    """
    path = Path(path)
    header, rows = _read_rows(path)
    fiducials = all(column in header for column in FIDUCIALS_COLUMNS)
    if fiducials:
        rows = [row for row in rows if row[2][header.index("stage")].strip() == "before"]
        value_columns = ["target_x_mm", "target_y_mm", "dx_mm", "dy_mm"]
    else:
        missing = [column for column in REQUIRED_COLUMNS if column not in header]
        if missing:
            raise InputError(f"{path}: missing column(s) {', '.join(missing)}; expected the header "
                             f"{','.join(REQUIRED_COLUMNS)}[,{TIME_COLUMN}] or a run's fiducials.csv, "
                             f"got {','.join(header)}")
        value_columns = list(REQUIRED_COLUMNS)
    sigma_column = next((column for column in SIGMA_COLUMNS if column in header), None)
    optional = [c for c in (TIME_COLUMN, sigma_column, REPEAT_COLUMN) if c is not None and c in header]
    columns = value_columns + optional
    index = {column: header.index(column) for column in columns}
    values = [[_parse_value(row[index[column]], number, column) for column in columns] for number, _, row in rows]
    table = np.array(values, dtype=float).reshape(-1, len(columns))
    valid = np.all(np.isfinite(table), axis=1)
    dropped = tuple(number for (number, _, _), ok in zip(rows, valid) if not ok)
    table = table[valid]
    kept = [(number, data_row) for (number, data_row, _), ok in zip(rows, valid) if ok]
    if fiducials:   # d = Q - P: the mark landed at P = Q - d
        table[:, 2:4] = table[:, 0:2] - table[:, 2:4]
    at = {column: i for i, column in enumerate(columns)}
    sigma = table[:, at[sigma_column]] if sigma_column else None
    if sigma is not None and np.any(sigma <= 0.0):
        bad = kept[int(np.argmax(sigma <= 0.0))][0]
        raise InputError(f"{path}: line {bad}, column {sigma_column!r}: the uncertainty must be > 0 mm")
    if REPEAT_COLUMN in at:
        return _repeats(path, table, at, kept, dropped, sigma)
    if len(table) < MIN_POINTS:
        raise InputError(f"{path}: only {len(table)} valid point(s) after dropping {len(dropped)} row(s) with NaN "
                         f"or empty values; at least {MIN_POINTS} are needed")
    _reject_duplicates(path, table[:, :2], [number for number, _ in kept])
    return Measurements(table[:, 0:2].copy(), table[:, 2:4].copy(),
                        table[:, at[TIME_COLUMN]].copy() if TIME_COLUMN in at else None, dropped, sigma,
                        tuple(data_row for _, data_row in kept), "fiducials" if fiducials else "measurements")


def _reject_duplicates(path: Path, targets_xy: np.ndarray, lines: list[int]) -> None:
    targets, first_index, counts = np.unique(targets_xy, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        duplicates = [(tuple(target), lines[first]) for target, first, count in zip(targets, first_index, counts)
                      if count > 1]
        shown = "; ".join(f"({x:g}, {y:g}) first on line {line}" for (x, y), line in duplicates[:5])
        raise InputError(f"{path}: {len(duplicates)} duplicate commanded target(s): {shown}")


def _repeats(path: Path, table: np.ndarray, at: dict, kept: list, dropped: tuple, sigma) -> Measurements:
    """Stack the repeats (R, N, 2); each must hold the same targets exactly once."""
    labels = table[:, at[REPEAT_COLUMN]]
    groups = [np.flatnonzero(labels == label) for label in np.unique(labels)]
    if len(groups) < 2:
        raise InputError(f"{path}: the {REPEAT_COLUMN!r} column holds a single repeat; drop it or add repeats")
    order = []
    reference = None
    for group in groups:
        _reject_duplicates(path, table[group, :2], [kept[i][0] for i in group])
        sort = group[np.lexsort((table[group, 1], table[group, 0]))]
        if reference is None:
            reference = table[sort, :2]
        elif table[sort, :2].shape != reference.shape or not np.array_equal(table[sort, :2], reference):
            raise InputError(f"{path}: repeat {labels[group[0]]:g} does not hold the same commanded targets as "
                             f"repeat {labels[groups[0][0]]:g} (after dropping rows with NaN)")
        order.append(sort)
    if len(reference) < MIN_POINTS:
        raise InputError(f"{path}: only {len(reference)} valid point(s) per repeat; at least {MIN_POINTS} are needed")
    first = order[0]
    stacked = np.stack([table[rows, 2:4] for rows in order])
    t = np.mean([table[rows, at[TIME_COLUMN]] for rows in order], axis=0) if TIME_COLUMN in at else None
    rows = tuple(tuple(kept[rows[i]][1] for rows in order) for i in range(len(first)))
    return Measurements(reference.copy(), stacked, t, dropped, None if sigma is None else sigma[first], rows,
                        "measurements")
