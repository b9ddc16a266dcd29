"""Test-only ROS peer for test_stream_calibrate.py: the robot and the line scanner of a whole cell, as
real drivers behave, in plain rclpy. It imports NOTHING of gls_calibration (checked at start); the
pieces it shares with test/_stream_peer.py (the same kind of peer) come from that file.

What it plays (metres, the optical frame, /tf and /tf_static, the motion contract of
docs/interfaces.md), against the package's default cell frames (those of _stream_peer.py):

- a flat steel plate on the galvo's work plane (gls z = 0), uniform intensity ``REFLECTIVITY``;
- the plate is plain for every commanded line up to and including the first line of no length (the
  stand-still at the marking pose: the calibration's documented order is plain sweeps, stand-still,
  marking, marked sweeps); on every later line it carries the fiducials, two rings each
  (``--radii-mm``), centred at the documented grid positions (``--grid``, ``--size-mm``:
  ``linspace(-size / 2, size / 2, grid)`` in gls x and y) moved by a KNOWN smooth field
  ``d(x, y) = a * (x * y, (x^2 - y^2) / 2)`` mm (``--field-a`` in 1/mm), as marks a galvo with that
  distortion burns;
- ``--fault mm|stops`` breaks the first marked line as a broken driver would: its profiles in
  millimetres, or no profile after the middle of the line;
- a ring darkens the steel with a Gaussian profile across it of full width at half maximum
  ``--line-fwhm-mm``; the laser line has points every ``POINT_SPACING_M`` over ``--line-width-mm``.

    python test/_cell_peer.py --rate 150 --grid 5 --size-mm 40 --field-a 5e-4 [--lifetime 300]
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import rclpy
from nav_msgs.msg import Path
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from _stream_peer import AFTER, BEFORE, HAND_EYE, LATCHED, RELIABLE, TF_RATE_HZ, cloud, pose, serve, stamp, transform

GLS_IN_BASE = pose((0.0, 0.1, 0.325), Rotation.from_euler("x", np.pi))   # the package's cell frames file's
POINT_SPACING_M = 1e-4
REFLECTIVITY = 0.6
MARK_DEPTH = 0.7          # a ring's darkening at its centre line (fraction of the reflectivity)
GAP_S = 1.0               # synthetic stamps of a line start this long after the previous line's end


def field_mm(xy_mm: np.ndarray, a: float) -> np.ndarray:
    """The peer's distortion: where a fiducial commanded at (x, y) lands, minus (x, y) (mm)."""
    x, y = xy_mm[..., 0], xy_mm[..., 1]
    return a * np.stack([x * y, 0.5 * (x * x - y * y)], axis=-1)


def grid_mm(per_side: int, size_mm: float) -> np.ndarray:
    """The documented grid: row-major, y outer, both increasing (gls mm)."""
    offsets = np.linspace(-0.5 * size_mm, 0.5 * size_mm, per_side)
    gx, gy = np.meshgrid(offsets, offsets, indexing="xy")
    return np.column_stack([gx.ravel(), gy.ravel()])


class CellPeer(Node):
    def __init__(self, args: argparse.Namespace) -> None:
        super().__init__("cell_peer")
        self.rate_hz = args.rate
        self.line_x_m = np.arange(-0.5 * args.line_width_mm * 1e-3, 0.5 * args.line_width_mm * 1e-3 + 1e-9,
                                  POINT_SPACING_M)
        grid = grid_mm(args.grid, args.size_mm)
        self.centres_mm = grid + field_mm(grid, args.field_a)
        self.radii_mm = np.asarray(args.radii_mm)
        self.sigma_mm = args.line_fwhm_mm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
        self.marked = False
        self.fault, self.faulted = args.fault, False
        self.next_start_ns = self.get_clock().now().nanoseconds
        self.tf = self.create_publisher(TFMessage, "/tf", RELIABLE)
        self.static = self.create_publisher(TFMessage, "/tf_static", LATCHED)
        self.profiles = self.create_publisher(PointCloud2, "/scanner/profile", RELIABLE)
        self.starts = self.create_publisher(Header, "/motion/start", RELIABLE)
        self.ends = self.create_publisher(Header, "/motion/end", RELIABLE)
        self.create_subscription(Path, "/motion/line", self.on_line, RELIABLE)
        self.static.publish(TFMessage(transforms=[transform("robot_base", "gls", GLS_IN_BASE, 0),
                                                  transform("flange", "scanner_optical", HAND_EYE, 0)]))

    def profile(self, sensor: np.ndarray) -> np.ndarray:
        """(W, 4) points (sensor frame, m) and intensity where the line of a sensor at ``sensor`` (base, m)
        meets the plate (gls z = 0)."""
        to_base = GLS_IN_BASE @ np.array([0.0, 0.0, 0.0, 1.0])
        normal = GLS_IN_BASE[:3, 2]
        rotation, origin = sensor[:3, :3], sensor[:3, 3]
        starts = origin + np.outer(self.line_x_m, rotation[:, 0])          # the line's points at range 0
        ray = rotation[:, 2]
        ranges = ((to_base[:3] - starts) @ normal) / (ray @ normal)
        in_gls = (np.linalg.inv(GLS_IN_BASE) @ np.column_stack([starts + np.outer(ranges, ray),
                                                                np.ones_like(ranges)]).T).T[:, :2] * 1e3
        intensity = np.full(ranges.shape, REFLECTIVITY)
        if self.marked:
            distance = np.linalg.norm(in_gls[:, None, :] - self.centres_mm[None, :, :], axis=-1)   # (W, F)
            off_ring = np.min(np.abs(distance[..., None] - self.radii_mm), axis=(1, 2))
            intensity *= 1.0 - MARK_DEPTH * np.exp(-off_ring ** 2 / (2.0 * self.sigma_mm ** 2))
        return np.column_stack([self.line_x_m, np.zeros_like(ranges), ranges, intensity])

    def on_line(self, message: Path) -> None:
        first, last = (pose([p.pose.position.x, p.pose.position.y, p.pose.position.z],
                            Rotation.from_quat([p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z,
                                                p.pose.orientation.w])) for p in message.poses)
        duration_ns = ((message.poses[1].header.stamp.sec - message.poses[0].header.stamp.sec) * 1_000_000_000
                       + message.poses[1].header.stamp.nanosec - message.poses[0].header.stamp.nanosec)
        deadline = time.monotonic() + 5.0     # volatile topics: send once the acquisition's readers matched
        while time.monotonic() < deadline and not all(
                publisher.get_subscription_count() for publisher in (self.tf, self.profiles, self.starts, self.ends)):
            time.sleep(0.01)
        start_ns = max(self.get_clock().now().nanoseconds, self.next_start_ns)
        end_ns = start_ns + duration_ns
        self.next_start_ns = end_ns + int(GAP_S * 1e9)

        def flange_at(ns: int) -> np.ndarray:
            matrix = first.copy()
            matrix[:3, 3] += min(max((ns - start_ns) / duration_ns, 0.0), 1.0) * (last[:3, 3] - first[:3, 3])
            return matrix

        tf_period_ns, period_ns = 1e9 / TF_RATE_HZ, 1e9 / self.rate_hz
        for k in range(-BEFORE * 50, int(duration_ns / tf_period_ns) + 50):
            ns = int(start_ns + round(k * tf_period_ns))
            self.tf.publish(TFMessage(transforms=[transform("robot_base", "flange", flange_at(ns), ns)]))
        fault = self.fault if self.marked and not self.faulted else None
        self.faulted = self.faulted or fault is not None
        for k in range(-BEFORE, round(duration_ns / period_ns) + 1 + AFTER):
            ns = int(start_ns + round(k * period_ns))
            if k == 0:
                self.starts.publish(Header(stamp=stamp(start_ns), frame_id="robot_base"))
            if fault == "stops" and ns > start_ns + duration_ns // 2:
                continue
            points = self.profile(flange_at(ns) @ HAND_EYE)
            message = cloud(points[:, :3] * (1000.0 if fault == "mm" else 1.0), ns)
            data = np.frombuffer(message.data, dtype="<f4").reshape(-1, 4).copy()
            data[:, 3] = points[:, 3]
            message.data = data.tobytes()
            self.profiles.publish(message)
        self.ends.publish(Header(stamp=stamp(end_ns), frame_id="robot_base"))
        if np.allclose(first[:3, 3], last[:3, 3]):
            self.marked = True      # the stand-still at the marking pose: the galvo marks next
        print(f"line of {duration_ns / 1e9:.3f} s run, plate {'marked' if self.marked else 'plain'} from now on",
              flush=True)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rate", type=float, required=True, help="profile rate (Hz)")
    parser.add_argument("--grid", type=int, required=True, help="fiducials per side")
    parser.add_argument("--size-mm", type=float, required=True, help="side of the grid (mm)")
    parser.add_argument("--radii-mm", type=float, nargs="+", default=[2.5, 2.7])
    parser.add_argument("--field-a", type=float, required=True, help="the distortion's coefficient (1/mm)")
    parser.add_argument("--line-width-mm", type=float, default=60.0)
    parser.add_argument("--line-fwhm-mm", type=float, default=0.1)
    parser.add_argument("--fault", choices=("mm", "stops"), default=None)
    parser.add_argument("--lifetime", type=float, default=300.0)
    args = parser.parse_args()
    assert not any(name.startswith("gls_calibration") for name in sys.modules), "the peer imported gls_calibration"
    rclpy.init()
    node = CellPeer(args)
    return serve(node, args.lifetime)


if __name__ == "__main__":
    sys.exit(main())
