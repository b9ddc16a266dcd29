"""stream_acquisition: serves ``scan/acquire`` from what real drivers give.

stream_acquisition: serves ``scan/acquire`` (and ``scan/acquire_standstill``) from what real drivers
give: a scanner streaming profiles, the robot's flange pose on TF and the motion contract.

For each request it commands the robot's straight line on ``/motion/line`` (see
:mod:`gls_calibration.ros.stream_topics`), collects the profile stream, ``/tf``, ``/tf_static`` and
the motion's start and end stamps into a :class:`~gls_calibration.scan.bag_io.StreamAssembler` (the code
bag replay runs), and answers with the sweep: the profiles stamped within the motion, each placed
through robot base -> flange -> sensor at its stamp, as one organized cloud in the robot base frame
(metres, like ``scan_acquisition``'s; the manager is unchanged). The frames come from the cell frames
file; the TF buffer is the package's (tf2_ros is not used: the assembler's buffer is the one bag
replay uses, so that a live sweep and its replay agree exactly).

The line: the sensor's nominal sweep (``sweep.nominal_start_pose``) turned into flange poses through
the file's hand-eye. A scanner streams at its own rate (``profile_rate_hz``, the driver's setting),
so a requested step sets the speed: step x rate; without a step the request's speed (or
``default_speed_mm_s``) is used. A stand-still is a line of no length at the marking pose (the middle
of a ``default_length_mm`` sweep), lasting as many profile periods as the request's length has steps.

Before commanding the line it waits (at most 5 s) for the hand-eye, flange -> sensor, on ``/tf_static``:
a new subscriber gets the fixed frames only after discovery, which may lag a service call; without it
the line is not commanded and the request is refused naming the fixed frames received.

Refused (``success`` false, the message naming the problem; the sweep is not used): a profile in
another frame or not in metres, a profile within the motion without a pose of the flange within
``max_pose_age_s`` (counted), a missing frame, a stream that stops mid-sweep, a robot that does not
start or end the line in time. Profiles stamped out of order (older than one already received: late
within the acquisition) are dropped and counted, profiles outside the motion are not used; both counts
are in the message. A profile of a sweep's motion that comes after the sweep was taken is logged and
counted in the next answer's message.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from nav_msgs.msg import Path
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.task import Future
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from gls_calibration.nodes.scan_acquisition import request_problem
from gls_calibration.registration.sweep_plan import ORIENTATIONS_DEG, ORIENTATIONS_TEXT
from gls_calibration.ros import cdr
from gls_calibration.ros.base import GlsNode, take_waiting
from gls_calibration.ros.pointcloud import xyzi_blocks_to_msg
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import ServiceCallError
from gls_calibration.ros.stream_topics import LAYOUT, LINE_TOPIC, line_msg, static_qos, stamp_ns, stream_qos, time_msg
from gls_calibration.scan.bag_io import BagLayout, ReplayLimits, StreamAssembler, SweepPlacement, max_pose_age_ns
from gls_calibration.scan.cell_frames import load_cell_frames
from gls_calibration.scan.sweep import SWEEP_LENGTH_MM, nominal_start_pose
from gls_calibration_msgs.srv import AcquireSweep

ROBOT_WAIT_S = 5.0     # how long to wait for the robot's command subscription to match before commanding
# Messages of a stream taken in one callback (see take_waiting): the executor's wake-up per message was most of
# the node's CPU; 100 profiles are ~5 ms of work, the longest a service request or the other stream waits.
TAKE_AT_ONCE = 100
# A callback that emptied its queue during a sweep lets the stream fill this long, then takes again: rclpy's
# executor spends ~0.2 ms of CPU a wake-up (its wait set rebuilt, the waiting acquisition resumed), more than a
# profile's handling, and a node that keeps up is woken for every message or two (seed 1 with the profiles read
# without copies: 11 000 wake-ups for 47 000 messages, a third of the node's CPU; 1 700 with the wait). The
# wait costs no CPU; the node's other callbacks (a request, the sweep's end) wait for it at most this long.
COALESCE_S = 0.01
# The streams' callbacks end the wait for a sweep's end as soon as they complete it (Session.complete); the
# wait's timer only catches streams gone quiet and the time limit. At POLL_PERIOD_S its wake-ups were two
# thirds of the node's (each rebuilds the executor's wait set and resumes the acquisition).
QUIET_CHECK_S = 0.25


@dataclass
class Session:
    """What one acquisition has received."""

    assembler: StreamAssembler
    newest_profile_ns: int = -1
    newest_tf_ns: int = -1
    out_of_order: int = 0
    profiles: int = 0
    started: bool = False
    end_ns: Optional[int] = None
    last_arrival_s: float = 0.0     # monotonic time of the latest message of the session's streams
    problems: list = field(default_factory=list)
    complete: Future = field(default_factory=Future)    # done once the streams complete the sweep


class StreamAcquisitionNode(GlsNode):
    """One acquisition at a time; memory bounded by ``max_profiles``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("stream_acquisition", **kwargs)
        path = self.declare("cell_frames", "", "cell frames file (empty: the package's config/cell_frames.yaml)")
        self.frames = load_cell_frames(path or None)
        scan_topic = self.declare("scan_topic", LAYOUT.scan_topic, "the scanner driver's profile topic")
        self.rate_hz = self.declare("profile_rate_hz", 150.0, "the scanner driver's profile rate (Hz)",
                                    minimum=0.1, maximum=100000.0)
        self.default_length_mm = self.declare("default_length_mm", SWEEP_LENGTH_MM,
                                              "sweep length when a request says 0", minimum=0.1, maximum=10000.0)
        self.default_speed_mm_s = self.declare("default_speed_mm_s", 15.0, "speed when a request gives neither "
                                               "step nor speed", minimum=0.01, maximum=10000.0)
        self.default_timeout_s = self.declare("default_timeout_s", 120.0, "time limit of a sweep when a request "
                                              "says 0", minimum=0.1, maximum=3600.0)
        # Only a stream that sends nothing after the end waits this long; 1 s closed sweeps early on a
        # loaded 2-core host (the subscriptions' thread starved while the TF of the line was still queued).
        self.end_grace_s = self.declare("end_grace_s", 5.0, "after the motion's end: how long the streams may be "
                                        "quiet before the sweep is taken without a profile and a pose stamped after "
                                        "the end", minimum=0.0, maximum=60.0)
        self.max_profiles = self.declare("max_profiles", 30000, "most profiles kept during one acquisition",
                                         minimum=2)
        self.limits = ReplayLimits(
            max_pose_age_s=self.declare("max_pose_age_s", 0.05, "a profile's newest flange pose may be this old (s)",
                                        minimum=0.0, maximum=10.0),
            max_gap_periods=self.declare("max_gap_periods", 5.0, "a gap of more profile periods in the stream "
                                         "means it stopped", minimum=1.0),
            max_range_m=self.declare("max_range_m", 10.0, "a profile whose median distance exceeds this is not in "
                                     "metres", minimum=0.01))
        self.frame_id = self.declare("frame_id", self.frames.base, "frame of the assembled cloud")
        self.layout = BagLayout(scan_topic=scan_topic, base_frame=self.frames.base, flange_frame=self.frames.flange,
                                sensor_frame=self.frames.sensor, gls_frame=self.frames.gls)
        self.statics: dict[str, TFMessage] = {}
        self.session: Optional[Session] = None
        self.closed: Optional[tuple[int, int]] = None   # the motion of the last sweep taken (ns)
        self.late = 0      # profiles of that motion that came after it was taken
        # the streams one callback at a time, each topic in arrival order: a profile's order and the newest
        # stamps mean what they say (a multi-threaded executor would otherwise run them side by side)
        # The two fast streams arrive serialised (raw): read by ros/cdr without rclpy's message objects, the point
        # data a view of the received bytes; a callback takes what queued meanwhile (TAKE_AT_ONCE).
        group = MutuallyExclusiveCallbackGroup()
        depth = self.max_profiles
        self.profile_subscription = self.create_subscription(PointCloud2, scan_topic, self.on_profile,
                                                             stream_qos(depth), callback_group=group, raw=True)
        self.tf_subscription = self.create_subscription(TFMessage, LAYOUT.tf_topic, self.on_tf, stream_qos(depth),
                                                        callback_group=group, raw=True)
        self.create_subscription(TFMessage, LAYOUT.tf_static_topic, self.on_tf_static, static_qos(),
                                 callback_group=group)
        self.create_subscription(Header, LAYOUT.motion_start_topic, self.on_start, stream_qos(10), callback_group=group)
        self.create_subscription(Header, LAYOUT.motion_end_topic, self.on_end, stream_qos(10), callback_group=group)
        self.line = self.create_publisher(Path, LINE_TOPIC, stream_qos(10))
        self.create_service(AcquireSweep, "scan/acquire", self.on_acquire, callback_group=self.reentrant_group)
        self.create_service(AcquireSweep, "scan/acquire_standstill", self.on_acquire_standstill,
                            callback_group=self.reentrant_group)

    # --- the streams ------------------------------------------------------------------------------

    def _add(self, session: Session, topic: str, message) -> None:
        try:
            session.assembler.add(topic, message)
        except ValueError as error:
            session.problems.append(str(error))

    def on_profile(self, raw: bytes) -> None:
        """Keep the profiles (serialised PointCloud2) of the running acquisition, this one and those queued.

        One stamped before the newest is dropped and counted.
        """
        self._profile(raw)
        self._take(self.profile_subscription, self._profile)
        self._signal_complete()

    def _profile(self, raw: bytes) -> None:
        session = self.session
        try:
            stamp = cdr.header_stamp_ns(raw)
        except ValueError as error:
            self._malformed(session, f"a profile on {self.layout.scan_topic}: {error}")
            return
        if session is None:
            if self.closed is not None and self.closed[0] <= stamp <= self.closed[1]:
                self.late += 1      # of the sweep already taken: said in the next answer
                self.get_logger().warning(f"a profile stamped {stamp} ns, within the last sweep's motion, came after "
                                          "the sweep was taken: not used", throttle_duration_sec=1.0)
            return
        if stamp <= session.newest_profile_ns:
            session.out_of_order += 1
            return
        session.newest_profile_ns = stamp
        session.last_arrival_s = time.monotonic()
        session.profiles += 1
        if session.profiles > self.max_profiles:
            if session.profiles == self.max_profiles + 1:
                session.problems.append(f"more than {self.max_profiles} profiles (parameter max_profiles) came "
                                        "during the acquisition")
            return
        try:
            message = cdr.read_pointcloud2(raw)
        except ValueError as error:
            session.problems.append(f"a profile on {self.layout.scan_topic}: {error}")
            return
        self._add(session, self.layout.scan_topic, message)

    def _malformed(self, session: Optional[Session], problem: str) -> None:
        """Note a message that is not what its topic carries: a problem of the running sweep, else a warning."""
        if session is not None:
            session.problems.append(problem)
        else:
            self.get_logger().warning(problem, throttle_duration_sec=1.0)

    def on_tf(self, raw: bytes) -> None:
        """Add the TF messages (serialised), this one and those queued, to the running sweep's buffer.

        Ignored between sweeps.
        """
        self._tf(raw)
        self._take(self.tf_subscription, self._tf)
        self._signal_complete()

    def _take(self, subscription, handle) -> None:
        """Handle what queued on ``subscription``; during a sweep, when that emptied it, again after ``COALESCE_S``."""
        taken = 0
        for waiting in take_waiting(subscription, TAKE_AT_ONCE):
            handle(waiting)
            taken += 1
        if taken < TAKE_AT_ONCE and self.session is not None:
            time.sleep(COALESCE_S)
            for waiting in take_waiting(subscription, TAKE_AT_ONCE):
                handle(waiting)

    def _tf(self, raw: bytes) -> None:
        session = self.session
        if session is None:
            return
        session.last_arrival_s = time.monotonic()
        try:
            message = cdr.read_tf_message(raw)
        except ValueError as error:
            session.problems.append(f"a message on {LAYOUT.tf_topic}: {error}")
            return
        for transform in message.transforms:
            if transform.child_frame_id == self.layout.flange_frame:
                session.newest_tf_ns = max(session.newest_tf_ns, stamp_ns(transform.header.stamp))
        self._add(session, LAYOUT.tf_topic, message)

    def on_tf_static(self, message: TFMessage) -> None:
        """Keep the fixed frames (the latest per child frame) for every acquisition."""
        for transform in message.transforms:
            self.statics[transform.child_frame_id] = TFMessage(transforms=[transform])
        session = self.session      # read once (see _complete)
        if session is not None:
            self._add(session, LAYOUT.tf_static_topic, message)

    def on_start(self, message: Header) -> None:
        """Note that the robot started the commanded line."""
        session = self.session
        if session is None or session.started:
            return
        session.started = True
        self._add(session, LAYOUT.motion_start_topic, message)
        self._signal_complete()

    def on_end(self, message: Header) -> None:
        """Note the stamp at which the robot ended the commanded line."""
        # The end may come before the start: DDS keeps the order within a topic, not across topics.
        session = self.session
        if session is None or session.end_ns is not None:
            return
        session.end_ns = stamp_ns(message.stamp)
        session.last_arrival_s = time.monotonic()
        self._add(session, LAYOUT.motion_end_topic, message)
        self._signal_complete()

    # --- the service ------------------------------------------------------------------------------

    async def on_acquire(self, request, response):
        """Command the line, collect the streams, answer with the assembled sweep."""
        return await self._acquire(request, response, standstill=False)

    async def on_acquire_standstill(self, request, response):
        """Profiles taken with the robot standing at the middle of the sweep (a line of no length)."""
        return await self._acquire(request, response, standstill=True)

    def _line(self, request, standstill: bool) -> tuple[np.ndarray, np.ndarray, float]:
        """Start and end flange poses (mm) and duration (s) of the request's line; ValueError naming a problem."""
        problem = request_problem(request)
        if problem:
            raise ValueError(f"request refused: {problem}")
        length = request.length_mm or self.default_length_mm
        direction = 1 if standstill else request.direction or 1
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1, -1 or 0 (+1), got {request.direction}")
        if request.orientation_deg not in ORIENTATIONS_DEG or (standstill and request.orientation_deg != 0.0):
            raise ValueError(f"orientation_deg must be {ORIENTATIONS_TEXT} (0 standing still), "
                             f"got {request.orientation_deg:g}")
        speed = request.step_mm * self.rate_hz if request.step_mm else request.speed_mm_s or self.default_speed_mm_s
        start = nominal_start_pose(length, direction, request.orientation_deg)
        end = start.copy()
        if standstill:     # at the marking pose: the middle of the default sweep; the request sets the count
            step = request.step_mm or speed / self.rate_hz
            start = nominal_start_pose(self.default_length_mm)
            start[:3, 3] += 0.5 * self.default_length_mm * start[:3, 1]
            end = start
            duration = math.floor(length / step + 1e-9) / self.rate_hz
        else:
            end[:3, 3] += direction * length * start[:3, 1]
            duration = length / speed
        to_flange = np.linalg.inv(self.frames.flange_to_sensor)
        return start @ to_flange, end @ to_flange, duration

    def _hand_eye_known(self) -> bool:
        """Tell whether the fixed frames received link the sensor frame to the flange (child -> parent)."""
        frame, seen = self.frames.sensor, set()
        while frame != self.frames.flange:
            if frame in seen or frame not in self.statics:
                return False
            seen.add(frame)
            frame = self.statics[frame].transforms[0].header.frame_id
        return True

    def _no_hand_eye_message(self) -> str:
        known = ", ".join(f"{message.transforms[0].header.frame_id} -> {child}"
                          for child, message in sorted(self.statics.items())) or "none"
        return (f"no fixed transform from {self.frames.flange} to {self.frames.sensor} on {LAYOUT.tf_static_topic} "
                f"within {ROBOT_WAIT_S:g} s (fixed frames received: {known}); line not commanded")

    def _complete(self) -> bool:
        """Tell whether the motion's streams are complete or quiet for ``end_grace_s``.

        The motion ended and a profile and a flange pose stamped after its end came, or the streams have
        been quiet for ``end_grace_s`` since.
        """
        session = self.session      # read once: the acquisition may close it in another executor thread
        if session is None or session.end_ns is None or not session.started:
            return False
        if time.monotonic() - session.last_arrival_s >= self.end_grace_s:
            return True
        return session.newest_profile_ns > session.end_ns and session.newest_tf_ns >= session.end_ns

    async def _acquire(self, request, response, standstill: bool):
        if self.session is not None:
            response.success, response.message = False, "a sweep is already being acquired; request refused"
            return response
        late, self.late = self.late, 0
        response = await self._answer(request, response, standstill)
        if late:
            response.message += f"; {late} profile(s) of the previous sweep came after it was taken (late, not used)"
        return response

    async def _answer(self, request, response, standstill: bool):
        try:
            start, end, duration = self._line(request, standstill)
        except ValueError as error:
            response.success, response.message = False, str(error)
            return response
        timeout_s = request.timeout_s or self.default_timeout_s
        try:
            # /tf_static reaches a new subscriber after discovery, which may lag a service call on a loaded
            # host (seen in CI: a sweep refused for a hand-eye that came a moment later): the line waits for it
            await self.wait_for(self._hand_eye_known, ROBOT_WAIT_S, self._no_hand_eye_message)
        except ServiceCallError as error:
            response.success, response.message = False, str(error)
            return response
        session = Session(StreamAssembler(self.layout, self.limits, "stream"))
        for message in list(self.statics.values()):    # a copy: the static subscription may add meanwhile
            self._add(session, LAYOUT.tf_static_topic, message)
        self.session = session
        try:
            await self.wait_for_peers((self.line,), lambda publisher: publisher.get_subscription_count(),
                                      ROBOT_WAIT_S, "nobody subscribes to", "line commanded anyway")
            self.line.publish(line_msg(self.frames.base, start, end, duration))
            await self.wait_for(self._complete, timeout_s, lambda: self._timeout_message(timeout_s),
                                wake=session.complete, period_s=QUIET_CHECK_S)
            self.session = None     # closed: what comes from now on is not added while the sweep is assembled
            if session.assembler.ends:
                self.closed = (session.assembler.starts[-1], session.assembler.ends[-1])
            placement = self._placement(session)
        except (ServiceCallError, ValueError) as error:
            response.success, response.message = False, str(error)
            return response
        finally:
            self.session = None
        # the profiles placed a block of rows at a time straight into the message (the sweep's float64
        # arrays are never made)
        height, width = placement.shape
        response.cloud = xyzi_blocks_to_msg(height, width, placement.place_rows, self.frame_id,
                                            time_msg(int(placement.stamps_ns[0])))
        response.placed_by_pose = True
        response.success = True
        outside = session.profiles - session.out_of_order - height
        response.message = (f"{height} profiles of {width} points, placed through "
                            f"{self.layout.base_frame} -> {self.layout.flange_frame} -> {self.layout.sensor_frame}; "
                            f"{max(outside, 0)} profile(s) outside the motion not used; "
                            f"{session.out_of_order} out of order dropped")
        return response

    def _placement(self, session: Session) -> SweepPlacement:
        """Return the sweep's profiles with their poses; ValueError naming the first problem of the streams."""
        try:
            session.assembler.flush()       # the flange poses into the TF buffer (a bad one is a problem)
        except ValueError as error:
            session.problems.append(str(error))
        if session.problems:
            more = f" (and {len(session.problems) - 1} more problem(s))" if len(session.problems) > 1 else ""
            raise ValueError(f"sweep refused: {session.problems[0]}{more}")
        assembler = session.assembler
        start, end = assembler.starts[-1], assembler.ends[-1]
        inside = [stamp for stamp, _ in assembler.profiles if start <= stamp <= end]
        _, failures = assembler.buffer.try_lookup_many(self.layout.base_frame, self.layout.sensor_frame,
                                                       np.array(inside, dtype=np.int64),
                                                       max_pose_age_ns(self.limits), "stream")
        unplaced = [failure for failure in failures if failure is not None]
        if unplaced:
            raise ValueError(f"sweep refused: {len(unplaced)} of {len(inside)} profiles within the motion have no pose "
                             f"({unplaced[0]})")
        return assembler.take_last_placement()

    def _signal_complete(self) -> None:
        """Wake the acquisition waiting for the running sweep once its streams are complete (:meth:`_complete`)."""
        session = self.session      # read once (see _complete)
        if session is not None and not session.complete.done() and self._complete():
            session.complete.set_result(None)

    def _timeout_message(self, timeout_s: float) -> str:
        session = self.session
        if session is None or not session.started:
            return f"the robot did not start the line within {timeout_s:g} s (nothing on {LAYOUT.motion_start_topic})"
        if session.end_ns is None:
            return (f"the robot did not end the line within {timeout_s:g} s (nothing on {LAYOUT.motion_end_topic}); "
                    f"{session.profiles} profile(s) received")
        return f"the sweep did not complete within {timeout_s:g} s"


def main(args=None) -> int:
    """Console script ``gls-stream-acquisition``."""
    return run_node(StreamAcquisitionNode, args)
