"""The calibration manager's parameters as one table.

Name, default, description, range, and whether an operator may set it while the node runs
(``ros2 param set``) or why not.

A settable parameter applies from the NEXT calibration run: a change while a run is in progress is
refused with a message (the run keeps the settings it started with), an invalid value is refused with
the reason, and the manager's configuration is rebuilt from the table's values by :func:`manager_config`
(the one place that turns values into settings, at start and on a change alike). A read-only one is
read once at start: its description says why.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from pathlib import Path
from typing import Any, Mapping, Optional

from gls_calibration.calibration import procedure
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.registration.sweep_plan import CellTimeModel, parse_plan, plan_label
from gls_calibration.ros.deadlines import Deadlines
from gls_calibration.ros.head_parameters import (HEAD_SPECS, SCANNER_TO_GLS_DEFAULTS, head_geometry_from,
                                                 scanner_to_gls_from)

KINDS = ("integer", "number", "numbers", "flag", "text")
NEXT_RUN = "settable: applies from the next calibration run"


@dataclass(frozen=True)
class ManagerParameter:
    """One parameter of the calibration manager. ``read_only_because`` empty: settable at run time."""

    name: str
    default: Any
    description: str
    kind: str = "number"
    minimum: Optional[float] = None
    maximum: Optional[float] = None
    read_only_because: str = ""

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        if self.kind not in KINDS:
            raise ValueError(f"parameter {self.name}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")

    @property
    def settable(self) -> bool:
        """Whether ``ros2 param set`` may change it while the node runs."""
        return not self.read_only_because

    @property
    def full_description(self) -> str:
        """Return the description the node declares: what it is, then settable or read-only and why."""
        return f"{self.description} [{NEXT_RUN if self.settable else 'read-only: ' + self.read_only_because}]"


_SETTINGS = procedure.ProcedureSettings()
_CELL_TIME = CellTimeModel()
_HEAD_WHY = ("the head's geometry is shared with the correction node and written into every calibration; "
             "changed on the manager alone it would mark with one head and correct with another (edit "
             "config/head.yaml and restart every node)")
_CLIENT_WHY = "its service client is created at start (restart the node to change it)"

MANAGER_PARAMETERS: tuple[ManagerParameter, ...] = (
    *(ManagerParameter(name, default, description, "number", minimum, maximum, _HEAD_WHY)
      for name, default, description, minimum, maximum in HEAD_SPECS),
    ManagerParameter("scanner_to_gls.translation_mm", SCANNER_TO_GLS_DEFAULTS["scanner_to_gls.translation_mm"],
                     "scanner frame origin in the gls frame at the start of a sweep (mm), 3 numbers", "numbers"),
    ManagerParameter("scanner_to_gls.rpy_rad", SCANNER_TO_GLS_DEFAULTS["scanner_to_gls.rpy_rad"],
                     "scanner frame orientation in the gls frame: roll, pitch, yaw (rad, extrinsic xyz), "
                     "3 numbers", "numbers"),
    ManagerParameter("sweep.length_mm", _CELL_TIME.sweep_length_mm,
                     "length of each sweep (mm), sent to the scanner; the passes turn about its middle, the error "
                     "separation's origin", minimum=1.0, maximum=5000.0),
    ManagerParameter("sweep.speed_mm_s", _CELL_TIME.sweep_speed_mm_s, "sensor speed of each sweep (mm/s), sent to "
                     "the scanner", minimum=0.1, maximum=10000.0),
    ManagerParameter("marking.speed_mm_s", 500.0, "the galvo's marking speed (mm/s), for the marking time limit",
                     minimum=1.0, maximum=100000.0),
    ManagerParameter("marking.jump_time_s", 0.005, "time of one jump between polylines (s), for the marking "
                     "time limit", minimum=0.0, maximum=10.0),
    ManagerParameter("deadline_factor", 2.0, "a sweep or marking job may take this many times its expected "
                     "duration", minimum=1.0, maximum=100.0),
    ManagerParameter("deadline_margin_s", 10.0, "added to every job's time limit (s)", minimum=0.1, maximum=600.0),
    ManagerParameter("grid.per_side", _SETTINGS.grid_per_side, "fiducials per side of the square grid",
                     "integer", 3, 101),
    ManagerParameter("grid.size_mm", _SETTINGS.grid_size_mm, "side of the fiducial grid (mm)",
                     minimum=1.0, maximum=1000.0),
    ManagerParameter("grid.ring_radii_mm", list(_SETTINGS.ring_radii_mm), "radii of the concentric rings of a "
                     "fiducial, increasing (mm); sent in every MeasureFiducials request", "numbers"),
    ManagerParameter("sweep.plain_step_mm", _SETTINGS.plain_sweep_step_mm, "profile spacing of the sweep of the "
                     "plain plate (mm)", minimum=0.01, maximum=10.0),
    ManagerParameter("sweep.plain_repeats", _SETTINGS.plain_sweeps, "sweeps of the plain plate whose poses are "
                     "averaged: the robot's path error in each tilts the plane (and, without sweep.standstill_height, "
                     "sets the plate height, hence the field's scale)",
                     "integer", 1, 20),
    ManagerParameter("sweep.standstill_height", _SETTINGS.standstill_height, "take the plate height from profiles "
                     "taken with the robot standing still at the marking pose (scan/acquire_standstill), not from "
                     "the sweeps, whose path error scales the marked field", "flag"),
    ManagerParameter("sweep.marked_step_mm", _SETTINGS.marked_sweep_step_mm, "profile spacing of the sweep of the "
                     "marked plate (mm)", minimum=0.01, maximum=1.0),
    ManagerParameter("tolerance_rms_mm", _SETTINGS.tolerance_rms_mm, "no training when the measured RMS deviation "
                     "is within this (mm)", minimum=0.0),
    ManagerParameter("min_found_fraction", _SETTINGS.min_found_fraction, "fail when fewer fiducials than this "
                     "fraction are found", minimum=0.0, maximum=1.0),
    ManagerParameter("max_outlying_points", _SETTINGS.max_outlying_points, "a plain plate with more points than "
                     "this beyond mark_check_sigmas of its texture carries old marks: refused unless forced",
                     "integer", 0),
    ManagerParameter("mark_check_sigmas", _SETTINGS.mark_check_sigmas, "robust standard deviations of the plate "
                     "texture beyond which a point looks like a mark", minimum=1.0, maximum=100.0),
    ManagerParameter("max_cluster_points", _SETTINGS.max_cluster_points, "a plain plate with more points than "
                     "this beyond mark_cluster_sigmas within one fiducial's extent carries old marks", "integer", 0),
    ManagerParameter("mark_cluster_sigmas", _SETTINGS.mark_cluster_sigmas, "robust standard deviations of the "
                     "plate texture beyond which a point counts towards a cluster of marks",
                     minimum=1.0, maximum=100.0),
    ManagerParameter("measurement_uncertainty_mm", _SETTINGS.measurement_uncertainty_mm, "uncertainty of one "
                     "measured fiducial centre (mm): the margin a candidate must beat the calibration in use by",
                     minimum=1e-6, maximum=10.0),
    ManagerParameter("max_cv_factor", _SETTINGS.max_cv_factor, "fail when the model's CV RMS exceeds this many "
                     "measurement uncertainties", minimum=1.0, maximum=1e6),
    ManagerParameter("max_cv_fraction", _SETTINGS.max_cv_fraction, "...and this fraction of the RMS deviation it "
                     "was trained on", minimum=0.01, maximum=100.0),
    ManagerParameter("default_iterations", _SETTINGS.default_iterations, "iterations when a request says 0",
                     "integer", 1, procedure.ITERATIONS_LIMIT),
    ManagerParameter("max_iterations", _SETTINGS.max_iterations, "most iterations a request may ask for (each "
                     "marks a fresh plate)", "integer", 1, procedure.ITERATIONS_LIMIT),
    ManagerParameter("sweep.plan", plan_label(_SETTINGS.sweep_plan), "passes over the marked plate, orientation "
                     "(0|45|90 deg) and direction (+|-) each, e.g. 0+,0-,90+,90-: errors fixed to the scanner frame "
                     "are separated from the marks; a 45 deg pass sees the plate's middle band and pins a shear "
                     "of the marks", "text"),
    ManagerParameter("sweep.placed_by_pose", _SETTINGS.profiles_placed_by_pose, "the scanner driver publishes the "
                     "robot's reported pose (scan/pose): the travel is trusted for the scale; false: profiles "
                     "placed by time, the sensor's line scale is trusted", "flag"),
    ManagerParameter("sweep.robot_move_s", _CELL_TIME.robot_move_s, "robot move between two sweeps, for the "
                     "cell-time estimate (s)", minimum=0.0, maximum=3600.0),
    ManagerParameter("service_timeout_s", 60.0, "time limit of one call to a processing node (plate pose, "
                     "fiducials, training, correction) (s)", minimum=0.1, maximum=3600.0),
    ManagerParameter("resend_after_s", 15.0, "send an idempotent request (correction, plate pose, fiducials, "
                     "training) again when unanswered this long: a server that has just started may drop its "
                     "first answers (s)", minimum=1.0, maximum=3600.0),
    ManagerParameter("plate_exchange_service", "", "Trigger service that loads a fresh plate (empty: none)",
                     "text", read_only_because=_CLIENT_WHY),
    ManagerParameter("ground_truth_service", "", "GetMarkedPaths service of a simulation, for the true error "
                     "(empty: none)", "text", read_only_because=_CLIENT_WHY),
    ManagerParameter("calibration_dir", "calibrations", "folder of the calibration store", "text",
                     read_only_because="the correction node serves the active calibration of the same store; "
                     "moved on the manager alone, activations would never reach it (restart both nodes)"),
    ManagerParameter("report_dir", "reports", "folder for calibration reports", "text"),
    ManagerParameter("report_per_run", True, "a subfolder of report_dir per calibration (false: report_dir "
                     "itself)", "flag"),
    ManagerParameter("chain_map_file", "", "chain map of the robot's programmed lines (chain_map's YAML, measured "
                     "with this sweep plan along the same lines): removed from every sweep of the marked plate; "
                     "read at every calibrate; a reference check must have been measured with the same map; "
                     "empty: none", "text"),
    ManagerParameter("reference_check_file", "", "reference check of the measurement chain (stated_accuracy's "
                     "YAML: a plate with known centres measured with this plan); read at every calibrate, written by "
                     "the reference_check service; empty: none, the cell then states no accuracy and labels its "
                     "measured figures self-consistency",
                     "text"),
    ManagerParameter("reference_plate_certificate", "", "certified centres of the reference plate the "
                     "reference_check service scans (CSV with a header x,y[,z], mm, in the gls frame where the "
                     "plate nominally lies, as gls-reference-check --certified); read at every check; empty: "
                     "no check", "text"),
    ManagerParameter("reference_plate_name", "", "names the reference plate and its certificate: recorded as "
                     "the check's reference (e.g. plate serial and certificate number); empty: no check", "text"),
    ManagerParameter("report.simulated_chain", "", "the simulated cell's measurement chain preset the figures come "
                     "from, said in the report and summary.json (gls-sim-cell sets it); empty: a real cell", "text"),
    ManagerParameter("rviz.arrow_scale", 50.0, "RViz deviation arrows are this many times longer than the "
                     "deviation", minimum=1.0, maximum=10000.0),
    ManagerParameter("rviz.colour_full_scale_mm", 1.0, "deviation drawn fully red in RViz (mm)", minimum=1e-4),
)
PARAMETERS_BY_NAME = {parameter.name: parameter for parameter in MANAGER_PARAMETERS}
SETTABLE = tuple(parameter.name for parameter in MANAGER_PARAMETERS if parameter.settable)


@dataclass(frozen=True)
class ManagerConfig:
    """What the manager runs with, built from the parameter values by :func:`manager_config`."""

    geometry: HeadGeometry
    settings: procedure.ProcedureSettings
    deadlines: Deadlines
    service_timeout_s: float
    resend_after_s: float
    plate_exchange_service: str
    ground_truth_service: str
    calibration_dir: Path
    report_root: Path
    report_per_run: bool
    reference_check_file: str
    reference_plate_certificate: str
    reference_plate_name: str
    chain_map_file: str
    simulated_chain: str
    arrow_scale: float
    colour_full_scale_mm: float


def numbers_value(name: str, value: Any) -> tuple[float, ...]:
    """Return a list-of-numbers parameter's value as floats; ValueError naming ``name``.

    The ValueError comes when it is not one; rcl reads ``[]`` as no value at all (None).
    """
    items = list(value) if isinstance(value, (list, tuple)) or hasattr(value, "tolist") else None
    if not items or not all(isinstance(item, (int, float)) and not isinstance(item, bool) for item in items) \
            or not all(math.isfinite(float(item)) for item in items):
        raise ValueError(f"parameter {name}: a non-empty list of finite numbers is needed, got {value!r}")
    return tuple(float(item) for item in items)


def value_problem(parameter: ManagerParameter, value: Any) -> str:
    """Why ``value`` (as YAML reads a ``-p`` rule) cannot be ``parameter``'s (empty when its type can).

    rcl keeps a parameter file's value when a ``-p`` rule gives one of another type, silently: a tool
    that passes parameter files checks its user's rules with this first.
    """
    if parameter.kind == "integer":
        fits = isinstance(value, int) and not isinstance(value, bool)
        wanted = "an integer"
    elif parameter.kind == "number":
        fits = isinstance(value, float) and math.isfinite(value)
        wanted = "a finite floating-point number (write 5.0 for 5)"
    elif parameter.kind == "numbers":
        fits = isinstance(value, list) and bool(value) and all(
            isinstance(item, float) and math.isfinite(item) for item in value)
        wanted = "a non-empty list of finite floating-point numbers"
    elif parameter.kind == "flag":
        fits, wanted = isinstance(value, bool), "true or false"
    else:
        fits, wanted = isinstance(value, str), "a text"
    if not fits:
        return f"{parameter.name} must be {wanted}, got {value!r}"
    low = parameter.minimum if parameter.minimum is not None else -math.inf
    high = parameter.maximum if parameter.maximum is not None else math.inf
    if parameter.kind in ("integer", "number") and not low <= value <= high:
        return f"{parameter.name} must be between {low:g} and {high:g}, got {value!r}"
    return ""


def manager_config(values: Mapping[str, Any]) -> ManagerConfig:
    """Build the manager's configuration from the value of every parameter of the table.

    ValueError naming the parameter when a value cannot be used, also for a combination (e.g.
    default_iterations above max_iterations).
    """
    def number(name: str) -> float:
        return float(values[name])

    def named(name: str, build):
        try:
            return build()
        except ValueError as error:
            raise ValueError(f"parameter {name}: {error}") from None

    deadlines = Deadlines(sweep_length_mm=number("sweep.length_mm"), sweep_speed_mm_s=number("sweep.speed_mm_s"),
                          marking_speed_mm_s=number("marking.speed_mm_s"), jump_time_s=number("marking.jump_time_s"),
                          factor=number("deadline_factor"), margin_s=number("deadline_margin_s"))
    radii = numbers_value("grid.ring_radii_mm", values["grid.ring_radii_mm"])
    plan = named("sweep.plan", lambda: parse_plan(values["sweep.plan"]))
    # ProcedureSettings names the setting it refuses (e.g. ring_radii_mm, default_iterations)
    settings = procedure.ProcedureSettings(
        grid_per_side=int(values["grid.per_side"]), grid_size_mm=number("grid.size_mm"), ring_radii_mm=radii,
        plain_sweep_step_mm=number("sweep.plain_step_mm"), plain_sweeps=int(values["sweep.plain_repeats"]),
        standstill_height=bool(values["sweep.standstill_height"]),
        marked_sweep_step_mm=number("sweep.marked_step_mm"),
        scanner_to_gls=scanner_to_gls_from(values["scanner_to_gls.translation_mm"], values["scanner_to_gls.rpy_rad"]),
        tolerance_rms_mm=number("tolerance_rms_mm"), min_found_fraction=number("min_found_fraction"),
        max_outlying_points=int(values["max_outlying_points"]), mark_check_sigmas=number("mark_check_sigmas"),
        max_cluster_points=int(values["max_cluster_points"]), mark_cluster_sigmas=number("mark_cluster_sigmas"),
        measurement_uncertainty_mm=number("measurement_uncertainty_mm"), max_cv_factor=number("max_cv_factor"),
        max_cv_fraction=number("max_cv_fraction"), default_iterations=int(values["default_iterations"]),
        max_iterations=int(values["max_iterations"]), sweep_plan=plan,
        profiles_placed_by_pose=bool(values["sweep.placed_by_pose"]),
        # sweep length and speed are the ones sent to the scanner (the deadlines' own)
        cell_time=CellTimeModel(sweep_length_mm=deadlines.sweep_length_mm, sweep_speed_mm_s=deadlines.sweep_speed_mm_s,
                                robot_move_s=number("sweep.robot_move_s")))
    return ManagerConfig(
        geometry=head_geometry_from(values), settings=settings, deadlines=deadlines,
        service_timeout_s=number("service_timeout_s"), resend_after_s=number("resend_after_s"),
        plate_exchange_service=str(values["plate_exchange_service"]),
        ground_truth_service=str(values["ground_truth_service"]),
        calibration_dir=Path(values["calibration_dir"]), report_root=Path(values["report_dir"]),
        report_per_run=bool(values["report_per_run"]), reference_check_file=str(values["reference_check_file"]),
        reference_plate_certificate=str(values["reference_plate_certificate"]),
        reference_plate_name=str(values["reference_plate_name"]),
        chain_map_file=str(values["chain_map_file"]), simulated_chain=str(values["report.simulated_chain"]),
        arrow_scale=number("rviz.arrow_scale"), colour_full_scale_mm=number("rviz.colour_full_scale_mm"))
