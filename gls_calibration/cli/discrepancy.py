"""``gls-discrepancy``: name the physical effects missing from the head model, and say what is left unexplained.

    gls-discrepancy --measured FILE.csv [--model MODEL.yaml] [--sigma MM] [--effects MODULE:FUNCTION ...] --out DIR

FILE.csv is either

- a measurement table with the header ``x_cmd,y_cmd,x_meas,y_meas`` and optionally ``t``, ``sigma``
  and ``repeat``: commanded nominal targets in the gls frame (mm), measured mark positions in any
  in-plane frame a rigid motion away (mm), marking time (s), the per-axis standard uncertainty of
  the measured position (mm) and the number of the repeated measurement (the same targets measured
  again; each repeat is one complete set);
- or a calibration run's own ``fiducials.csv`` (``stage,index,target_x_mm,target_y_mm,dx_mm,dy_mm,...``,
  written by ``gls-sim-cell`` and the calibration manager): its ``before`` rows are used, the measured
  position being ``target - d`` (the first plate is marked through the nominal model).

Rows with NaN or empty values are dropped with a warning. MODEL.yaml is a head configuration (see
:mod:`gls_calibration.geometry.head_config`; default ``config/head.yaml``). The noise floor comes from the
repeats, else the ``sigma`` column, else ``--sigma``, else (with a warning in the report) from the
residual itself. ``--effects`` adds a user effect (a function returning a
:class:`gls_calibration.geometry.effect_table.UserEffect`; the module is imported from the working directory
or ``PYTHONPATH``).

Writes DIR/discrepancy.json, DIR/report.md, DIR/residual_field.png (before, after, and the map of
what is left unexplained) and DIR/gap_per_step.png. Every input is checked before anything is written; the files are rendered
in a temporary directory beside DIR and moved in with atomic renames. Bad input: message on
stderr, exit code 2, nothing written.
"""
from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass
import json
import math
import os
from pathlib import Path
import shutil
import sys
import tempfile
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:   # the workflow (scipy) is imported only when it runs: start-up stays short
    from gls_calibration.discrepancy import DiscrepancyResult

PROGRAM = "gls-discrepancy"
MIN_POINTS = 10     # = gls_calibration.discrepancy.MIN_POINTS (checked by a test; not imported at start-up)
REQUIRED_COLUMNS = ("x_cmd", "y_cmd", "x_meas", "y_meas")
TIME_COLUMN = "t"
SIGMA_COLUMNS = ("sigma", "sigma_mm")
REPEAT_COLUMN = "repeat"
FIDUCIALS_COLUMNS = ("stage", "target_x_mm", "target_y_mm", "dx_mm", "dy_mm")
EXIT_OK = 0
EXIT_BAD_INPUT = 2


class InputError(ValueError):
    """Bad command-line input: reported on stderr with exit code 2."""


@dataclass(frozen=True)
class Measurements:
    """Validated rows of the measurement CSV."""

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
    """Read and validate the measurement CSV (or a run's fiducials.csv); raise InputError naming the problem."""
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


# --------------------------------------------------------------------------------------------------
# outputs

def _plot_residual_fields(result: DiscrepancyResult, path: Path) -> None:
    """Residual arrows before and after (same scale), and the map of what is left unexplained."""
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    points = result.commanded_xy
    before, after = result.residual_before_xy, result.residual_after_xy
    span = float(np.max(np.ptp(points, axis=0))) or 1.0
    longest = float(np.max(np.hypot(*before.T))) or 1e-9
    scale = longest / (0.08 * span)        # data mm per plot mm: longest arrow ~8 % of the field, both panels
    key = float(f"{longest:.1g}")
    figure, axes = plt.subplots(1, 3, figsize=(18, 5.8), sharex=True, sharey=True)
    for axis, residual, title in ((axes[0], before, f"before: RMS {result.rms_before_mm:.4f} mm"),
                                  (axes[1], after, f"after {', '.join(result.named_effects) or 'nothing'}: "
                                                   f"RMS {result.rms_after_mm:.4f} mm")):
        arrows = axis.quiver(points[:, 0], points[:, 1], residual[:, 0], residual[:, 1], angles="xy",
                             scale_units="xy", scale=scale, width=0.003, color="tab:red")
        axis.quiverkey(arrows, 0.82, 1.02, key, f"{key:g} mm", labelpos="E")
        axis.set_title(title, fontsize=10, loc="left")
    # the map of the verdict: |residual| after the named effects, outliers marked
    shown = axes[2].scatter(points[:, 0], points[:, 1], c=np.hypot(*after.T), s=30, cmap="viridis", vmin=0.0)
    figure.colorbar(shown, ax=axes[2], label="|residual| after (mm)")
    if result.outliers:
        axes[2].scatter([o.position_mm[0] for o in result.outliers], [o.position_mm[1] for o in result.outliers],
                        marker="x", s=80, color="tab:red", label="outliers (excluded)")
        axes[2].legend(loc="upper right", fontsize=8)
    axes[2].set_title(f"{result.verdict.verdict}: {result.verdict.unexplained_rms_mm:.4f} mm "
                      + ("of structure below the floor" if result.verdict.below_floor else "above the floor"),
                      fontsize=10, loc="left")
    for axis in axes:
        axis.set_xlabel("x (mm, gls)")
        axis.set_aspect("equal")
    axes[0].set_ylabel("y (mm, gls)")
    figure.suptitle(f"residual after rigid alignment (same arrow scale); {result.floor.source} noise floor "
                    f"{result.noise_floor_mm:.4f} mm")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _plot_gap(result: DiscrepancyResult, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    labels = ["model"] + [f"+ {step.name}" for step in result.steps]
    gaps = result.gap_per_step_mm
    figure, axis = plt.subplots(figsize=(max(5.0, 1.4 * len(labels) + 2), 4))
    axis.bar(range(len(gaps)), gaps, color="tab:blue")
    axis.axhline(result.noise_floor_mm, color="tab:red", linestyle="--", label=f"noise floor {result.noise_floor_mm:.4f} mm")
    axis.set_xticks(range(len(gaps)), labels, rotation=20, ha="right")
    axis.set_ylabel("residual RMS (mm)")
    axis.set_title("gap between model and measurement per step")
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _format_parameters(step) -> str:
    return "; ".join(f"{name} = {value:.4g} ± {step.uncertainty[name]:.2g} {step.units[name]}"
                     for name, value in step.parameters.items())


def _data_row(data: Measurements, index: int):
    return data.data_rows[index] if data.data_rows else index


def _format_values(values, units) -> str:
    return "; ".join(f"{name} = {value:.4g} {units.get(name, '')}".rstrip() for name, value in values.items())


def _report_markdown(result: DiscrepancyResult, measured: Path, model: Path | None, data: Measurements) -> str:
    from gls_calibration.discrepancy import verdict_lines
    from gls_calibration.discrepancy.separability import SEPARABLE_AT
    from gls_calibration.discrepancy.verdict import naming_phrase

    criterion = result.criterion.upper()
    floor = result.floor
    lines = [
        "# Discrepancy report",
        "",
        f"- measurements: `{measured}` ({len(data.commanded_xy)} points"
        + (f", {floor.repeats} repeats averaged" if floor.repeats > 1 else "")
        + (", a calibration run's fiducials.csv, stage 'before'" if data.source_format == "fiducials" else "")
        + (f", {len(data.dropped_lines)} row(s) with NaN dropped" if data.dropped_lines else "")
        + (", with marking time" if result.t is not None else ", no marking time") + ")",
        f"- model: `{model}`" if model is not None else "- model: published defaults",
        f"- known effects: {', '.join(f'{k} = {list(v)}' for k, v in result.known_effects.values.items()) or 'none'}",
        f"- user effects: {', '.join(effect.name for effect in result.user_effects) or 'none'}",
        "",
        "## Verdict",
        "",
    ] + verdict_lines(result) + [
        "",
        "![residual before, after, and where the unexplained part is](residual_field.png)",
        "",
        "## Gap",
        "",
        "| | value |",
        "|---|---|",
        f"| residual RMS before | {result.rms_before_mm:.4f} mm |",
        f"| residual RMS after | {result.rms_after_mm:.4f} mm |",
        f"| noise floor ({floor.source}) | {floor.noise_floor_mm:.4f} mm ({floor.sigma_axis_mm:.4f} mm per axis) |",
        f"| residual roughness (cross-check) | {floor.residual_estimate_mm:.4f} mm |",
        f"| structure test before (F-test p) | {result.structure_before.p_value:.3g} "
        f"({'smooth structure' if result.structure_before.is_structure else 'no smooth structure'}) |",
        f"| structure test after (F-test p) | {result.structure_after.p_value:.3g} "
        f"({'smooth structure' if result.structure_after.is_structure else 'no smooth structure'}) |",
        f"| named effects | {naming_phrase(result) if result.named_effects or result.named_groups else 'none'} |",
        f"| outliers excluded | {len(result.outliers)} |",
        "",
        f"Stopped because {result.stop_reason}.",
        "",
        "![gap per step](gap_per_step.png)",
        "",
    ]
    if result.outliers:
        lines += ["## Outliers (excluded from every fit)", "",
                  "| data row | size (mm) | x (mm) | y (mm) |", "|---|---|---|---|"]
        lines += [f"| {_data_row(data, o.index)} | {o.size_mm:.4f} | {o.position_mm[0]:.2f} | {o.position_mm[1]:.2f} |"
                  for o in result.outliers]
        lines.append("")
    lines += ["## Steps", ""]
    if result.steps:
        lines += [f"| step | effect | parameters (± 1 sigma) | indistinguishable from | {criterion} gain | RMS before → after (mm) | dropped |",
                  "|---|---|---|---|---|---|---|"]
        for number, step in enumerate(result.steps, start=1):
            lines.append(f"| {number} | {step.name} | {_format_parameters(step)} | "
                         f"{', '.join(step.indistinguishable_from) or '-'} | {step.improvement:.1f} | "
                         f"{step.rms_before_mm:.4f} → {step.rms_after_mm:.4f} | {', '.join(step.removed) or '-'} |")
        lines += ["", "Final joint fit (± 1 sigma; correlation with the rigid rotation / translation x / y). "
                  f"z is the size of what survives the rigid alignment and the other fitted effects over its "
                  f"standard error; an effect is named alone at z >= {SEPARABLE_AT:g} when no other candidate "
                  "brings it below that. Each effect's definition (the convention its values refer to) follows "
                  "its values.", ""]
        separability = {record.name: record for record in result.separability}
        for name in result.fitted_effects:
            values = result.model_effects.get(name) if name in result.model_effects.values else result.user_values[name]
            spec = _effect_spec(result, name)
            record = separability.get(name)
            status = ("named" if name in result.named_effects else
                      f"named as a group with {', '.join(record.group[1:])}" if record is not None
                      and record.separable_from_rigid else "not named: not separable from the rigid motion")
            lines.append(f"- **{name}** ({status}" + (f"; z = {record.z:.1f}" if record is not None else "") + ")")
            for i, (parameter, unit) in enumerate(zip(spec.parameter_names, spec.units)):
                label = f"{name}.{parameter}"
                corr = result.rigid_correlation.get(label, {})
                lines.append(f"  - {label} = {values[i]:.4g} ± {result.model_uncertainty[name][i]:.2g} {unit} "
                             f"(correlation {corr.get('rotation', math.nan):+.2f} / {corr.get('translation_x', math.nan):+.2f}"
                             f" / {corr.get('translation_y', math.nan):+.2f})")
            lines.append(f"  - definition: {spec.doc}")
        for number, step in enumerate(result.steps, start=1):
            lines += ["", f"### Candidates at step {number}", "",
                      f"| candidate | {criterion} gain | RMS after (mm) | field difference to best (mm) |",
                      "|---|---|---|---|"]
            lines += [f"| {c.name} | {c.improvement:.1f} | {c.rms_after_mm:.4f} | {c.field_difference_mm:.4f} |"
                      for c in step.candidates]
    else:
        lines.append("No missing effect named.")
    if result.implausible:
        lines += ["", "## Not named: physically implausible fits", ""]
        lines += [f"- step {i.step}: {i.name} ({_format_values(i.parameters, {})}): {i.why}" for i in result.implausible]
    lines += ["", "## Where the residual lives", ""]
    for label, location in (("before", result.location_before), ("after", result.location_after)):
        lines.append(f"- {label}: RMS x {location.rms_x_mm:.4f} mm, y {location.rms_y_mm:.4f} mm; centre "
                     f"{location.rms_centre_mm:.4f} mm, edge {location.rms_edge_mm:.4f} mm"
                     + (f"; {'; '.join(location.findings)}" if location.findings else ""))
    lines += ["", "## Notes", ""] + [f"- {note}" for note in result.notes] + [""]
    return "\n".join(lines)


def _effect_spec(result: DiscrepancyResult, name: str):
    """The table entry (library or user effect) that defines ``name``'s parameters."""
    from gls_calibration.geometry.effect_table import EFFECT_TABLE

    for effect in result.user_effects:
        if effect.name == name:
            return effect.spec
    return EFFECT_TABLE[name]


def _write_outputs(result: DiscrepancyResult, out: Path, measured: Path, model: Path | None,
                   data: Measurements) -> None:
    """Render everything in a temporary directory beside ``out``, then move it in atomically."""
    from gls_calibration.common.files import nan_to_none, to_plain

    out = out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        document = result.to_dict()
        for entry, outlier in zip(document["outliers"], result.outliers):
            entry["index"] = _data_row(data, outlier.index)      # the CSV's 0-based data row
        document["input"] = {"measured": str(measured), "model": None if model is None else str(model),
                             "format": data.source_format, "dropped_lines": list(data.dropped_lines)}
        text = json.dumps(nan_to_none(to_plain(document)), indent=2) + "\n"
        (staging / "discrepancy.json").write_text(text, encoding="utf-8")
        _plot_residual_fields(result, staging / "residual_field.png")
        _plot_gap(result, staging / "gap_per_step.png")
        (staging / "report.md").write_text(_report_markdown(result, measured, model, data), encoding="utf-8")
        for item in staging.iterdir():
            with item.open("rb") as handle:
                os.fsync(handle.fileno())
        if not out.exists():
            os.replace(staging, out)      # the whole directory appears at once
            return
        for item in staging.iterdir():   # existing directory: each file replaced atomically
            os.replace(item, out / item.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of gls-discrepancy."""
    parser = argparse.ArgumentParser(
        prog=PROGRAM, description="Name the physical effects missing from the galvo head model, from measured marks, "
                                  "and say what they leave unexplained.")
    parser.add_argument("--measured", required=True, type=Path,
                        help="CSV with header x_cmd,y_cmd,x_meas,y_meas[,t][,sigma][,repeat] (mm, mm, s, mm), "
                             "or a calibration run's fiducials.csv")
    parser.add_argument("--model", type=Path, default=None,
                        help="head configuration YAML (nominal d, e, limits; optional known effects); "
                             "default config/head.yaml")
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--sigma", type=float, default=None, metavar="MM",
                        help="stated per-axis standard uncertainty of a measured position (mm); used when the CSV "
                             "has no repeats and no sigma column")
    parser.add_argument("--effects", action="append", default=[], metavar="MODULE:FUNCTION",
                        help="add a user effect: FUNCTION() returns a gls_calibration.geometry.effect_table.UserEffect "
                             "(repeatable)")
    parser.add_argument("--criterion", choices=("bic", "aic"), default="bic", help="information criterion (default bic)")
    parser.add_argument("--max-steps", type=int, default=6, help="most effects to add (default 6)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the discrepancy workflow; exit code 0 on success, 2 on bad input."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_request:   # argparse has printed its message
        return int(exit_request.code or 0)
    try:
        if args.max_steps < 0:
            raise InputError(f"--max-steps must be >= 0, got {args.max_steps}")
        if args.sigma is not None and not (math.isfinite(args.sigma) and args.sigma > 0.0):
            raise InputError(f"--sigma must be a finite number > 0 (mm), got {args.sigma}")
        data = read_measurements(args.measured)
        from gls_calibration.geometry.head_config import default_head_config_path, load_head_config
        model_path = args.model
        if model_path is None:
            default = default_head_config_path()
            model_path = default if default.is_file() else None
        try:
            geometry, known = load_head_config(model_path) if model_path is not None else (None, None)
        except ValueError as error:
            raise InputError(str(error)) from None
        if args.out.exists() and not args.out.is_dir():
            raise InputError(f"--out {args.out} exists and is not a directory")
        if data.dropped_lines:
            shown = ", ".join(map(str, data.dropped_lines[:10])) + (", ..." if len(data.dropped_lines) > 10 else "")
            print(f"{PROGRAM}: warning: dropped {len(data.dropped_lines)} row(s) with NaN or empty values "
                  f"(line(s) {shown})", file=sys.stderr)
        from gls_calibration.discrepancy import explain
        from gls_calibration.geometry.effect_table import load_user_effect
        sys.path.insert(0, os.getcwd())   # user effects live in the working directory unless on PYTHONPATH
        try:
            user_effects = tuple(load_user_effect(reference) for reference in args.effects)
            sigma = data.sigma_mm if data.sigma_mm is not None else args.sigma
            result = explain(data.commanded_xy, data.measured_xy, geometry, known, data.t, sigma_mm=sigma,
                             user_effects=user_effects, criterion=args.criterion, max_steps=args.max_steps)
        except ValueError as error:
            raise InputError(str(error)) from None
        finally:
            sys.path.remove(os.getcwd())
    except InputError as error:
        print(f"{PROGRAM}: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        _write_outputs(result, args.out, args.measured, model_path, data)
    except OSError as error:
        print(f"{PROGRAM}: error: cannot write {args.out}: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    from gls_calibration.discrepancy.verdict import naming_phrase

    named = naming_phrase(result) if result.named_effects or result.named_groups else "none"
    print(f"named effects: {named}; residual RMS {result.rms_before_mm:.4f} -> {result.rms_after_mm:.4f} mm "
          f"({result.floor.source} noise floor {result.noise_floor_mm:.4f} mm); verdict {result.verdict.verdict}"
          + (f", {result.verdict.unexplained_rms_mm:.4f} mm unexplained"
             + (" (smooth structure below the noise floor)" if result.verdict.below_floor else "")
             + f": {result.verdict.pattern}"
             if result.verdict.verdict != "explained" else "") + f"; wrote {args.out}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
