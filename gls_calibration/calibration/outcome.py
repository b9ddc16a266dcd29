"""One calibration's outcome and its figures: typed deviation metrics, the outcome, the run summary.

The summary is computed here once; the calibration manager answers ``calibrate`` from it, the
report writes it as ``summary.json`` and ``gls-sim-cell`` prints it.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
import math
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Optional

import numpy as np

from gls_calibration.calibration.stated_accuracy import SELF_CONSISTENCY, ChainCheck, stated_accuracy
from gls_calibration.calibration.uncertainty import VALIDATION_FLOOR
from gls_calibration.common.time_budget import StageTimes
from gls_calibration.common.validation import as_points, as_positive_number
from gls_calibration.correction.uncertainty_grid import UNCERTAINTY_KEY
from gls_calibration.registration.chain_map import NO_CHAIN_MAP
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.scan.plate_pose import PlatePose

if TYPE_CHECKING:  # the procedure builds outcomes from these; imported for the annotations only
    from gls_calibration.correction.setpoints import Correction
    from gls_calibration.models.training import TrainedModel

FULL_FIELD = "full"

INDEPENDENT = "independent"
"""Kind of a figure measured at positions the calibration it judges was not trained on (the
validation grid, half a pitch off), or through the nominal model; the chain that measures is the
same. ``SELF_CONSISTENCY`` (``stated_accuracy``): a calibration measured again at its own training
positions by the chain that trained it, which re-measures its own repeating errors."""


@dataclass(frozen=True)
class FieldMetrics:
    """Max and RMS of ``u_x``, ``u_y`` and ``|delta|`` (mm) over one (sub-)field; NaN when it holds no point."""

    count: int
    max_ux_mm: float
    rms_ux_mm: float
    max_uy_mm: float
    rms_uy_mm: float
    max_abs_mm: float
    rms_abs_mm: float


@dataclass(frozen=True)
class DeviationMetrics:
    """Metrics of a deviation field by (sub-)field name: ``"full"``, then ``"150x150"``, ``"50x50"`` ..."""

    fields: Mapping[str, FieldMetrics]

    @property
    def full(self) -> FieldMetrics:
        """Return the metrics over every point."""
        return self.fields[FULL_FIELD]

    def field(self, size_mm: Optional[float]) -> FieldMetrics:
        """Return the metrics of the centred ``size_mm`` square (None: the full field); KeyError when not computed."""
        return self.fields[_field_name(size_mm)]

    def to_dict(self) -> dict:
        """Plain nested dict (record, report): ``{field name: {count, max_ux_mm, ...}}``."""
        return {name: asdict(entry) for name, entry in self.fields.items()}


def _field_name(size_mm: Optional[float]) -> str:
    return FULL_FIELD if size_mm is None else f"{size_mm:g}x{size_mm:g}"


def deviation_metrics(targets_xy, deviations_xy,
                      subfields_mm: Sequence[Optional[float]] = (None, 150.0, 50.0)) -> DeviationMetrics:
    """Max and RMS of ``u_x``, ``u_y`` and ``|delta|`` (mm) over the full field and centred square sub-fields.

    Sub-fields are centred on the centre of the targets' bounding box and keep points with
    ``|x - cx|, |y - cy| <= size / 2 + 1e-9``; ``None`` means the full field. "max" is the maximum
    absolute value. A sub-field with no point has count 0 and NaN values (stored as null).
    """
    targets_xy = as_points(targets_xy, "targets_xy", 2)
    deviations_xy = as_points(deviations_xy, "deviations", 2)
    if targets_xy.shape[0] != deviations_xy.shape[0]:
        raise ValueError(f"targets_xy and deviations must have the same number of points, "
                         f"got {targets_xy.shape[0]} and {deviations_xy.shape[0]}")
    centre = 0.5 * (targets_xy.min(axis=0) + targets_xy.max(axis=0))
    offsets = np.abs(targets_xy - centre)
    magnitude = np.hypot(deviations_xy[:, 0], deviations_xy[:, 1])
    entries: dict[str, FieldMetrics] = {}
    for size in subfields_mm:
        if size is None:
            selected = np.ones(targets_xy.shape[0], dtype=bool)
        else:
            half = 0.5 * as_positive_number(size, "subfields_mm") + 1e-9
            selected = np.all(offsets <= half, axis=1)
        values: dict[str, Any] = {"count": int(np.count_nonzero(selected))}
        for label, column in (("ux", deviations_xy[selected, 0]), ("uy", deviations_xy[selected, 1]),
                              ("abs", magnitude[selected])):
            empty = column.size == 0
            values[f"max_{label}_mm"] = math.nan if empty else float(np.max(np.abs(column)))
            values[f"rms_{label}_mm"] = math.nan if empty else float(np.sqrt(np.mean(column ** 2)))
        entries[_field_name(size)] = FieldMetrics(**values)
    return DeviationMetrics(MappingProxyType(entries))


@dataclass(frozen=True)
class PlateRun:
    """One plate marked with a grid and measured: paired targets and deviations (gls frame, mm).

    Parameters
    ----------
    targets : numpy.ndarray, shape (N, 3)
        All commanded fiducial centres, mm.
    paired_targets_xy : numpy.ndarray, shape (M, 2)
        The targets paired with a measured centre, mm.
    deviations : numpy.ndarray, shape (M, 2)
        delta = Q - P after rigid alignment, mm.
    measured_gls : numpy.ndarray, shape (M, 3)
        Measured centres P, aligned into the gls frame, mm.
    corrections : numpy.ndarray, shape (M, 2)
        K(Q) - K(P): what to add at P to land on P (training data), mm.
    true_deviations : numpy.ndarray, shape (M, 2), or None
        From the ground truth (simulation only), mm.
    plate_pose_gls : PlatePose
        The plate in the gls frame.
    fiducials_found : int
        Fiducials with a measured centre (seen in at least one pass of the plan; a turned pass sees
        only part of the grid, so this is not the count of any one sweep).
    alignment : RigidTransform
        The rigid alignment of the measured centres.
    metrics : DeviationMetrics
        Of ``deviations``.
    true_metrics : DeviationMetrics or None
        Over every target, from the ground truth.
    sigma_mm : numpy.ndarray, shape (M,), optional
        Standard uncertainty per axis of each measured centre, mm.
    sweep_plan : str, default "0+"
        The passes over the marked plate (``sweep_plan.parse_plan``).
    chain_map : str, default NO_CHAIN_MAP
        Identity of the chain map removed from every sweep.
    cell_time_s : float, optional
        Sweeps at the configured speed, robot moves, marking, s.
    scanner_error_rms_mm, motion_error_rms_mm : float, optional
        RMS of the removed scanner-frame (lateral) error and per-sweep motion error, mm.
    """

    targets: np.ndarray             # (N, 3) all commanded fiducial centres
    paired_targets_xy: np.ndarray   # (M, 2)
    deviations: np.ndarray          # (M, 2) delta = Q - P after rigid alignment
    measured_gls: np.ndarray        # (M, 3) measured centres P, aligned into the gls frame
    corrections: np.ndarray         # (M, 2) K(Q) - K(P): what to add at P to land on P (training data)
    true_deviations: Optional[np.ndarray]  # (M, 2) from the ground truth (simulation only)
    plate_pose_gls: PlatePose
    fiducials_found: int
    alignment: RigidTransform
    metrics: DeviationMetrics              # of ``deviations``
    true_metrics: Optional[DeviationMetrics]  # over every target, from the ground truth
    sigma_mm: Optional[np.ndarray] = None  # (M,) standard uncertainty per axis of each measured centre
    sweep_plan: str = "0+"                 # the passes over the marked plate (``sweep_plan.parse_plan``)
    chain_map: str = NO_CHAIN_MAP          # identity of the chain map removed from every sweep (``chain_map``)
    cell_time_s: float = math.nan          # sweeps at the configured speed, robot moves, marking
    scanner_error_rms_mm: float = math.nan  # RMS of the removed scanner-frame (lateral) error
    motion_error_rms_mm: float = math.nan   # RMS of the removed per-sweep motion error


@dataclass(frozen=True)
class Candidate:
    """A calibration saved (not activated) during a run, with its validated record.

    It holds its file, its validated record and the correction it describes; it travels as this
    object (``Cell.use_candidate``), never re-read.
    """

    path: str
    correction: "Correction"
    record: Optional[Mapping] = None


@dataclass(frozen=True)
class CalibrationOutcome:
    """What one successful calibrate request produced (a failure raises ``CalibrationError`` instead).

    Parameters
    ----------
    message : str
        One line on the result.
    runs : tuple of PlateRun
        The training plates, one per iteration.
    validation : PlateRun or None
        The validation plate, marked through the candidate.
    models : tuple of TrainedModel
        The models trained, one per iteration.
    candidate : Candidate or None
        The calibration saved (not activated); None when nothing was trained (the first plate was
        within the tolerance).
    duration_s : float
        Wall time of the run, s.
    rejection : str, optional
        Why a validated candidate must not replace the calibration in use (empty: accepted); the run
        then went through, but nothing is activated.
    active_validation : PlateRun, optional
        The plate marked through the calibration in use at the validation positions, which the
        candidate was judged against (None when it was judged against the first plate).
    active_calibration : bool, default False
        The first plate was marked through a trained calibration (not the nominal model).
    stage_times : StageTimes, optional
        Wall time per stage of the flow (``time_budget``).
    """

    message: str
    runs: tuple[PlateRun, ...]
    validation: Optional[PlateRun]
    models: tuple["TrainedModel", ...]
    candidate: Optional[Candidate]
    duration_s: float
    rejection: str = ""
    active_validation: Optional[PlateRun] = None
    active_calibration: bool = False
    stage_times: StageTimes = StageTimes()     # wall time per stage of the flow (``time_budget``)


@dataclass(frozen=True)
class RunSummary:
    """The figures of one calibration (mm; NaN where a figure does not apply).

    ``pre``: the first plate, marked through the calibration active before; ``post``: the
    validation plate, marked through the new one. Measured figures come from the scanner's
    measurement; ``true_*`` from the simulation's ground truth (NaN on a real cell).
    ``active_post_*``: the calibration in use marked on the validation grid too (when one was active
    and the run validated). ``*_kind`` say which figures are self-consistency (a calibration at its
    own training positions: the first plate through an active calibration, or a validation grid on
    the training positions) and which are independent of the training positions; every measured
    figure comes from the same chain, which cannot see its own repeating errors. Built by
    :func:`summarise`; its fields are the parameters.

    Parameters
    ----------
    message : str
        One line on the result.
    pre_rms_mm, pre_max_mm, post_rms_mm, post_max_mm : float
        Measured deviation RMS and maximum before and after, mm.
    true_pre_rms_mm, true_pre_max_mm, true_post_rms_mm, true_post_max_mm : float
        The same from the ground truth, mm.
    true_post_rms_150_mm : float
        True RMS after over the central 150 x 150 mm, mm.
    fiducials_expected, fiducials_found : int
        On the first plate.
    iterations, neurons : int
        Plates trained on; units of the last model.
    method : str
        The last model's method.
    cv_rms_mm : float
        Its cross-validated RMS, mm.
    duration_s : float
        Wall time of the run, s.
    calibration_file : str
        The candidate's file ("" without one).
    iteration_rms_mm : tuple of float
        Measured RMS of each training plate, mm.
    sweep_plan, chain_map : str, optional
        The plan and the chain map's identity.
    cell_time_s : float, optional
        Every plate: sweeps at the configured speed, moves, marking, s.
    fiducial_sigma_median_mm, fiducial_sigma_max_mm : float, optional
        First plate: standard uncertainty per axis of a centre, mm.
    scanner_error_rms_mm, motion_error_rms_mm : float, optional
        First plate: removed error fixed to the scanner frame and per-sweep motion error, mm.
    scanner_share : float, optional
        Removed (scanner + motion) RMS / measured deviation RMS.
    stated_rms_mm : float, optional
        The accuracy the cell states (2-D RMS), mm, on the basis ``stated_basis``.
    stated_basis, stated_explanation : str, optional
        A reference check of the chain, or ``self-consistency`` when there is none; why.
    reference_sigma_mm : tuple of float, optional
        The reference check's per-axis sigma (k = 1), mm, when used.
    pre_kind, post_kind, active_post_kind : str, optional
        INDEPENDENT or SELF_CONSISTENCY ("" when not measured).
    active_post_rms_mm, active_post_max_mm, true_active_post_rms_mm : float, optional
        The calibration in use, marked on the validation grid, mm.
    accepted_against : str, optional
        What the candidate was judged against.
    stage_wall_s : mapping of str to float, optional
        Wall time per stage, s.
    last_sweep_to_result_s : float, optional
        End of the last marked-plate sweep to the flow's result, s.
    last_profile_to_activation_s : float, optional
        End of the last marked-plate sweep (its last profile) to the candidate activated and the
        correction node asked to load it, s; the report and its files come before the activation.
        Filled in by the calibration manager after the activation (``summary.json`` is written
        again); NaN where nothing was activated.
    compute_cpu_s : float, optional
        The pipeline's CPU (its nodes' threads, the simulation's excluded), s. Measurable only where
        the nodes share one process: ``gls-sim-cell`` fills it in; NaN otherwise.
    measurement_preset : str, optional
        The simulated measurement chain's preset; empty: a real cell.
    certificate_u95_full_mm, certificate_u95_central_mm, certificate_u95_median_mm : float, optional
        The certificate's U (95 % radius of the 2-D landing) of the candidate: largest over the
        centred 190 x 190 mm and over the central 150 x 150 mm, median over its grid, mm.
    certificate_coverage : float, optional
        In simulation, the fraction of validation fiducials whose TRUE landing error is within U.
    certificate_reference : str, optional
        What the chain term rests on.
    certificate_validation_mm : float, optional
        The per-axis standard uncertainty (k = 1) the validation plate added to U over the field
        (``uncertainty.with_validation_floor``), mm: 0 where the budget as trained already implied
        more; NaN without a U map or a validation plate.
    """

    message: str
    pre_rms_mm: float
    pre_max_mm: float
    post_rms_mm: float
    post_max_mm: float
    true_pre_rms_mm: float
    true_pre_max_mm: float
    true_post_rms_mm: float
    true_post_max_mm: float
    true_post_rms_150_mm: float
    fiducials_expected: int
    fiducials_found: int
    iterations: int
    neurons: int
    method: str
    cv_rms_mm: float
    duration_s: float
    calibration_file: str
    iteration_rms_mm: tuple[float, ...]
    sweep_plan: str = "0+"
    chain_map: str = NO_CHAIN_MAP               # identity of the chain map removed from every sweep
    cell_time_s: float = math.nan               # every plate: sweeps at the configured speed, moves, marking
    fiducial_sigma_median_mm: float = math.nan  # first plate: standard uncertainty per axis of a centre
    fiducial_sigma_max_mm: float = math.nan
    scanner_error_rms_mm: float = math.nan      # first plate: removed error fixed to the scanner frame
    motion_error_rms_mm: float = math.nan       # first plate: removed per-sweep motion error
    scanner_share: float = math.nan             # removed (scanner + motion) RMS / measured deviation RMS
    stated_rms_mm: float = math.nan             # the accuracy stated (2-D RMS), see stated_accuracy
    stated_basis: str = "self-consistency"
    stated_explanation: str = ""
    reference_sigma_mm: tuple[float, ...] = ()  # the reference check's per-axis sigma (k = 1), when used
    # which kind each figure is (INDEPENDENT or SELF_CONSISTENCY; "" when not measured), and what
    # the candidate was judged against: "active calibration on the validation grid", "first plate" or ""
    pre_kind: str = ""
    post_kind: str = ""
    active_post_kind: str = ""
    active_post_rms_mm: float = math.nan        # the calibration in use, marked on the validation grid
    active_post_max_mm: float = math.nan
    true_active_post_rms_mm: float = math.nan
    accepted_against: str = ""
    stage_wall_s: Mapping[str, float] = field(default_factory=dict)   # wall time per stage (time_budget)
    last_sweep_to_result_s: float = math.nan    # end of the last marked-plate sweep to the flow's result
    last_profile_to_activation_s: float = math.nan   # ... to the activation (set after it)
    compute_cpu_s: float = math.nan             # the pipeline's CPU, where the nodes share a process
    measurement_preset: str = ""                # the simulated measurement chain's preset; empty: a real cell
    # the certificate (calibration.uncertainty): U (95 % radius of the 2-D landing, mm) of the candidate,
    # largest over the centred 190 x 190 mm and over the central 150 x 150 mm, median over its grid; in
    # simulation the fraction of validation fiducials whose TRUE landing error is within U; what the
    # chain term rests on
    certificate_u95_full_mm: float = math.nan
    certificate_u95_central_mm: float = math.nan
    certificate_u95_median_mm: float = math.nan
    certificate_coverage: float = math.nan
    certificate_reference: str = ""
    certificate_validation_mm: float = math.nan

    def to_dict(self) -> dict:
        """Return the summary as plain values, in field order (``summary.json``)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values["iteration_rms_mm"] = list(self.iteration_rms_mm)
        values["reference_sigma_mm"] = list(self.reference_sigma_mm)
        values["stage_wall_s"] = dict(self.stage_wall_s)
        return values


def _full(metrics: Optional[DeviationMetrics], name: str) -> float:
    return float(getattr(metrics.full, name)) if metrics is not None else math.nan


def summarise(outcome: CalibrationOutcome, chain_check: Optional[ChainCheck] = None,
              placement: str = "pose", *, measurement_preset: str = "") -> RunSummary:
    """Return the run summary of ``outcome`` with the stated accuracy and measurement preset.

    Parameters
    ----------
    outcome : CalibrationOutcome
        The run.
    chain_check : ChainCheck, optional
        The reference check of the chain, measured with the plan the run used and profiles placed
        by ``placement``; it gives the stated accuracy.
    placement : str, default "pose"
        How the run placed its profiles (by the robot's reported pose, or by time).
    measurement_preset : str, optional
        Names the simulated measurement chain (empty: a real cell).

    Returns
    -------
    RunSummary
        The run's figures (mm; NaN where a figure does not apply).
    """
    first, validation = outcome.runs[0], outcome.validation
    last_model = outcome.models[-1] if outcome.models else None
    measured_after = validation.metrics if validation else None
    true_after = validation.true_metrics if validation else None
    return RunSummary(
        message=outcome.message, measurement_preset=measurement_preset,
        pre_rms_mm=_full(first.metrics, "rms_abs_mm"), pre_max_mm=_full(first.metrics, "max_abs_mm"),
        post_rms_mm=_full(measured_after, "rms_abs_mm"), post_max_mm=_full(measured_after, "max_abs_mm"),
        true_pre_rms_mm=_full(first.true_metrics, "rms_abs_mm"),
        true_pre_max_mm=_full(first.true_metrics, "max_abs_mm"),
        true_post_rms_mm=_full(true_after, "rms_abs_mm"), true_post_max_mm=_full(true_after, "max_abs_mm"),
        true_post_rms_150_mm=float(true_after.field(150.0).rms_abs_mm) if true_after else math.nan,
        fiducials_expected=len(first.targets), fiducials_found=first.fiducials_found,
        iterations=len(outcome.runs),
        neurons=last_model.neurons if last_model else 0,
        method=last_model.method if last_model else "",
        cv_rms_mm=last_model.cv_rms_mm if last_model else math.nan,
        duration_s=outcome.duration_s,
        calibration_file=outcome.candidate.path if outcome.candidate else "",
        iteration_rms_mm=tuple(_full(run.metrics, "rms_abs_mm") for run in outcome.runs),
        sweep_plan=first.sweep_plan, chain_map=first.chain_map,
        cell_time_s=float(sum(run.cell_time_s for run in outcome.runs + tuple(
            plate for plate in (validation, outcome.active_validation) if plate is not None))),
        fiducial_sigma_median_mm=_nan_stat(np.nanmedian, first.sigma_mm),
        fiducial_sigma_max_mm=_nan_stat(np.nanmax, first.sigma_mm),
        scanner_error_rms_mm=first.scanner_error_rms_mm, motion_error_rms_mm=first.motion_error_rms_mm,
        scanner_share=math.hypot(first.scanner_error_rms_mm, first.motion_error_rms_mm)
        / _full(first.metrics, "rms_abs_mm"),
        **_stated(measured_after, chain_check, first, placement),
        stage_wall_s=dict(outcome.stage_times.wall_s),
        last_sweep_to_result_s=outcome.stage_times.last_sweep_to_result_s,
        **_kinds(outcome), **_certificate(outcome, chain_check))


def _certificate(outcome: CalibrationOutcome, check: Optional[ChainCheck]) -> dict:
    """Return the certificate's figures of the candidate's U map, and its coverage where the truth is known."""
    correction = outcome.candidate.correction if outcome.candidate is not None else None
    grid = getattr(correction, "uncertainty", None)
    if grid is None:
        return {}
    full = grid.field_figures(190.0)[1]         # the grid's 190 x 190 mm (it spans the rings' margin too)
    _, central, median = grid.field_figures(150.0)
    values: dict[str, Any] = {"certificate_u95_full_mm": full, "certificate_u95_central_mm": central,
                              "certificate_u95_median_mm": median,
                              "certificate_reference": (f"reference check: {check.reference}" if check is not None
                                                        else "none (no reference check: the chain term is assumed "
                                                             "and the scale is the scanner's own)")}
    validation = outcome.validation
    if validation is not None:
        stored = (outcome.candidate.record or {}).get(UNCERTAINTY_KEY) or {}
        values["certificate_validation_mm"] = next((float(line["rms_mm"]) for line in stored.get("budget", [])
                                                    if line.get("name") == VALIDATION_FLOOR), 0.0)
    if validation is not None and validation.true_deviations is not None:
        u = grid.at(validation.paired_targets_xy[:, 0], validation.paired_targets_xy[:, 1])
        values["certificate_coverage"] = float(np.mean(np.hypot(*validation.true_deviations.T) <= u))
    return values


def _kinds(outcome: CalibrationOutcome) -> dict:
    """Return the kind of each figure of ``outcome`` and the figures the candidate was judged by.

    Which kind each figure of ``outcome`` is, the active calibration's validation figures, and
    what the candidate was judged against.
    """
    validation, active = outcome.validation, outcome.active_validation
    values: dict[str, Any] = {"pre_kind": SELF_CONSISTENCY if outcome.active_calibration else INDEPENDENT}
    if validation is not None:
        # the validation grid is the training grid unless it is offset (ProcedureSettings.validation_offset_half_pitch)
        on_training = np.array_equal(np.asarray(validation.targets)[:, :2], np.asarray(outcome.runs[0].targets)[:, :2])
        kind = SELF_CONSISTENCY if on_training else INDEPENDENT
        values["post_kind"] = kind
        values["accepted_against"] = "first plate" if active is None else "active calibration on the validation grid"
        if active is not None:
            values.update(active_post_kind=kind, active_post_rms_mm=_full(active.metrics, "rms_abs_mm"),
                          active_post_max_mm=_full(active.metrics, "max_abs_mm"),
                          true_active_post_rms_mm=_full(active.true_metrics, "rms_abs_mm"))
    return values


def _stated(measured: Optional[DeviationMetrics], check: Optional[ChainCheck], first: PlateRun,
            placement: str) -> dict:
    """Return the stated-accuracy fields of the summary: only a validated run states a figure."""
    if measured is None or not math.isfinite(measured.full.rms_abs_mm):
        return {"stated_basis": SELF_CONSISTENCY,
                "stated_explanation": "not validated: no figure of the calibration's accuracy"}
    stated = stated_accuracy(float(measured.full.rms_abs_mm), check, plan=first.sweep_plan, placement=placement,
                             chain_map=first.chain_map, targets_xy_mm=first.targets)
    return {"stated_rms_mm": stated.rms_mm, "stated_basis": stated.basis, "stated_explanation": stated.explanation,
            "reference_sigma_mm": tuple(check.sigma_mm) if check is not None and math.isfinite(stated.rms_mm) else ()}


def _nan_stat(statistic, values: Optional[np.ndarray]) -> float:
    """``statistic`` of the finite ``values``; NaN when there is none."""
    if values is None:
        return math.nan
    values = np.asarray(values, dtype=float)
    return float(statistic(values[np.isfinite(values)])) if np.any(np.isfinite(values)) else math.nan
