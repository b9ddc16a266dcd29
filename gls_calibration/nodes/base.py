"""What every node of the package shares: parameter declaration, async service calls, main()."""
from __future__ import annotations

from typing import Any, Callable

import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

DEFAULT_NAMESPACE = "gls"


class ServiceCallError(RuntimeError):
    """A service another node serves did not answer in time, or answered with a failure."""


class GlsNode(Node):
    """A node of the package: ``gls`` namespace by default, helpers for parameters and calls."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        kwargs.setdefault("namespace", DEFAULT_NAMESPACE)
        super().__init__(name, **kwargs)
        # Services that await other services, their clients and timers share one reentrant group:
        # a mutually exclusive group would stay busy while the awaiting coroutine runs and block the
        # very response it waits for.
        self.reentrant_group = ReentrantCallbackGroup()

    def declare(self, name: str, default: Any, description: str, *,
                minimum: float | None = None, maximum: float | None = None,
                read_only: bool = False) -> Any:
        """Declare a parameter with a descriptor (and range) and return its value."""
        descriptor = ParameterDescriptor(description=description, read_only=read_only)
        if minimum is not None or maximum is not None:
            if isinstance(default, bool):
                raise TypeError(f"parameter {name}: a range makes no sense for a bool")
            if isinstance(default, int):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(minimum if minimum is not None else -(2 ** 31)),
                    to_value=int(maximum if maximum is not None else 2 ** 31 - 1), step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(minimum if minimum is not None else -1e308),
                    to_value=float(maximum if maximum is not None else 1e308), step=0.0)]
        return self.declare_parameter(name, default, descriptor).value

    def client(self, srv_type: type, name: str):
        """A client in the reentrant group, so that coroutine callbacks can await it."""
        return self.create_client(srv_type, name, callback_group=self.reentrant_group)

    async def call(self, client, request: Any, timeout_s: float) -> Any:
        """Await ``client``'s answer to ``request``; ServiceCallError after ``timeout_s`` (never blocks)."""
        if not client.service_is_ready():
            await self.wait_for(lambda: client.service_is_ready(), min(timeout_s, 10.0),
                                f"service {client.srv_name} is not available")
        future = client.call_async(request)
        response = await self._with_timeout(future, timeout_s, f"service {client.srv_name} did not answer "
                                                                f"within {timeout_s:g} s")
        return response

    async def wait_for(self, condition: Callable[[], bool], timeout_s: float, message: str | Callable[[], str],
                       period_s: float = 0.05) -> None:
        """Await ``condition()`` becoming true, polled by a timer; ServiceCallError(message) on timeout.

        ``message`` may be a callable, so that it can tell the state at the time of the timeout.
        """
        if condition():
            return
        done = Future()

        def poll() -> None:
            if not done.done() and condition():
                done.set_result(True)
        timer = self.create_timer(period_s, poll, callback_group=self.reentrant_group)
        try:
            await self._with_timeout(done, timeout_s, message)
        finally:
            self.destroy_timer(timer)

    async def _with_timeout(self, future: Future, timeout_s: float, message: str | Callable[[], str]) -> Any:
        waiter = Future()
        future.add_done_callback(lambda f: waiter.done() or waiter.set_result(True))

        def expire() -> None:
            if not waiter.done():
                waiter.set_result(False)
        timer = self.create_timer(timeout_s, expire, callback_group=self.reentrant_group)
        try:
            finished = await waiter
        finally:
            self.destroy_timer(timer)
        if not finished:
            future.cancel()
            raise ServiceCallError(message() if callable(message) else message)
        return future.result()


def spin_nodes(nodes: list[Node], threads: int = 4) -> None:
    """Spin ``nodes`` on one multi-threaded executor until shutdown or Ctrl-C."""
    executor = MultiThreadedExecutor(num_threads=threads)
    for node in nodes:
        executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()


def run_node(factory: Callable[[], Node], args: list[str] | None = None) -> None:
    """Console-script entry: init rclpy (ROS arguments such as remaps apply), spin one node, shut down."""
    rclpy.init(args=args)
    try:
        spin_nodes([factory()])
    finally:
        if rclpy.ok():
            rclpy.shutdown()
