"""Test-only ROS peer for test_stream_peer.py: a robot and a line scanner as a real cell's drivers
behave, in plain rclpy. It imports NOTHING of gls_calibration (checked at start).

- ``/tf_static`` (transient local): flange -> scanner_optical (its own hand-eye, HAND_EYE_*) and
  robot_base -> gls.
- On each ``/motion/line`` command (nav_msgs/Path: the flange's start and end poses, the duration as
  the stamps' difference) it runs the line with synthetic stamps from its clock: ``/motion/start``,
  the flange pose on ``/tf`` every 1/TF_RATE_HZ s, a PointCloud2 profile (x, y, z, intensity float32,
  metres, frame scanner_optical) every 1/--rate s of a flat plate with a ridge (PLATE_*), then
  ``/motion/end``. It also streams BEFORE profiles before the start and AFTER after the end, as a
  running sensor does.
- ``--modes a,b,...``: the n-th command is run in the n-th mode: ``normal``; ``stale`` (the flange
  pose only every 0.2 s); ``stops`` (the profiles stop halfway through the line); ``mm`` (profiles in
  millimetres); ``out_of_order`` (two profiles swapped); ``late`` (one profile of the line sent LATE_S
  after the end).
- ``--hand-eye-on-request``: flange -> scanner_optical is published only when a message comes on
  ``/peer/hand_eye`` (std_msgs/Empty): until then a frame is missing.

    python test/_stream_peer.py --rate 50 --modes normal,stale [--lifetime 60]
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Empty, Header
from tf2_msgs.msg import TFMessage

HAND_EYE_T_M = (0.04, 0.0, 0.18)                 # scanner_optical in flange (the shipped cell file's)
HAND_EYE_YAW_RAD = np.pi / 2
PLATE_Z_M = 0.3                                   # the plate's surface: base z (the sensor looks along +z)
RIDGE_X_M = (0.00225, 0.00625)                    # a ridge across base x ...
RIDGE_Z_M = 0.29                                  # ... 10 mm nearer the sensor
LINE_X_M = -0.010 + 0.0005 * np.arange(41)        # the laser line's points along the sensor x
TF_RATE_HZ = 250.0
BEFORE, AFTER = 3, 5
RELIABLE = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
MODES = ("normal", "stale", "stops", "mm", "out_of_order", "late")
# "late": one profile of the line held back this long after the motion's end. It must come after the
# sweep was taken: at 1.5 s it once came before, on a 2-core host at load 6 (then it is dropped as out
# of order and never counted late).
LATE_S = 3.0


def pose(translation_m, rotation: Rotation) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = rotation.as_matrix()
    matrix[:3, 3] = translation_m
    return matrix


HAND_EYE = pose(HAND_EYE_T_M, Rotation.from_euler("z", HAND_EYE_YAW_RAD))


def stamp(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def transform(parent: str, child: str, matrix: np.ndarray, ns: int) -> TransformStamped:
    message = TransformStamped()
    message.header.frame_id, message.child_frame_id, message.header.stamp = parent, child, stamp(ns)
    t, q = matrix[:3, 3], Rotation.from_matrix(matrix[:3, :3]).as_quat()
    message.transform.translation.x, message.transform.translation.y, message.transform.translation.z = map(float, t)
    r = message.transform.rotation
    r.x, r.y, r.z, r.w = map(float, q)
    return message


def profile_points_m(sensor: np.ndarray) -> np.ndarray:
    """(W, 3) points of the plate in the sensor frame for a sensor pose (base, m) turned about z only."""
    rotation, origin = sensor[:3, :3], sensor[:3, 3]
    base_x = origin[0] + rotation[0, 0] * LINE_X_M
    plate_z = np.where((base_x > RIDGE_X_M[0]) & (base_x < RIDGE_X_M[1]), RIDGE_Z_M, PLATE_Z_M)
    return np.column_stack([LINE_X_M, np.zeros_like(LINE_X_M), plate_z - origin[2]])


def cloud(points_m: np.ndarray, ns: int) -> PointCloud2:
    data = np.zeros(len(points_m), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    data["x"], data["y"], data["z"], data["intensity"] = points_m[:, 0], points_m[:, 1], points_m[:, 2], 0.5
    message = PointCloud2(height=1, width=len(points_m), is_bigendian=False, point_step=16,
                          row_step=16 * len(points_m), is_dense=True)
    message.header.frame_id, message.header.stamp = "scanner_optical", stamp(ns)
    message.fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                      for i, name in enumerate(("x", "y", "z", "intensity"))]
    message.data = data.tobytes()
    return message


class Peer(Node):
    def __init__(self, rate_hz: float, modes: list[str], hand_eye_on_request: bool = False) -> None:
        super().__init__("stream_peer")
        self.rate_hz, self.modes = rate_hz, modes
        self.tf = self.create_publisher(TFMessage, "/tf", RELIABLE)
        self.static = self.create_publisher(TFMessage, "/tf_static", LATCHED)
        self.profiles = self.create_publisher(PointCloud2, "/scanner/profile", RELIABLE)
        self.starts = self.create_publisher(Header, "/motion/start", RELIABLE)
        self.ends = self.create_publisher(Header, "/motion/end", RELIABLE)
        self.create_subscription(Path, "/motion/line", self.on_line, RELIABLE)
        self.commands = 0
        self.publish_static(with_hand_eye=not hand_eye_on_request)
        if hand_eye_on_request:     # a driver that starts late: the hand-eye comes when the test says
            self.create_subscription(Empty, "/peer/hand_eye", lambda _: self.publish_static(with_hand_eye=True),
                                     RELIABLE)

    def publish_static(self, with_hand_eye: bool) -> None:
        transforms = [transform("robot_base", "gls", pose((0.0, 0.1, 0.325), Rotation.from_euler("x", np.pi)), 0)]
        if with_hand_eye:
            transforms.append(transform("flange", "scanner_optical", HAND_EYE, 0))
        self.static.publish(TFMessage(transforms=transforms))

    def wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + 5.0
        publishers = (self.tf, self.profiles, self.starts, self.ends)
        while time.monotonic() < deadline and not all(p.get_subscription_count() for p in publishers):
            time.sleep(0.01)

    def on_line(self, message: Path) -> None:
        mode = self.modes[min(self.commands, len(self.modes) - 1)]
        self.commands += 1
        first, last = (pose([p.pose.position.x, p.pose.position.y, p.pose.position.z],
                            Rotation.from_quat([p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z,
                                                p.pose.orientation.w])) for p in message.poses)
        duration_ns = ((message.poses[1].header.stamp.sec - message.poses[0].header.stamp.sec) * 1_000_000_000
                       + message.poses[1].header.stamp.nanosec - message.poses[0].header.stamp.nanosec)
        self.wait_for_subscribers()
        start_ns = self.get_clock().now().nanoseconds
        end_ns = start_ns + duration_ns

        def flange_at(ns: int) -> np.ndarray:
            fraction = min(max((ns - start_ns) / duration_ns, 0.0), 1.0)
            matrix = first.copy()
            matrix[:3, 3] = first[:3, 3] + fraction * (last[:3, 3] - first[:3, 3])
            return matrix

        period_ns = 1e9 / self.rate_hz
        tf_period_ns = 1e9 / (5.0 if mode == "stale" else TF_RATE_HZ)
        tf_samples = range(-BEFORE * 50, int(duration_ns / tf_period_ns) + 50)
        tf_stamps = [int(start_ns + round(k * tf_period_ns)) for k in tf_samples]
        profile_stamps = [int(start_ns + round(k * period_ns)) for k in range(-BEFORE, round(duration_ns / period_ns)
                                                                              + 1 + AFTER)]
        if mode == "stops":
            profile_stamps = [ns for ns in profile_stamps if ns < start_ns + duration_ns // 2]
        for ns in tf_stamps:      # the robot state publisher's stream (poses first: nothing waits on them)
            self.tf.publish(TFMessage(transforms=[transform("robot_base", "flange", flange_at(ns), ns)]))
        order = list(range(len(profile_stamps)))
        if mode == "out_of_order":
            order[BEFORE + 4], order[BEFORE + 5] = order[BEFORE + 5], order[BEFORE + 4]
        held_back = order.pop(BEFORE + 10) if mode == "late" else None
        for index in order:
            ns = profile_stamps[index]
            if ns == start_ns:
                self.starts.publish(Header(stamp=stamp(start_ns), frame_id="robot_base"))
            points = profile_points_m(flange_at(ns) @ HAND_EYE)
            self.profiles.publish(cloud(points * (1000.0 if mode == "mm" else 1.0), ns))
        self.ends.publish(Header(stamp=stamp(end_ns), frame_id="robot_base"))
        if held_back is not None:
            time.sleep(LATE_S)
            ns = profile_stamps[held_back]
            self.profiles.publish(cloud(profile_points_m(flange_at(ns) @ HAND_EYE), ns))


def serve(node: Node, lifetime_s: float) -> int:
    """Say ready, spin ``node`` until the lifetime is over or it is interrupted, then shut down."""
    print("peer ready", flush=True)
    deadline = time.monotonic() + lifetime_s
    try:
        while rclpy.ok() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rate", type=float, required=True)
    parser.add_argument("--modes", default="normal")
    parser.add_argument("--lifetime", type=float, default=120.0)
    parser.add_argument("--hand-eye-on-request", action="store_true",
                        help="publish flange -> scanner_optical only when a message comes on /peer/hand_eye")
    args = parser.parse_args()
    modes = args.modes.split(",")
    assert all(mode in MODES for mode in modes), modes
    assert not any(name.startswith("gls_calibration") for name in sys.modules), "the peer imported gls_calibration"
    rclpy.init()
    node = Peer(args.rate, modes, args.hand_eye_on_request)
    return serve(node, args.lifetime)


if __name__ == "__main__":
    sys.exit(main())
