"""calibration_manager: serves ``calibrate`` (an action with feedback and cancel, and a service for
simple clients) and ``explain_deviations``, publishes progress.

It implements the procedure's ``Cell`` with service calls to the scanner, the galvo and the
processing nodes; the flow itself is ``gls_calibration.procedure``. A run's candidate calibration
is evaluated here, in-process: the correction node keeps serving the active calibration until the
run has succeeded and the candidate is activated.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
import time
import traceback
from typing import Callable, Optional

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from gls_calibration import discrepancy, kinematics, procedure
from gls_calibration.nodes import conversions, rviz
from gls_calibration.calibration_record import (build_record, correction_from_record, record_fiducials,
                                                record_models, save_candidate)
from gls_calibration.correction import Correction
from gls_calibration.nodes.base import SERVER_WAIT_S, GlsNode, ServiceCallError, answers_errors, run_node
from gls_calibration.nodes.deadlines import declare_deadlines
from gls_calibration.nodes.request_ids import RESEND_WITH_ID_AFTER_S, new_request_id
from gls_calibration.nodes.diagnostics import NOMINAL_SUMMARY, Health, publish_diagnostics, record_summary, with_age
from gls_calibration.nodes.head_parameters import declare_head_geometry, declare_scanner_to_gls
from gls_calibration.outcome import RunSummary, summarise
from gls_calibration.persistence import CalibrationFileError, CalibrationStore
from gls_calibration.report import json_safe
from gls_calibration.run_report import write_outcome_report
from gls_calibration.stated_accuracy import SELF_CONSISTENCY, load_chain_check
from gls_calibration.sweep_plan import CellTimeModel, parse_plan, plan_label
from gls_calibration_msgs.action import Calibrate as CalibrateAction
from gls_calibration_msgs.msg import CalibrationProgress
from gls_calibration_msgs.srv import (AcquireSweep, Calibrate, CorrectSetpoints, EstimatePlatePose,
                                      ExplainDeviations, GetMarkedPaths, LoadCalibration,
                                      MarkPolylines, MeasureFiducials, TrainCorrection)


class CalibrationCanceled(Exception):
    """The client canceled the run; raised at the next step boundary (the message names the stage)."""


class ServiceCell:
    """The procedure's Cell, reached through the services of the other nodes.

    A candidate calibration loaded by the procedure is evaluated here (``correct``), never by the
    correction node, which serves only the active calibration to everybody else.
    """

    def __init__(self, node: "CalibrationManager") -> None:
        self.node = node
        self.candidate: Optional[Correction] = None
        self.timeout_s = node.service_timeout_s
        self.deadlines = node.deadlines
        self.acquire = node.client(AcquireSweep, "scan/acquire")
        self.acquire_still = node.client(AcquireSweep, "scan/acquire_standstill")
        self.pose = node.client(EstimatePlatePose, "plate_pose/estimate")
        self.fiducials = node.client(MeasureFiducials, "fiducials/measure")
        # The marking grid's ring points are a large request: on the batch name, its answer does not
        # hold up other clients' single targets (see the correction node).
        self.corrector = node.client(CorrectSetpoints, "correct_setpoints_batch")
        self.loader = node.client(LoadCalibration, "correction/load")
        self.galvo = node.client(MarkPolylines, "galvo/mark")
        self.trainer = node.client(TrainCorrection, "rbf/train")
        self.exchange = node.client(Trigger, node.plate_exchange_service) if node.plate_exchange_service else None
        self.truth = node.client(GetMarkedPaths, node.ground_truth_service) if node.ground_truth_service else None

    async def _checked(self, client, request, timeout_s: Optional[float] = None, *, idempotent: bool = True,
                       resend_after_s: Optional[float] = None):
        # Only a request that may safely be served twice is sent again: an idempotent one, or one whose
        # id lets its server answer a repeat without doing the work again (``resend_after_s``); never
        # a sweep request (scan_acquisition sends the scanner's request itself) or a plate exchange.
        if resend_after_s is None and idempotent:
            resend_after_s = self.node.resend_after_s
        response = await self.node.call(client, request, timeout_s or self.timeout_s, resend_after_s=resend_after_s)
        if not response.success:
            raise procedure.CalibrationError(f"{client.srv_name}: {response.message}")
        return response

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0):
        deadlines = self.deadlines
        sweep_s = deadlines.sweep_s()
        request = AcquireSweep.Request(timeout_s=sweep_s, length_mm=deadlines.sweep_length_mm,
                                       speed_mm_s=deadlines.sweep_speed_mm_s, step_mm=step_mm,
                                       direction=int(direction), orientation_deg=float(orientation_deg))
        # scan_acquisition gives up at sweep_s and answers; the margin is for that answer.
        response = await self._checked(self.acquire, request, sweep_s + deadlines.margin_s, idempotent=False)
        if response.placed_by_pose != self.node.settings.profiles_placed_by_pose:
            self.node.get_logger().warning(
                f"profiles were placed {'by pose' if response.placed_by_pose else 'by time'} but "
                f"sweep.placed_by_pose is {self.node.settings.profiles_placed_by_pose}: the error separation "
                "trusts the wrong scale; set the parameter to match the scanner driver")
        return response.cloud  # forwarded as it came: the processing nodes convert it themselves

    async def acquire_standstill(self, profiles: int):
        deadlines = self.deadlines
        step_mm = self.node.settings.marked_sweep_step_mm   # sets the profile rate, as in a sweep at this step
        request = AcquireSweep.Request(timeout_s=deadlines.sweep_s(), length_mm=(int(profiles) - 1) * step_mm,
                                       speed_mm_s=deadlines.sweep_speed_mm_s, step_mm=step_mm)
        response = await self._checked(self.acquire_still, request, deadlines.sweep_s() + deadlines.margin_s,
                                       idempotent=False)
        return response.cloud

    async def estimate_plate_pose(self, cloud):
        response = await self._checked(self.pose, EstimatePlatePose.Request(cloud=cloud))
        return conversions.plate_pose_from_msg(response.pose)

    async def measure_fiducials(self, cloud, pose, expected_count):
        request = MeasureFiducials.Request(cloud=cloud, pose=conversions.plate_pose_to_msg(pose),
                                           expected_count=int(expected_count),
                                           ring_radii_mm=[float(r) for r in self.node.settings.ring_radii_mm])
        response = await self._checked(self.fiducials, request)
        return conversions.fiducials_from_response(response, pose)

    async def correct(self, x, y, z):
        if self.candidate is not None:
            return self.candidate.correct(x, y, z)
        request = CorrectSetpoints.Request(x=conversions.float64_sequence(x), y=conversions.float64_sequence(y),
                                           z=conversions.float64_sequence(z))
        return conversions.setpoints_from_response(await self._checked(self.corrector, request))

    async def mark(self, alpha_x, alpha_y, focus_shift, polyline_starts):
        request = MarkPolylines.Request(alpha_x=alpha_x, alpha_y=alpha_y, focus_shift=focus_shift,
                                        polyline_starts=np.asarray(polyline_starts, dtype=np.uint32),
                                        request_id=new_request_id())
        xy = np.column_stack(kinematics.forward(self.node.geometry, request.alpha_x, request.alpha_y))
        # The job's id lets the driver tell a repeat from a new job: it is sent again, never marked twice.
        response = await self._checked(self.galvo, request, self.deadlines.marking_s(xy, polyline_starts),
                                       resend_after_s=RESEND_WITH_ID_AFTER_S)
        return response.duration_s

    async def train(self, landed_xy, corrections):
        request = TrainCorrection.Request(
            x=conversions.float64_sequence(landed_xy[:, 0]), y=conversions.float64_sequence(landed_xy[:, 1]),
            dx=conversions.float64_sequence(corrections[:, 0]), dy=conversions.float64_sequence(corrections[:, 1]))
        response = await self._checked(self.trainer, request)
        return conversions.trained_model_from_response(response)

    async def load_calibration(self, path: str) -> None:
        """Evaluate the candidate ``path`` here from now on; the correction node does not see it."""
        self.candidate = correction_from_record(self.node.store.load(Path(path)), self.node.geometry)

    async def reload_active(self) -> None:
        """Correct through the active calibration again (the correction node's): drop the candidate."""
        self.candidate = None

    async def reload_correction_node(self, server_wait_s: float = SERVER_WAIT_S) -> str:
        """Make the correction node serve the store's (newly) active calibration; its answer."""
        response = await self.node.call(self.loader, LoadCalibration.Request(file=""), self.timeout_s,
                                        server_wait_s=server_wait_s, resend_after_s=self.node.resend_after_s)
        if not response.success:
            raise procedure.CalibrationError(f"{self.loader.srv_name}: {response.message}")
        return response.message

    async def exchange_plate(self) -> None:
        if self.exchange is None:
            raise procedure.CalibrationError(
                "a fresh plate is needed (second iteration or validation) but no plate_exchange_service "
                "is configured")
        await self._checked(self.exchange, Trigger.Request(), idempotent=False)

    def points_and_intensities(self, cloud):
        return conversions.cloud_arrays_from_msg(cloud)

    async def true_marks(self):
        if self.truth is None:
            return None
        paths = (await self._checked(self.truth, GetMarkedPaths.Request())).paths
        points = np.column_stack([conversions.float64_array(paths.x), conversions.float64_array(paths.y),
                                  conversions.float64_array(paths.z)])
        return np.split(points, np.asarray(paths.polyline_starts[1:], dtype=int))


class CalibrationManager(GlsNode):
    """Runs calibrations on request; refuses a second request while one runs."""

    def __init__(self, **kwargs) -> None:
        super().__init__("calibration_manager", **kwargs)
        self.geometry = declare_head_geometry(self)
        scanner_to_gls = declare_scanner_to_gls(self)
        self.deadlines = declare_deadlines(self)
        defaults = procedure.ProcedureSettings()
        self.settings = procedure.ProcedureSettings(
            grid_per_side=self.declare("grid.per_side", defaults.grid_per_side,
                                       "fiducials per side of the square grid", minimum=3, maximum=101),
            grid_size_mm=self.declare("grid.size_mm", defaults.grid_size_mm, "side of the fiducial grid (mm)",
                                      minimum=1.0, maximum=1000.0),
            ring_radii_mm=tuple(self.declare("grid.ring_radii_mm", list(defaults.ring_radii_mm),
                                             "radii of the two concentric rings of a fiducial (mm)")),
            plain_sweep_step_mm=self.declare("sweep.plain_step_mm", defaults.plain_sweep_step_mm,
                                             "profile spacing of the sweep of the plain plate (mm)",
                                             minimum=0.01, maximum=10.0),
            plain_sweeps=self.declare("sweep.plain_repeats", defaults.plain_sweeps,
                                      "sweeps of the plain plate whose poses are averaged: the robot's path "
                                      "error in each sets the plate height, hence the field's scale",
                                      minimum=1, maximum=20),
            standstill_height=self.declare("sweep.standstill_height", defaults.standstill_height,
                                           "take the plate height from profiles taken with the robot standing "
                                           "still at the marking pose (scan/acquire_standstill), not from the "
                                           "sweeps, whose path error scales the marked field"),
            marked_sweep_step_mm=self.declare("sweep.marked_step_mm", defaults.marked_sweep_step_mm,
                                              "profile spacing of the sweep of the marked plate (mm)",
                                              minimum=0.01, maximum=1.0),
            scanner_to_gls=scanner_to_gls,
            tolerance_rms_mm=self.declare("tolerance_rms_mm", defaults.tolerance_rms_mm,
                                          "no training when the measured RMS deviation is within this (mm)",
                                          minimum=0.0),
            min_found_fraction=self.declare("min_found_fraction", defaults.min_found_fraction,
                                            "fail when fewer fiducials than this fraction are found",
                                            minimum=0.0, maximum=1.0),
            max_outlying_points=self.declare(
                "max_outlying_points", defaults.max_outlying_points, "a plain plate with more points than this "
                "beyond mark_check_sigmas of its texture carries old marks: refused unless forced", minimum=0),
            mark_check_sigmas=self.declare("mark_check_sigmas", defaults.mark_check_sigmas,
                                           "robust standard deviations of the plate texture beyond which a "
                                           "point looks like a mark", minimum=1.0, maximum=100.0),
            max_cluster_points=self.declare(
                "max_cluster_points", defaults.max_cluster_points, "a plain plate with more points than this "
                "beyond mark_cluster_sigmas within one fiducial's extent carries old marks", minimum=0),
            mark_cluster_sigmas=self.declare("mark_cluster_sigmas", defaults.mark_cluster_sigmas,
                                             "robust standard deviations of the plate texture beyond which a "
                                             "point counts towards a cluster of marks", minimum=1.0, maximum=100.0),
            measurement_uncertainty_mm=self.declare(
                "measurement_uncertainty_mm", defaults.measurement_uncertainty_mm,
                "uncertainty of one measured fiducial centre (mm): the margin a candidate must beat the "
                "calibration in use by", minimum=1e-6, maximum=10.0),
            max_cv_factor=self.declare("max_cv_factor", defaults.max_cv_factor,
                                       "fail when the model's CV RMS exceeds this many measurement uncertainties",
                                       minimum=1.0, maximum=1e6),
            max_cv_fraction=self.declare("max_cv_fraction", defaults.max_cv_fraction,
                                         "...and this fraction of the RMS deviation it was trained on",
                                         minimum=0.01, maximum=100.0),
            default_iterations=self.declare("default_iterations", defaults.default_iterations,
                                            "iterations when a request says 0", minimum=1,
                                            maximum=procedure.ITERATIONS_LIMIT),
            max_iterations=self.declare("max_iterations", defaults.max_iterations,
                                        "most iterations a request may ask for (each marks a fresh plate)",
                                        minimum=1, maximum=procedure.ITERATIONS_LIMIT),
            sweep_plan=parse_plan(self.declare(
                "sweep.plan", plan_label(defaults.sweep_plan),
                "passes over the marked plate, orientation (0|90 deg) and direction (+|-) each, e.g. "
                "0+,0-,90+,90-: errors fixed to the scanner frame are separated from the marks")),
            profiles_placed_by_pose=self.declare(
                "sweep.placed_by_pose", defaults.profiles_placed_by_pose,
                "the scanner driver publishes the robot's reported pose (scan/pose): the travel is trusted "
                "for the scale; false: profiles placed by time, the sensor's line scale is trusted"),
            # sweep length and speed are the ones sent to the scanner (declared with the deadlines)
            cell_time=CellTimeModel(
                sweep_length_mm=self.deadlines.sweep_length_mm,
                sweep_speed_mm_s=self.deadlines.sweep_speed_mm_s,
                robot_move_s=self.declare("sweep.robot_move_s", defaults.cell_time.robot_move_s,
                                          "robot move between two sweeps, for the cell-time estimate (s)",
                                          minimum=0.0, maximum=3600.0)),
        )
        self.service_timeout_s = self.declare(
            "service_timeout_s", 60.0, "time limit of one call to a processing node (plate pose, fiducials, "
            "training, correction) (s)", minimum=0.1, maximum=3600.0)
        self.resend_after_s = self.declare(
            "resend_after_s", 15.0, "send an idempotent request (correction, plate pose, fiducials, training) "
            "again when unanswered this long: a server that has just started may drop its first answers (s)",
            minimum=1.0, maximum=3600.0)
        self.plate_exchange_service = self.declare(
            "plate_exchange_service", "", "Trigger service that loads a fresh plate (empty: none)")
        self.ground_truth_service = self.declare(
            "ground_truth_service", "", "GetMarkedPaths service of a simulation, for the true error (empty: none)")
        self.store = CalibrationStore(Path(self.declare("calibration_dir", "calibrations",
                                                        "folder of the calibration store")))
        self.report_root = Path(self.declare("report_dir", "reports", "folder for calibration reports"))
        self.report_per_run = self.declare("report_per_run", True,
                                           "a subfolder of report_dir per calibration (false: report_dir itself)")
        self.reference_check_file = self.declare(
            "reference_check_file", "", "reference check of the measurement chain (stated_accuracy's YAML: a "
            "plate with known centres measured with this plan); read at every calibrate; empty: none, the "
            "cell then states no accuracy and labels its measured figures self-consistency")
        self.arrow_scale = self.declare("rviz.arrow_scale", 50.0,
                                        "RViz deviation arrows are this many times longer than the deviation",
                                        minimum=1.0, maximum=10000.0)
        self.colour_full_scale_mm = self.declare("rviz.colour_full_scale_mm", 1.0,
                                                 "deviation drawn fully red in RViz (mm)", minimum=1e-4)
        self.plate_pose_publisher = self.create_publisher(PoseStamped, "calibration/plate_pose", rviz.LATCHED)
        self.markers_publisher = self.create_publisher(MarkerArray, "calibration/markers", rviz.LATCHED)
        self.cell = ServiceCell(self)
        self.progress = self.create_publisher(CalibrationProgress, "calibration/progress", 10)
        self._running = False
        self.create_service(Calibrate, "calibrate", self.on_calibrate, callback_group=self.reentrant_group)
        self.action_server = ActionServer(
            self, CalibrateAction, "calibrate", execute_callback=self.execute_calibrate,
            goal_callback=self.on_goal, cancel_callback=lambda goal_handle: CancelResponse.ACCEPT,
            callback_group=self.reentrant_group)
        self.create_service(ExplainDeviations, "explain_deviations", self.on_explain,
                            callback_group=self.reentrant_group)
        self.last_failed, self.last_message, self.last_rms_mm = False, "no calibration run yet", math.nan
        self._active_cache: tuple[object, dict] = ("not read yet", {})
        publish_diagnostics(self, self.health)

    def health(self) -> Health:
        """What /diagnostics says: state, the last run, the store's active calibration."""
        state = "running" if self._running else ("failed" if self.last_failed else "idle")
        values: dict[str, object] = {"state": state, "last_run": self.last_message,
                                     "last_measured_rms_mm": f"{self.last_rms_mm:.4f}"}
        try:
            active = self.store.active_path()
            if active != self._active_cache[0]:
                summary = record_summary(self.store.load(active)) if active else NOMINAL_SUMMARY
                self._active_cache = (active, summary)
        except CalibrationFileError as error:
            return Health("error", f"calibration store: {error}", values)
        values |= with_age(self._active_cache[1])
        return Health("warn" if self.last_failed else "ok", f"{state}; {self.last_message}", values)

    def publish_progress(self, stage: str, fraction: float, text: str) -> None:
        """Publish one progress message and log it."""
        message = CalibrationProgress(stage=stage, fraction=float(min(max(fraction, 0.0), 1.0)), text=text)
        message.stamp = self.get_clock().now().to_msg()
        self.progress.publish(message)
        self.get_logger().info(f"[{fraction:4.0%}] {stage}: {text}")

    def on_goal(self, goal_request) -> GoalResponse:
        """Accept a ``calibrate`` goal unless a calibration runs (it is then refused at once)."""
        if self._running:
            self.get_logger().warning("a calibration is already running; goal refused")
            return GoalResponse.REJECT
        self._running = True   # claimed now: a service request between acceptance and execution is refused
        return GoalResponse.ACCEPT

    async def execute_calibrate(self, goal_handle):
        """Run an accepted goal with feedback; a cancel request stops it after the current step."""
        result = CalibrateAction.Result()

        def feedback(stage: str, fraction: float, text: str) -> None:
            goal_handle.publish_feedback(CalibrateAction.Feedback(
                stage=stage, fraction=float(min(max(fraction, 0.0), 1.0)), message=text))
        status = await self._run(goal_handle.request, result, feedback, lambda: goal_handle.is_cancel_requested)
        {"succeeded": goal_handle.succeed, "aborted": goal_handle.abort, "canceled": goal_handle.canceled}[status]()
        return result

    async def on_calibrate(self, request: Calibrate.Request, response: Calibrate.Response):
        """Serve ``calibrate``: run the procedure, keep the active calibration unless it succeeds."""
        if self._running:
            response.success = False
            response.message = "a calibration is already running; request refused"
            return response
        problem = self.settings.iterations_problem(request.iterations)
        if problem:
            response.success, response.message = False, f"request refused: {problem}"
            return response
        self._running = True
        await self._run(request, response, None, lambda: False)
        return response

    async def _run(self, request, response, feedback: Optional[Callable[[str, float, str], None]],
                   cancel_requested: Callable[[], bool]) -> str:
        """One calibration into ``response`` (service response or action result); its final status:
        "succeeded", "aborted" or "canceled". Whatever ends it early, the active calibration stays."""
        began = time.monotonic()
        for name in ("pre_rms_mm", "pre_max_mm", "post_rms_mm", "post_max_mm", "cv_rms_mm", "stated_rms_mm"):
            setattr(response, name, math.nan)   # what a failed run answers
        response.stated_basis = SELF_CONSISTENCY

        def progress(stage: str, fraction: float, text: str) -> None:
            if cancel_requested():
                raise CalibrationCanceled(stage)
            self.publish_progress(stage, fraction, text)
            if feedback is not None:
                feedback(stage, fraction, text)
        status = "aborted"
        try:
            await self._calibrate(request, response, progress, cancel_requested)
            status = "succeeded" if response.success else "aborted"
        except CalibrationCanceled as stop:
            response.success = False
            response.message = (f"calibration canceled before stage {stop}; the active calibration stays in use")
            self.get_logger().warning(response.message)
            status = "canceled"
        except (procedure.CalibrationError, ServiceCallError, ValueError, CalibrationFileError) as error:
            response.success = False
            response.message = f"calibration failed: {error}"
            self.get_logger().error(response.message)
        except Exception as error:  # a bug must not kill the node nor leave a candidate in use
            response.success = False
            response.message = f"calibration failed on an internal error: {type(error).__name__}: {error}"
            self.get_logger().error(f"{response.message}\n{traceback.format_exc()}")
        finally:
            await self.cell.reload_active()
            self._running = False
            response.duration_s = time.monotonic() - began
        self.last_failed, self.last_message = status == "aborted", response.message
        measured = response.post_rms_mm if math.isfinite(response.post_rms_mm) else response.pre_rms_mm
        if math.isfinite(measured):
            self.last_rms_mm = measured
        return status

    async def _calibrate(self, request, response, progress, cancel_requested: Callable[[], bool]) -> None:
        # A configured check that cannot be read refuses the run before anything moves: the operator
        # asked for an independent figure and would otherwise get none without noticing.
        chain_check = load_chain_check(self.reference_check_file) if self.reference_check_file else None
        active = self.store.active_path()
        existing_models = record_models(self.store.load(active)) if active else []
        report_dir = self.report_root
        if self.report_per_run:
            report_dir = report_dir / time.strftime("calibration_%Y%m%dT%H%M%SZ", time.gmtime())

        def save(runs, models):
            record = build_record(self.geometry, self.settings, runs, models, existing_models)
            return save_candidate(self.store, record, self.geometry)

        outcome = await procedure.calibrate(
            self.cell, self.settings, iterations=request.iterations, validate=request.validate,
            force=request.force, want_truth=bool(self.ground_truth_service),
            progress=progress, save_candidate=save, active_calibration=active is not None)
        stamp = self.get_clock().now().to_msg()
        self.plate_pose_publisher.publish(rviz.plate_pose_msg(outcome.runs[-1].plate_pose_gls, stamp))
        self.markers_publisher.publish(rviz.calibration_markers(outcome.runs[0], outcome.validation, stamp,
                                                                self.arrow_scale, self.colour_full_scale_mm))
        summary = summarise(outcome, chain_check,
                            "pose" if self.settings.profiles_placed_by_pose else "time")
        message = summary.message
        # Every file first, activation last: a failure before it leaves the old calibration in force.
        response.report_dir = str(write_outcome_report(report_dir, outcome, summary))
        if outcome.candidate is not None and not outcome.rejection:
            if cancel_requested():
                raise CalibrationCanceled("activation")
            self.store.activate(outcome.candidate.path)
            await self.cell.reload_active()
            try:
                await self.cell.reload_correction_node()
            except (procedure.CalibrationError, ServiceCallError) as error:
                message += (f"; activated, but the correction node did not reload it ({error}): "
                            "call correction/load")
                self.get_logger().error(message)
        elif outcome.candidate is not None:
            await self.cell.reload_active()   # a rejected candidate: the active calibration stays
        _fill_response(response, summary)
        response.message = message
        response.success = not outcome.rejection

    @answers_errors(CalibrationFileError, ValueError)
    def on_explain(self, request, response):
        """Serve ``explain_deviations``: the discrepancy workflow on a calibration's measured fiducials."""
        path = Path(request.calibration_file) if request.calibration_file else self.store.active_path()
        if path is None:
            raise CalibrationFileError(self.store.pointer_path, "no active calibration (nothing saved yet)")
        record = self.store.load(path)
        if not record["fiducials"].get("commanded_through_nominal_model", True):
            self.get_logger().warning(f"{path}: the first plate was marked through an earlier calibration; "
                                      "the named effects describe what that calibration left")
        commanded, measured = record_fiducials(record)
        result = discrepancy.explain(commanded, measured, self.geometry)
        response.success = True
        response.named_effects = list(result.named_effects)
        response.rms_before_mm = float(result.rms_before_mm)
        response.rms_after_mm = float(result.rms_after_mm)
        response.noise_floor_mm = float(result.noise_floor_mm)
        response.report_json = json.dumps(json_safe(result.to_dict()))
        named = discrepancy.naming_phrase(result)   # groups the data cannot split included
        response.message = (f"{path.name}: {named}; residual {result.rms_before_mm:.4f} -> "
                            f"{result.rms_after_mm:.4f} mm RMS (noise floor {result.noise_floor_mm:.4f} mm)")
        return response


def _fill_response(response, summary: RunSummary) -> None:
    """The ``calibrate`` answer: the run summary's figures."""
    response.success = True
    response.message = summary.message
    for name in ("pre_rms_mm", "pre_max_mm", "post_rms_mm", "post_max_mm", "fiducials_expected",
                 "fiducials_found", "neurons", "cv_rms_mm", "calibration_file", "stated_rms_mm", "stated_basis"):
        setattr(response, name, getattr(summary, name))


def main(args=None) -> None:
    """Console script ``gls-calibration-manager``."""
    run_node(CalibrationManager, args)
