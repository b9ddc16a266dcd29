"""What the operator tools share: ROS arguments, service waits, a progress bar, the summary.

Splitting the ROS arguments off, waiting for a service answer, a progress bar and the summary table.
"""
from __future__ import annotations

from contextlib import contextmanager
import math
import sys
import time
import uuid
from typing import Any, Iterator, Optional, Sequence, TextIO

from action_msgs.msg import GoalStatusArray
import rclpy
from rclpy.action.client import ClientGoalHandle
from rclpy.context import Context
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_action_status_default
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from rclpy.utilities import remove_ros_args
from unique_identifier_msgs.msg import UUID


def split_ros_arguments(argv: Sequence[str] | None) -> tuple[list[str], list[str]]:
    """Split a command line into the tool's own arguments and the command line for rclpy.

    (the tool's own arguments, the whole command line for rclpy, which reads only what follows
    ``--ros-args``) of e.g. ``gls-calibrate --iterations 2 --ros-args -r __ns:=/cell2``; None means
    sys.argv[1:].
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    return remove_ros_args(["tool"] + argv)[1:], argv


def ros_rules(argv: Sequence[str], *flags: str) -> list[str]:
    """Return the values given to ``flags`` among the ROS arguments of ``argv``, in their order.

    ``flags`` are e.g. ``-p``, ``--param``; the ROS arguments run from ``--ros-args`` to ``--`` or
    the end. rcl applies the values in this order, so the last one of a name wins.
    """
    rules, inside, tokens = [], False, iter(argv)
    for token in tokens:
        if token in ("--ros-args", "--"):
            inside = token == "--ros-args"
        elif inside and token in flags:
            value = next(tokens, None)
            if value is not None:
                rules.append(value)
    return rules


@contextmanager
def client_node(name: str, namespace: str, ros_arguments: Sequence[str] = ()
                ) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """Initialise rclpy and give one node for an operator tool; shut both down afterwards.

    An initialised rclpy (with ``ros_arguments``: remaps, namespace, parameters) and one node for
    an operator tool, shut down afterwards. rclpy's signal handlers stay off, so Ctrl-C raises
    KeyboardInterrupt where the tool can answer it.
    """
    context = Context()
    rclpy.init(args=["tool", *ros_arguments], context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name, namespace=namespace, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()


RESEND_AFTER_S = 1.0
"""An idempotent request unanswered this long is sent again, then after twice as long, and so on. A
server that has not yet discovered this client's answer reader drops its answer (Fast DDS waits
100 ms for the match, then logs "failed to send response (timeout)"): a tool's process is new to the
graph at every call, and on a busy host that first answer can be lost."""


def call_and_wait(executor: Executor, client, request: Any, timeout_s: float,
                  resend_after_s: Optional[float] = None) -> Optional[Any]:
    """Call ``client`` asynchronously and spin ``executor`` until the answer or the timeout (None).

    ``resend_after_s`` (only for requests a server may receive twice): when no answer came within
    that time, send the request again, then after twice that time, and so on; the first answer to any
    copy counts.
    """
    deadline_s = min(timeout_s, 30.0)
    if not client.wait_for_service(timeout_sec=deadline_s):
        raise TimeoutError(f"service {client.srv_name} is not available (waited {deadline_s:g} s)")
    sent: list[Future] = []
    try:
        answered = _send_until_answered(executor, lambda: client.call_async(request), sent, timeout_s,
                                        resend_after_s, f"service {client.srv_name}")
        return None if answered is None else answered.result()
    finally:
        for future in sent:
            if not future.done():
                client.remove_pending_request(future)


def send_goal(executor: Executor, node: Node, client, action_type: type, action_name: str, goal: Any,
              wait_s: float, feedback_callback=None, resend_after_s: Optional[float] = RESEND_AFTER_S):
    """Send ``goal`` through ``client`` and return its accepted goal handle, or None.

    Send ``goal`` through ``client``, an ActionClient of ``node`` for ``action_type`` named
    ``action_name``, and return its accepted goal handle, or None when the server refused it or gave
    no sign within ``wait_s``.

    The goal's answer can be lost like a service's (see ``RESEND_AFTER_S``) while the goal runs. So
    the goal carries an id of its own: unanswered after ``resend_after_s`` (then twice as long, ...),
    it is sent again with the same id, which a server refuses rather than starting a second run; and
    the action's status topic (``action_name``/_action/status), where the server lists the goals it
    accepted, shows an accepted goal whose answer never came.
    """
    goal_id = UUID(uuid=list(uuid.uuid4().bytes))
    key = bytes(goal_id.uuid)
    listed: set[bytes] = set()
    status = node.create_subscription(
        GoalStatusArray, f"{action_name}/_action/status",
        lambda message: listed.update(bytes(entry.goal_info.goal_id.uuid) for entry in message.status_list),
        qos_profile_action_status_default)
    try:
        answered = _send_until_answered(
            executor, lambda: client.send_goal_async(goal, feedback_callback=feedback_callback, goal_uuid=goal_id),
            [], wait_s, resend_after_s, f"action {action_name}", given_up=lambda: key in listed)
        if answered is not None and answered.result().accepted:
            return answered.result()
        if answered is not None:
            # Refused: a copy whose first answer was lost is refused as a known id; the status says.
            _spin_until(executor, lambda: key in listed, min(wait_s, 2.0))
        # Listed by the server although no accepting answer came: the handle of our goal.
        return (ClientGoalHandle(client, goal_id, action_type.Impl.SendGoalService.Response(accepted=True))
                if key in listed else None)
    finally:
        node.destroy_subscription(status)


def _send_until_answered(executor: Executor, send, sent: list, timeout_s: float,
                         resend_after_s: Optional[float], what: str, given_up=lambda: False):
    """Call ``send()`` and spin ``executor`` until a future is done, or give up.

    Call ``send()`` (it returns a future, kept in ``sent``) and spin ``executor`` until one of its
    futures is done (returned), ``given_up()`` holds or ``timeout_s`` has passed (None). With
    ``resend_after_s``, send again when unanswered that long, then after twice as long, and so on.
    """
    deadline = time.monotonic() + timeout_s
    answered: Future = Future()
    wait_s = resend_after_s
    while True:
        future = send()
        future.add_done_callback(lambda done: answered.done() or answered.set_result(done))
        sent.append(future)
        remaining = deadline - time.monotonic()
        attempt_s = remaining if wait_s is None else min(remaining, wait_s)
        _spin_until(executor, lambda: answered.done() or given_up(), attempt_s)
        if answered.done():
            return answered.result()
        if given_up() or attempt_s >= remaining:
            return None
        print(f"no answer from {what} after {attempt_s:g} s: sent again", file=sys.stderr)
        wait_s *= 2.0


def _spin_until(executor: Executor, condition, timeout_s: float) -> None:
    """Spin ``executor`` until ``condition()`` holds or ``timeout_s`` has passed."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=min(0.05, max(deadline - time.monotonic(), 0.0)))


class ProgressBar:
    """Draws ``calibration/progress`` messages: one redrawn line on a terminal, plain lines otherwise."""

    def __init__(self, stream: TextIO, width: int = 30) -> None:
        self.stream = stream
        self.width = width
        self.interactive = stream.isatty()
        self.last_stage = ""
        self.line_open = False

    def update(self, message) -> None:
        """Show a ``calibration/progress`` message or the action's feedback on the progress bar."""
        text = message.text if hasattr(message, "text") else message.message
        # The message comes from the network: a NaN or out-of-range fraction must not end the tool.
        fraction = min(max(message.fraction, 0.0), 1.0) if math.isfinite(message.fraction) else 0.0
        filled = int(round(self.width * fraction))
        line = f"[{'#' * filled}{'.' * (self.width - filled)}] {fraction:4.0%} {message.stage}: {text}"
        if self.interactive:
            self.stream.write("\r" + line[:120].ljust(120))
            self.line_open = True
        elif message.stage != self.last_stage:
            self.stream.write(line + "\n")
        self.last_stage = message.stage
        self.stream.flush()

    def finish(self) -> None:
        """End the redrawn line (once)."""
        if self.line_open:
            self.stream.write("\n")
            self.stream.flush()
            self.line_open = False


def _mm(value: float) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.4f}"


def summary_table(response) -> str:
    """Return the ``calibrate`` answer as a small table for people."""
    rows = [
        ("result", "success" if response.success else "FAILED", response.message),
        ("deviation before (measured)", f"RMS {_mm(response.pre_rms_mm)} mm", f"max {_mm(response.pre_max_mm)} mm"),
        ("deviation after (validation)", f"RMS {_mm(response.post_rms_mm)} mm",
         f"max {_mm(response.post_max_mm)} mm  (self-consistency: measured by the chain that trained it)"),
        ("stated accuracy", f"RMS {_mm(response.stated_rms_mm)} mm", f"basis: {response.stated_basis}"),
        ("fiducials", f"{response.fiducials_found} found", f"of {response.fiducials_expected}"),
        ("model", f"{response.neurons} units", f"CV RMS {_mm(response.cv_rms_mm)} mm"),
        ("duration", f"{response.duration_s:.1f} s", ""),
        ("calibration file", response.calibration_file or "-", ""),
    ]
    width = max(len(row[0]) for row in rows)
    return "\n".join(f"{name.ljust(width)}  {first}  {second}".rstrip() for name, first, second in rows)
