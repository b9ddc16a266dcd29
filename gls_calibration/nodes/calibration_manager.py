"""calibration_manager: serves ``calibrate`` and ``explain_deviations``, publishes progress.

It implements the procedure's ``Cell`` with service calls to the scanner, the galvo and the
processing nodes; the flow itself is ``gls_calibration.procedure``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
import time
import traceback
from typing import Optional

import numpy as np
from std_srvs.srv import Trigger

from gls_calibration import discrepancy, kinematics, procedure
from gls_calibration.nodes import conversions
from gls_calibration.calibration_record import build_record, record_fiducials, record_models, save_candidate
from gls_calibration.nodes.base import SERVER_WAIT_S, GlsNode, ServiceCallError, answers_errors, run_node
from gls_calibration.nodes.deadlines import declare_deadlines
from gls_calibration.nodes.head_parameters import declare_head_geometry, declare_scanner_to_gls
from gls_calibration.outcome import RunSummary, summarise
from gls_calibration.persistence import CalibrationFileError, CalibrationStore
from gls_calibration.report import json_safe
from gls_calibration.run_report import write_outcome_report
from gls_calibration.sweep_plan import CellTimeModel, parse_plan, plan_label
from gls_calibration_msgs.msg import CalibrationProgress
from gls_calibration_msgs.srv import (AcquireSweep, Calibrate, CorrectSetpoints, EstimatePlatePose,
                                      ExplainDeviations, GetMarkedPaths, LoadCalibration,
                                      MarkPolylines, MeasureFiducials, TrainCorrection)


RESTORE_SERVER_WAIT_S = 1.0


class ServiceCell:
    """The procedure's Cell, reached through the services of the other nodes."""

    def __init__(self, node: "CalibrationManager") -> None:
        self.node = node
        self.timeout_s = node.service_timeout_s
        self.deadlines = node.deadlines
        self.acquire = node.client(AcquireSweep, "scan/acquire")
        self.pose = node.client(EstimatePlatePose, "plate_pose/estimate")
        self.fiducials = node.client(MeasureFiducials, "fiducials/measure")
        self.corrector = node.client(CorrectSetpoints, "correct_setpoints")
        self.loader = node.client(LoadCalibration, "correction/load")
        self.galvo = node.client(MarkPolylines, "galvo/mark")
        self.trainer = node.client(TrainCorrection, "rbf/train")
        self.exchange = node.client(Trigger, node.plate_exchange_service) if node.plate_exchange_service else None
        self.truth = node.client(GetMarkedPaths, node.ground_truth_service) if node.ground_truth_service else None

    async def _checked(self, client, request, timeout_s: Optional[float] = None, *, idempotent: bool = True):
        # Only a request that may safely be served twice is sent again (not a sweep, a marking job
        # or a plate exchange).
        response = await self.node.call(client, request, timeout_s or self.timeout_s,
                                        resend_after_s=self.node.resend_after_s if idempotent else None)
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

    async def estimate_plate_pose(self, cloud):
        response = await self._checked(self.pose, EstimatePlatePose.Request(cloud=cloud))
        return conversions.plate_pose_from_msg(response.pose)

    async def measure_fiducials(self, cloud, pose, expected_count):
        request = MeasureFiducials.Request(cloud=cloud, pose=conversions.plate_pose_to_msg(pose),
                                           expected_count=int(expected_count))
        response = await self._checked(self.fiducials, request)
        return conversions.fiducials_from_response(response, pose)

    async def correct(self, x, y, z):
        request = CorrectSetpoints.Request(x=conversions.float64_sequence(x), y=conversions.float64_sequence(y),
                                           z=conversions.float64_sequence(z))
        return conversions.setpoints_from_response(await self._checked(self.corrector, request))

    async def mark(self, alpha_x, alpha_y, focus_shift, polyline_starts):
        request = MarkPolylines.Request(alpha_x=alpha_x, alpha_y=alpha_y, focus_shift=focus_shift,
                                        polyline_starts=np.asarray(polyline_starts, dtype=np.uint32))
        xy = np.column_stack(kinematics.forward(self.node.geometry, request.alpha_x, request.alpha_y))
        response = await self._checked(self.galvo, request, self.deadlines.marking_s(xy, polyline_starts),
                                       idempotent=False)
        return response.duration_s

    async def train(self, landed_xy, corrections):
        request = TrainCorrection.Request(
            x=conversions.float64_sequence(landed_xy[:, 0]), y=conversions.float64_sequence(landed_xy[:, 1]),
            dx=conversions.float64_sequence(corrections[:, 0]), dy=conversions.float64_sequence(corrections[:, 1]))
        response = await self._checked(self.trainer, request)
        return conversions.trained_model_from_response(response)

    async def load_calibration(self, path: str, server_wait_s: float = SERVER_WAIT_S) -> None:
        response = await self.node.call(self.loader, LoadCalibration.Request(file=path), self.timeout_s,
                                        server_wait_s=server_wait_s, resend_after_s=self.node.resend_after_s)
        if not response.success:
            raise procedure.CalibrationError(f"{self.loader.srv_name}: {response.message}")

    async def reload_active(self, server_wait_s: float = SERVER_WAIT_S) -> None:
        await self.load_calibration("", server_wait_s)  # empty: the store's active one

    async def exchange_plate(self) -> None:
        if self.exchange is None:
            raise procedure.CalibrationError(
                "a fresh plate is needed (second iteration or validation) but no plate_exchange_service "
                "is configured")
        await self._checked(self.exchange, Trigger.Request(), idempotent=False)

    def intensities(self, cloud):
        return conversions.cloud_arrays_from_msg(cloud)[1]

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
                                            "iterations when a request says 0", minimum=1, maximum=10),
            max_iterations=self.declare("max_iterations", defaults.max_iterations,
                                        "most iterations a request may ask for (each marks a fresh plate)",
                                        minimum=1, maximum=10),
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
        self.cell = ServiceCell(self)
        self.progress = self.create_publisher(CalibrationProgress, "calibration/progress", 10)
        self._running = False
        self.create_service(Calibrate, "calibrate", self.on_calibrate, callback_group=self.reentrant_group)
        self.create_service(ExplainDeviations, "explain_deviations", self.on_explain,
                            callback_group=self.reentrant_group)

    def publish_progress(self, stage: str, fraction: float, text: str) -> None:
        """Publish one progress message and log it."""
        message = CalibrationProgress(stage=stage, fraction=float(min(max(fraction, 0.0), 1.0)), text=text)
        message.stamp = self.get_clock().now().to_msg()
        self.progress.publish(message)
        self.get_logger().info(f"[{fraction:4.0%}] {stage}: {text}")

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
        began = time.monotonic()
        for name in ("pre_rms_mm", "pre_max_mm", "post_rms_mm", "post_max_mm", "cv_rms_mm"):
            setattr(response, name, math.nan)   # what a failed run answers
        try:
            await self._calibrate(request, response)
        except (procedure.CalibrationError, ServiceCallError, ValueError, CalibrationFileError) as error:
            response.success = False
            response.message = f"calibration failed: {error}"
            self.get_logger().error(response.message)
            await self._restore_active()
        except Exception as error:  # a bug must not kill the node nor leave the candidate loaded
            response.success = False
            response.message = f"calibration failed on an internal error: {type(error).__name__}: {error}"
            self.get_logger().error(f"{response.message}\n{traceback.format_exc()}")
            await self._restore_active()
        finally:
            self._running = False
            response.duration_s = time.monotonic() - began
        return response

    async def _calibrate(self, request, response) -> None:
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
            progress=self.publish_progress, save_candidate=save)
        summary = summarise(outcome)
        # Every file first, activation last: a failure before it leaves the old calibration in force.
        response.report_dir = str(write_outcome_report(report_dir, outcome, summary))
        if outcome.candidate is not None and not outcome.rejection:
            self.store.activate(outcome.candidate.path)
        elif outcome.candidate is not None:
            await self._restore_active()   # a rejected candidate was loaded for the validation
        _fill_response(response, summary)
        response.success = not outcome.rejection

    async def _restore_active(self) -> None:
        # A correction node that is not there loads the active calibration itself when it starts:
        # waiting long for it would only keep the failed run's caller waiting.
        try:
            await self.cell.reload_active(server_wait_s=RESTORE_SERVER_WAIT_S)
        except (procedure.CalibrationError, ServiceCallError) as error:
            self.get_logger().error(f"could not restore the active calibration in the correction node: {error}")

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
        named = ", ".join(result.named_effects) or "no effect"
        response.message = (f"{path.name}: {named}; residual {result.rms_before_mm:.4f} -> "
                            f"{result.rms_after_mm:.4f} mm RMS (noise floor {result.noise_floor_mm:.4f} mm)")
        return response


def _fill_response(response, summary: RunSummary) -> None:
    """The ``calibrate`` answer: the run summary's figures."""
    response.success = True
    response.message = summary.message
    for name in ("pre_rms_mm", "pre_max_mm", "post_rms_mm", "post_max_mm", "fiducials_expected",
                 "fiducials_found", "neurons", "cv_rms_mm", "calibration_file"):
        setattr(response, name, getattr(summary, name))


def main(args=None) -> None:
    """Console script ``gls-calibration-manager``."""
    run_node(CalibrationManager, args)
