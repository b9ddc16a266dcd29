"""gls-correct: send targets from a CSV (x,y[,z] in mm, gls frame) to ``correct_setpoints``; write
the corrected targets, mirror angles and focus shift as CSV."""
from __future__ import annotations

import argparse
import csv
from pathlib import Path
import sys

import numpy as np
from gls_calibration.cli.client import call_and_wait, client_node
from gls_calibration.nodes.conversions import float64_sequence
from gls_calibration.persistence import atomic_write_text
from gls_calibration_msgs.srv import CorrectSetpoints

OUTPUT_COLUMNS = ("x", "y", "z", "k_x", "k_y", "alpha_x_rad", "alpha_y_rad", "focus_shift_mm",
                  "inside_calibrated_field", "within_limits")


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
    try:
        x = np.array([float(row["x"]) for row in rows])
        y = np.array([float(row["y"]) for row in rows])
        z = np.array([float(row["z"]) for row in rows]) if "z" in columns else np.empty(0)
    except ValueError as error:
        raise ValueError(f"{path}: non-numeric value: {error}") from None
    return x, y, z


def main(argv: list[str] | None = None) -> int:
    """Exit 0 on success, 1 when the service refused, 2 on bad input."""
    parser = argparse.ArgumentParser(prog="gls-correct", description=__doc__.splitlines()[0])
    parser.add_argument("targets", type=Path, help="CSV with columns x,y[,z] (mm)")
    parser.add_argument("--out", type=Path, required=True, help="CSV to write")
    parser.add_argument("--namespace", default="gls")
    parser.add_argument("--timeout", type=float, default=30.0)
    args = parser.parse_args(argv)
    try:
        x, y, z = read_targets(args.targets)
    except (OSError, ValueError) as error:
        print(error, file=sys.stderr)
        return 2
    with client_node("gls_correct_client", args.namespace) as (node, executor):
        try:
            response = call_and_wait(executor, node.create_client(CorrectSetpoints, "correct_setpoints"),
                                     CorrectSetpoints.Request(x=float64_sequence(x), y=float64_sequence(y),
                                                              z=float64_sequence(z)), args.timeout)
        except TimeoutError as error:
            print(error, file=sys.stderr)
            return 1
    if response is None or not response.success:
        print(f"correct_setpoints: {'no answer' if response is None else response.message}", file=sys.stderr)
        return 1
    z_out = z if len(z) else np.zeros_like(x)
    lines = [",".join(OUTPUT_COLUMNS)]
    for row in zip(x, y, z_out, response.x, response.y, response.alpha_x, response.alpha_y,
                   response.focus_shift, response.inside_calibrated_field, response.within_limits):
        lines.append(",".join(repr(float(value)) if not isinstance(value, (bool, np.bool_)) else str(int(value))
                              for value in row))
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print(f"{len(x)} targets corrected ({response.message}); written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
