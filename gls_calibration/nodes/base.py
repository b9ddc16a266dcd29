"""What every node of the package shares: parameter declaration, async service calls, main()."""
from __future__ import annotations

import functools
import inspect
import threading
import time
from typing import Any, Callable

import rclpy
from rclpy.context import Context
from rclpy.signals import SignalHandlerOptions
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

DEFAULT_NAMESPACE = "gls"


class ServiceCallError(RuntimeError):
    """A service another node serves did not answer in time, or answered with a failure."""


def answers_errors(*errors: type[BaseException]) -> Callable:
    """Decorate a service handler ``(self, request, response)``: when it raises one of ``errors``
    (default ValueError), answer ``success=false`` with the error's text instead of failing the call.

    Works on plain and coroutine handlers. Only expected, explained errors belong in ``errors``; a
    bug still surfaces as an exception in the executor's log.
    """
    caught = errors or (ValueError,)

    def refuse(response: Any, error: BaseException) -> Any:
        response.success, response.message = False, str(error)
        return response

    def decorate(handler: Callable) -> Callable:
        if inspect.iscoroutinefunction(handler):
            @functools.wraps(handler)
            async def answer_async(self, request, response):
                try:
                    return await handler(self, request, response)
                except caught as error:
                    return refuse(response, error)
            return answer_async

        @functools.wraps(handler)
        def answer(self, request, response):
            try:
                return handler(self, request, response)
            except caught as error:
                return refuse(response, error)
        return answer
    return decorate


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


class NodeThreads:
    """Spins each node on its own single-threaded executor in its own thread.

    One executor for many nodes rebuilds the wait set of every entity of every node for each
    callback; a full sweep (2001 profile messages) then took 15 s instead of 1.5 s. Coroutine
    callbacks (services that await other services) interleave on a single thread, so no node
    needs more than one.
    """

    def __init__(self, nodes: list[Node]) -> None:
        self.nodes = nodes
        self.executors = [SingleThreadedExecutor(context=node.context) for node in nodes]
        self.threads = []
        for node, executor in zip(nodes, self.executors):
            executor.add_node(node)
            thread = threading.Thread(target=self._spin, args=(executor,), name=node.get_name(), daemon=True)
            self.threads.append(thread)
            thread.start()

    @staticmethod
    def _spin(executor: SingleThreadedExecutor) -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass

    def join(self) -> None:
        """Block until the executors stop (shutdown of the context)."""
        for thread in self.threads:
            thread.join()

    def stop(self) -> None:
        """Stop the executors, wait for their threads and destroy the nodes."""
        for executor in self.executors:
            executor.shutdown()
        for thread in self.threads:
            thread.join(timeout=5.0)
        for node in self.nodes:
            node.destroy_node()


def run_node(factory: Callable[[], Node], args: list[str] | None = None) -> None:
    """Console-script entry: init rclpy (ROS arguments such as remaps apply), spin one node until
    Ctrl-C, then destroy the node before the context shuts down (the other order aborts in DDS)."""
    context = Context()
    rclpy.init(args=args, context=context, signal_handler_options=SignalHandlerOptions.NO)
    threads = NodeThreads([factory(context=context)])
    try:
        while context.ok():
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        threads.stop()
        context.try_shutdown()
