"""sim_scanner: the simulated laser-line scanner, a drop-in for a real scanner driver.

Serves ``scanner/start_sweep`` and ``scanner/start_standstill``; each sweep's profiles go out on
``scan/points`` (PointCloud2 with x, y, z in metres and intensity, in the moving sensor frame ``frame_id``,
y = 0 on the line, stamped with the time each profile was taken), then ``scan/sweep_done``. The plate's
marks come from the simulated galvo (``sim/marked_paths``) at the start of each sweep, as a real scanner
sees the real plate.

Hooks for placing profiles by pose and for sweep plans (see ``simulation/scanner.py``):

- ``StartSweep.direction`` (+1 / -1, 0 means +1) and ``StartSweep.orientation_deg`` (0, 45 or 90);
  ``SweepDone.direction`` is then ``(0, direction, 0)`` in the sensor frame.
- ``scanner/start_standstill`` (``StartSweep``): profiles taken with the robot standing still at the
  marking pose, the sensor over the middle of the sweep (``LaserLineScanner.standstill``): as many
  as a sweep of ``length_mm`` every ``step_mm`` would take, at the same rate, without travel
  (``SweepDone.direction`` (0, 0, 0)). Its ids count from ``STANDSTILL_IDS`` and its random draws
  have a stream of their own, so the sweeps' ids and draws stay what they were.
- ``scan/pose`` (``geometry_msgs/PoseStamped``, frame ``scanner_base``): for every profile, published
  just before it with the SAME stamp, the sensor pose the robot reports (its encoder pose: it
  follows the speed error and ripple, not the path wander). Position in METRES (REP 103), the
  sensor frame -> the scanner base frame (the frame the CAD mounting maps to the gls frame). A
  point ``(x, 0, z)`` of a profile (mm) lies at ``R @ (x, 0, z) + 1000 * p`` mm in the base frame.
"""
from __future__ import annotations

import math
from typing import Iterator, Optional

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from gls_calibration.registration.sweep_plan import ORIENTATIONS_DEG, ORIENTATIONS_TEXT
from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.request_ids import AnsweredRequests
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import ServiceCallError, answers_errors
from gls_calibration.ros.sim_parameters import declare_sim_config
from gls_calibration.simulation.scanner import Profile
from gls_calibration_msgs.msg import SweepDone
from gls_calibration_msgs.srv import GetMarkedPaths, StartSweep
from geometry_msgs.msg import PoseStamped
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2

LISTENER_WAIT_S = 3.0   # a sweep waits this long at most for subscribers on its topics

# The marks query is read-only, so a repeat is harmless: asked again when unanswered (a galvo just
# restarted may drop the first answer while DDS still matches it: "failed to send response").
MARKS_RESEND_AFTER_S = 2.0

STANDSTILL_IDS = 2 ** 31   # first id of a stand-still acquisition: apart from the sweeps' ids


class SimScannerNode(GlsNode):
    """Publishes a sweep's profiles in batches from a timer, so that subscribers keep up."""

    def __init__(self, **kwargs) -> None:
        super().__init__("sim_scanner", **kwargs)
        self.config = declare_sim_config(self)
        self.batch = self.declare("profiles_per_tick", 50, "profiles published per timer tick", minimum=1)
        self.max_profiles = self.declare("max_profiles", 20000, "most profiles of one sweep", minimum=1,
                                         maximum=1_000_000)
        depth = self.declare("queue_depth", 4000, "profiles the reliable publisher keeps for slow subscribers",
                             minimum=1)
        self.frame_id = self.declare("frame_id", "scanner_sensor", "frame of the profiles: the moving sensor")
        self.scanner = self.config.make_scanner()
        self.plate = self.config.make_plate()
        self.sweep_id = 0
        self.standstills = 0
        self.job: Optional[Iterator[Profile]] = None
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        self.points = self.create_publisher(PointCloud2, "scan/points", qos)
        self.poses = self.create_publisher(PoseStamped, "scan/pose", qos)
        self.done = self.create_publisher(SweepDone, "scan/sweep_done",
                                          QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self.marks_client = self.client(GetMarkedPaths, "sim/marked_paths")
        self.answered = AnsweredRequests()
        self.create_service(StartSweep, "scanner/start_sweep", self.on_start_sweep,
                            callback_group=self.reentrant_group)
        self.create_service(StartSweep, "scanner/start_standstill", self.on_start_standstill,
                            callback_group=self.reentrant_group)
        # One tick at a time: the sweep is a generator and profiles must go out in order.
        self.timer = self.create_timer(0.001, self.publish_batch, callback_group=MutuallyExclusiveCallbackGroup())
        self.timer.cancel()

    @answers_errors(ValueError)
    async def on_start_sweep(self, request, response):
        """Load the plate's marks, then start publishing the sweep.

        A repeated request id gets the first answer again and starts nothing.
        """
        return await self.answered.answer_async(request.request_id, lambda: self._start_sweep(request, response))

    @answers_errors(ValueError)
    async def on_start_standstill(self, request, response):
        """Load the plate's marks, then publish profiles taken standing still.

        A repeated request id gets the first answer again.
        """
        return await self.answered.answer_async(request.request_id,
                                                lambda: self._start_sweep(request, response, standstill=True))

    async def _start_sweep(self, request, response, standstill: bool = False):
        if self.job is not None:
            response.success, response.message = False, "a sweep is running; request refused"
            return response
        length = request.length_mm or self.config.sweep_length_mm   # 0 in the request: the default
        try:
            profiles, speed, step = self.scanner.sweep_parameters(length, request.speed_mm_s or None,
                                                                  request.step_mm or None)
            if profiles > self.max_profiles or not math.isfinite(speed):
                raise ValueError(f"a sweep of {length:g} mm at {speed:g} mm/s every {step:g} mm is refused: "
                                 f"at most {self.max_profiles} profiles (parameter max_profiles) at a finite speed")
        except (ValueError, OverflowError) as error:
            response.success, response.message = False, f"request refused: {error}"
            return response
        direction = request.direction or 1
        if standstill and request.orientation_deg != 0.0:
            response.success = False
            response.message = f"a stand-still is taken at orientation 0, got {request.orientation_deg:g}"
            return response
        if direction not in (1, -1) or request.orientation_deg not in ORIENTATIONS_DEG:
            response.success = False
            response.message = (f"direction must be +1 or -1 (got {request.direction}) and orientation_deg "
                                f"{ORIENTATIONS_TEXT} (got {request.orientation_deg:g})")
            return response
        try:
            await self._load_marks()
            await self._wait_for_listeners()
        except ServiceCallError as error:
            response.success, response.message = False, f"cannot see the plate's marks: {error}"
            return response
        if standstill:
            self.standstills += 1
            sweep_id, direction = STANDSTILL_IDS + self.standstills, 0    # no travel
            self.job = self.scanner.standstill(self.plate, profiles, seed=self.config.seed * 100003 + self.standstills,
                                               position_mm=(0.0, 0.5 * self.config.sweep_length_mm, 0.0),
                                               marking_pose_error=self.plate.marking_pose_error,
                                               period_s=step / speed)
        else:
            self.sweep_id += 1
            sweep_id = self.sweep_id
            self.job = self.scanner.sweep(self.plate, length, speed, step, seed=self.config.seed * 100003 + sweep_id,
                                          direction=direction, orientation_deg=request.orientation_deg)
        self.sweep = (sweep_id, speed, step, self.get_clock().now(), direction)
        self.published = 0
        response.sweep_id = sweep_id
        response.expected_profiles = profiles
        response.success = True
        response.message = f"{'stand-still' if standstill else 'sweep'} {sweep_id} started"
        self.timer.reset()
        return response

    async def _wait_for_listeners(self) -> None:
        """Wait (at most ``LISTENER_WAIT_S``) until every topic of the sweep has a matched subscriber.

        A sweep is not repeated: published before this node's writers know the acquisition's readers
        (after a restart, discovery may take seconds one way while the other already works), its
        profiles would be lost. Nobody listening after the wait: the sweep goes out anyway, as a real
        sensor's would.
        """
        await self.wait_for_peers((self.points, self.poses, self.done),
                                  lambda publisher: publisher.get_subscription_count(), LISTENER_WAIT_S,
                                  "nobody listens on", "sweep published anyway")

    async def _load_marks(self) -> None:
        answer = await self.call(self.marks_client, GetMarkedPaths.Request(), 10.0,
                                 resend_after_s=MARKS_RESEND_AFTER_S)
        # the galvo's plate itself: its id names it in the galvo's fixture, and so its seed
        self.config.load_plate(self.plate, answer.paths.plate_id, conversions.marked_polylines(answer.paths))

    def publish_batch(self) -> None:
        """Publish the next profiles of the running sweep; at its end, the end-of-sweep message."""
        if self.job is None:
            self.timer.cancel()
            return
        sweep_id, speed, step, began, direction = self.sweep
        for _ in range(self.batch):
            profile = next(self.job, None)
            if profile is None:
                self.job = None
                self.timer.cancel()
                done = SweepDone(sweep_id=sweep_id, profiles=self.published, step_mm=step, speed_mm_s=speed,
                                 direction=[0.0, float(direction), 0.0], complete=True)
                done.stamp = self.get_clock().now().to_msg()
                self.done.publish(done)
                return
            points = profile.points
            # A real sensor measures each profile in its own moving frame: take the travel out again.
            points["y"] -= np.float32(direction * profile.stamp_s * speed)
            stamp = (began + Duration(nanoseconds=int(round(profile.stamp_s * 1e9)))).to_msg()
            self.poses.publish(reported_pose_message(profile.reported_pose, stamp))
            self.points.publish(conversions.cloud_to_msg(points, self.frame_id, stamp))
            self.published += 1


def reported_pose_message(pose: np.ndarray, stamp) -> PoseStamped:
    """Convert a 4x4 sensor pose (mm) to a PoseStamped in the scanner base frame (metres)."""
    message = PoseStamped()
    message.header.stamp = stamp
    message.header.frame_id = "scanner_base"
    message.pose.position.x, message.pose.position.y, message.pose.position.z = (float(v) * 1e-3 for v in pose[:3, 3])
    qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    message.pose.orientation.x, message.pose.orientation.y = float(qx), float(qy)
    message.pose.orientation.z, message.pose.orientation.w = float(qz), float(qw)
    return message


def main(args=None) -> int:
    """Console script ``gls-sim-scanner``."""
    return run_node(SimScannerNode, args)
