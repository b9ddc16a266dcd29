"""gls-calibrate: run the ``calibrate`` action on a running system, show its feedback and result.

Ctrl-C cancels the goal: the manager stops after the current step and keeps the active calibration.
ROS arguments follow ``--ros-args`` (e.g. ``--ros-args -r __ns:=/cell2``).
"""
from __future__ import annotations

import argparse
import sys

from rclpy.action import ActionClient

from gls_calibration.cli import timeout_seconds
from gls_calibration.cli.client import ProgressBar, client_node, send_goal, split_ros_arguments, summary_table
from gls_calibration_msgs.action import Calibrate

CANCEL_WAIT_S = 300.0   # the current step (a sweep, a marking job) ends before the run stops


def main(argv: list[str] | None = None) -> int:
    """Run gls-calibrate; return its exit code.

    Exit 0 when the calibration succeeded, 1 when it failed or timed out, 2 on bad arguments,
    130 when canceled with Ctrl-C.
    """
    own_arguments, ros_arguments = split_ros_arguments(argv)
    parser = argparse.ArgumentParser(prog="gls-calibrate", description=__doc__.splitlines()[0])
    parser.add_argument("--namespace", default="gls", help="namespace of the calibration manager")
    parser.add_argument("--iterations", type=int, default=0, help="0: the configured default")
    parser.add_argument("--no-validate", action="store_true", help="skip the validation grid")
    parser.add_argument("--force", action="store_true",
                        help="train even when within tolerance, and mark a plate that carries old marks")
    parser.add_argument("--timeout", type=timeout_seconds, default=900.0, help="give up after this (s)")
    args = parser.parse_args(own_arguments)
    if not 0 <= args.iterations <= 255:
        parser.error("--iterations must be between 0 and 255 (the manager refuses more than its max_iterations)")
    bar = ProgressBar(sys.stderr)
    with client_node("gls_calibrate_client", args.namespace, ros_arguments) as (node, executor):
        client = ActionClient(node, Calibrate, "calibrate")
        name = node.resolve_service_name("calibrate")   # an action's name resolves like a service's
        print(f"gls-calibrate: action {name}", file=sys.stderr, flush=True)
        wait_s = min(args.timeout, 30.0)
        if not client.wait_for_server(timeout_sec=wait_s):
            print(f"action {name} is not available (waited {wait_s:g} s)", file=sys.stderr)
            return 1
        goal = Calibrate.Goal(iterations=args.iterations, validate=not args.no_validate, force=args.force)
        goal_handle = None
        try:
            goal_handle = send_goal(executor, node, client, Calibrate, "calibrate", goal, wait_s,
                                    feedback_callback=lambda message: bar.update(message.feedback))
            if goal_handle is None:
                print(f"action {name} refused the goal or did not answer within {wait_s:g} s "
                      "(a calibration already running is refused)", file=sys.stderr)
                return 1
            result_future = goal_handle.get_result_async()
            executor.spin_until_future_complete(result_future, timeout_sec=args.timeout)
        except KeyboardInterrupt:
            bar.finish()
            if goal_handle is None or not goal_handle.accepted:
                print("interrupted before the calibration started", file=sys.stderr)
                return 130
            print("canceling the calibration: it stops after the current step ...", file=sys.stderr, flush=True)
            goal_handle.cancel_goal_async()
            result_future = goal_handle.get_result_async()
            try:
                executor.spin_until_future_complete(result_future, timeout_sec=CANCEL_WAIT_S)
            except KeyboardInterrupt:
                print("not waiting for the cancel to finish", file=sys.stderr)
                return 130
            if not result_future.done():
                print(f"no answer to the cancel within {CANCEL_WAIT_S:g} s", file=sys.stderr)
                return 130
            print(result_future.result().result.message, file=sys.stderr)
            return 130
        finally:
            bar.finish()
        if not result_future.done():
            print(f"calibrate did not finish within {args.timeout:g} s", file=sys.stderr)
            goal_handle.cancel_goal_async()
            executor.spin_once(timeout_sec=1.0)
            return 1
        response = result_future.result().result
    print(summary_table(response))
    if response.report_dir:
        print(f"report: {response.report_dir}")
    return 0 if response.success else 1


if __name__ == "__main__":
    sys.exit(main())
