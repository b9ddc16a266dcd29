"""What every node of the package shares: parameter declaration, async service calls, main()."""
from __future__ import annotations

import math
import threading
import time
from typing import Any, Callable, Iterator, Optional, Sequence

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult

from gls_calibration.common.parameter_specs import FLOAT_LIMITS, INTEGER_LIMITS, ParameterSpec
from gls_calibration.ros.service_errors import DeadlineExpired, ServiceCallError


DEFAULT_NAMESPACE = "gls"
POLL_PERIOD_S = 0.05          # how often a wait for a condition checks it
# How often a pending call checks its deadline and its server. Each check wakes the node's executor
# twice, and every wake rebuilds its wait set and resumes every coroutine in progress (rclpy): at
# 0.05 s this was most of the calibration manager's CPU while it waited for sweeps.
WATCH_PERIOD_S = 0.15
SERVER_GONE_CONFIRM_S = 0.3   # a server absent from the graph this long is gone (not a discovery blip)
SERVER_WAIT_S = 2.0           # how long a call waits for its server to appear before failing


# Fast DDS hands every answer of a service to the reader of each of its clients, which drops those not
# its own when it takes them. With the default queue of 10, a client among others that are busy can
# find its own answer pushed out before it took it: 1 single-target answer in ~4000-8000 was lost
# with 4 clients (bench_concurrency.py), none in 32 000 with a queue of 1000.
CLIENT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)


class GlsNode(Node):
    """A node of the package: ``gls`` namespace by default, helpers for parameters and calls."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        kwargs.setdefault("namespace", DEFAULT_NAMESPACE)
        super().__init__(name, **kwargs)
        # Services that await other services, their clients and timers share one reentrant group:
        # a mutually exclusive group would stay busy while the awaiting coroutine runs and block the
        # very response it waits for.
        self.reentrant_group = ReentrantCallbackGroup()
        self.dynamic_parameters: set[str] = set()
        self.stopping = False
        self._workers: list[threading.Thread] = []
        self._workers_lock = threading.Lock()

    # --- stopping (see NodeThreads.stop for the order) ------------------------------------------

    def stop_accepting(self) -> None:
        """Take no new work from now on (the node is being stopped); nodes with runs refuse them."""
        self.stopping = True

    def busy(self) -> bool:
        """Whether work accepted before :meth:`stop_accepting` is still in progress."""
        return False

    def start_worker(self, target: Callable[[], Any], name: str) -> Optional[threading.Thread]:
        """Run ``target`` on a thread this node owns: joined before the node is destroyed.

        Not a daemon: a daemon thread still inside compiled code when the interpreter finalises is
        ended by ``pthread_exit``, whose unwinding through C++ frames aborts the process
        ("terminate called without an active exception"). None (nothing started) once stopping.
        """
        with self._workers_lock:
            if self.stopping:
                self.get_logger().info(f"stopping: {name} not started")
                return None
            self._workers = [thread for thread in self._workers if thread.is_alive()]
            thread = threading.Thread(target=target, name=name, daemon=False)
            self._workers.append(thread)
        thread.start()
        return thread

    def join_workers(self, timeout_s: float) -> list[str]:
        """Join the threads of :meth:`start_worker`; return the names of those still running.

        ``timeout_s`` is for all of them together; each thread still running is logged.
        """
        deadline = time.monotonic() + timeout_s
        with self._workers_lock:
            workers = list(self._workers)
        left = []
        for thread in workers:
            thread.join(timeout=max(deadline - time.monotonic(), 0.0))
            if thread.is_alive():
                self.get_logger().error(f"thread {thread.name} still running {timeout_s:g} s after the stop")
                left.append(thread.name)
        return left

    def declare(self, name: str, default: Any, description: str, *,
                minimum: float | None = None, maximum: float | None = None,
                dynamic: bool = False) -> Any:
        """Declare a parameter with a descriptor (and range) and return its value.

        A parameter is read-only after start unless ``dynamic``: then the node must apply its changes
        through :meth:`apply_parameter_changes` (a change nobody applied would be accepted and ignored).
        """
        descriptor = ParameterDescriptor(description=description, read_only=not dynamic)
        if minimum is not None or maximum is not None:
            if isinstance(default, bool):
                raise TypeError(f"parameter {name}: a range makes no sense for a bool")
            if isinstance(default, int):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(minimum if minimum is not None else INTEGER_LIMITS[0]),
                    to_value=int(maximum if maximum is not None else INTEGER_LIMITS[1]), step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(minimum if minimum is not None else FLOAT_LIMITS[0]),
                    to_value=float(maximum if maximum is not None else FLOAT_LIMITS[1]), step=0.0)]
        return self.declare_parameter(name, default, descriptor).value

    def apply_parameter_changes(self, names: Sequence[str],
                                apply: Callable[[dict[str, Any]], Optional[str]]) -> None:
        """Apply run-time changes of the dynamic parameters ``names`` with ``apply(values)``.

        ``values`` holds every one of ``names`` with the requested changes in; ``apply`` returns None
        once it has applied them, or the reason to refuse them (the parameters then keep their values).
        """
        watched = list(names)
        self.dynamic_parameters.update(watched)

        def on_set(parameters) -> SetParametersResult:
            changed = {parameter.name: parameter.value for parameter in parameters if parameter.name in watched}
            if not changed:
                return SetParametersResult(successful=True)
            values = {name: self.get_parameter(name).value for name in watched} | changed
            reason = apply(values)
            return SetParametersResult(successful=reason is None, reason=reason or "")
        self.add_on_set_parameters_callback(on_set)

    def declare_numbers(self, name: str, default: list, description: str, *, positive: bool = True,
                        allow_empty: bool = False, length: int | None = None) -> list[float]:
        """Declare a list-of-numbers parameter and check it at start.

        ROS ranges do not apply to lists, so the values are checked here: finite, positive (or not
        negative), not empty unless allowed, of ``length`` when given. ValueError naming the
        parameter otherwise, so a bad value stops the node at start with the reason.
        """
        values = self.declare(name, default, description)
        if values is None and allow_empty:
            values = []    # rcl reads "[]" (file or -p) as no value: an empty list has no element type
        numbers = [float(value) for value in values] if isinstance(values, (list, tuple)) else None
        bound_ok = numbers is not None and all(
            math.isfinite(value) and (value > 0.0 if positive else value >= 0.0) for value in numbers)
        if not bound_ok or (not numbers and not allow_empty) or (length is not None and len(numbers) != length):
            size = f"{length} " if length is not None else ("" if allow_empty else "one or more ")
            raise ValueError(f"parameter {name}: {size}finite {'positive' if positive else 'non-negative'} "
                             f"numbers are needed, got {values!r}")
        return numbers

    def declare_specs(self, specs: Sequence[ParameterSpec]) -> dict[str, Any]:
        """Declare the parameters ``specs`` describe (see ``parameter_specs``) and return their values."""
        values = {}
        for spec in specs:
            if spec.kind == "numbers":
                values[spec.name] = self.declare_numbers(spec.name, list(spec.default), spec.description,
                                                         positive=spec.positive, allow_empty=spec.allow_empty)
            else:
                values[spec.name] = self.declare(spec.name, spec.default, spec.description, minimum=spec.minimum,
                                                 maximum=spec.maximum)
        return values

    def client(self, srv_type: type, name: str):
        """Create a client in the reentrant group with a deep answer queue (``CLIENT_QOS``).

        The group lets coroutine callbacks await it.
        """
        return self.create_client(srv_type, name, qos_profile=CLIENT_QOS, callback_group=self.reentrant_group)

    async def call(self, client, request: Any, timeout_s: float, *, server_wait_s: float = SERVER_WAIT_S,
                   resend_after_s: float | None = None) -> Any:
        """Await ``client``'s answer to ``request``; ServiceCallError after ``timeout_s`` (never blocks).

        The server is watched while the call runs: when it leaves the node graph (a crashed or
        stopped node), the call fails within about ``SERVER_GONE_CONFIRM_S`` of the graph noticing,
        naming the service and its node, instead of waiting for the deadline.
        ``resend_after_s`` (only for requests a server may receive twice: idempotent ones, or ones
        carrying a request id, see ``request_ids``): when no answer came within that time, send the
        request again, then after twice that time, and so on; the first answer to any copy counts.
        A server that has just started may not yet know this client's reader and then drops its
        answer (DDS discovery is not symmetric); a later copy gets through.
        """
        if not math.isfinite(timeout_s) or timeout_s <= 0.0:
            raise ServiceCallError(f"invalid time limit {timeout_s!r} s for {client.srv_name}")
        if not client.service_is_ready():
            await self.wait_for(client.service_is_ready, min(timeout_s, server_wait_s),
                                f"service {client.srv_name} is not available (no server within "
                                f"{min(timeout_s, server_wait_s):g} s)")
        deadline = time.monotonic() + timeout_s
        sent: list[Future] = []
        wait_s = resend_after_s
        try:
            while True:
                sent.append(client.call_async(request))
                remaining = deadline - time.monotonic()
                attempt_s = remaining if wait_s is None else min(remaining, wait_s)
                try:
                    return await self._await(_first_answer(sent), max(attempt_s, 1e-3),
                                             f"service {client.srv_name} did not answer within {timeout_s:g} s",
                                             watch=[client])
                except DeadlineExpired:
                    if attempt_s >= remaining:
                        raise
                self.get_logger().warning(f"no answer from {client.srv_name} after {attempt_s:g} s: request sent again")
                wait_s *= 2.0
        finally:
            for future in sent:
                if not future.done():
                    client.remove_pending_request(future)

    async def wait_for_peers(self, endpoints: Sequence, matched: Callable[[Any], int], timeout_s: float,
                             nobody: str, anyway: str) -> None:
        """Await a matched peer for every one of ``endpoints``, at most ``timeout_s``.

        Await every one of ``endpoints`` (publishers or subscriptions) having a matched peer
        (``matched(endpoint) > 0``), at most ``timeout_s``; then warn "``nobody`` <topics> after ..:
        ``anyway``" for those without one and return: the caller goes on regardless.

        After a restart DDS discovery may take seconds one way while the other already works, and a
        volatile topic loses what is sent before both ends have matched.
        """
        try:
            await self.wait_for(lambda: all(matched(endpoint) > 0 for endpoint in endpoints), timeout_s, "no peer")
        except ServiceCallError:
            silent = [endpoint.topic_name for endpoint in endpoints if matched(endpoint) == 0]
            self.get_logger().warning(f"{nobody} {', '.join(silent)} after {timeout_s:g} s: {anyway}")

    async def yield_to_executor(self) -> None:
        """Let the executor serve what is waiting (other requests) before this coroutine goes on."""
        resumed = Future()
        timer = self.create_timer(0.0, lambda: resumed.done() or resumed.set_result(None),
                                  callback_group=self.reentrant_group)
        try:
            await resumed
        finally:
            self.destroy_timer(timer)

    def server_names(self, client) -> str:
        """Return the nodes that serve ``client``'s service, from the node graph (for messages)."""
        names = []
        for name, namespace in self.get_node_names_and_namespaces():
            try:
                services = self.get_service_names_and_types_by_node(name, namespace)
            except Exception:  # the node left the graph between the two queries
                continue
            if any(service == self.resolve_service_name(client.srv_name) for service, _ in services):
                names.append(f"{namespace.rstrip('/')}/{name}")
        return ", ".join(names) or "unknown node"

    async def wait_for(self, condition: Callable[[], bool], timeout_s: float, message: str | Callable[[], str],
                       *, watch: Sequence = (), wake: Optional[Future] = None,
                       period_s: Optional[float] = None) -> None:
        """Await ``condition()`` becoming true, polled by a timer; ServiceCallError(message) on timeout.

        ``message`` may be a callable, so that it can tell the state at the time of the timeout.
        ``watch``: clients whose servers must stay in the node graph meanwhile (see ``call``).
        ``wake``: a future the node's callbacks complete when they make the condition true, which ends
        the wait at once; the timer then only has to catch what no callback signals (time passing),
        so ``period_s`` (default ``POLL_PERIOD_S``) may be longer: each poll wakes the executor.
        """
        if condition():
            return
        await self._await(Future() if wake is None else wake, timeout_s, message, watch=watch, condition=condition,
                          period_s=period_s)

    async def _await(self, future: Future, timeout_s: float, message: str | Callable[[], str], *,
                     watch: Sequence = (), condition: Callable[[], bool] | None = None,
                     period_s: Optional[float] = None) -> Any:
        """Await ``future`` (or ``condition()``) with a deadline, failing early when a watched server leaves.

        One polling timer does all the checks, so any finite ``timeout_s`` is safe (a timer of 1e308 s
        is not): every ``period_s``, by default ``POLL_PERIOD_S`` with a ``condition``, else
        ``WATCH_PERIOD_S`` (the deadline is then met within that).
        """
        if not math.isfinite(timeout_s) or timeout_s <= 0.0:
            raise ServiceCallError(f"invalid time limit {timeout_s!r} s")
        servers = {client: self.server_names(client) for client in watch}
        waiter = Future()
        future.add_done_callback(lambda _: waiter.done() or waiter.set_result(None))
        began = time.monotonic()
        gone_since: dict = {}

        def poll() -> None:
            if waiter.done():
                return
            try:
                met = condition is not None and condition()
            except Exception as error:  # a failing check fails this wait, never the executor
                waiter.done() or waiter.set_result(ServiceCallError(f"the wait's check failed: {error!r}"))
                return
            if met:
                waiter.done() or waiter.set_result(None)
                return
            now = time.monotonic()
            if now - began >= timeout_s:
                waiter.set_result(DeadlineExpired(message() if callable(message) else message))
                return
            for client in watch:
                if client.service_is_ready():
                    gone_since.pop(client, None)
                elif now - gone_since.setdefault(client, now) >= SERVER_GONE_CONFIRM_S:
                    waiter.set_result(ServiceCallError(
                        f"the server of {client.srv_name} ({servers[client]}) disappeared after "
                        f"{now - began:.1f} s; step abandoned"))
                    return
        if period_s is None:
            period_s = POLL_PERIOD_S if condition is not None else WATCH_PERIOD_S
        timer = self.create_timer(min(period_s, timeout_s), poll, callback_group=self.reentrant_group)
        try:
            failure = await waiter
        finally:
            self.destroy_timer(timer)
        if failure is not None:
            future.cancel()
            raise failure
        return future.result() if condition is None else None


def take_waiting(subscription, limit: int) -> Iterator[Any]:
    """Yield the messages waiting in ``subscription``'s queue, at most ``limit``, without the executor.

    Called from the subscription's callback, it hands over the messages that queued meanwhile in
    arrival order, as the executor would, but without a wake-up each: rclpy's executor rebuilds its
    wait set and runs a task for every message (~150 us of CPU a message). ``limit`` bounds how long
    other callbacks of the node wait. Raw subscriptions yield the serialised bytes.

    Hazard: it calls the subscription handle's ``take_message``, the internal call rclpy's executor
    makes (rclpy 7, Jazzy); it is not public API. Where it is missing or takes other arguments the
    generator yields nothing and the executor delivers every message itself, as before (slower, the
    same messages in the same order).

    Parameters
    ----------
    subscription : rclpy.subscription.Subscription
        The subscription whose callback is running.
    limit : int
        The most messages taken.

    Yields
    ------
    object
        Each message (bytes for a ``raw=True`` subscription).
    """
    for _ in range(limit):
        try:
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
        except InvalidHandle:      # destroyed meanwhile (the node stops)
            return
        except (AttributeError, TypeError):     # another rclpy: leave the queue to the executor
            return
        if taken is None:
            return
        yield taken[0]


def _first_answer(futures: Sequence[Future]) -> Future:
    """Return a future done with the result of the first of ``futures`` to be done."""
    first = Future()

    def take(future: Future) -> None:
        if not first.done() and not future.cancelled():
            first.set_result(future.result())
    for future in futures:
        future.add_done_callback(take)
    return first
