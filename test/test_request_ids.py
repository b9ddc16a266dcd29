"""Requests sent again after a lost answer: the id makes a server answer a repeat without doing the
work twice, and ``GlsNode.call`` resends, backs off, and takes the first answer to any copy."""
from __future__ import annotations

import asyncio
from contextlib import contextmanager
import gc
import time

import pytest
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger

from gls_calibration.cli.client import call_and_wait
from gls_calibration.nodes.sim_galvo import SimGalvoNode
from gls_calibration.nodes.sim_scanner import SimScannerNode
from gls_calibration.ros.base import DEFAULT_NAMESPACE, GlsNode
from gls_calibration.ros.request_ids import AnsweredRequests, id_key, new_request_id
from gls_calibration.ros.service_errors import DeadlineExpired, ServiceCallError
from gls_calibration_msgs.msg import SweepDone
from gls_calibration_msgs.srv import MarkPolylines, StartSweep
from unique_identifier_msgs.msg import UUID

from ros_helpers import wait_for


class Counted:
    """A handler that counts its services and answers with a fresh object each time."""

    def __init__(self) -> None:
        self.served = 0

    def __call__(self) -> dict:
        self.served += 1
        return {"service": self.served}


def test_a_repeated_id_gets_the_first_answer_and_is_not_served_again():
    answered, serve = AnsweredRequests(), Counted()
    request_id = new_request_id()
    first = answered.answer(request_id, serve)
    repeat = answered.answer(UUID(uuid=list(request_id.uuid)), serve)   # the same id in another message
    assert repeat is first and serve.served == 1
    assert answered.answer(new_request_id(), serve) == {"service": 2}


def test_requests_without_an_id_are_served_each_time():
    answered, serve = AnsweredRequests(), Counted()
    assert [answered.answer(UUID(), serve) for _ in range(3)] == [{"service": 1}, {"service": 2}, {"service": 3}]
    assert not answered.answers


def test_a_request_whose_service_raised_is_served_again():
    answered, calls = AnsweredRequests(), []

    def fail_once():
        calls.append(1)
        if len(calls) == 1:
            raise ValueError("refused")
        return "ok"
    request_id = new_request_id()
    with pytest.raises(ValueError, match="refused"):
        answered.answer(request_id, fail_once)
    assert answered.answer(request_id, fail_once) == "ok" and len(calls) == 2


def test_only_the_last_answers_are_kept():
    answered, serve = AnsweredRequests(keep=2), Counted()
    ids = [new_request_id() for _ in range(3)]
    for request_id in ids:
        answered.answer(request_id, serve)
    assert list(answered.answers) == [id_key(ids[1]), id_key(ids[2])]
    assert answered.answer(ids[0], serve) == {"service": 4}    # forgotten: served again
    with pytest.raises(ValueError, match="keep must be at least 1, got 0"):
        AnsweredRequests(keep=0)


def test_a_repeat_arriving_while_the_first_is_served_awaits_its_answer():
    answered, release, served = AnsweredRequests(), Future(), []

    async def serve():
        served.append(1)
        await release
        return "swept"

    async def both():
        request_id = new_request_id()
        first = asyncio.ensure_future(answered.answer_async(request_id, serve))
        repeat = asyncio.ensure_future(answered.answer_async(request_id, serve))
        await asyncio.sleep(0.01)
        assert not first.done() and not repeat.done()
        release.set_result(None)
        return await first, await repeat
    assert asyncio.run(both()) == ("swept", "swept") and len(served) == 1


class DropsFirstAnswer(GlsNode):
    """Never answers its first request (as when DDS drops the answer); answers the others."""

    def __init__(self, **kwargs) -> None:
        super().__init__("drops_first_answer", **kwargs)
        self.requests = 0
        self.create_service(Trigger, "flaky", self.on_request, callback_group=ReentrantCallbackGroup())

    async def on_request(self, request, response):
        self.requests += 1
        if self.requests == 1:
            await Future()    # never done
        response.success, response.message = True, f"answer to request {self.requests}"
        return response


class Caller(GlsNode):
    def __init__(self, **kwargs) -> None:
        super().__init__("caller", **kwargs)
        self.flaky = self.client(Trigger, "flaky")


def _run(node: GlsNode, coroutine_function):
    """Run ``coroutine_function()`` as a task of ``node``'s executor; its result or exception."""
    done = Future()

    async def task():
        try:
            done.set_result(("ok", await coroutine_function()))
        except Exception as error:  # handed to the test thread
            done.set_result(("error", error))
    node.executor.create_task(task)
    wait_for(done.done, 30.0, what="the call")
    return done.result()


def test_call_sends_again_after_a_lost_answer_and_takes_the_later_answer(ros_context, add_node):
    server = add_node(DropsFirstAnswer(context=ros_context))
    caller = add_node(Caller(context=ros_context))
    began = time.monotonic()
    outcome, answer = _run(caller, lambda: caller.call(caller.flaky, Trigger.Request(), 20.0, resend_after_s=0.5))
    assert outcome == "ok" and answer.message == "answer to request 2", answer
    assert time.monotonic() - began < 10.0 and server.requests == 2


def test_call_without_resending_waits_for_its_deadline(ros_context, add_node):
    add_node(DropsFirstAnswer(context=ros_context))
    caller = add_node(Caller(context=ros_context))
    outcome, error = _run(caller, lambda: caller.call(caller.flaky, Trigger.Request(), 1.5))
    assert outcome == "error" and isinstance(error, DeadlineExpired)
    assert "did not answer within 1.5 s" in str(error)


def test_a_wait_whose_check_raises_fails_and_the_executor_serves_on(ros_context, add_node):
    server = add_node(DropsFirstAnswer(context=ros_context))
    caller = add_node(Caller(context=ros_context))
    checks = []

    def broken_check() -> bool:
        checks.append(1)
        if len(checks) > 1:      # the first call is made in the coroutine; the rest by the polling timer
            raise AttributeError("'NoneType' object has no attribute 'members'")
        return False
    outcome, error = _run(caller, lambda: caller.wait_for(broken_check, 5.0, "never"))
    assert outcome == "error" and isinstance(error, ServiceCallError), error
    assert str(error) == ("the wait's check failed: "
                          "AttributeError(\"'NoneType' object has no attribute 'members'\")")
    # The polling timer's thread survived: the executor still serves the caller's calls.
    outcome, answer = _run(caller, lambda: caller.call(caller.flaky, Trigger.Request(), 20.0, resend_after_s=0.5))
    assert outcome == "ok" and server.requests == 2, answer


@contextmanager
def tool_client(context):
    """A client of ``flaky`` on a node of its own, spun only by the call, as in an operator tool."""
    tool = Node("tool", namespace=DEFAULT_NAMESPACE, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(tool)
    try:
        yield executor, tool.create_client(Trigger, "flaky")
    finally:
        executor.shutdown()
        tool.destroy_node()


def test_a_tool_sends_again_after_a_lost_answer_and_takes_the_later_answer(ros_context, add_node):
    server = add_node(DropsFirstAnswer(context=ros_context))
    with tool_client(ros_context) as (executor, client):
        began = time.monotonic()
        answer = call_and_wait(executor, client, Trigger.Request(), 20.0, resend_after_s=0.5)
    assert answer is not None and answer.message == "answer to request 2", answer
    assert time.monotonic() - began < 10.0 and server.requests == 2


def test_a_tool_without_resending_gives_up_at_its_deadline(ros_context, add_node):
    server = add_node(DropsFirstAnswer(context=ros_context))
    with tool_client(ros_context) as (executor, client):
        began = time.monotonic()
        assert call_and_wait(executor, client, Trigger.Request(), 1.5) is None
    assert 1.4 <= time.monotonic() - began < 10.0 and server.requests == 1


def test_the_simulated_scanner_starts_one_sweep_for_a_repeated_request(start_cell):
    cell = start_cell(node_types=(SimGalvoNode, SimScannerNode))
    ends = []
    cell.client_node.create_subscription(SweepDone, "scan/sweep_done", ends.append, 10)
    request = StartSweep.Request(length_mm=2.0, step_mm=0.1, request_id=new_request_id())
    first = cell.call(StartSweep, "scanner/start_sweep", request, 10.0)
    repeat = cell.call(StartSweep, "scanner/start_sweep", request, 10.0)
    assert first.success and (repeat.success, repeat.sweep_id, repeat.message) == (True, first.sweep_id, first.message)
    wait_for(lambda: ends, 20.0, what="the end of the sweep")
    other = cell.call(StartSweep, "scanner/start_sweep", StartSweep.Request(length_mm=2.0, step_mm=0.1,
                                                                            request_id=new_request_id()), 10.0)
    assert other.success and other.sweep_id == first.sweep_id + 1
    wait_for(lambda: len(ends) == 2, 20.0, what="the second end of sweep")
    assert [end.sweep_id for end in ends] == [first.sweep_id, other.sweep_id]


def test_the_simulated_galvo_marks_a_repeated_job_once(start_cell):
    from gls_calibration_msgs.srv import GetMarkedPaths
    cell = start_cell(node_types=(SimGalvoNode,))
    request = MarkPolylines.Request(alpha_x=[0.0, 0.01], alpha_y=[0.0, 0.0], focus_shift=[0.0, 0.0],
                                    polyline_starts=[0], request_id=new_request_id())
    first = cell.call(MarkPolylines, "galvo/mark", request, 10.0)
    repeat = cell.call(MarkPolylines, "galvo/mark", request, 10.0)
    assert first.success and (repeat.duration_s, repeat.message) == (first.duration_s, first.message)
    marked = cell.call(GetMarkedPaths, "sim/marked_paths", GetMarkedPaths.Request(), 10.0).paths
    assert len(marked.polyline_starts) == 1
    request.request_id = new_request_id()
    assert cell.call(MarkPolylines, "galvo/mark", request, 10.0).success
    marked = cell.call(GetMarkedPaths, "sim/marked_paths", GetMarkedPaths.Request(), 10.0).paths
    assert len(marked.polyline_starts) == 2


def test_a_repeat_waiting_for_a_service_that_raised_gets_the_error():
    answered, release = AnsweredRequests(), Future()

    async def serve():
        await release
        raise ValueError("refused")

    async def both():
        request_id = new_request_id()
        first = asyncio.ensure_future(answered.answer_async(request_id, serve))
        repeat = asyncio.ensure_future(answered.answer_async(request_id, serve))
        await asyncio.sleep(0.01)
        release.set_result(None)
        return await asyncio.gather(first, repeat, return_exceptions=True)
    assert [str(outcome) for outcome in asyncio.run(both())] == ["refused", "refused"]
    assert not answered.answers


def test_an_error_raised_to_the_caller_is_not_reported_again_as_never_retrieved(capfd):
    answered = AnsweredRequests()

    async def serve():
        raise ValueError("refused")
    with pytest.raises(ValueError, match="refused"):
        asyncio.run(answered.answer_async(new_request_id(), serve))
    gc.collect()
    assert "never retrieved" not in capfd.readouterr().err
