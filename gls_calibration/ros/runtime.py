"""A node's process: executor threads per node, ordered stop, signals, ``main()`` of every executable."""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from typing import Callable, Optional, Sequence

import rclpy
from rclpy.context import Context
from rclpy.exceptions import ParameterException
from rclpy.signals import SignalHandlerOptions
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from gls_calibration.ros.base import GlsNode, POLL_PERIOD_S
from gls_calibration.ros.dds import use_fast_liveliness
from gls_calibration.ros.parameter_rules import unapplied_rule_problem


# Stopping: a run in progress gets this long to end at its next step, each owned thread and each
# executor thread this long to end; what is still alive after that is logged (see NodeThreads.stop).
RUN_STOP_TIMEOUT_S = 10.0
THREAD_JOIN_TIMEOUT_S = 10.0


def with_companions(node: Node) -> tuple[Node, ...]:
    """Return ``node`` and its companions, to be spun and destroyed with it.

    ``node`` and its companions (``node.companions``: nodes of the same process that need an
    executor thread of their own, e.g. the correction's batch service), to be spun and destroyed
    with it.
    """
    return (node, *getattr(node, "companions", ()))


class NodeThreads:
    """Spins each node on its own single-threaded executor in its own thread.

    One executor for many nodes rebuilds the wait set of every entity of every node for each
    callback; a full sweep (2001 profile messages) then took 15 s instead of 1.5 s. Coroutine
    callbacks (services that await other services) interleave on a single thread, so no node
    needs more than one. rclpy's ``experimental.EventsExecutor`` (whose C++ loop would cut the
    executors' share of the nodes' CPU) was tried in its place on 2026-11-28: the main job hung,
    one thread at 100 % CPU, in its reference check; not used.
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
        """Return the CPU time (s) each node's executor thread has used so far, by node name.

        CPU time (s) each node's executor thread has used so far, by node name (``time_budget``);
        read it while the threads spin (an ended thread gives NaN).
        """
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
    """SIGINT and SIGTERM, handled once per process.

    The first one asks the process to stop, later ones are noted and ignored (a second Ctrl-C must
    not break the ordered stop half-way).

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
        """Note that the stop has begun: a signal from now on must not raise into it."""
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
    """Run one node as a console script, from rclpy's init to its ordered stop.

    Console-script entry: init rclpy (ROS arguments such as remaps apply), spin one node until
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
    """Return the name of the running console script."""
    return os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "gls node"
