"""Transport of point clouds and CorrectSetpoints calls between nodes, in one process and across two.

The CorrectSetpoints server here is the test-only nominal one from _transport_server.py; the real
correction node replaces it later.
"""
from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from gls_calibration import kinematics
from gls_calibration.conversions import pointcloud2_to_array
from gls_calibration_msgs.srv import CorrectSetpoints

from _transport_server import (CLOUD_QOS, CLOUD_SHAPE, CLOUD_TOPIC, NAMESPACE, SERVICE_NAME,
                               publish_cloud, serve_nominal_correction, transport_cloud)
from ros_helpers import call_service, stop_process, wait_for

PEER_SCRIPT = Path(__file__).with_name("_transport_server.py")
TIMEOUT_S = 10.0
PROCESS_START_TIMEOUT_S = 30.0      # interpreter start, rclpy import and discovery on a busy machine


class CloudInbox:
    """Subscription callback target that keeps every received cloud (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.messages: list[PointCloud2] = []

    def __call__(self, message: PointCloud2) -> None:
        with self._lock:
            self.messages.append(message)

    def count(self) -> int:
        with self._lock:
            return len(self.messages)


def subscribe_clouds(node: Node) -> CloudInbox:
    inbox = CloudInbox()
    node.create_subscription(PointCloud2, CLOUD_TOPIC, inbox, CLOUD_QOS)
    return inbox


def assert_received_cloud_equals(message: PointCloud2, seed: int) -> None:
    expected = transport_cloud(seed)
    received = pointcloud2_to_array(message)
    assert received.shape == CLOUD_SHAPE
    assert received.dtype == expected.dtype
    assert received.tobytes() == expected.tobytes()       # bit for bit, NaN points included
    assert message.header.frame_id == "scanner"
    assert not message.is_dense


def request_for(seed: int) -> tuple[CorrectSetpoints.Request, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-95.0, 95.0, size=25)
    y = rng.uniform(-95.0, 95.0, size=25)
    return CorrectSetpoints.Request(x=x.tolist(), y=y.tolist()), x, y


def assert_nominal_answer(response: CorrectSetpoints.Response, x: np.ndarray, y: np.ndarray) -> None:
    expected = kinematics.inverse(kinematics.HeadGeometry(), x, y)
    assert response.success, response.message
    np.testing.assert_array_equal(np.asarray(response.x), x)
    np.testing.assert_array_equal(np.asarray(response.y), y)
    np.testing.assert_array_equal(np.asarray(response.alpha_x), expected.alpha_x)
    np.testing.assert_array_equal(np.asarray(response.alpha_y), expected.alpha_y)
    np.testing.assert_array_equal(np.asarray(response.focus_shift), expected.focus_shift)
    assert list(response.inside_calibrated_field) == [False] * x.size


def test_cloud_and_service_between_nodes_in_one_process(ros_context, add_node):
    seed = 3
    publisher_node = add_node(Node("cloud_source", namespace=NAMESPACE, context=ros_context))
    receiver_node = add_node(Node("cloud_sink", namespace=NAMESPACE, context=ros_context))
    inbox = subscribe_clouds(receiver_node)
    serve_nominal_correction(receiver_node)
    publisher, _ = publish_cloud(publisher_node, seed)
    assert publisher.topic_name == "/gls/scan/points"

    wait_for(lambda: inbox.count() > 0, TIMEOUT_S, what="a PointCloud2 on /gls/scan/points")
    assert_received_cloud_equals(inbox.messages[0], seed)

    client = publisher_node.create_client(CorrectSetpoints, SERVICE_NAME)
    assert publisher_node.resolve_service_name(client.srv_name) == "/gls/correct_setpoints"
    request, x, y = request_for(seed)
    assert_nominal_answer(call_service(publisher_node, client, request, TIMEOUT_S), x, y)


def test_cloud_and_service_across_processes(ros_context, add_node, tmp_path):
    seed = 11
    log_path = tmp_path / "peer.log"
    with open(log_path, "w") as log:
        # The child inherits the session's ROS_DOMAIN_ID through the environment.
        peer = subprocess.Popen([sys.executable, str(PEER_SCRIPT), "--seed", str(seed), "--lifetime", "60"],
                                stdout=log, stderr=subprocess.STDOUT)
    try:
        node = add_node(Node("transport_test", namespace=NAMESPACE, context=ros_context))
        inbox = subscribe_clouds(node)
        client = node.create_client(CorrectSetpoints, SERVICE_NAME)
        if not client.wait_for_service(timeout_sec=PROCESS_START_TIMEOUT_S):
            service = node.resolve_service_name(client.srv_name)
            raise AssertionError(f"peer service {service} did not appear within {PROCESS_START_TIMEOUT_S} s; "
                                 f"peer exit code {peer.poll()}, log:\n{log_path.read_text()}")
        request, x, y = request_for(seed)
        assert_nominal_answer(call_service(node, client, request, TIMEOUT_S), x, y)

        wait_for(lambda: inbox.count() > 0, TIMEOUT_S, what="the peer's latched PointCloud2")
        assert_received_cloud_equals(inbox.messages[0], seed)
    finally:
        exit_code = stop_process(peer)
    assert exit_code == 0, f"peer exited with {exit_code}; log:\n{log_path.read_text()}"


def test_call_service_without_server_times_out(ros_context, add_node):
    node = add_node(Node("lonely_client", namespace=NAMESPACE, context=ros_context))
    client = node.create_client(CorrectSetpoints, SERVICE_NAME)
    request, _, _ = request_for(0)
    with pytest.raises(TimeoutError, match=r"^service /gls/correct_setpoints is not available after 0.5 s$"):
        call_service(node, client, request, timeout_s=0.5)


def test_call_service_spins_a_node_outside_any_executor(ros_context, add_node):
    server_node = add_node(Node("server", namespace=NAMESPACE, context=ros_context))
    serve_nominal_correction(server_node)
    client_node = Node("unspun_client", namespace=NAMESPACE, context=ros_context)
    try:
        client = client_node.create_client(CorrectSetpoints, SERVICE_NAME)
        request, x, y = request_for(1)
        assert_nominal_answer(call_service(client_node, client, request, TIMEOUT_S), x, y)
    finally:
        client_node.destroy_node()


def test_wait_for_reports_what_did_not_happen():
    with pytest.raises(TimeoutError, match=r"^the impossible did not hold within 0.05 s$"):
        wait_for(lambda: False, 0.05, what="the impossible")
