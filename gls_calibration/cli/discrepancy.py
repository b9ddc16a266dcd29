"""``gls-discrepancy``: name the physical effects missing from the head model, from one measured grid.

    gls-discrepancy --measured FILE.csv [--model MODEL.yaml] --out DIR

FILE.csv has the header ``x_cmd,y_cmd,x_meas,y_meas`` and optionally ``t``: commanded nominal
targets in the gls frame (mm), measured mark positions in any in-plane frame a rigid motion away (mm),
marking time (s). Rows with NaN or empty values are dropped with a warning. MODEL.yaml is a head
configuration (see :mod:`gls_calibration.head_config`; default ``config/head.yaml``).

Writes DIR/discrepancy.json, DIR/report.md, DIR/residual_field.png and DIR/gap_per_step.png. Every
input is checked before anything is written; the files are rendered in a temporary directory beside
DIR and moved in with atomic renames. Bad input: message on stderr, exit code 2, nothing written.
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

import numpy as np

from gls_calibration.discrepancy import MIN_POINTS, DiscrepancyResult, explain
from gls_calibration.head_config import default_head_config_path, load_head_config
from gls_calibration.report import json_safe

PROGRAM = "gls-discrepancy"
REQUIRED_COLUMNS = ("x_cmd", "y_cmd", "x_meas", "y_meas")
TIME_COLUMN = "t"
EXIT_OK = 0
EXIT_BAD_INPUT = 2


class InputError(ValueError):
    """Bad command-line input: reported on stderr with exit code 2."""


@dataclass(frozen=True)
class Measurements:
    """Validated rows of the measurement CSV."""

    commanded_xy: np.ndarray
    measured_xy: np.ndarray
    t: np.ndarray | None
    dropped_lines: tuple[int, ...]     # file line numbers of rows dropped for NaN or empty values


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


def read_measurements(path: str | Path) -> Measurements:
    """Read and validate the measurement CSV; raise InputError with a message naming the problem."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            lines = list(csv.reader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise InputError(f"cannot read {path}: {getattr(error, 'strerror', None) or error}") from None
    numbered = [(number, row) for number, row in enumerate(lines, start=1) if any(cell.strip() for cell in row)]
    if not numbered:
        raise InputError(f"{path} is empty; expected the header {','.join(REQUIRED_COLUMNS)}[,{TIME_COLUMN}]")
    header = [cell.strip() for cell in numbered[0][1]]
    missing = [column for column in REQUIRED_COLUMNS if column not in header]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}; "
                         f"expected the header {','.join(REQUIRED_COLUMNS)}[,{TIME_COLUMN}], got {','.join(header)}")
    columns = list(REQUIRED_COLUMNS) + ([TIME_COLUMN] if TIME_COLUMN in header else [])
    index = {column: header.index(column) for column in columns}
    values, line_numbers = [], []
    for number, row in numbered[1:]:
        if len(row) != len(header):
            raise InputError(f"{path}: line {number} has {len(row)} field(s), the header has {len(header)}")
        values.append([_parse_value(row[index[column]], number, column) for column in columns])
        line_numbers.append(number)
    table = np.array(values, dtype=float).reshape(-1, len(columns))
    valid = np.all(np.isfinite(table), axis=1)
    dropped = tuple(number for number, ok in zip(line_numbers, valid) if not ok)
    table = table[valid]
    kept_lines = [number for number, ok in zip(line_numbers, valid) if ok]
    if len(table) < MIN_POINTS:
        raise InputError(f"{path}: only {len(table)} valid point(s) after dropping {len(dropped)} row(s) with NaN "
                         f"or empty values; at least {MIN_POINTS} are needed")
    targets, first_index, counts = np.unique(table[:, :2], axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        duplicates = [(tuple(target), kept_lines[first]) for target, first, count in zip(targets, first_index, counts)
                      if count > 1]
        shown = "; ".join(f"({x:g}, {y:g}) first on line {line}" for (x, y), line in duplicates[:5])
        raise InputError(f"{path}: {len(duplicates)} duplicate commanded target(s): {shown}")
    return Measurements(table[:, 0:2].copy(), table[:, 2:4].copy(),
                        table[:, 4].copy() if TIME_COLUMN in columns else None, dropped)


# --------------------------------------------------------------------------------------------------
# outputs

def _plot_residual_fields(result: DiscrepancyResult, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    points = result.commanded_xy
    before, after = result.residual_before_xy, result.residual_after_xy
    span = float(np.max(np.ptp(points, axis=0))) or 1.0
    longest = float(np.max(np.hypot(*before.T))) or 1e-9
    scale = longest / (0.08 * span)        # data mm per plot mm: longest arrow ~8 % of the field, both panels
    key = float(f"{longest:.1g}")
    figure, axes = plt.subplots(1, 2, figsize=(12, 5.8), sharex=True, sharey=True)
    for axis, residual, title in ((axes[0], before, f"before: RMS {result.rms_before_mm:.4f} mm"),
                                  (axes[1], after, f"after {', '.join(result.named_effects) or 'nothing'}: "
                                                   f"RMS {result.rms_after_mm:.4f} mm")):
        arrows = axis.quiver(points[:, 0], points[:, 1], residual[:, 0], residual[:, 1], angles="xy",
                             scale_units="xy", scale=scale, width=0.003, color="tab:red")
        axis.quiverkey(arrows, 0.82, 1.02, key, f"{key:g} mm", labelpos="E")
        axis.set_title(title, fontsize=10, loc="left")
        axis.set_xlabel("x (mm, gls)")
        axis.set_aspect("equal")
    axes[0].set_ylabel("y (mm, gls)")
    figure.suptitle(f"residual after rigid alignment (same arrow scale); noise floor {result.noise_floor_mm:.4f} mm")
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


def _report_markdown(result: DiscrepancyResult, measured: Path, model: Path | None, data: Measurements) -> str:
    criterion = result.criterion.upper()
    lines = [
        "# Discrepancy report",
        "",
        f"- measurements: `{measured}` ({len(result.commanded_xy)} points"
        + (f", {len(data.dropped_lines)} row(s) with NaN dropped" if data.dropped_lines else "")
        + (", with marking time" if result.t is not None else ", no marking time") + ")",
        f"- model: `{model}`" if model is not None else "- model: published defaults",
        f"- known effects: {', '.join(f'{k} = {list(v)}' for k, v in result.known_effects.values.items()) or 'none'}",
        "",
        "## Gap",
        "",
        "| | value |",
        "|---|---|",
        f"| residual RMS before | {result.rms_before_mm:.4f} mm |",
        f"| residual RMS after | {result.rms_after_mm:.4f} mm |",
        f"| noise floor (from the data) | {result.noise_floor_mm:.4f} mm ({result.noise.sigma_axis_mm:.4f} mm per axis) |",
        f"| structure test before (F-test p) | {result.structure_before.p_value:.3g} "
        f"({'structure' if result.structure_before.is_structure else 'noise'}) |",
        f"| structure test after (F-test p) | {result.structure_after.p_value:.3g} "
        f"({'structure' if result.structure_after.is_structure else 'noise'}) |",
        f"| named effects | {', '.join(result.named_effects) or 'none'} |",
        "",
        f"Stopped because {result.stop_reason}.",
        "",
        "![residual field before and after](residual_field.png)",
        "",
        "![gap per step](gap_per_step.png)",
        "",
        "## Steps",
        "",
    ]
    if result.steps:
        lines += [f"| step | effect | parameters (± 1 sigma) | indistinguishable from | {criterion} gain | RMS before → after (mm) | dropped |",
                  "|---|---|---|---|---|---|---|"]
        for number, step in enumerate(result.steps, start=1):
            lines.append(f"| {number} | {step.name} | {_format_parameters(step)} | "
                         f"{', '.join(step.indistinguishable_from) or '-'} | {step.improvement:.1f} | "
                         f"{step.rms_before_mm:.4f} → {step.rms_after_mm:.4f} | {', '.join(step.removed) or '-'} |")
        for number, step in enumerate(result.steps, start=1):
            lines += ["", f"### Candidates at step {number}", "",
                      f"| candidate | {criterion} gain | RMS after (mm) | field difference to best (mm) |",
                      "|---|---|---|---|"]
            lines += [f"| {c.name} | {c.improvement:.1f} | {c.rms_after_mm:.4f} | {c.field_difference_mm:.4f} |"
                      for c in step.candidates]
    else:
        lines.append("No missing effect named.")
    lines += ["", "## Where the residual lives", ""]
    for label, location in (("before", result.location_before), ("after", result.location_after)):
        lines.append(f"- {label}: RMS x {location.rms_x_mm:.4f} mm, y {location.rms_y_mm:.4f} mm; centre "
                     f"{location.rms_centre_mm:.4f} mm, edge {location.rms_edge_mm:.4f} mm"
                     + (f"; {'; '.join(location.findings)}" if location.findings else ""))
    lines += ["", "## Notes", ""] + [f"- {note}" for note in result.notes] + [""]
    return "\n".join(lines)


def _write_outputs(result: DiscrepancyResult, out: Path, measured: Path, model: Path | None,
                   data: Measurements) -> None:
    """Render everything in a temporary directory beside ``out``, then move it in atomically."""
    out = out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        document = result.to_dict()
        document["input"] = {"measured": str(measured), "model": None if model is None else str(model),
                             "dropped_lines": list(data.dropped_lines)}
        (staging / "discrepancy.json").write_text(json.dumps(json_safe(document), indent=2) + "\n", encoding="utf-8")
        _plot_residual_fields(result, staging / "residual_field.png")
        _plot_gap(result, staging / "gap_per_step.png")
        (staging / "report.md").write_text(_report_markdown(result, measured, model, data), encoding="utf-8")
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
        prog=PROGRAM, description="Name the physical effects missing from the galvo head model, from measured marks.")
    parser.add_argument("--measured", required=True, type=Path,
                        help="CSV with header x_cmd,y_cmd,x_meas,y_meas[,t] (mm, mm, s)")
    parser.add_argument("--model", type=Path, default=None,
                        help="head configuration YAML (nominal d, e, limits; optional known effects); "
                             "default config/head.yaml")
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--criterion", choices=("bic", "aic"), default="bic", help="information criterion (default bic)")
    parser.add_argument("--max-steps", type=int, default=4, help="most effects to add (default 4)")
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
        data = read_measurements(args.measured)
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
        try:
            result = explain(data.commanded_xy, data.measured_xy, geometry, known, data.t,
                             criterion=args.criterion, max_steps=args.max_steps)
        except ValueError as error:
            raise InputError(str(error)) from None
    except InputError as error:
        print(f"{PROGRAM}: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        _write_outputs(result, args.out, args.measured, model_path, data)
    except OSError as error:
        print(f"{PROGRAM}: error: cannot write {args.out}: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    named = ", ".join(result.named_effects) or "none"
    print(f"named effects: {named}; residual RMS {result.rms_before_mm:.4f} -> {result.rms_after_mm:.4f} mm "
          f"(noise floor {result.noise_floor_mm:.4f} mm); wrote {args.out}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
