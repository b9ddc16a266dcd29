"""Test-only ROS peer for test_transport.py (not a product node): a latched PointCloud2.

The cloud is built from a seed, so the receiving test can rebuild the expected one. Imported by the
tests for the same pieces, and run as a separate process:

    python test/_cloud_peer.py --seed 7 [--lifetime 60]

It stops on SIGINT/SIGTERM or after ``--lifetime`` seconds, so it never outlives a broken test.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from gls_calibration.ros.conversions import array_to_pointcloud2, xyzi_array

NAMESPACE = "gls"
CLOUD_TOPIC = "scan/points"
CLOUD_SHAPE = (50, 100)                 # organized: height 50, width 100
# Latched so a subscriber that joins after the one-shot publication still gets the cloud.
CLOUD_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)


def transport_cloud(seed: int) -> np.ndarray:
    """Seeded organized x, y, z, intensity cloud (mm) with a few NaN points, as a scanner gives."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-100.0, 100.0, size=CLOUD_SHAPE + (3,))
    xyz[rng.random(CLOUD_SHAPE) < 0.05] = np.nan
    return xyzi_array(xyz, rng.random(CLOUD_SHAPE))


def publish_cloud(node: Node, seed: int, frame_id: str = "scanner") -> tuple[Publisher, PointCloud2]:
    """Publish the seeded cloud once on the latched cloud topic; return the publisher and message."""
    publisher = node.create_publisher(PointCloud2, CLOUD_TOPIC, CLOUD_QOS)
    message = array_to_pointcloud2(transport_cloud(seed), frame_id, node.get_clock().now())
    publisher.publish(message)
    return publisher, message


def main() -> None:
    """Run the peer: the latched cloud, until a signal or the lifetime ends."""
    parser = argparse.ArgumentParser(description="test-only cloud peer")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--lifetime", type=float, default=60.0)
    args = parser.parse_args()
    rclpy.init()
    node = Node("cloud_peer", namespace=NAMESPACE)
    try:
        publish_cloud(node, args.seed)
        deadline = time.monotonic() + args.lifetime
        while rclpy.ok() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
