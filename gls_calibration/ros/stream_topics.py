"""Messages of the streaming cell at the ROS boundary: motion contract, TF, line command.

The motion contract's topics and QoS, TF messages from 4x4 poses and back, and the line command
(``nav_msgs/Path``).

The motion contract, with standard types only (the shared message package cannot grow here):

- ``/motion/line`` (``nav_msgs/Path``): a command. ``header.frame_id`` the robot base frame, exactly
  two poses: the flange's start and end pose (metres, quaternion). The line's duration is the second
  pose's stamp minus the first's (stamps as durations from 0); the speed is the length over it.
- ``/motion/start`` and ``/motion/end`` (``std_msgs/Header``): published by the robot when it begins
  and ends a commanded line, stamped with those instants (robot clock), ``frame_id`` its base frame.
- ``/tf``: the flange pose the robot reports, robot base -> flange; ``/tf_static`` (transient local):
  flange -> sensor optical frame and robot base -> gls, from the cell frames file.
"""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, PoseStamped, TransformStamped
from nav_msgs.msg import Path
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation

from gls_calibration.scan.bag_io import BagLayout, NS_PER_S

LAYOUT = BagLayout()
LINE_TOPIC = "/motion/line"
MM_PER_M = 1000.0


def stream_qos(depth: int) -> QoSProfile:
    """Reliable, ``depth`` deep: TF samples and profiles of a whole sweep must not be lost."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def static_qos() -> QoSProfile:
    """``/tf_static``'s QoS (as tf2's static broadcaster): a late subscriber still gets the fixed frames."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def time_msg(stamp_ns: int) -> Time:
    """Return a ROS time stamp of ``stamp_ns`` (integer nanoseconds)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def stamp_ns(stamp: Time) -> int:
    """Integer nanoseconds of a ROS time stamp."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def pose_msg(pose_mm: np.ndarray) -> Pose:
    """Return a 4x4 pose (mm) as a Pose (metres, quaternion)."""
    message = Pose()
    message.position.x, message.position.y, message.position.z = (float(v) / MM_PER_M for v in pose_mm[:3, 3])
    x, y, z, w = Rotation.from_matrix(pose_mm[:3, :3]).as_quat()
    message.orientation.x, message.orientation.y, message.orientation.z, message.orientation.w = (
        float(x), float(y), float(z), float(w))
    return message


def pose_from_msg(message: Pose, where: str) -> np.ndarray:
    """4x4 pose (mm) of a Pose; ValueError for a non-finite one or a quaternion that is not unit."""
    q = message.orientation
    quaternion = np.array([q.x, q.y, q.z, q.w], dtype=float)
    position = np.array([message.position.x, message.position.y, message.position.z], dtype=float)
    if not (np.all(np.isfinite(quaternion)) and np.all(np.isfinite(position))):
        raise ValueError(f"{where}: the pose is not finite")
    if abs(np.linalg.norm(quaternion) - 1.0) > 1e-6:
        raise ValueError(f"{where}: the quaternion's norm is {np.linalg.norm(quaternion):.6g}, not 1")
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    pose[:3, 3] = position * MM_PER_M
    return pose


def transform_msg(parent: str, child: str, pose_mm: np.ndarray, stamp_ns_: int) -> TransformStamped:
    """Build the TransformStamped (metres) of ``child`` in ``parent`` from a 4x4 pose in mm."""
    message = TransformStamped()
    message.header.stamp = time_msg(stamp_ns_)
    message.header.frame_id = parent
    message.child_frame_id = child
    pose = pose_msg(pose_mm)
    message.transform.translation.x = pose.position.x
    message.transform.translation.y = pose.position.y
    message.transform.translation.z = pose.position.z
    message.transform.rotation = pose.orientation
    return message


def line_msg(base_frame: str, start_flange_mm: np.ndarray, end_flange_mm: np.ndarray, duration_s: float) -> Path:
    """Return the ``/motion/line`` command of a straight flange line."""
    message = Path()
    message.header.frame_id = base_frame
    for pose_mm, at_s in ((start_flange_mm, 0.0), (end_flange_mm, duration_s)):
        stamped = PoseStamped()
        stamped.header.frame_id = base_frame
        stamped.header.stamp = time_msg(int(round(at_s * NS_PER_S)))
        stamped.pose = pose_msg(pose_mm)
        message.poses.append(stamped)
    return message


def line_from_msg(message: Path, base_frame: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Start and end flange poses (4x4, mm) and duration (s) of a line command; ValueError naming a problem."""
    if message.header.frame_id != base_frame:
        raise ValueError(f"a line must be given in the robot base frame {base_frame!r}, "
                         f"got {message.header.frame_id!r}")
    if len(message.poses) != 2:
        raise ValueError(f"a line has two poses (start, end), got {len(message.poses)}")
    start, end = (pose_from_msg(stamped.pose, f"line pose {number}") for number, stamped in enumerate(message.poses))
    duration_s = (stamp_ns(message.poses[1].header.stamp) - stamp_ns(message.poses[0].header.stamp)) / NS_PER_S
    if not duration_s > 0.0:
        raise ValueError("a line's duration (second pose's stamp minus the first's) must be positive, "
                         f"got {duration_s:g} s")
    return start, end, duration_s
