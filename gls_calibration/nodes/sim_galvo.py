"""sim_galvo: the simulated galvo head and the plate it marks.

Serves ``galvo/mark`` (what a real galvo driver serves) and, for the simulation only,
``sim/landing_positions`` (where commands really land), ``sim/marked_paths`` (the plate's marks, read
by the simulated scanner) and ``sim/exchange_plate`` (load a clean plate).
"""
from __future__ import annotations

import numpy as np
from std_srvs.srv import Trigger

from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.request_ids import AnsweredRequests
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import answers_errors
from gls_calibration.ros.sim_parameters import declare_sim_config
from gls_calibration.simulation.head import TruthHead
from gls_calibration_msgs.msg import MarkedPaths
from gls_calibration_msgs.srv import GetMarkedPaths, LandingPositions, MarkPolylines


class SimGalvoNode(GlsNode):
    """Truth head with the configured defects; marks accumulate on the loaded plate."""

    def __init__(self, **kwargs) -> None:
        super().__init__("sim_galvo", **kwargs)
        self.config = declare_sim_config(self)
        self.plate = self.config.make_plate()
        self.head = TruthHead(self.config.geometry, self.config.effects, plate=self.plate,
                              mark_speed_mm_s=self.config.mark_speed_mm_s, jump_time_s=self.config.jump_time_s)
        self.landed: list[np.ndarray] = []
        self.times: list[np.ndarray] = []
        self.max_points = self.declare("max_points", 5_000_000, "most points of one marking job",
                                       minimum=1, maximum=100_000_000)
        self.answered = AnsweredRequests()    # on_mark runs one at a time (the default group)
        self.create_service(MarkPolylines, "galvo/mark", self.on_mark)
        self.create_service(LandingPositions, "sim/landing_positions", self.on_landing_positions)
        self.create_service(GetMarkedPaths, "sim/marked_paths", self.on_marked_paths)
        self.create_service(Trigger, "sim/exchange_plate", self.on_exchange_plate)

    def on_mark(self, request, response):
        """Mark every polyline; ``success=false`` with the reason on malformed or unreachable ones.

        A repeated request id gets the first answer again and marks nothing.
        """
        return self.answered.answer(request.request_id, lambda: self._mark(request, response))

    def _mark(self, request, response):
        alpha_x = conversions.float64_array(request.alpha_x)
        alpha_y = conversions.float64_array(request.alpha_y)
        focus = conversions.float64_array(request.focus_shift)
        starts = np.asarray(request.polyline_starts, dtype=np.int64)
        problem = _polyline_problem(alpha_x, alpha_y, focus, starts, self.config.geometry)
        if len(alpha_x) > self.max_points:
            problem = f"{len(alpha_x)} points refused: at most {self.max_points} per job (parameter max_points)"
        if problem:
            response.success, response.message = False, problem
            return response
        began = self.head.clock_s
        for ax, ay in zip(np.split(alpha_x, starts[1:]), np.split(alpha_y, starts[1:])):
            self.landed.append(self.head.mark(ax, ay))
            self.times.append(self.head.log[-1].vertex_times)
        response.success = True
        response.duration_s = self.head.clock_s - began
        response.message = f"{len(starts)} polylines marked in {response.duration_s:.2f} s"
        return response

    @answers_errors(ValueError)
    def on_landing_positions(self, request, response):
        """Where the commands land on the plate with the true head (gls frame, mm)."""
        alpha_x = conversions.float64_array(request.alpha_x)
        alpha_y = conversions.float64_array(request.alpha_y)
        t = conversions.float64_array(request.t)
        if len(alpha_x) != len(alpha_y) or (len(t) and len(t) != len(alpha_x)):
            response.success = False
            response.message = "alpha_x, alpha_y (and t when given) must have the same length"
            return response
        if not (np.all(np.isfinite(alpha_x)) and np.all(np.isfinite(alpha_y)) and np.all(np.isfinite(t))):
            response.success, response.message = False, "alpha_x, alpha_y and t must be finite"
            return response
        if len(alpha_x) > self.max_points:
            response.success = False
            response.message = f"{len(alpha_x)} points refused: at most {self.max_points} (parameter max_points)"
            return response
        landed = self.head.land(alpha_x, alpha_y, t if len(t) else None)
        response.x, response.y, response.z = (conversions.float64_sequence(landed[:, i]) for i in range(3))
        response.success, response.message = True, f"{len(landed)} landing positions"
        return response

    def on_marked_paths(self, request, response):
        """Answer with the marks of the loaded plate."""
        points = np.vstack(self.landed) if self.landed else np.empty((0, 3))
        starts = np.cumsum([0] + [len(path) for path in self.landed[:-1]]) if self.landed else []
        response.paths = MarkedPaths(
            plate_id=self.plate.plate_id, x=conversions.float64_sequence(points[:, 0]),
            y=conversions.float64_sequence(points[:, 1]), z=conversions.float64_sequence(points[:, 2]),
            t=conversions.float64_sequence(np.concatenate(self.times) if self.times else []),
            polyline_starts=conversions.uint32_sequence(starts),
            spot_width_mm=self.config.plate.line_width_fwhm_mm)
        response.success, response.message = True, f"{len(self.landed)} marked polylines"
        return response

    def on_exchange_plate(self, request, response):
        """Load a clean plate; the marking clock runs on (the head stays warm)."""
        plate_id = self.config.load_plate(self.plate, self.plate.plate_id + 1)
        self.landed.clear()
        self.times.clear()
        response.success, response.message = True, f"clean plate {plate_id} loaded"
        return response


def _polyline_problem(alpha_x, alpha_y, focus, starts, geometry) -> str:
    """Why a marking request cannot be executed, or an empty string."""
    count = len(alpha_x)
    if count == 0:
        return "no points to mark"
    if len(alpha_y) != count or len(focus) != count:
        return f"alpha_x, alpha_y and focus_shift must have the same length, got {count}, {len(alpha_y)}, {len(focus)}"
    if len(starts) == 0 or starts[0] != 0 or np.any(np.diff(starts) < 1) or starts[-1] >= count:
        return "polyline_starts must begin with 0 and increase strictly within the point count"
    if not (np.all(np.isfinite(alpha_x)) and np.all(np.isfinite(alpha_y)) and np.all(np.isfinite(focus))):
        return "commands contain NaN or infinite values"
    limit = geometry.mirror_limit_rad
    if np.any(np.abs(alpha_x) > limit) or np.any(np.abs(alpha_y) > limit):
        return "commands beyond the mirror limits"
    if np.any(np.abs(focus) > geometry.focus_range_mm):
        return "focus shift beyond the focus range"
    return ""


def main(args=None) -> int:
    """Console script ``gls-sim-galvo``."""
    return run_node(SimGalvoNode, args)
