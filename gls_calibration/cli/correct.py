"""gls-correct: corrected setpoints for CSV targets, from a calibration file or the running cell.

Corrected targets, mirror angles and focus shift for targets from a CSV (x,y[,z] in mm, gls frame),
from a calibration file (``--calibration FILE``, no running cell needed) or from the running cell's
correction node (``correct_setpoints_batch``).

One output row per target, in input order. Exit 0 when every target is reachable, 1 when some lie
beyond the mirror limits or the focus range (the file is still written, complete, with its
``within_limits`` flags) or the service failed, 2 on bad input (nothing written).
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path
import sys
from typing import Optional, Sequence

import numpy as np

from gls_calibration.common.files import atomic_write_text, require_regular_output

OUTPUT_COLUMNS = ("x", "y", "z", "k_x", "k_y", "alpha_x_rad", "alpha_y_rad", "focus_shift_mm",
                  "inside_calibrated_field", "within_limits", "uncertainty_k2_mm")


def read_targets(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Targets from a CSV with the header x,y and optionally z; ValueError with the reason."""
    with path.open(newline="") as stream:
        reader = csv.DictReader(stream)
        columns = reader.fieldnames or []
        missing = [name for name in ("x", "y") if name not in columns]
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(missing)} (header: {','.join(columns)})")
        rows = list(reader)
    if not rows:
        raise ValueError(f"{path}: no targets")
    names = ("x", "y", "z") if "z" in columns else ("x", "y")
    try:
        values = np.array([[float(row[name]) for name in names] for row in rows])
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: non-numeric value: {error}") from None
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if bad.size:
        raise ValueError(f"{path}: {bad.size} row(s) with NaN or infinite values (first: data row {bad[0] + 1})")
    return values[:, 0], values[:, 1], values[:, 2] if "z" in columns else np.empty(0)


def corrected_csv_text(x, y, z, k_x, k_y, alpha_x, alpha_y, focus_shift, inside, within, uncertainty) -> str:
    """Format the output table: OUTPUT_COLUMNS, floats at full precision, flags as 0/1.

    The uncertainty (mm, 95 % radius) is ``nan`` outside the calibrated field or without the
    calibration's map.
    """
    lines = [",".join(OUTPUT_COLUMNS)]
    floats = np.column_stack([x, y, z, k_x, k_y, alpha_x, alpha_y, focus_shift]).tolist()
    uncertainty = np.full(len(floats), np.nan) if uncertainty is None else np.asarray(uncertainty, dtype=float)
    for row, inside_flag, within_flag, u in zip(floats, np.asarray(inside, bool), np.asarray(within, bool),
                                                uncertainty.tolist()):
        lines.append(",".join(map(repr, row)) + f",{int(inside_flag)},{int(within_flag)},{u!r}")
    return "\n".join(lines) + "\n"


def correct_offline(calibration: Path, x, y, z):
    """(k_x, k_y, alpha_x, alpha_y, focus_shift, inside, within, uncertainty, note) from a calibration file."""
    from gls_calibration.calibration.record import correction_from_record
    from gls_calibration.calibration.record_file import head_geometry, load_record
    record = load_record(calibration)
    try:
        correction = correction_from_record(record, head_geometry(record))
    except ValueError as error:
        raise ValueError(f"calibration file {calibration}: {error}") from None
    result = correction.correct(x, y, z if len(z) else None)
    return (result.x, result.y, result.alpha_x, result.alpha_y, result.focus_shift,
            result.inside_calibrated_field, result.within_limits, result.uncertainty_k2_mm,
            f"calibration {calibration}")


SERVICE = "correct_setpoints_batch"

RESEND_PER_TARGET_S = 1e-5
"""A large request is sent again only after this long per target (the correction takes about 0.5 µs
per target on a 2-core machine), so that a slow answer is not taken for a lost one."""


def correct_by_service(namespace: str, timeout: float, x, y, z, ros_arguments: Sequence[str] = ()):
    """Correct the targets through the running cell's ``correct_setpoints_batch`` service.

    The same from the running cell's correction node (``ros_arguments``: remaps, namespace), through
    ``correct_setpoints_batch``: a file of targets is a large request, whose answer on
    ``correct_setpoints`` would hold up other clients' single targets. RuntimeError when it gives no
    usable answer.
    """
    from gls_calibration.cli.client import RESEND_AFTER_S, call_and_wait, client_node
    from gls_calibration.ros.base import CLIENT_QOS
    from gls_calibration.ros.conversions import float64_sequence, setpoints_from_response
    from gls_calibration_msgs.srv import CorrectSetpoints
    with client_node("gls_correct_client", namespace, ros_arguments) as (node, executor):
        print(f"gls-correct: service {node.resolve_service_name(SERVICE)}", file=sys.stderr)
        try:
            response = call_and_wait(executor, node.create_client(CorrectSetpoints, SERVICE, qos_profile=CLIENT_QOS),
                                     CorrectSetpoints.Request(x=float64_sequence(x), y=float64_sequence(y),
                                                              z=float64_sequence(z)), timeout,
                                     resend_after_s=max(RESEND_AFTER_S, len(x) * RESEND_PER_TARGET_S))
        except TimeoutError as error:
            raise RuntimeError(str(error)) from None
    if response is None:
        raise RuntimeError(f"{SERVICE}: no answer")
    complete = all(len(values) == len(x) for values in (response.x, response.y, response.alpha_x, response.alpha_y,
                                                        response.focus_shift, response.inside_calibrated_field,
                                                        response.within_limits))
    # A refusal for unreachable targets still carries every answer and its flags.
    if not complete or (not response.success and all(response.within_limits)):
        raise RuntimeError(f"{SERVICE}: {response.message}")
    result = setpoints_from_response(response)
    return (result.x, result.y, result.alpha_x, result.alpha_y, result.focus_shift,
            result.inside_calibrated_field, result.within_limits, result.uncertainty_k2_mm,
            f"service: {response.message}")


def main(argv: Optional[list[str]] = None) -> int:
    """Run gls-correct; return its exit code.

    Exit 0 on success, 1 when targets are unreachable or the service failed, 2 on bad input. ROS
    arguments (remaps, namespace) follow ``--ros-args``.
    """
    from gls_calibration.cli import timeout_seconds
    from gls_calibration.cli.client import split_ros_arguments
    own_arguments, ros_arguments = split_ros_arguments(argv)
    parser = argparse.ArgumentParser(prog="gls-correct", description=__doc__.split("\n\n")[0])
    parser.add_argument("targets", type=Path, help="CSV with columns x,y[,z] (mm)")
    parser.add_argument("--out", type=Path, required=True, help="CSV to write")
    parser.add_argument("--calibration", type=Path, help="calibration file: correct without a running cell")
    parser.add_argument("--namespace", default="gls",
                        help="namespace of the cell's correction node (default: gls; without --calibration)")
    parser.add_argument("--timeout", type=timeout_seconds, default=30.0,
                        help="give up on the correction service after this (s, default 30; without --calibration)")
    args = parser.parse_args(own_arguments)
    try:
        require_regular_output(args.out)   # checked before anything is asked of the cell
        x, y, z = read_targets(args.targets)
        if not args.out.parent.is_dir():
            raise ValueError(f"cannot write {args.out}: folder {args.out.parent} does not exist")
        if args.calibration is not None:
            answers = correct_offline(args.calibration, x, y, z)
    except (OSError, ValueError) as error:
        print(error, file=sys.stderr)
        return 2
    if args.calibration is None:
        try:
            answers = correct_by_service(args.namespace, args.timeout, x, y, z, ros_arguments)
        except RuntimeError as error:
            print(error, file=sys.stderr)
            return 1
    *columns, note = answers
    try:
        atomic_write_text(args.out, corrected_csv_text(x, y, z if len(z) else np.zeros_like(x), *columns))
    except OSError as error:
        print(f"cannot write {args.out}: {error.strerror or error}", file=sys.stderr)
        return 2
    within = columns[OUTPUT_COLUMNS.index("within_limits") - 3]     # the answers start at k_x
    unreachable = int(np.count_nonzero(~np.asarray(within, bool)))
    if unreachable:
        first = int(np.argmin(within))
        print(f"{unreachable} of {len(x)} target(s) beyond the mirror limits or the focus range (first: data row "
              f"{first + 1}); all {len(x)} written to {args.out} with within_limits flags", file=sys.stderr)
        return 1
    print(f"{len(x)} targets corrected ({note}); written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
