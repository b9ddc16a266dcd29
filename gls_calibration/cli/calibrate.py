"""gls-calibrate: call ``calibrate`` on a running system and show its progress and result."""
from __future__ import annotations

import argparse
import math
import sys

from gls_calibration.cli.client import ProgressBar, call_and_wait, client_node, summary_table
from gls_calibration_msgs.msg import CalibrationProgress
from gls_calibration_msgs.srv import Calibrate


def main(argv: list[str] | None = None) -> int:
    """Exit 0 when the calibration succeeded, 1 when it failed, 2 on bad arguments."""
    parser = argparse.ArgumentParser(prog="gls-calibrate", description=__doc__.splitlines()[0])
    parser.add_argument("--namespace", default="gls", help="namespace of the calibration manager")
    parser.add_argument("--iterations", type=int, default=0, help="0: the configured default")
    parser.add_argument("--no-validate", action="store_true", help="skip the validation grid")
    parser.add_argument("--force", action="store_true",
                        help="train even when within tolerance, and mark a plate that carries old marks")
    parser.add_argument("--timeout", type=float, default=900.0, help="give up after this (s)")
    args = parser.parse_args(argv)
    if not 0 <= args.iterations <= 255:
        parser.error("--iterations must be between 0 and 255 (the manager refuses more than its max_iterations)")
    if not math.isfinite(args.timeout) or args.timeout <= 0.0:
        parser.error("--timeout must be a positive number of seconds")
    bar = ProgressBar(sys.stderr)
    with client_node("gls_calibrate_client", args.namespace) as (node, executor):
        node.create_subscription(CalibrationProgress, "calibration/progress", bar.update, 10)
        try:
            response = call_and_wait(executor, node.create_client(Calibrate, "calibrate"), Calibrate.Request(
                iterations=args.iterations, validate=not args.no_validate, force=args.force), args.timeout)
        except TimeoutError as error:
            print(error, file=sys.stderr)
            return 1
        finally:
            bar.finish()
    if response is None:
        print(f"calibrate did not answer within {args.timeout:g} s", file=sys.stderr)
        return 1
    print(summary_table(response))
    if response.report_dir:
        print(f"report: {response.report_dir}")
    return 0 if response.success else 1


if __name__ == "__main__":
    sys.exit(main())
