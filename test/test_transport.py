"""Transport of point clouds and CorrectSetpoints calls between nodes, in one process and across processes.

The CorrectSetpoints server is the real correction node with an empty calibration store (so the
nominal model); the cloud comes from the test-only peer in _cloud_peer.py.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from rclpy.parameter import Parameter

from gls_calibration.cli.client import RESEND_AFTER_S
from gls_calibration.geometry import kinematics
from gls_calibration.nodes.correction import CorrectionNode
from gls_calibration.ros.conversions import pointcloud2_to_array
from gls_calibration_msgs.srv import CorrectSetpoints

from _cloud_peer import CLOUD_QOS, CLOUD_SHAPE, CLOUD_TOPIC, NAMESPACE, publish_cloud, transport_cloud
from ros_helpers import call_service, default_sigint, stop_process, wait_for, wait_for_peer_service

PEER_SCRIPT = Path(__file__).with_name("_cloud_peer.py")
SERVICE_NAME = "correct_setpoints"
# The correction node's console-script entry, run by the interpreter (the module has no __main__ guard).
CORRECTION_MAIN = "from gls_calibration.nodes.correction import main; main()"
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


def correction_node(context, calibration_dir: Path) -> CorrectionNode:
    """The real correction node on an empty store: it answers with the nominal model."""
    return CorrectionNode(context=context, parameter_overrides=[
        Parameter("calibration_dir", value=str(calibration_dir))])


def request_for(seed: int) -> tuple[CorrectSetpoints.Request, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-95.0, 95.0, size=25)
    y = rng.uniform(-95.0, 95.0, size=25)
    return CorrectSetpoints.Request(x=x.tolist(), y=y.tolist()), x, y


def assert_nominal_answer(response: CorrectSetpoints.Response, x: np.ndarray, y: np.ndarray) -> None:
    expected = kinematics.inverse(kinematics.HeadGeometry(), x, y)
    assert response.success, response.message
    assert response.message == "no calibration loaded: nominal model"
    np.testing.assert_array_equal(np.asarray(response.x), x)
    np.testing.assert_array_equal(np.asarray(response.y), y)
    np.testing.assert_array_equal(np.asarray(response.alpha_x), expected.alpha_x)
    np.testing.assert_array_equal(np.asarray(response.alpha_y), expected.alpha_y)
    np.testing.assert_array_equal(np.asarray(response.focus_shift), expected.focus_shift)
    assert list(response.inside_calibrated_field) == [False] * x.size
    assert list(response.within_limits) == [True] * x.size


def test_cloud_and_service_between_nodes_in_one_process(ros_context, add_node, tmp_path):
    seed = 3
    publisher_node = add_node(Node("cloud_source", namespace=NAMESPACE, context=ros_context))
    receiver_node = add_node(Node("cloud_sink", namespace=NAMESPACE, context=ros_context))
    inbox = subscribe_clouds(receiver_node)
    add_node(correction_node(ros_context, tmp_path / "empty_store"))
    publisher, _ = publish_cloud(publisher_node, seed)
    assert publisher.topic_name == "/gls/scan/points"

    wait_for(lambda: inbox.count() > 0, TIMEOUT_S, what="a PointCloud2 on /gls/scan/points")
    assert_received_cloud_equals(inbox.messages[0], seed)

    client = publisher_node.create_client(CorrectSetpoints, SERVICE_NAME)
    assert publisher_node.resolve_service_name(client.srv_name) == "/gls/correct_setpoints"
    request, x, y = request_for(seed)
    assert_nominal_answer(call_service(publisher_node, client, request, TIMEOUT_S, RESEND_AFTER_S), x, y)


def test_cloud_and_service_across_processes(ros_context, add_node, tmp_path):
    seed = 11
    correction_log, cloud_log = tmp_path / "correction.log", tmp_path / "cloud_peer.log"
    # The children inherit the session's ROS_DOMAIN_ID through the environment.
    with open(correction_log, "w") as log:
        correction = subprocess.Popen(
            [sys.executable, "-c", CORRECTION_MAIN, "--ros-args",
             "-p", f"calibration_dir:={tmp_path / 'empty_store'}"], stdout=log, stderr=subprocess.STDOUT,
            preexec_fn=default_sigint)
    with open(cloud_log, "w") as log:
        cloud_peer = subprocess.Popen([sys.executable, str(PEER_SCRIPT), "--seed", str(seed), "--lifetime", "60"],
                                      stdout=log, stderr=subprocess.STDOUT,
                                      preexec_fn=default_sigint)
    try:
        node = add_node(Node("transport_test", namespace=NAMESPACE, context=ros_context))
        inbox = subscribe_clouds(node)
        client = node.create_client(CorrectSetpoints, SERVICE_NAME)
        wait_for_peer_service(node, client, correction, correction_log, PROCESS_START_TIMEOUT_S)
        request, x, y = request_for(seed)
        assert_nominal_answer(call_service(node, client, request, TIMEOUT_S, RESEND_AFTER_S), x, y)

        wait_for(lambda: inbox.count() > 0 or cloud_peer.poll() is not None, PROCESS_START_TIMEOUT_S,
                 what="the peer's latched PointCloud2")
        assert inbox.count() > 0, f"cloud peer exited with {cloud_peer.poll()}; log:\n{cloud_log.read_text()}"
        assert_received_cloud_equals(inbox.messages[0], seed)
    finally:
        correction_code = stop_process(correction)
        cloud_code = stop_process(cloud_peer)
    # The correction node must stop on SIGINT (not need the SIGKILL fallback); that it exits with 0
    # is test_correction_process_exits_cleanly_on_sigint.
    assert correction_code != -signal.SIGKILL, f"correction node ignored SIGINT; log:\n{correction_log.read_text()}"
    assert cloud_code == 0, f"cloud peer exited with {cloud_code}; log:\n{cloud_log.read_text()}"


def test_correction_process_exits_cleanly_on_sigint(ros_context, add_node, tmp_path):
    log_path = tmp_path / "correction.log"
    with open(log_path, "w") as log:
        correction = subprocess.Popen(
            [sys.executable, "-c", CORRECTION_MAIN, "--ros-args",
             "-p", f"calibration_dir:={tmp_path / 'empty_store'}"], stdout=log, stderr=subprocess.STDOUT,
            preexec_fn=default_sigint)
    try:
        node = add_node(Node("sigint_test", namespace=NAMESPACE, context=ros_context))
        client = node.create_client(CorrectSetpoints, SERVICE_NAME)
        wait_for_peer_service(node, client, correction, log_path, PROCESS_START_TIMEOUT_S)
    finally:
        exit_code = stop_process(correction)
    assert exit_code == 0, f"correction node exited with {exit_code}; log:\n{log_path.read_text()}"


# A node that gets Ctrl-C while it is being built (after its first service is in the graph, as a
# test or an operator may send it), then says it was built.
SIGINT_WHILE_BUILT = """
import os, signal, sys
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.runtime import run_node
from std_srvs.srv import Trigger

class Interrupted(GlsNode):
    def __init__(self, **kwargs):
        super().__init__("interrupted", **kwargs)
        self.create_service(Trigger, "first", lambda request, response: response)
        os.kill(os.getpid(), signal.SIGINT)
        self.create_service(Trigger, "second", lambda request, response: response)
        print("built", flush=True)

run_node(Interrupted)
"""


def test_a_node_interrupted_while_it_is_built_exits_cleanly(tmp_path):
    """Ctrl-C during construction waits until the node spins, then stops it as usual (exit 0, not
    a KeyboardInterrupt out of a half-built node)."""
    result = subprocess.run([sys.executable, "-c", SIGINT_WHILE_BUILT], capture_output=True, text=True,
                            timeout=PROCESS_START_TIMEOUT_S, preexec_fn=default_sigint)
    assert result.returncode == 0 and result.stdout.strip() == "built", result.stdout + result.stderr


def test_call_service_without_server_times_out(ros_context, add_node):
    node = add_node(Node("lonely_client", namespace=NAMESPACE, context=ros_context))
    client = node.create_client(CorrectSetpoints, SERVICE_NAME)
    request, _, _ = request_for(0)
    with pytest.raises(TimeoutError, match=r"^service /gls/correct_setpoints is not available after 0.5 s$"):
        call_service(node, client, request, timeout_s=0.5)


def test_call_service_spins_a_node_outside_any_executor(ros_context, add_node, tmp_path):
    add_node(correction_node(ros_context, tmp_path / "empty_store"))
    client_node = Node("unspun_client", namespace=NAMESPACE, context=ros_context)
    try:
        client = client_node.create_client(CorrectSetpoints, SERVICE_NAME)
        request, x, y = request_for(1)
        assert_nominal_answer(call_service(client_node, client, request, TIMEOUT_S, RESEND_AFTER_S), x, y)
    finally:
        client_node.destroy_node()


def test_wait_for_reports_what_did_not_happen():
    with pytest.raises(TimeoutError, match=r"^the impossible did not hold within 0.05 s$"):
        wait_for(lambda: False, 0.05, what="the impossible")
