"""sim_robot: the simulated robot of the streaming cell; runs commanded straight flange lines.

Takes a line on ``/motion/line`` (``nav_msgs/Path``, see :mod:`gls_calibration.ros.stream_topics`),
publishes ``/motion/start``, the flange pose it REPORTS (encoders) on ``/tf`` (robot base -> flange)
every ``1 / tf_rate_hz`` s from just before the start to just after the end, then ``/motion/end``.
The fixed frames of ``cell_frames`` go out once on ``/tf_static`` (transient local). The simulated
scanner (:mod:`gls_calibration.nodes.sim_line_scanner`) streams the same motion's profiles: the
simulation computes a motion's profiles and reported poses together
(:class:`~gls_calibration.simulation.line_motion.SimulatedLineMotion`, owned here), so the scanner's
profile rate is this node's ``profile_rate_hz``. Stamps run on from the node clock at the start, as
fast as the subscribers take them (simulated time, not real time): a motion's stamps may lie ahead of
the wall clock when the next line comes, so a line starts at the node clock or, if later, just after
the previous motion's last stamp (its TF margin and the profiles streamed after its end), never
before: motions do not overlap in time, as on a real robot. A line the simulation cannot run is
refused with an error in the log: nothing is published.
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np
from nav_msgs.msg import Path
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from gls_calibration.nodes.sim_scanner import MARKS_RESEND_AFTER_S
from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.service_errors import ServiceCallError
from gls_calibration.ros.sim_parameters import declare_sim_config
from gls_calibration.ros.stream_topics import (LAYOUT, LINE_TOPIC, line_from_msg, static_qos, stream_qos, time_msg,
                                               transform_msg)
from gls_calibration.scan.cell_frames import load_cell_frames
from gls_calibration.simulation.line_motion import LineCommand, MotionRun, SimulatedLineMotion
from gls_calibration.simulation.world import SimulatedCell
from gls_calibration_msgs.srv import GetMarkedPaths

TF_MARGIN_SAMPLES = 2     # TF samples before the start and after the end: a lookup never extrapolates


class SimRobotNode(GlsNode):
    """One line at a time; its TF samples go out in batches from a timer."""

    def __init__(self, **kwargs) -> None:
        super().__init__("sim_robot", **kwargs)
        config = declare_sim_config(self)
        self.tf_rate_hz = self.declare("tf_rate_hz", 250.0, "rate of the reported flange pose on /tf while moving (Hz)",
                                       minimum=1.0, maximum=10000.0)
        rate = self.declare("profile_rate_hz", 150.0, "the simulated scanner's profile rate (Hz): the simulation "
                            "computes a motion's profiles with its poses", minimum=0.1, maximum=100000.0)
        self.batch = self.declare("samples_per_tick", 50, "TF samples published per timer tick", minimum=1)
        path = self.declare("cell_frames", "", "cell frames file (empty: the package's config/cell_frames.yaml)")
        self.frames = load_cell_frames(path or None)
        marks = self.declare("marks_service", "", "the simulated galvo's marks query (sim/marked_paths), asked before "
                             "each line so that the simulated scanner sees the plate's marks (empty: a plain plate)")
        self.marks_client = self.client(GetMarkedPaths, marks) if marks else None
        self.motion = SimulatedLineMotion(SimulatedCell(config), self.frames.flange_to_sensor, rate)
        self.run_listeners: list[Callable[[MotionRun], None]] = []
        self.tf = self.create_publisher(TFMessage, LAYOUT.tf_topic, stream_qos(10000))
        self.static = self.create_publisher(TFMessage, LAYOUT.tf_static_topic, static_qos())
        self.starts = self.create_publisher(Header, LAYOUT.motion_start_topic, stream_qos(10))
        self.ends = self.create_publisher(Header, LAYOUT.motion_end_topic, stream_qos(10))
        self.static.publish(TFMessage(transforms=[
            transform_msg(self.frames.flange, self.frames.sensor, self.frames.flange_to_sensor, 0),
            transform_msg(self.frames.base, self.frames.gls, self.frames.base_to_gls, 0)]))
        self.job: Optional[tuple[MotionRun, np.ndarray, np.ndarray]] = None
        self.free_at_ns = 0     # the next line starts no earlier: after everything stamped for the last one
        self.refused = 0
        group = MutuallyExclusiveCallbackGroup()   # commands and ticks one at a time: samples go out in order
        self.create_subscription(Path, LINE_TOPIC, self.on_line, stream_qos(10), callback_group=group)
        self.timer = self.create_timer(0.001, self.publish_batch, callback_group=group)
        self.timer.cancel()

    async def on_line(self, message: Path) -> None:
        """Run a commanded line (refused, with an error in the log, while one runs or when malformed)."""
        try:
            if self.job is not None:
                raise ValueError("a line is running")
            start, end, duration_s = line_from_msg(message, self.frames.base)
            if self.marks_client is not None:
                await self._load_marks()
            began_ns = max(self.get_clock().now().nanoseconds, self.free_at_ns)
            run = self.motion.run(LineCommand(start, end, duration_s), began_ns)
        except (ValueError, ServiceCallError) as error:
            self.refused += 1
            self.get_logger().error(f"line refused: {error}")
            return
        period_ns = 1e9 / self.tf_rate_hz
        first = -TF_MARGIN_SAMPLES
        last = int(np.ceil((run.end_ns - run.start_ns) / period_ns)) + TF_MARGIN_SAMPLES
        stamps = run.start_ns + np.round(np.arange(first, last + 1) * period_ns).astype(np.int64)
        self.job = (run, stamps, run.flange_at(stamps))
        self.published = 0
        self.free_at_ns = max(int(stamps[-1]), run.streamed_until_ns) + 1
        self.starts.publish(Header(stamp=time_msg(run.start_ns), frame_id=self.frames.base))
        for listener in self.run_listeners:
            listener(run)
        self.timer.reset()

    async def _load_marks(self) -> None:
        """Load the plate's marks as the simulated galvo landed them (the simulation's truth, as sim_scanner does)."""
        answer = await self.call(self.marks_client, GetMarkedPaths.Request(), 10.0, resend_after_s=MARKS_RESEND_AFTER_S)
        self.motion.sim.config.load_plate(self.motion.sim.plate, answer.paths.plate_id,
                                          conversions.marked_polylines(answer.paths))

    def publish_batch(self) -> None:
        """Publish the next TF samples of the running line; after the last, the end of the motion."""
        if self.job is None:
            self.timer.cancel()
            return
        run, stamps, poses = self.job
        stop = min(self.published + self.batch, stamps.size)
        for index in range(self.published, stop):
            self.tf.publish(TFMessage(transforms=[
                transform_msg(self.frames.base, self.frames.flange, poses[index], int(stamps[index]))]))
        self.published = stop
        if stop == stamps.size:
            self.ends.publish(Header(stamp=time_msg(run.end_ns), frame_id=self.frames.base))
            self.job = None
            self.timer.cancel()
