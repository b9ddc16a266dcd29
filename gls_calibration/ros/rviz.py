"""What RViz shows of a calibration: the plate pose and the fiducials with deviation arrows.

The plate pose is a PoseStamped, the fiducials with their deviation arrows before and after a
MarkerArray, in the ``gls`` frame, in metres.

Published transient-local, so an RViz started later still gets the last calibration
(``config/gls_calibration.rviz`` displays both). Arrows run from the commanded target towards where
the mark landed, lengthened by ``arrow_scale`` (deviations are tenths of a millimetre on a 190 mm
field), and are coloured from green (0) to red (``colour_full_scale_mm`` and above).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from geometry_msgs.msg import Point, PoseStamped, Quaternion
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from gls_calibration.calibration.outcome import PlateRun
from gls_calibration.ros.conversions import MM_PER_M
from gls_calibration.scan.plate_pose import PlatePose

FRAME_ID = "gls"
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
FIDUCIAL_DIAMETER_M = 0.0054          # the outer ring (2 x 2.7 mm)


def plate_pose_msg(pose: PlatePose, stamp) -> PoseStamped:
    """Return the plate frame in the gls frame (metres)."""
    message = PoseStamped()
    message.header.frame_id, message.header.stamp = FRAME_ID, stamp
    centre = np.asarray(pose.centre, dtype=float) / MM_PER_M
    message.pose.position.x, message.pose.position.y, message.pose.position.z = (float(v) for v in centre)
    x, y, z, w = Rotation.from_matrix(np.asarray(pose.rotation, dtype=float)).as_quat()
    message.pose.orientation = Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))
    return message


def _point(xyz_mm: np.ndarray) -> Point:
    x, y, z = (float(v) / MM_PER_M for v in xyz_mm)
    return Point(x=x, y=y, z=z)


def _colour(size_mm: float, full_scale_mm: float) -> ColorRGBA:
    level = float(np.clip(size_mm / full_scale_mm, 0.0, 1.0))
    return ColorRGBA(r=level, g=1.0 - level, b=0.0, a=1.0)


def deviation_arrows(run: PlateRun, namespace: str, stamp, arrow_scale: float,
                     colour_full_scale_mm: float) -> list[Marker]:
    """One arrow per paired fiducial: from the target Q towards the landed point P = Q - delta."""
    markers = []
    targets = np.column_stack([run.paired_targets_xy, run.measured_gls[:, 2]])
    for index, (target, deviation) in enumerate(zip(targets, run.deviations)):
        tip = target.copy()
        tip[:2] -= arrow_scale * deviation
        marker = Marker(ns=namespace, id=index, type=Marker.ARROW, action=Marker.ADD)
        marker.header.frame_id, marker.header.stamp = FRAME_ID, stamp
        marker.points = [_point(target), _point(tip)]
        marker.scale.x, marker.scale.y, marker.scale.z = 0.0008, 0.0016, 0.002   # shaft, head width, head length
        marker.color = _colour(float(np.hypot(*deviation)), colour_full_scale_mm)
        marker.pose.orientation.w = 1.0
        markers.append(marker)
    return markers


def fiducial_spheres(run: PlateRun, namespace: str, stamp) -> Marker:
    """Return the measured fiducial centres as one sphere list."""
    marker = Marker(ns=namespace, id=0, type=Marker.SPHERE_LIST, action=Marker.ADD)
    marker.header.frame_id, marker.header.stamp = FRAME_ID, stamp
    marker.points = [_point(centre) for centre in run.measured_gls]
    marker.scale.x = marker.scale.y = marker.scale.z = FIDUCIAL_DIAMETER_M
    marker.color = ColorRGBA(r=0.9, g=0.9, b=0.9, a=0.8)
    marker.pose.orientation.w = 1.0
    return marker


def calibration_markers(first: PlateRun, validation: Optional[PlateRun], stamp, arrow_scale: float,
                        colour_full_scale_mm: float) -> MarkerArray:
    """Everything of one calibration, after a DELETEALL that clears the previous one."""
    clear = Marker(action=Marker.DELETEALL)
    clear.header.frame_id = FRAME_ID
    markers = [clear, fiducial_spheres(first, "fiducials", stamp)]
    markers += deviation_arrows(first, "deviation_before", stamp, arrow_scale, colour_full_scale_mm)
    if validation is not None:
        markers.append(fiducial_spheres(validation, "validation_fiducials", stamp))
        markers += deviation_arrows(validation, "deviation_after", stamp, arrow_scale, colour_full_scale_mm)
    return MarkerArray(markers=markers)
