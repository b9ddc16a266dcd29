"""sim_line_scanner: the simulated laser-line scanner of the streaming cell.

As off-the-shelf drivers behave: one ``sensor_msgs/PointCloud2`` per profile on ``/scanner/profile``
while switched on, in its optical frame (``frame_id``), in metres, stamped when taken; nothing else
(no sweep id, no start or end of sweep). ``scanner/enable`` (``std_srvs/SetBool``) switches it on
and off (on at start).

The simulation computes a motion's profiles together with the robot's poses, so this node streams the
profiles of the motions of the :class:`~gls_calibration.nodes.sim_robot.SimRobotNode` it is given
(same process), and a few more after each motion's end (the robot standing at the end), as a
running sensor keeps streaming. Between motions it is silent: the simulation has no profiles there.
"""
from __future__ import annotations

from collections import deque

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import SetBool

from gls_calibration.nodes.sim_robot import SimRobotNode
from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.stream_topics import LAYOUT, stream_qos, time_msg
from gls_calibration.simulation.line_motion import MotionRun


class SimLineScannerNode(GlsNode):
    """Streams the profiles of ``robot``'s motions in batches from a timer."""

    def __init__(self, robot: SimRobotNode, **kwargs) -> None:
        super().__init__("sim_line_scanner", **kwargs)
        self.frame_id = self.declare("frame_id", robot.frames.sensor, "frame of the profiles: the optical frame")
        self.topic = self.declare("topic", LAYOUT.scan_topic, "topic of the profiles")
        self.batch = self.declare("profiles_per_tick", 50, "profiles published per timer tick", minimum=1)
        depth = self.declare("queue_depth", 4000, "profiles the reliable publisher keeps for slow subscribers",
                             minimum=1)
        self.enabled = True
        self.pending: deque[tuple[int, np.ndarray]] = deque()
        self.points = self.create_publisher(PointCloud2, self.topic, stream_qos(depth))
        self.create_service(SetBool, "scanner/enable", self.on_enable)
        self.timer = self.create_timer(0.001, self.publish_batch, callback_group=MutuallyExclusiveCallbackGroup())
        self.timer.cancel()     # ticks only while profiles are pending
        robot.run_listeners.append(self.on_run)

    def on_enable(self, request, response):
        """Switch the stream on or off."""
        self.enabled = bool(request.data)
        response.success, response.message = True, "streaming" if self.enabled else "stopped"
        return response

    def on_run(self, run: MotionRun) -> None:
        """Queue a motion's profiles and the ones after its end (dropped while switched off)."""
        if not self.enabled:
            return
        after_stamps, after_profiles = run.after_profiles()
        self.pending.extend(zip(run.profile_stamps_ns.tolist(), run.profiles_m))
        self.pending.extend(zip(after_stamps.tolist(), after_profiles))
        self.timer.reset()

    def publish_batch(self) -> None:
        """Publish the next profiles of the stream; stop the timer when none wait or the sensor is off."""
        for _ in range(self.batch):
            if not self.pending or not self.enabled:
                self.pending.clear()
                self.timer.cancel()
                return
            stamp, profile = self.pending.popleft()
            points = conversions.xyzi_array(profile[:, :3], profile[:, 3])
            self.points.publish(conversions.array_to_pointcloud2(points, self.frame_id, time_msg(stamp)))
