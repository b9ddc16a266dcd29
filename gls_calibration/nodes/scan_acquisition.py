"""scan_acquisition: serves ``scan/acquire``; starts a sweep, collects ``scan/points`` profiles and
returns them assembled as one organized cloud in the scanner base frame, each profile placed by the
robot's reported sensor pose (``scan/pose``, PoseStamped, metres, interpolated at the profile's
stamp) when that stream covers the sweep, else by its stamp and the sweep's nominal motion."""
from __future__ import annotations

from typing import Optional

from geometry_msgs.msg import PoseStamped
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2

from gls_calibration.nodes import conversions
from gls_calibration.nodes.base import GlsNode, ServiceCallError, run_node
from gls_calibration.sweep import PoseTrack, SweepCollector, SweepMotion, nominal_start_pose
from gls_calibration_msgs.msg import SweepDone
from gls_calibration_msgs.srv import AcquireSweep, StartSweep


def profile_qos(depth: int) -> QoSProfile:
    """Reliable, deep enough to hold a whole sweep: a profile must never be lost."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


class ScanAcquisitionNode(GlsNode):
    """One sweep at a time; memory bounded by ``max_profiles`` x ``max_points_per_profile``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("scan_acquisition", **kwargs)
        self.max_profiles = self.declare("max_profiles", 4000, "most profiles kept from one sweep",
                                         minimum=1, maximum=100000)
        self.max_points = self.declare("max_points_per_profile", 4096, "most points kept from one profile",
                                       minimum=1, maximum=100000)
        self.default_timeout_s = self.declare("timeout_s", 120.0, "default time limit of one sweep (s)",
                                              minimum=0.1)
        self.use_poses = self.declare("use_pose_stream", True,
                                      "place profiles by the reported sensor pose on scan/pose when it covers "
                                      "the sweep (else by time at the nominal speed)")
        self.collector: Optional[SweepCollector] = None
        self.poses: Optional[PoseTrack] = None
        self.done: Optional[SweepDone] = None
        self.start_client = self.client(StartSweep, "scanner/start_sweep")
        self.create_subscription(PointCloud2, "scan/points", self.on_profile, profile_qos(self.max_profiles),
                                 callback_group=self.reentrant_group)
        self.create_subscription(PoseStamped, "scan/pose", self.on_pose, profile_qos(self.max_profiles),
                                 callback_group=self.reentrant_group)
        self.create_subscription(SweepDone, "scan/sweep_done", self.on_sweep_done, profile_qos(10),
                                 callback_group=self.reentrant_group)
        self.create_service(AcquireSweep, "scan/acquire", self.on_acquire, callback_group=self.reentrant_group)

    def on_profile(self, message: PointCloud2) -> None:
        """Keep a profile of the running sweep; profiles outside a sweep are ignored."""
        collector = self.collector
        if collector is None:
            return
        try:
            profile = conversions.pointcloud2_to_array(message)
        except ValueError as error:
            self.get_logger().warning(f"profile dropped: {error}")
            collector.dropped += 1
            return
        collector.add(Time.from_msg(message.header.stamp).nanoseconds * 1e-9, profile)

    def on_pose(self, message: PoseStamped) -> None:
        """Keep a reported sensor pose of the running sweep (metres -> mm)."""
        poses = self.poses
        if poses is None:
            return
        position, orientation = message.pose.position, message.pose.orientation
        poses.add(Time.from_msg(message.header.stamp).nanoseconds * 1e-9,
                  (1000.0 * position.x, 1000.0 * position.y, 1000.0 * position.z),
                  (orientation.x, orientation.y, orientation.z, orientation.w))

    def on_sweep_done(self, message: SweepDone) -> None:
        """Remember the end of the sweep; the acquire coroutine waits for it."""
        if self.collector is not None:
            self.done = message

    async def on_acquire(self, request, response):
        """Start a sweep, wait for all its profiles, answer with the organized cloud."""
        if self.collector is not None:
            response.success = False
            response.message = "a sweep is already being acquired; request refused"
            return response
        timeout_s = request.timeout_s or self.default_timeout_s
        direction = request.direction or 1
        if direction not in (1, -1):
            response.success = False
            response.message = f"direction must be +1, -1 or 0 (+1), got {request.direction}"
            return response
        self.collector, self.done = SweepCollector(self.max_profiles, self.max_points), None
        self.poses = PoseTrack(self.max_profiles) if self.use_poses else None
        try:
            started = await self.call(self.start_client, StartSweep.Request(
                length_mm=request.length_mm, speed_mm_s=request.speed_mm_s, step_mm=request.step_mm,
                direction=direction, orientation_deg=request.orientation_deg), timeout_s)
            if not started.success:
                raise ServiceCallError(f"the scanner refused the sweep: {started.message}")
            await self.wait_for(lambda: self.done is not None and self.done.sweep_id == started.sweep_id
                                and len(self.collector) + self.collector.dropped >= self.done.profiles,
                                timeout_s, self._timeout_message(timeout_s, started.expected_profiles))
            done, collector = self.done, self.collector
            if not done.complete:
                raise ServiceCallError(f"the sweep was cut short after {done.profiles} profiles")
            if collector.dropped:
                raise ServiceCallError(f"{collector.dropped} of {done.profiles} profiles were dropped "
                                       f"(bounds: {self.max_profiles} profiles of {self.max_points} points)")
            length_mm = (done.profiles - 1) * done.step_mm
            cloud, by_pose = collector.assemble(SweepMotion(tuple(done.direction), done.speed_mm_s),
                                                nominal_start_pose(length_mm, direction, request.orientation_deg),
                                                self.poses)
        except (ServiceCallError, ValueError) as error:
            response.success = False
            response.message = str(error)
            return response
        finally:
            self.collector = self.poses = None
        response.cloud = conversions.array_to_pointcloud2(cloud, frame_id="scanner")
        response.placed_by_pose = by_pose
        response.success = True
        response.message = (f"{cloud.shape[0]} profiles of {cloud.shape[1]} points, placed "
                            + ("by the reported pose" if by_pose else "by time at the nominal speed"))
        return response

    def _timeout_message(self, timeout_s: float, expected: int):
        def message() -> str:
            received = len(self.collector) if self.collector is not None else 0
            return (f"sweep not complete after {timeout_s:g} s: {received} of {expected} profiles "
                    "received and no end of sweep")
        return message


def main(args=None) -> None:
    """Console script ``gls-scan-acquisition``."""
    run_node(ScanAcquisitionNode, args)
