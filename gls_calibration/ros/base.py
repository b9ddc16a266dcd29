"""What every node of the package shares: parameter declaration, async service calls, main()."""
from __future__ import annotations

import functools
import inspect
import math
import os
import signal
import sys
import threading
import time
import traceback
from typing import Any, Callable, Optional, Sequence

import rclpy
from rclpy.context import Context
from rclpy.exceptions import ParameterException
from rclpy.signals import SignalHandlerOptions
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult

from gls_calibration.common.parameter_specs import FLOAT_LIMITS, INTEGER_LIMITS, ParameterSpec
from gls_calibration.ros.parameter_rules import unapplied_rule_problem

DEFAULT_NAMESPACE = "gls"
POLL_PERIOD_S = 0.05          # how often a pending call checks its deadline and its server
SERVER_GONE_CONFIRM_S = 0.3   # a server absent from the graph this long is gone (not a discovery blip)
SERVER_WAIT_S = 2.0           # how long a call waits for its server to appear before failing
# Stopping: a run in progress gets this long to end at its next step, each owned thread and each
# executor thread this long to end; what is still alive after that is logged (see NodeThreads.stop).
RUN_STOP_TIMEOUT_S = 10.0
THREAD_JOIN_TIMEOUT_S = 10.0


# Fast DDS hands every answer of a service to the reader of each of its clients, which drops those not
# its own when it takes them. With the default queue of 10, a client among others that are busy can
# find its own answer pushed out before it took it: 1 single-target answer in ~4000-8000 was lost
# with 4 clients (bench_concurrency.py), none in 32 000 with a queue of 1000.
CLIENT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)

FAST_DDS_PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def use_fast_liveliness() -> None:
    """Make a crashed node leave the DDS graph within 1.5 s (Fast DDS's default lease is 20 s).

    Call before ``rclpy.init``: the lease is read when the process creates its DDS participant, and
    it is each node's own announced lease that the others wait out. A profile file already named
    in the environment wins; child processes inherit the choice.
    """
    if any(os.environ.get(name) for name in FAST_DDS_PROFILE_VARIABLES):
        return
    from gls_calibration.common.config_files import config_path
    try:
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(config_path("fastdds_liveliness.xml"))
    except FileNotFoundError:  # an install without the profile: Fast DDS's defaults apply
        pass


class ServiceCallError(RuntimeError):
    """A service another node serves did not answer in time, or answered with a failure."""


class DeadlineExpired(ServiceCallError):
    """No answer (or condition) within the time limit, the server still being there."""


def answers_errors(*errors: type[BaseException]) -> Callable:
    """Decorate a service handler ``(self, request, response)``: when it raises one of ``errors``
    (default ValueError), answer ``success=false`` with the error's text instead of failing the call.

    Works on plain and coroutine handlers. Only expected, explained errors belong in ``errors``. Any
    other exception is a bug: it is logged with its traceback and answered ``success=false``
    ("internal error ..."), so that the caller learns at once and the node goes on serving (raised
    into the executor, it ended the node's spinning thread: every later call went unanswered).
    """
    caught = errors or (ValueError,)

    def refuse(response: Any, error: BaseException) -> Any:
        response.success, response.message = False, str(error)
        return response

    def internal(node: Node, handler: Callable, response: Any, error: Exception) -> Any:
        node.get_logger().error(f"{handler.__name__} failed (a bug):\n{traceback.format_exc()}")
        response.success = False
        response.message = f"internal error: {type(error).__name__}: {error} (see the node's log)"
        return response

    def decorate(handler: Callable) -> Callable:
        if inspect.iscoroutinefunction(handler):
            @functools.wraps(handler)
            async def answer_async(self, request, response):
                try:
                    return await handler(self, request, response)
                except caught as error:
                    return refuse(response, error)
                except Exception as error:
                    return internal(self, handler, response, error)
            return answer_async

        @functools.wraps(handler)
        def answer(self, request, response):
            try:
                return handler(self, request, response)
            except caught as error:
                return refuse(response, error)
            except Exception as error:
                return internal(self, handler, response, error)
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
        """Join the threads of :meth:`start_worker` (``timeout_s`` for all); the names of those still
        running, each logged."""
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
        """Declare a list-of-numbers parameter and check it at start (ROS ranges do not apply to lists):
        finite, positive (or not negative), not empty unless allowed, of ``length`` when given.
        ValueError naming the parameter otherwise, so a bad value stops the node at start with the reason."""
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
        """A client in the reentrant group, so that coroutine callbacks can await it, with a deep
        answer queue (``CLIENT_QOS``)."""
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
        """Await every one of ``endpoints`` (publishers or subscriptions) having a matched peer
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
        """The nodes that serve ``client``'s service, from the node graph (for messages)."""
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
                       *, watch: Sequence = ()) -> None:
        """Await ``condition()`` becoming true, polled by a timer; ServiceCallError(message) on timeout.

        ``message`` may be a callable, so that it can tell the state at the time of the timeout.
        ``watch``: clients whose servers must stay in the node graph meanwhile (see ``call``).
        """
        if condition():
            return
        await self._await(Future(), timeout_s, message, watch=watch, condition=condition)

    async def _await(self, future: Future, timeout_s: float, message: str | Callable[[], str], *,
                     watch: Sequence = (), condition: Callable[[], bool] | None = None) -> Any:
        """Await ``future`` (or ``condition()``) with a deadline, failing early when a watched server leaves.

        One polling timer does all the checks, so any finite ``timeout_s`` is safe (a timer of 1e308 s
        is not).
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
            if condition is not None and condition():
                waiter.set_result(None)
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
        timer = self.create_timer(min(POLL_PERIOD_S, timeout_s), poll, callback_group=self.reentrant_group)
        try:
            failure = await waiter
        finally:
            self.destroy_timer(timer)
        if failure is not None:
            future.cancel()
            raise failure
        return future.result() if condition is None else None


def _first_answer(futures: Sequence[Future]) -> Future:
    """A future done with the result of the first of ``futures`` to be done."""
    first = Future()

    def take(future: Future) -> None:
        if not first.done() and not future.cancelled():
            first.set_result(future.result())
    for future in futures:
        future.add_done_callback(take)
    return first


def with_companions(node: Node) -> tuple[Node, ...]:
    """``node`` and its companions (``node.companions``: nodes of the same process that need an
    executor thread of their own, e.g. the correction's batch service), to be spun and destroyed
    with it."""
    return (node, *getattr(node, "companions", ()))


class NodeThreads:
    """Spins each node on its own single-threaded executor in its own thread.

    One executor for many nodes rebuilds the wait set of every entity of every node for each
    callback; a full sweep (2001 profile messages) then took 15 s instead of 1.5 s. Coroutine
    callbacks (services that await other services) interleave on a single thread, so no node
    needs more than one.
    """

    def __init__(self, nodes: list[Node]) -> None:
        self.nodes = [member for node in nodes for member in with_companions(node)]
        self.executors = [SingleThreadedExecutor(context=node.context) for node in self.nodes]
        self.threads = []
        self._stop_lock = threading.Lock()
        self._left: Optional[list[str]] = None
        for node, executor in zip(self.nodes, self.executors):
            executor.add_node(node)
            thread = threading.Thread(target=self._spin, args=(executor, node), name=node.get_name(), daemon=True)
            self.threads.append(thread)
            thread.start()

    @staticmethod
    def _spin(executor: SingleThreadedExecutor, node: Node) -> None:
        # A callback's exception ends executor.spin(): logged, and spinning goes on, or the node
        # would stay in the graph and never answer again.
        while True:
            try:
                executor.spin()
                return
            except ExternalShutdownException:
                return
            except Exception:
                if not executor.context.ok() or executor._is_shutdown:
                    return
                node.get_logger().error(f"a callback failed (a bug); still serving:\n{traceback.format_exc()}")

    def cpu_s(self) -> dict[str, float]:
        """CPU time (s) each node's executor thread has used so far, by node name (``time_budget``);
        read it while the threads spin (an ended thread gives NaN)."""
        from gls_calibration.common.time_budget import thread_cpu_s

        return {node.get_name(): thread_cpu_s(thread) for node, thread in zip(self.nodes, self.threads)}

    def join(self) -> None:
        """Block until the executors stop (shutdown of the context)."""
        for thread in self.threads:
            thread.join()

    def stop(self, run_timeout_s: float = RUN_STOP_TIMEOUT_S, join_timeout_s: float = THREAD_JOIN_TIMEOUT_S
             ) -> list[str]:
        """Stop everything in an order that cannot abort; the names of threads still running (logged).

        1. the nodes take no new work; 2. a run in progress is canceled and gets ``run_timeout_s`` to
        end at its next step (the executors still spin: it awaits other nodes); 3. the threads the
        nodes own are joined; 4. the executors shut down and their threads are joined; 5. the nodes
        are destroyed (one whose executor thread is still running is left alone: destroying it under
        a running wait crashes). The context is the caller's to shut down, after this. Idempotent:
        a second call returns the first one's answer.
        """
        with self._stop_lock:
            if self._left is not None:
                return self._left
            left: list[str] = []
            gls_nodes = [node for node in self.nodes if isinstance(node, GlsNode)]
            for node in gls_nodes:
                node.stop_accepting()
            spinning = any(thread.is_alive() for thread in self.threads)
            deadline = time.monotonic() + run_timeout_s
            while spinning and any(node.busy() for node in gls_nodes) and time.monotonic() < deadline:
                time.sleep(POLL_PERIOD_S)
            for node in gls_nodes:
                if node.busy():
                    node.get_logger().error(f"a run still in progress {run_timeout_s:g} s after the stop; abandoned")
            deadline = time.monotonic() + join_timeout_s
            for node in gls_nodes:
                left += node.join_workers(max(deadline - time.monotonic(), 0.0))
            for executor in self.executors:
                executor.shutdown(timeout_sec=max(deadline - time.monotonic(), 0.1))
            for node, thread in zip(self.nodes, self.threads):
                thread.join(timeout=max(deadline - time.monotonic(), 0.1))
                if thread.is_alive():
                    node.get_logger().error(f"executor thread {thread.name} still running "
                                            f"{join_timeout_s:g} s after the stop; node not destroyed")
                    left.append(thread.name)
                else:
                    node.destroy_node()
            self._left = left
            return left


class StopSignals:
    """SIGINT and SIGTERM, handled once per process: the first one asks the process to stop, later
    ones are noted and ignored (a second Ctrl-C must not break the ordered stop half-way).

    While ``interrupting`` (a tool blocked in a call), the first signal raises KeyboardInterrupt in
    the main thread; otherwise it only sets :attr:`requested`, which the main loop waits on. Install
    it from the main thread (Python runs signal handlers there).
    """

    def __init__(self, *, interrupting: bool = False) -> None:
        self.requested = threading.Event()
        self.signal_number: Optional[int] = None
        self.interrupting = interrupting
        self._previous = {number: signal.signal(number, self._handle) for number in (signal.SIGINT, signal.SIGTERM)}

    def restore(self) -> None:
        """Put back the handlers found at construction (the process goes on, e.g. a test calling main)."""
        for number, handler in self._previous.items():
            signal.signal(number, handler)

    def _handle(self, number: int, frame) -> None:
        if self.requested.is_set():
            os.write(2, f"{signal.Signals(number).name} again: already stopping\n".encode())
            return
        self.signal_number = number
        self.requested.set()
        if self.interrupting:
            self.interrupting = False
            raise KeyboardInterrupt

    def stopping(self) -> None:
        """The stop has begun: a signal from now on must not raise into it."""
        self.interrupting = False

    @property
    def exit_status(self) -> int:
        """128 + the signal's number (130 for SIGINT, 143 for SIGTERM), as a shell reports it."""
        return 128 + (self.signal_number or signal.SIGINT)


def exit_now_if_stuck(left: Sequence[str], status: int) -> None:
    """With threads still running after the stop (``left``), end the process with ``status`` at once.

    The interpreter's finalisation would end those (daemon) threads with ``pthread_exit`` inside
    compiled code, which aborts the process (exit 134); the stop has already logged them.
    """
    if left:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)


def run_node(factory: Callable[..., Node], args: list[str] | None = None) -> int:
    """Console-script entry: init rclpy (ROS arguments such as remaps apply), spin one node until
    SIGINT or SIGTERM, then stop it (``NodeThreads.stop``) before the context shuts down.

    Exit status: 0 once stopped by a signal (a node's normal end, as launch expects it); 2 when the
    node refuses its parameters at start (the reason printed, nothing spun).
    """
    use_fast_liveliness()
    stop = StopSignals()        # a signal while the node is built is acted upon once it is built
    context = Context()
    rclpy.init(args=args, context=context, signal_handler_options=SignalHandlerOptions.NO)
    threads = None
    left: list[str] = []
    try:
        try:
            node = factory(context=context)
        except (ValueError, TypeError, ParameterException) as error:
            print(f"{_program()}: {error}", file=sys.stderr)
            return 2
        # rcl drops a -p rule of another type than the parameter file's without a word: say so, spin nothing
        problem = unapplied_rule_problem(node, sys.argv if args is None else args)
        if problem:
            print(f"{_program()}: {problem}", file=sys.stderr)
            discard(node)
            return 2
        threads = NodeThreads([node])
        while context.ok() and not stop.requested.wait(0.2):
            pass
    finally:
        stop.stopping()
        if threads is not None:
            left = threads.stop()
        context.try_shutdown()
        stop.restore()
    exit_now_if_stuck(left, 0)
    return 0


def discard(node: Node) -> None:
    """Destroy a node that was built but never spun, with its companions, once its own threads end."""
    for member in with_companions(node):
        if isinstance(member, GlsNode):
            member.join_workers(THREAD_JOIN_TIMEOUT_S)
        member.destroy_node()


def _program() -> str:
    """The name of the running console script."""
    return os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "gls node"


