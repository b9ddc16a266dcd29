"""gls-calibrate's goal survives a lost answer: sent again under the same id (refused as a known id,
never run twice) and recognised from the action's status topic (``cli.client.send_goal``)."""
from __future__ import annotations

from contextlib import contextmanager

from rclpy.action import ActionClient, ActionServer, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from gls_calibration.cli.client import send_goal
from gls_calibration_msgs.action import Calibrate

NAMESPACE = "goal_resend_test"


class CountingServer(Node):
    """A ``calibrate`` action that accepts goals (or refuses them all) and counts the runs."""

    def __init__(self, accept: bool, **kwargs) -> None:
        super().__init__("counting_server", namespace=NAMESPACE, **kwargs)
        self.runs = 0
        self.accept = accept
        self.server = ActionServer(self, Calibrate, "calibrate", self.execute,
                                   goal_callback=lambda goal: GoalResponse.ACCEPT if accept else GoalResponse.REJECT,
                                   callback_group=ReentrantCallbackGroup())

    def execute(self, goal_handle):
        self.runs += 1
        goal_handle.succeed()
        return Calibrate.Result(success=True, message=f"run {self.runs}")


class LosesGoalAnswers(ActionClient):
    """An ActionClient whose first ``lose`` goal answers never arrive (as when DDS drops them)."""

    def __init__(self, node, lose: int) -> None:
        super().__init__(node, Calibrate, "calibrate")
        self.lose = lose

    async def execute(self, taken_data):
        if "goal" in taken_data and self.lose > 0:
            self.lose -= 1
            taken_data = {kind: data for kind, data in taken_data.items() if kind != "goal"}
        await super().execute(taken_data)


@contextmanager
def tool(context, lose: int):
    """A tool's node, its executor (spun only by the calls) and a client that loses ``lose`` answers."""
    node = Node("tool", namespace=NAMESPACE, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    client = LosesGoalAnswers(node, lose)
    try:
        assert client.wait_for_server(timeout_sec=10.0)
        yield executor, node, client
    finally:
        client.destroy()
        executor.shutdown()
        node.destroy_node()


def run_to_result(executor, handle):
    result = handle.get_result_async()
    executor.spin_until_future_complete(result, timeout_sec=10.0)
    assert result.done()
    return result.result().result


def test_a_goal_whose_answer_was_lost_runs_once_and_its_result_arrives(ros_context, add_node):
    server = add_node(CountingServer(accept=True, context=ros_context))
    with tool(ros_context, lose=1) as (executor, node, client):
        handle = send_goal(executor, node, client, Calibrate, "calibrate", Calibrate.Goal(), 20.0, resend_after_s=0.5)
        assert handle is not None and handle.accepted
        assert run_to_result(executor, handle).message == "run 1"
    assert server.runs == 1


def test_the_status_topic_alone_shows_an_accepted_goal_whose_answers_were_lost(ros_context, add_node):
    server = add_node(CountingServer(accept=True, context=ros_context))
    with tool(ros_context, lose=100) as (executor, node, client):
        handle = send_goal(executor, node, client, Calibrate, "calibrate", Calibrate.Goal(), 20.0, resend_after_s=0.5)
        assert handle is not None and run_to_result(executor, handle).message == "run 1"
    assert server.runs == 1


def test_a_refused_goal_gives_none(ros_context, add_node):
    server = add_node(CountingServer(accept=False, context=ros_context))
    with tool(ros_context, lose=0) as (executor, node, client):
        assert send_goal(executor, node, client, Calibrate, "calibrate", Calibrate.Goal(), 20.0) is None
    assert server.runs == 0
