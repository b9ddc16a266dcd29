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
what is left unexplained) and DIR/gap_per_step.png. Every input is checked before anything is
written; the files are rendered in a temporary directory beside DIR and moved in with atomic renames.
Bad input: message on stderr, exit code 2, nothing written.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
import sys

from gls_calibration.discrepancy.measurements_file import InputError, read_measurements
from gls_calibration.report.discrepancy_report import write_discrepancy_report

PROGRAM = "gls-discrepancy"
EXIT_OK = 0
EXIT_BAD_INPUT = 2


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
    parser.add_argument("--criterion", choices=("bic", "aic"), default="bic",
                        help="information criterion (default bic)")
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
        write_discrepancy_report(result, args.out, args.measured, model_path, data)
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
