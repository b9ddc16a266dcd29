"""A bug in a service handler must not silence the node: the caller gets an answer, later calls too."""
from __future__ import annotations

import pytest
from rclpy.node import Node
from std_srvs.srv import Trigger

from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.runtime import NodeThreads
from gls_calibration.ros.service_errors import answers_errors
from ros_helpers import call_service

TIMEOUT_S = 10.0


class FlakyNode(GlsNode):
    """``decorated`` and ``bare`` raise ZeroDivisionError on their first call and succeed afterwards."""

    def __init__(self, **kwargs) -> None:
        super().__init__("flaky_server", **kwargs)
        self.calls = {"decorated": 0, "bare": 0}
        self.create_service(Trigger, "decorated", self.on_decorated)
        self.create_service(Trigger, "bare", self.on_bare)

    def _answer(self, name: str, response):
        self.calls[name] += 1
        if self.calls[name] == 1:
            return 1 / 0
        response.success, response.message = True, "fine"
        return response

    @answers_errors(ValueError)
    def on_decorated(self, request, response):
        return self._answer("decorated", response)

    def on_bare(self, request, response):
        return self._answer("bare", response)


@pytest.fixture
def served(ros_context, add_node):
    """The server spun by ``NodeThreads`` as in a node process; the caller in the test's executor."""
    threads = NodeThreads([FlakyNode(context=ros_context)])
    try:
        yield threads.nodes[0], add_node(Node("flaky_caller", namespace="gls", context=ros_context))
    finally:
        threads.stop()


def test_a_handler_bug_is_answered_as_an_internal_error_and_the_node_goes_on(served):
    _, caller = served
    client = caller.create_client(Trigger, "decorated")
    first = call_service(caller, client, Trigger.Request(), TIMEOUT_S)
    assert not first.success and first.message.startswith("internal error: ZeroDivisionError")
    assert call_service(caller, client, Trigger.Request(), TIMEOUT_S).success


def test_an_unguarded_callback_bug_does_not_stop_the_node_spinning(served):
    server, caller = served
    client = caller.create_client(Trigger, "bare")
    with pytest.raises(TimeoutError):            # the failed call itself is not answered
        call_service(caller, client, Trigger.Request(), 2.0)
    assert server.calls["bare"] == 1
    assert call_service(caller, client, Trigger.Request(), TIMEOUT_S).success
