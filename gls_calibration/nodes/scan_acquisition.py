"""scan_acquisition: serves ``scan/acquire`` and returns the sweep as one organized cloud.

scan_acquisition: serves ``scan/acquire``; starts a sweep, collects ``scan/points`` profiles and
returns them assembled as one organized cloud in the scanner base frame, each profile placed by the
robot's reported sensor pose (``scan/pose``, PoseStamped, metres, interpolated at the profile's
stamp) when that stream covers the sweep, else by its stamp and the sweep's nominal motion.

Profiles come in the driver's moving sensor frame, in metres (REP 103; ``profile_unit`` "mm" takes a
driver that publishes millimetres). The assembled cloud is in metres too, in the frame ``frame_id``
(default ``scanner``), stamped with the sweep's first profile.

``scan/acquire_standstill`` (same request) asks the scanner for profiles taken with the robot standing
still (``scanner/start_standstill``): placed by the reported pose only, since without travel the time
says nothing about where the sensor stands.
"""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np

from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.request_ids import RESEND_WITH_ID_AFTER_S, new_request_id
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import ServiceCallError
from gls_calibration.scan.sweep import (PoseTrack, ProfileRules, SweepCollector, SweepMotion, nominal_start_pose,
                                        unit_check_distance)
from gls_calibration_msgs.msg import SweepDone
from gls_calibration_msgs.srv import AcquireSweep, StartSweep


PROFILE_UNITS_MM = {"m": conversions.MM_PER_M, "mm": 1.0}
# a profile's median point distance from the sensor outside this window (mm) is not in profile_unit:
# metres read as millimetres give ~0.3 "mm", millimetres read as metres ~300 m (no line scanner ranges so)
RANGE_WINDOW_MM = (10.0, 10000.0)
MAX_TIMEOUT_S = 3600.0     # an hour: longer than any sweep; bounds what a caller can make the node wait
MAX_LENGTH_MM = 10000.0
MAX_SPEED_MM_S = 10000.0
MAX_STEP_MM = 100.0
MALFORMED_GRACE_S = 2.0    # profiles still in flight after the end of sweep: wait this before giving up
MAX_ENDS_KEPT = 16         # ends of sweep remembered during one acquisition, per sweep id and of ids
POSE_GRACE_S = 0.5         # the robot's poses of the last profiles may come after the end of sweep
SCANNER_TOPICS_WAIT_S = 5.0  # before a sweep: how long to wait for the scanner's topics to match (after a restart)


def profile_qos(depth: int) -> QoSProfile:
    """Reliable, deep enough to hold a whole sweep: a profile must never be lost."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


class ScanAcquisitionNode(GlsNode):
    """One sweep at a time; memory bounded by ``max_profiles`` x ``max_points_per_profile``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("scan_acquisition", **kwargs)
        self.max_profiles = self.declare("max_profiles", 4000, "most profiles kept from one sweep",
                                         minimum=1, maximum=100000)
        defaults = ProfileRules()
        self.max_points = self.declare("max_points_per_profile", defaults.max_points,
                                       "most points of one profile; a wider one is dropped (counted), the sweep "
                                       "goes on", minimum=1, maximum=100000)
        field_type = self.declare("profile_field_type", defaults.field_type,
                                  "type the scanner declares for x, y, z, intensity on scan/points: float32 or "
                                  "float64; profiles declaring another are dropped (counted)")
        big_endian = self.declare("profile_big_endian", defaults.big_endian,
                                  "byte order the scanner declares on scan/points (false: little-endian); "
                                  "profiles with the other flag are dropped (counted)")
        self.rules = ProfileRules(field_type=field_type, big_endian=big_endian, max_points=self.max_points)
        self.default_timeout_s = self.declare("timeout_s", 120.0, "default time limit of one sweep (s)",
                                              minimum=0.1, maximum=MAX_TIMEOUT_S)
        unit = self.declare("profile_unit", "m",
                            "unit of x, y, z in the driver's scan/points profiles: m (REP 103) or mm")
        if unit not in PROFILE_UNITS_MM:
            raise ValueError(f"profile_unit must be one of {', '.join(PROFILE_UNITS_MM)}, got {unit!r}")
        self.mm_per_unit = PROFILE_UNITS_MM[unit]
        self.unit = unit
        self.unit_problem = ""                 # the first profile of the sweep not in profile_unit...
        self.wrong_unit = 0                    # ...and how many were not (dropped)
        self.frame_id = self.declare("frame_id", "scanner",
                                     "frame of the assembled cloud: the sensor's nominal pose at the start of a sweep")
        self.use_poses = self.declare("use_pose_stream", True,
                                      "place profiles by the reported sensor pose on scan/pose when it covers "
                                      "the sweep (else by time at the nominal speed)")
        self.collector: Optional[SweepCollector] = None
        self.stamps: dict[float, object] = {}   # stamp message of each kept profile, by its seconds
        self.poses: Optional[PoseTrack] = None
        self.ends: dict[int, list] = {}        # [(end of sweep, arrival)] received while acquiring, by id
        self.end: Optional[tuple] = None       # the end of this node's sweep that was believed, and its arrival
        self.sweep_id: Optional[int] = None    # the sweep this node started; other ends of sweep are ignored
        self.expected_profiles = 0             # what the scanner announced for it
        self.ignored_end = ""                  # why an end of sweep with this sweep's id was not believed
        self.malformed = 0
        self.wrong_format = 0                  # profiles not in the scanner's declared format (self.rules)
        # A sweep this node started whose end never came (the acquisition failed first): its id and until
        # when its end is awaited before the next sweep is asked for, so that a scanner still sweeping
        # does not refuse the next one.
        self.unfinished: Optional[tuple[int, float]] = None
        self.waiting = False                   # an acquisition waits for the unfinished sweep's end
        self.start_client = self.client(StartSweep, "scanner/start_sweep")
        self.standstill_client = self.client(StartSweep, "scanner/start_standstill")
        # The streams one callback at a time, each topic in arrival order (as stream_acquisition): side by
        # side, a later profile could be checked first (the unit problem then named the second profile).
        streams = MutuallyExclusiveCallbackGroup()
        self.points_subscription = self.create_subscription(
            PointCloud2, "scan/points", self.on_profile, profile_qos(self.max_profiles), callback_group=streams)
        self.create_subscription(PoseStamped, "scan/pose", self.on_pose, profile_qos(self.max_profiles),
                                 callback_group=streams)
        self.done_subscription = self.create_subscription(SweepDone, "scan/sweep_done", self.on_sweep_done,
                                                          profile_qos(10), callback_group=streams)
        self.create_service(AcquireSweep, "scan/acquire", self.on_acquire, callback_group=self.reentrant_group)
        self.create_service(AcquireSweep, "scan/acquire_standstill", self.on_acquire_standstill,
                            callback_group=self.reentrant_group)

    def on_profile(self, message: PointCloud2) -> None:
        """Keep a profile of the running sweep; profiles outside a sweep are ignored.

        A profile not in the scanner's declared format (``self.rules``: field type, byte order) or
        malformed (see ``sweep.profile_problem``, or a message that does not hold what its header says)
        is dropped with a throttled warning and counted; it never stops the node.
        Well-formed profiles that are not of the sweep (another wire layout than the sweep's, a
        stamp outside its time window) are kept apart at the end (``SweepCollector.members``).
        """
        collector = self.collector
        if collector is None:
            return
        problem = self.rules.format_problem(
            {field.name: conversions.point_field_type_name(field.datatype) for field in message.fields},
            message.is_bigendian)
        if problem:
            self.wrong_format += 1
            self.get_logger().warning(f"profile dropped ({self.wrong_format} in this sweep): {problem}",
                                      throttle_duration_sec=1.0)
            return
        try:
            stamp = message.header.stamp
            stamp_s = stamp.sec + stamp.nanosec * 1e-9
            layout = (tuple((field.name, field.offset, field.datatype, field.count) for field in message.fields),
                      bool(message.is_bigendian), int(message.point_step))
            points = conversions.cloud_from_msg(message, self.mm_per_unit)
            if self._unit_problem(points, stamp_s):
                return
            kept = collector.add(stamp_s, points, layout)
        except (ValueError, TypeError, AttributeError) as error:
            self.malformed += 1
            self.get_logger().warning(f"malformed profile dropped ({self.malformed} in this sweep): {error}",
                                      throttle_duration_sec=1.0)
            return
        if kept:
            self.stamps[stamp_s] = stamp

    def on_pose(self, message: PoseStamped) -> None:
        """Keep a reported sensor pose of the running sweep (metres -> mm)."""
        poses = self.poses
        if poses is None:
            return
        position, orientation = message.pose.position, message.pose.orientation
        stamp = message.header.stamp
        poses.add(stamp.sec + stamp.nanosec * 1e-9,
                  (1000.0 * position.x, 1000.0 * position.y, 1000.0 * position.z),
                  (orientation.x, orientation.y, orientation.z, orientation.w))

    def on_sweep_done(self, message: SweepDone) -> None:
        """Remember an end of sweep while acquiring; only the one of the sweep this node started counts.

        Kept by id because it may arrive before the scanner's answer that tells the id. The end of an
        unfinished sweep (see ``_wait_for_unfinished``) frees the scanner for the next one.
        """
        unfinished = self.unfinished
        if unfinished is not None and message.sweep_id == unfinished[0]:
            self.unfinished = None
        collector = self.collector
        if collector is None:
            return
        if message.sweep_id == self.sweep_id and self._ignored(message, collector):
            return
        if message.sweep_id not in self.ends and len(self.ends) >= MAX_ENDS_KEPT:
            self.ends.pop(next(iter(self.ends)))
        kept = self.ends.setdefault(message.sweep_id, [])
        if len(kept) >= MAX_ENDS_KEPT:
            kept.pop(0)
        kept.append((message, time.monotonic()))

    @property
    def done(self) -> Optional[SweepDone]:
        """Return the end of the sweep being acquired, once it came and was believed."""
        return None if self.end is None else self.end[0]

    def _ignored(self, done: SweepDone, collector: SweepCollector) -> bool:
        """Return True (with a warning) when ``done``, of this node's sweep, cannot be its end."""
        problem = self._end_problem(done, collector)
        if problem:
            self.ignored_end = f"an end of sweep {done.sweep_id} was ignored: {problem}"
            self.get_logger().warning(self.ignored_end)
        return bool(problem)

    def _members(self, done: SweepDone, collector: SweepCollector):
        """Mask of ``collector``'s profiles that form the sweep ``done`` ends (layout and time window).

        The collector is passed in, not read from the node: the acquisition may end (and drop it)
        in another executor thread while a callback that took it is still running.
        """
        return collector.members(self.rules.stamp_window_s(done.profiles, done.step_mm, done.speed_mm_s))

    def _end_problem(self, done: SweepDone, collector: SweepCollector) -> str:
        """Say why an end of sweep with this sweep's id cannot be its end (empty when it can).

        Its count must be the scanner's announcement when complete, and no less than what already
        came.
        """
        if done.complete and done.profiles != self.expected_profiles:
            return (f"it counts {done.profiles} profiles, complete, but the scanner announced "
                    f"{self.expected_profiles}")
        if done.profiles > self.expected_profiles:
            return f"it counts {done.profiles} profiles, more than the {self.expected_profiles} announced"
        received = int(np.count_nonzero(self._members(done, collector)))
        if not done.complete and received > done.profiles:
            return f"it says the sweep was cut short after {done.profiles} profiles, but {received} came"
        return ""

    async def _wait_for_poses(self, stamps_s: np.ndarray) -> None:
        """Wait up to ``POSE_GRACE_S`` for the reported poses to cover ``stamps_s``, once any came.

        The pose stream and the scanner are separate publishers: the poses of the last profiles may
        arrive after the end of sweep. Without any pose (a driver without a pose stream) nothing is
        awaited; still uncovered after the grace, the sweep is placed by time and the answer says so.
        """
        poses = self.poses
        if poses is None or not len(poses) or poses.covers(stamps_s):
            return
        try:
            await self.wait_for(lambda: poses.covers(stamps_s), POSE_GRACE_S, "poses do not cover the sweep")
        except ServiceCallError:
            self.get_logger().warning(f"the reported pose does not cover the sweep {POSE_GRACE_S:g} s after its "
                                      "end: placed by time")

    def _sweep_over(self) -> bool:
        """Tell whether every profile of the sweep is kept or, after a grace time, accounted for.

        Every profile of the sweep kept (or over the bounds); or, once the end of the sweep is
        ``MALFORMED_GRACE_S`` old, accounted for with the dropped ones (the sweep then fails).

        An end of sweep that contradicts the scanner's announcement or what was received is not
        believed (a spoof): it is forgotten with a warning and the acquisition waits for the real one,
        so that it never returns while the scanner is still sweeping. An end saying the sweep was cut
        short is believed only once ``MALFORMED_GRACE_S`` old with no more profiles than it counts.
        """
        collector = self.collector
        if self.sweep_id is None or collector is None:
            return False
        ends = self.ends.get(self.sweep_id, [])
        ends[:] = [(done, arrived) for done, arrived in ends if not self._ignored(done, collector)]
        if not ends:
            return False
        done, arrived = ends[0]
        if not done.complete and time.monotonic() - arrived < MALFORMED_GRACE_S:
            return False
        self.end = (done, arrived)
        members = int(np.count_nonzero(self._members(done, collector)))
        accounted = members + collector.dropped
        junk = (self.malformed + self.wrong_format + self.wrong_unit + collector.too_wide + len(collector)
                - members)
        return accounted >= done.profiles or (
            accounted + junk >= done.profiles and time.monotonic() - arrived >= MALFORMED_GRACE_S)

    async def on_acquire(self, request, response):
        """Start a sweep, wait for all its profiles, answer with the organized cloud."""
        return await self._acquire(request, response, standstill=False)

    async def on_acquire_standstill(self, request, response):
        """Take profiles standing still as an organized cloud placed by the reported pose.

        Profiles taken standing still (as many as a sweep of the request's length and step), as
        an organized cloud placed by the reported pose; refused without the pose stream.
        """
        if not self.use_poses:
            response.success = False
            response.message = ("a stand-still acquisition needs the reported pose (use_pose_stream is false): "
                                "without travel the time cannot place its profiles")
            return response
        return await self._acquire(request, response, standstill=True)

    async def _acquire(self, request, response, standstill: bool):
        if self.collector is not None or self.waiting:
            response.success = False
            response.message = "a sweep is already being acquired; request refused"
            return response
        problem = request_problem(request)
        if problem:
            response.success, response.message = False, f"request refused: {problem}"
            return response
        timeout_s = request.timeout_s or self.default_timeout_s
        direction = 1 if standstill else request.direction or 1
        if direction not in (1, -1):
            response.success = False
            response.message = f"direction must be +1, -1 or 0 (+1), got {request.direction}"
            return response
        await self._wait_for_unfinished(timeout_s)
        self.collector, self.sweep_id, self.malformed = SweepCollector(self.max_profiles, self.max_points), None, 0
        self.wrong_format, self.wrong_unit, self.unit_problem = 0, 0, ""
        self.poses = PoseTrack(self.max_profiles) if self.use_poses else None
        self.ends.clear()
        self.stamps, self.ignored_end, self.expected_profiles, self.end = {}, "", 0, None
        try:
            await self._wait_for_scanner_topics()
            start_client = self.standstill_client if standstill else self.start_client
            started = await self.call(start_client, StartSweep.Request(
                length_mm=request.length_mm, speed_mm_s=request.speed_mm_s, step_mm=request.step_mm,
                direction=direction, orientation_deg=request.orientation_deg, request_id=new_request_id()),
                timeout_s, resend_after_s=RESEND_WITH_ID_AFTER_S)
            if not started.success:
                raise ServiceCallError(f"the scanner refused the sweep: {started.message}")
            self.sweep_id, self.expected_profiles = started.sweep_id, started.expected_profiles
            # The scanner owns the count (its rounding, its own step); a mismatch is said, not refused.
            announced = self.rules.announcement_problem(started.expected_profiles, request.length_mm,
                                                        request.step_mm)
            if announced:
                self.get_logger().warning(f"sweep {started.sweep_id}: {announced}")
            # Complete when the end of this sweep came and each of its profiles was kept or dropped;
            # the scanner is watched meanwhile, so a scanner that dies fails the sweep at once.
            await self.wait_for(self._sweep_over, timeout_s,
                                self._timeout_message(timeout_s, started.expected_profiles),
                                watch=[start_client])
            done, collector = self.done, self.collector
            if self.unit_problem:
                raise ServiceCallError(f"sweep refused: {self.unit_problem}")
            if not done.complete:
                raise ServiceCallError(f"the sweep was cut short after {done.profiles} profiles")
            if done.profiles != started.expected_profiles:
                raise ServiceCallError(f"the end of sweep {done.sweep_id} counts {done.profiles} profiles; the "
                                       f"scanner announced {started.expected_profiles}")
            members = self._members(done, collector)
            kept = int(np.count_nonzero(members))
            junk = self._junk_phrase(len(collector) - kept, collector)
            if collector.dropped or kept < done.profiles:
                raise ServiceCallError(
                    f"{kept} of {done.profiles} profiles kept: {collector.dropped} over the bound of "
                    f"{self.max_profiles} profiles" + (f"; dropped {junk}" if junk else ""))
            if kept > done.profiles:
                raise ServiceCallError(f"{kept} profiles fit this sweep, its end counts {done.profiles}: profiles "
                                       "from another source are mixed in; sweep refused")
            length_mm = (done.profiles - 1) * done.step_mm
            # standing still the sensor does not travel: its motion only matters when placed by time, refused below
            motion = SweepMotion((0.0, 1.0, 0.0) if standstill else tuple(done.direction), done.speed_mm_s)
            start = nominal_start_pose(length_mm, direction, request.orientation_deg)
            await self._wait_for_poses(collector.stamps_s(members))
            cloud, by_pose = collector.assemble(motion, start, self.poses, members)
            if standstill and not by_pose:
                raise ServiceCallError("the reported pose (scan/pose) does not cover the stand-still profiles: "
                                       "without travel the time cannot place them")
            first_stamp = self.stamps.get(collector.first_stamp_s(members))
        except (ServiceCallError, ValueError) as error:
            response.success = False
            response.message = str(error)
            return response
        finally:
            if self.sweep_id is not None and self.end is None:
                # the scanner accepted a sweep whose end never came: it may still be sweeping
                self.unfinished = (self.sweep_id, time.monotonic() + max(timeout_s, self.default_timeout_s))
            self.collector, self.poses, self.sweep_id = None, None, None
        response.cloud = conversions.cloud_to_msg(cloud, self.frame_id, first_stamp)
        response.placed_by_pose = by_pose
        response.success = True
        response.message = (f"{cloud.shape[0]} profiles of {cloud.shape[1]} points, placed "
                            + ("by the reported pose" if by_pose else "by time at the nominal speed"))
        if junk:
            response.message += f"; dropped {junk}"
        if announced:
            response.message += f"; {announced}"
        return response

    async def _wait_for_unfinished(self, timeout_s: float) -> None:
        """Await the end of a sweep a failed acquisition left running, so that the scanner is free.

        Before a sweep: await the end of the sweep a failed acquisition left running, so that the
        scanner is free. At most ``timeout_s`` (this sweep's limit), and no longer than the larger of
        that acquisition's limit and ``timeout_s`` (the parameter) after it failed; a scanner that leaves
        the graph ends the wait. Then the sweep is asked for anyway (the scanner says if it is busy).
        """
        unfinished = self.unfinished
        if unfinished is None:
            return
        sweep_id, until = unfinished
        remaining_s = min(until - time.monotonic(), timeout_s)
        if remaining_s > 0.0:
            self.waiting = True
            self.get_logger().info(f"waiting up to {remaining_s:.1f} s for the end of sweep {sweep_id}, "
                                   "left running by a failed acquisition")
            try:
                await self.wait_for(lambda: self.unfinished is None, remaining_s, "", watch=[self.start_client])
            except ServiceCallError:
                self.get_logger().warning(f"sweep {sweep_id} never ended; the next sweep is asked for anyway")
            finally:
                self.waiting = False
        self.unfinished = None

    def _unit_problem(self, points: np.ndarray, stamp_s: float) -> bool:
        """Tell whether the profile's median range lies outside ``RANGE_WINDOW_MM``.

        True (the first such profile's problem kept for the answer) when the profile's median point
        distance from the sensor lies outside ``RANGE_WINDOW_MM``: not in ``profile_unit``.
        """
        low, high = RANGE_WINDOW_MM
        median = unit_check_distance(np.stack([points["x"], points["y"], points["z"]], axis=-1), low, high)
        if math.isnan(median) or low <= median <= high:     # no finite point says nothing of the unit
            return False
        self.wrong_unit += 1
        if not self.unit_problem:
            other = "metres" if self.unit == "mm" else "millimetres"
            self.unit_problem = (f"profile at {stamp_s:.6f} s: median point distance {median:.4g} mm is outside "
                                 f"{low:g} to {high:g} mm: the profiles are not in {self.unit} (profile_unit; "
                                 f"{other}?)")
        return True

    def _junk_phrase(self, foreign: int, collector: Optional[SweepCollector]) -> str:
        """Return the profiles dropped from ``collector``'s sweep, by reason ('' when none)."""
        parts = [(self.malformed, "malformed"),
                 (self.wrong_format, f"not in the scanner's declared format ({self.rules.describe()}; parameters "
                                     "profile_field_type, profile_big_endian)"),
                 (collector.too_wide if collector is not None else 0,
                  f"wider than {self.max_points} points (parameter max_points_per_profile)"),
                 (foreign, "not of this sweep (another wire layout or a stamp outside its time window)")]
        return ", ".join(f"{count} profile(s) {why}" for count, why in parts if count)

    async def _wait_for_scanner_topics(self) -> None:
        """Wait until the profile and end-of-sweep subscriptions have matched a publisher.

        Wait (at most ``SCANNER_TOPICS_WAIT_S``) until the profile and end-of-sweep subscriptions
        have matched a publisher.

        A scanner that has just (re)started may send its first profiles before this node's readers
        know its writers; a volatile reader then never gets them (the scanner, for its part, waits
        for its writers to match). The pose stream is optional, so not waited for. No publisher after
        the wait: the sweep is asked for anyway (a driver may create its publishers on demand).
        """
        await self.wait_for_peers((self.points_subscription, self.done_subscription),
                                  lambda subscription: subscription.get_publisher_count(), SCANNER_TOPICS_WAIT_S,
                                  "nobody publishes on", "sweep asked for anyway")

    def _timeout_message(self, timeout_s: float, expected: int):
        def message() -> str:
            collector = self.collector      # read once: the acquisition may end in another thread
            received = len(collector) if collector is not None else 0
            junk = self._junk_phrase(0, collector) if collector is not None else ""
            malformed = f" ({junk} dropped)" if junk else ""
            ignored = f"; {self.ignored_end}" if self.ignored_end else ""
            return (f"sweep not complete after {timeout_s:g} s: {received} of {expected} profiles "
                    f"received{malformed} and no end of sweep{ignored}")
        return message


def request_problem(request) -> str:
    """Why an AcquireSweep request cannot be served (empty string when it can)."""
    limits = (("timeout_s", MAX_TIMEOUT_S), ("length_mm", MAX_LENGTH_MM), ("speed_mm_s", MAX_SPEED_MM_S),
              ("step_mm", MAX_STEP_MM))
    for name, limit in limits:
        value = getattr(request, name)
        if not math.isfinite(value) or value < 0.0 or value > limit:
            return f"{name} must be 0 (the default) or a positive number up to {limit:g}, got {value!r}"
    return ""


def main(args=None) -> int:
    """Console script ``gls-scan-acquisition``."""
    return run_node(ScanAcquisitionNode, args)
