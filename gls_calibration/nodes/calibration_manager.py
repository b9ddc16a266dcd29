"""calibration_manager: serves ``calibrate``, ``reference_check`` and ``explain_deviations``, publishes progress.

calibration_manager: serves ``calibrate`` (an action with feedback and cancel, and a service for
simple clients), ``reference_check`` (scans the reference plate and writes the check the calibrations
state their accuracy from) and ``explain_deviations``, publishes progress.

It implements the procedure's ``Cell`` with service calls to the scanner, the galvo and the
processing nodes; the flow itself is ``gls_calibration.calibration.procedure``. A run's candidate calibration
is evaluated here, in-process: the correction node keeps serving the active calibration until the
run has succeeded and the candidate is activated.
"""
from __future__ import annotations

from dataclasses import replace
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

from gls_calibration import discrepancy
from gls_calibration.calibration import procedure
from gls_calibration.calibration.outcome import RunSummary, summarise
from gls_calibration.calibration.record import (build_record, certified_candidate, record_fiducials, record_models,
                                                save_candidate)
from gls_calibration.calibration.record_file import CalibrationFileError
from gls_calibration.calibration.reference_check import (certified_reach, read_certified_centres,
                                                         scan_reference_check)
from gls_calibration.calibration.stated_accuracy import (SELF_CONSISTENCY, load_chain_check, placement_name,
                                                         save_chain_check)
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.calibration.uncertainty import check_matches_run
from gls_calibration.common.files import require_regular_output
from gls_calibration.correction.setpoints import Correction
from gls_calibration.geometry import kinematics
from gls_calibration.registration.chain_map import load_chain_map
from gls_calibration.report.files import json_safe, write_summary_json
from gls_calibration.report.run_report import write_outcome_report
from gls_calibration.ros import conversions, rviz
from gls_calibration.ros.base import GlsNode, SERVER_WAIT_S
from gls_calibration.ros.diagnostics import NOMINAL_SUMMARY, Health, publish_diagnostics, record_summary, with_age
from gls_calibration.ros.manager_parameters import (MANAGER_PARAMETERS, SETTABLE, ManagerConfig, ManagerParameter,
                                                    manager_config)
from gls_calibration.ros.request_ids import RESEND_WITH_ID_AFTER_S, new_request_id
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import ServiceCallError, answers_errors
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

    @property
    def timeout_s(self) -> float:
        """Return the node's service time limit (settable between runs)."""
        return self.node.service_timeout_s

    @property
    def deadlines(self):
        """Return the node's job time limits (settable between runs)."""
        return self.node.deadlines

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
        """Acquire one sweep through the scan node (see ``Cell.acquire_sweep``)."""
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
        """Acquire profiles standing still through the scan node (see ``Cell.acquire_standstill``)."""
        deadlines = self.deadlines
        step_mm = self.node.settings.marked_sweep_step_mm   # sets the profile rate, as in a sweep at this step
        request = AcquireSweep.Request(timeout_s=deadlines.sweep_s(), length_mm=(int(profiles) - 1) * step_mm,
                                       speed_mm_s=deadlines.sweep_speed_mm_s, step_mm=step_mm)
        response = await self._checked(self.acquire_still, request, deadlines.sweep_s() + deadlines.margin_s,
                                       idempotent=False)
        return response.cloud

    async def estimate_plate_pose(self, cloud):
        """Plate pose from the plate pose node (see ``Cell.estimate_plate_pose``)."""
        response = await self._checked(self.pose, EstimatePlatePose.Request(cloud=cloud))
        return conversions.plate_pose_from_msg(response.pose)

    async def measure_fiducials(self, cloud, pose, expected_count, ring_radii_mm):
        """Fiducial centres from the fiducial node (see ``Cell.measure_fiducials``)."""
        request = MeasureFiducials.Request(cloud=cloud, pose=conversions.plate_pose_to_msg(pose),
                                           expected_count=int(expected_count),
                                           ring_radii_mm=[float(r) for r in ring_radii_mm])
        response = await self._checked(self.fiducials, request)
        return conversions.fiducials_from_response(response, pose)

    async def correct(self, x, y, z):
        """Correct setpoints by the candidate in hand, else by the correction node's active calibration."""
        candidate = self.candidate      # read once: another thread may drop it meanwhile
        if candidate is not None:
            return candidate.correct(x, y, z)
        request = CorrectSetpoints.Request(x=conversions.float64_sequence(x), y=conversions.float64_sequence(y),
                                           z=conversions.float64_sequence(z))
        return conversions.setpoints_from_response(await self._checked(self.corrector, request))

    async def mark(self, alpha_x, alpha_y, focus_shift, polyline_starts):
        """Mark polylines with the galvo node (see ``Cell.mark``); returns the marking time, s."""
        request = MarkPolylines.Request(alpha_x=alpha_x, alpha_y=alpha_y, focus_shift=focus_shift,
                                        polyline_starts=np.asarray(polyline_starts, dtype=np.uint32),
                                        request_id=new_request_id())
        xy = np.column_stack(kinematics.forward(self.node.geometry, request.alpha_x, request.alpha_y))
        # The job's id lets the driver tell a repeat from a new job: it is sent again, never marked twice.
        response = await self._checked(self.galvo, request, self.deadlines.marking_s(xy, polyline_starts),
                                       resend_after_s=RESEND_WITH_ID_AFTER_S)
        return response.duration_s

    async def train(self, landed_xy, corrections):
        """Train a correction with the training node (see ``Cell.train``)."""
        request = TrainCorrection.Request(
            x=conversions.float64_sequence(landed_xy[:, 0]), y=conversions.float64_sequence(landed_xy[:, 1]),
            dx=conversions.float64_sequence(corrections[:, 0]), dy=conversions.float64_sequence(corrections[:, 1]))
        response = await self._checked(self.trainer, request)
        return conversions.trained_model_from_response(response)

    async def use_candidate(self, candidate) -> None:
        """Evaluate ``candidate`` here from now on; the correction node does not see it.

        Its correction is used as built, not its file read again.
        """
        self.candidate = candidate.correction

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
        """Ask the configured plate exchange service for a fresh plate (see ``Cell.exchange_plate``)."""
        if self.exchange is None:
            raise procedure.CalibrationError(
                "a fresh plate is needed (second iteration or validation) but no plate_exchange_service "
                "is configured")
        await self._checked(self.exchange, Trigger.Request(), idempotent=False)

    def start(self, step):
        """Return a task of the node's executor running ``step`` beside the procedure (``Cell.start``).

        Awaiting the task returns the step's result or raises its error; the step's service calls run
        on the reentrant group like the procedure's own.
        """
        return self.node.executor.create_task(step)

    def points_and_intensities(self, cloud):
        """Points and intensities of a PointCloud2 (see ``Cell.points_and_intensities``)."""
        return conversions.cloud_arrays_from_msg(cloud)

    async def true_marks(self):
        """Return the marks where they truly landed, from a simulated galvo; None in a real cell."""
        if self.truth is None:
            return None
        return conversions.marked_polylines((await self._checked(self.truth, GetMarkedPaths.Request())).paths)


class CalibrationManager(GlsNode):
    """Runs calibrations on request; refuses a second request while one runs."""

    def __init__(self, **kwargs) -> None:
        super().__init__("calibration_manager", **kwargs)
        # One table (manager_parameters): read-only ones are read here once, settable ones apply from
        # the next run (refused while one runs).
        values = {parameter.name: self._declare_parameter(parameter) for parameter in MANAGER_PARAMETERS}
        self._use(manager_config(values))
        self.store = CalibrationStore(self.config.calibration_dir)
        self.plate_exchange_service = self.config.plate_exchange_service
        self.ground_truth_service = self.config.ground_truth_service
        self.geometry = self.config.geometry
        self._running = False
        self._job = "a calibration"     # what runs while _running: "a calibration" or "a reference check"
        self.apply_parameter_changes(SETTABLE, self._apply_settable)
        self.plate_pose_publisher = self.create_publisher(PoseStamped, "calibration/plate_pose", rviz.LATCHED)
        self.markers_publisher = self.create_publisher(MarkerArray, "calibration/markers", rviz.LATCHED)
        self.cell = ServiceCell(self)
        self.progress = self.create_publisher(CalibrationProgress, "calibration/progress", 10)
        self.create_service(Calibrate, "calibrate", self.on_calibrate, callback_group=self.reentrant_group)
        self.action_server = ActionServer(
            self, CalibrateAction, "calibrate", execute_callback=self.execute_calibrate,
            goal_callback=self.on_goal, cancel_callback=lambda goal_handle: CancelResponse.ACCEPT,
            callback_group=self.reentrant_group)
        self.create_service(Trigger, "reference_check", self.on_reference_check, callback_group=self.reentrant_group)
        self.create_service(ExplainDeviations, "explain_deviations", self.on_explain,
                            callback_group=self.reentrant_group)
        self.last_failed, self.last_message, self.last_rms_mm = False, "no calibration run yet", math.nan
        self._active_cache: tuple[object, dict] = ("not read yet", {})
        publish_diagnostics(self, self.health)

    def _declare_parameter(self, parameter: ManagerParameter):
        """Declare one parameter of the table; its value (list parameters as lists)."""
        value = self.declare(parameter.name, parameter.default, parameter.full_description,
                             minimum=parameter.minimum, maximum=parameter.maximum, dynamic=parameter.settable)
        return _plain(value)

    def _use(self, config: ManagerConfig) -> None:
        """Run from now on with ``config`` (never during a run: see ``_apply_settable``)."""
        self.config = config
        self.settings, self.deadlines = config.settings, config.deadlines
        self.service_timeout_s, self.resend_after_s = config.service_timeout_s, config.resend_after_s
        self.report_root, self.report_per_run = config.report_root, config.report_per_run
        self.reference_check_file = config.reference_check_file
        self.reference_plate_certificate = config.reference_plate_certificate
        self.reference_plate_name = config.reference_plate_name
        self.chain_map_file = config.chain_map_file
        self.simulated_chain = config.simulated_chain
        self.arrow_scale, self.colour_full_scale_mm = config.arrow_scale, config.colour_full_scale_mm

    def _apply_settable(self, requested: dict) -> Optional[str]:
        """Handle ``ros2 param set`` of settable parameters: refused during a run or when invalid.

        ``requested`` holds every settable one with the requested values in. A refusal returns the
        reason; an accepted value is in use from the next run.
        """
        values = {parameter.name: _plain(self.get_parameter(parameter.name).value) for parameter in MANAGER_PARAMETERS}
        requested = {name: _plain(value) for name, value in requested.items()}
        names = ", ".join(sorted(name for name, value in requested.items() if value != values[name])) or "nothing"
        if self._running:
            return (f"{names} not changed: a calibration is running and keeps the settings it started with; "
                    "set it again once the run has ended")
        values |= requested
        try:
            config = manager_config(values)
        except (ValueError, TypeError) as error:
            return f"{names} not changed: {error}"
        self._use(config)
        self.get_logger().info(f"{names} set: applies from the next calibration run")
        return None

    def health(self) -> Health:
        """Return what /diagnostics says: state, the last run, the store's active calibration."""
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

    def busy(self) -> bool:
        """Tell whether a calibration or a reference check runs (stopping: it ends at its next step, canceled)."""
        return self._running

    def on_goal(self, goal_request) -> GoalResponse:
        """Accept a ``calibrate`` goal unless a calibration runs (it is then refused at once)."""
        if self.stopping:
            self.get_logger().warning("the node is stopping; goal refused")
            return GoalResponse.REJECT
        if self._running:
            self.get_logger().warning(f"{self._job} is already running; goal refused")
            return GoalResponse.REJECT
        # claimed now: a service request between acceptance and execution is refused
        self._running, self._job = True, "a calibration"
        return GoalResponse.ACCEPT

    async def execute_calibrate(self, goal_handle):
        """Run an accepted goal with feedback; a cancel request stops it after the current step."""
        result = CalibrateAction.Result()

        def feedback(stage: str, fraction: float, text: str) -> None:
            goal_handle.publish_feedback(CalibrateAction.Feedback(
                stage=stage, fraction=float(min(max(fraction, 0.0), 1.0)), message=text))
        status = await self._run(goal_handle.request, result, feedback,
                                 lambda: goal_handle.is_cancel_requested or self.stopping)
        {"succeeded": goal_handle.succeed, "aborted": goal_handle.abort, "canceled": goal_handle.canceled}[status]()
        return result

    async def on_calibrate(self, request: Calibrate.Request, response: Calibrate.Response):
        """Serve ``calibrate``: run the procedure, keep the active calibration unless it succeeds."""
        if self.stopping:
            response.success, response.message = False, "the calibration manager is stopping; request refused"
            return response
        if self._running:
            response.success = False
            response.message = f"{self._job} is already running; request refused"
            return response
        problem = self.settings.iterations_problem(request.iterations)
        if problem:
            response.success, response.message = False, f"request refused: {problem}"
            return response
        self._running, self._job = True, "a calibration"
        await self._run(request, response, None, lambda: self.stopping)
        return response

    async def _run(self, request, response, feedback: Optional[Callable[[str, float, str], None]],
                   cancel_requested: Callable[[], bool]) -> str:
        """Run one calibration into ``response``; return its final status.

        One calibration into ``response`` (service response or action result); its final status:
        "succeeded", "aborted" or "canceled". Whatever ends it early, the active calibration stays.
        """
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
        # likewise a configured chain map: the run applies it to every sweep of the marked plate
        settings = self.settings
        if self.chain_map_file:
            settings = replace(settings, chain_map=load_chain_map(self.chain_map_file))
        active = self.store.active_path()
        existing_models = record_models(self.store.load(active)) if active else []
        report_dir = self.report_root
        if self.report_per_run:
            report_dir = report_dir / time.strftime("calibration_%Y%m%dT%H%M%SZ", time.gmtime())

        def save(runs, models):
            record = build_record(self.geometry, settings, runs, models, existing_models, chain_check)
            return save_candidate(self.store, record, self.geometry)

        def certify(candidate, validation):
            return certified_candidate(self.store, candidate, self.geometry, validation.metrics.full.rms_abs_mm,
                                       chain_check, check_matches_run(chain_check, validation, settings))

        outcome = await procedure.calibrate(
            self.cell, settings, iterations=request.iterations, validate=request.validate,
            force=request.force, want_truth=bool(self.ground_truth_service),
            progress=progress, save_candidate=save, active_calibration=active is not None, certify=certify)
        stamp = self.get_clock().now().to_msg()
        self.plate_pose_publisher.publish(rviz.plate_pose_msg(outcome.runs[-1].plate_pose_gls, stamp))
        self.markers_publisher.publish(rviz.calibration_markers(outcome.runs[0], outcome.validation, stamp,
                                                                self.arrow_scale, self.colour_full_scale_mm))
        summary = summarise(outcome, chain_check, placement_name(settings.profiles_placed_by_pose),
                            measurement_preset=self.simulated_chain)
        message = summary.message
        # Every file first, activation last: a failure before it leaves the old calibration in force.
        response.report_dir = str(write_outcome_report(report_dir, outcome, summary))
        if outcome.candidate is not None and not outcome.rejection:
            if cancel_requested():
                raise CalibrationCanceled("activation")
            self.store.activate(outcome.candidate.path)
            # /diagnostics describes the record in hand, not the file read back
            self._active_cache = (Path(outcome.candidate.path), record_summary(outcome.candidate.record))
            await self.cell.reload_active()
            try:
                await self.cell.reload_correction_node()
            except (procedure.CalibrationError, ServiceCallError) as error:
                message += (f"; activated, but the correction node did not reload it ({error}): "
                            "call correction/load")
                self.get_logger().error(message)
            summary = replace(summary, last_profile_to_activation_s=(
                time.monotonic() - outcome.stage_times.last_sweep_end_s))
            try:    # the summary as written before the activation stays if this fails
                write_summary_json(response.report_dir, summary.to_dict())
            except OSError as error:
                self.get_logger().warning(f"summary.json not updated with the activation time: {error}")
        elif outcome.candidate is not None:
            await self.cell.reload_active()   # a rejected candidate: the active calibration stays
        _fill_response(response, summary)
        response.message = message
        response.success = not outcome.rejection

    def _reference_check_inputs(self):
        """Return what a reference check needs (file, settings, certified centres, plate name); ValueError why not.

        Everything the check reads is read here, before anything moves: a refusal writes nothing.
        """
        if not self.reference_check_file:
            raise ValueError("reference_check_file is empty: the check would be lost; set it to the file the "
                             "calibrations read the check from")
        require_regular_output(self.reference_check_file)
        if not self.reference_plate_certificate:
            raise ValueError("reference_plate_certificate is empty: set it to the CSV of the plate's certified "
                             "centres (x,y[,z], mm, gls frame)")
        if not self.reference_plate_name.strip():
            raise ValueError("reference_plate_name is empty: set it to name the plate and its certificate")
        known = read_certified_centres(self.reference_plate_certificate)
        settings = self.settings
        short = certified_reach(known, settings)
        if short:
            raise ValueError(f"{self.reference_plate_certificate}: {short}")
        if self.chain_map_file:     # the calibrations remove it from every sweep: so does their check
            settings = replace(settings, chain_map=load_chain_map(self.chain_map_file))
        return Path(self.reference_check_file), settings, known, self.reference_plate_name.strip()

    async def on_reference_check(self, request: Trigger.Request, response: Trigger.Response):
        """Serve ``reference_check``: scan the reference plate as a calibration scans, write the check.

        The plate with certified centres (``reference_plate_certificate``) lies on the bed; it is
        scanned through the cell with the calibration's own sweep plan, placement and chain map
        (``reference_check.scan_reference_check``) and the check is written atomically to
        ``reference_check_file``, which the following calibrations state their accuracy from. Refused
        (nothing written, the old file untouched) while a calibration runs, when stopping, on bad
        parameters or certificate; a failed scan writes nothing either.
        """
        response.success = False
        if self.stopping:
            response.message = "the calibration manager is stopping; request refused"
            return response
        if self._running:
            response.message = f"{self._job} is already running; request refused"
            return response
        try:
            path, settings, known, name = self._reference_check_inputs()
        except ValueError as error:
            response.message = f"request refused: {error}"
            self.get_logger().error(response.message)
            return response
        self._running, self._job = True, "a reference check"

        def progress(stage: str, fraction: float, text: str) -> None:
            if self.stopping:
                raise CalibrationCanceled(stage)
            self.publish_progress(stage, fraction, text)
        try:
            check = await scan_reference_check(self.cell, settings, known, name, progress)
            save_chain_check(path, check)
            response.success = True
            response.message = (f"reference check written to {path}: sigma x {check.sigma_mm[0]:.4f} mm, "
                                f"y {check.sigma_mm[1]:.4f} mm (k = 1) from {check.centres} of {len(known)} "
                                f"certified centres; plan {check.plan}, placed by {check.placement}, chain map "
                                f"{check.chain_map}")
            self.get_logger().info(response.message)
        except CalibrationCanceled as stop:
            response.message = f"reference check canceled before stage {stop}; {path} not written"
            self.get_logger().warning(response.message)
        except (procedure.CalibrationError, ServiceCallError, ValueError, CalibrationFileError, OSError) as error:
            response.message = f"reference check failed: {error}; {path} not written"
            self.get_logger().error(response.message)
        except Exception as error:  # a bug must not kill the node
            response.message = (f"reference check failed on an internal error: {type(error).__name__}: {error}; "
                                f"{path} not written")
            self.get_logger().error(f"{response.message}\n{traceback.format_exc()}")
        finally:
            self._running = False
        return response

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


def _plain(value):
    """Return a parameter value with a list as a list (rclpy gives arrays of numbers as ``array.array``)."""
    return list(value) if hasattr(value, "tolist") and not isinstance(value, (str, bytes)) else value


def _fill_response(response, summary: RunSummary) -> None:
    """Fill the ``calibrate`` answer with the run summary's figures."""
    response.success = True
    response.message = summary.message
    for name in ("pre_rms_mm", "pre_max_mm", "post_rms_mm", "post_max_mm", "fiducials_expected",
                 "fiducials_found", "neurons", "cv_rms_mm", "calibration_file", "stated_rms_mm", "stated_basis"):
        setattr(response, name, getattr(summary, name))


def main(args=None) -> int:
    """Console script ``gls-calibration-manager``."""
    return run_node(CalibrationManager, args)
