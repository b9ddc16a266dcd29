"""What the operator tools share: waiting for a service answer, a progress bar, the summary table."""
from __future__ import annotations

from contextlib import contextmanager
import math
from typing import Any, Iterator, Optional, TextIO

import rclpy
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node


@contextmanager
def client_node(name: str, namespace: str) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """An initialised rclpy with one node for an operator tool, shut down afterwards."""
    rclpy.init()
    node = rclpy.create_node(name, namespace=namespace)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown()


def call_and_wait(executor: Executor, client, request: Any, timeout_s: float) -> Optional[Any]:
    """Call ``client`` asynchronously and spin ``executor`` until the answer or the timeout (None)."""
    deadline_s = min(timeout_s, 30.0)
    if not client.wait_for_service(timeout_sec=deadline_s):
        raise TimeoutError(f"service {client.srv_name} is not available (waited {deadline_s:g} s)")
    future = client.call_async(request)
    executor.spin_until_future_complete(future, timeout_sec=timeout_s)
    if not future.done():
        future.cancel()
        return None
    return future.result()


class ProgressBar:
    """Draws ``calibration/progress`` messages: one redrawn line on a terminal, plain lines otherwise."""

    def __init__(self, stream: TextIO, width: int = 30) -> None:
        self.stream = stream
        self.width = width
        self.interactive = stream.isatty()
        self.last_stage = ""

    def update(self, message) -> None:
        """Subscription callback."""
        # The message comes from the network: a NaN or out-of-range fraction must not end the tool.
        fraction = min(max(message.fraction, 0.0), 1.0) if math.isfinite(message.fraction) else 0.0
        filled = int(round(self.width * fraction))
        line = f"[{'#' * filled}{'.' * (self.width - filled)}] {fraction:4.0%} {message.stage}: {message.text}"
        if self.interactive:
            self.stream.write("\r" + line[:120].ljust(120))
        elif message.stage != self.last_stage:
            self.stream.write(line + "\n")
        self.last_stage = message.stage
        self.stream.flush()

    def finish(self) -> None:
        """End the redrawn line."""
        if self.interactive:
            self.stream.write("\n")
            self.stream.flush()


def _mm(value: float) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.4f}"


def summary_table(response) -> str:
    """The ``calibrate`` answer as a small table for people."""
    rows = [
        ("result", "success" if response.success else "FAILED", response.message),
        ("deviation before (measured)", f"RMS {_mm(response.pre_rms_mm)} mm", f"max {_mm(response.pre_max_mm)} mm"),
        ("deviation after (validation)", f"RMS {_mm(response.post_rms_mm)} mm", f"max {_mm(response.post_max_mm)} mm"),
        ("fiducials", f"{response.fiducials_found} found", f"of {response.fiducials_expected}"),
        ("model", f"{response.neurons} units", f"CV RMS {_mm(response.cv_rms_mm)} mm"),
        ("duration", f"{response.duration_s:.1f} s", ""),
        ("calibration file", response.calibration_file or "-", ""),
    ]
    width = max(len(row[0]) for row in rows)
    return "\n".join(f"{name.ljust(width)}  {first}  {second}".rstrip() for name, first, second in rows)
