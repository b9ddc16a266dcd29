"""A calibration run <-> the calibration record the store keeps (plain numbers, YAML).

The record carries everything the correction needs (models in order of application and the
calibrated region), what a person or the discrepancy workflow needs later (metrics, hyper-
parameters, the measured fiducials of the first plate) and where it came from (head, plate pose).
"""
from __future__ import annotations

from datetime import datetime, timezone
import hashlib
import logging
from typing import Mapping, Optional, Sequence

import numpy as np

from gls_calibration.calibration.outcome import Candidate
from gls_calibration.calibration.outcome import PlateRun
from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.calibration.record_file import CalibrationRecord, dump_record, new_record
from gls_calibration.calibration.stated_accuracy import ChainCheck
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.calibration.uncertainty import run_budget, with_validation_floor_stored
from gls_calibration.correction.setpoints import CalibratedRegion, Correction
from gls_calibration.correction.uncertainty_grid import UNCERTAINTY_KEY, UncertaintyGrid
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.deviation_models import model_from_dict
from gls_calibration.models.training import TrainedModel


_LOG = logging.getLogger(__name__)
TAPER_MM = 10.0   # fade of the correction beyond the calibrated region (correction.taper_weight)


def region_around(targets_xy: np.ndarray, ring_radii_mm: Sequence[float], plane_z_mm: float = 0.0) -> CalibratedRegion:
    """Return the calibrated region: the fiducial targets' box padded by the outer ring radius.

    The one rule of the calibrated region: padded so that whole rings stay inside, on the plane
    ``z = plane_z_mm`` where the plate was measured.

    Parameters
    ----------
    targets_xy : numpy.ndarray, shape (N, 2)
        The fiducial targets, gls frame, mm.
    ring_radii_mm : sequence of float
        The ring radii, mm.
    plane_z_mm : float, default 0.0
        Height of the calibration plane, mm.

    Returns
    -------
    CalibratedRegion
        The padded box.

    Raises
    ------
    ValueError
        If ``targets_xy`` is not (N, 2) finite or the plane is not finite.

    Examples
    --------
    >>> region_around(np.array([[-95.0, -95.0], [95.0, 95.0]]), (2.5, 2.7))
    CalibratedRegion(x_min=-97.7, x_max=97.7, y_min=-97.7, y_max=97.7, plane_z_mm=0.0)
    """
    box = CalibratedRegion.from_points(targets_xy, plane_z_mm)
    pad = max(ring_radii_mm)
    return CalibratedRegion(box.x_min - pad, box.x_max + pad, box.y_min - pad, box.y_max + pad, plane_z_mm)


def calibrated_region(settings: ProcedureSettings, plane_z_mm: float = 0.0) -> CalibratedRegion:
    """:func:`region_around` the training grid of ``settings``."""
    half = settings.grid_size_mm / 2.0
    return region_around(np.array([[-half, -half], [half, half]]), settings.ring_radii_mm, plane_z_mm)


def calibration_record(geometry: HeadGeometry, *, plate_pose, models: Sequence[Mapping],
                       trained: Sequence[TrainedModel], region: CalibratedRegion, targets_xy: np.ndarray,
                       measured_xyz: np.ndarray, deviations_xy: np.ndarray, through_nominal_model: bool,
                       metrics: Mapping, source: Mapping | None = None,
                       uncertainty: Mapping | None = None) -> CalibrationRecord:
    """Return the record of a calibration, built the same way by the calibrate flow and by ``gls-train``.

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    plate_pose : PlatePose
        The plate (normal, centre, rotation, flatness).
    models : sequence of mapping
        Every model's ``to_dict()`` in order of application (earlier calibrations' first).
    trained : sequence of TrainedModel
        The ones trained now (their hyper-parameters are recorded).
    region : CalibratedRegion
        Where the models were trained.
    targets_xy : numpy.ndarray, shape (N, 2)
        The first plate's targets, mm.
    measured_xyz : numpy.ndarray, shape (N, 3)
        Its measured centres, gls frame, aligned, mm.
    deviations_xy : numpy.ndarray, shape (N, 2)
        Q - P, mm.
    through_nominal_model : bool
        That plate was marked through the nominal model (what the discrepancy workflow assumes),
        else through an earlier calibration.
    metrics : mapping
        The run's metrics.
    source : mapping, optional
        Where the data came from (an offline tool's inputs).
    uncertainty : mapping, optional
        The certificate's U map (``correction.uncertainty_grid``), when there is one.

    Returns
    -------
    CalibrationRecord
        The validated record.

    Raises
    ------
    CalibrationFileError
        If the record does not validate.
    """
    hyper_parameters = {"trained_models": [
        {"method": model.method, "neurons": model.neurons, "spread_mm": model.spread_mm,
         "cv_rms_mm": model.cv_rms_mm} for model in trained]}
    if source is not None:
        hyper_parameters["source"] = dict(source)
    return new_record(
        head=geometry, plate_pose=plate_pose, models=list(models),
        calibrated_region={**region.to_dict(), "taper_mm": TAPER_MM},
        hyper_parameters=hyper_parameters, metrics=metrics,
        fiducials={"target_x": targets_xy[:, 0], "target_y": targets_xy[:, 1],
                   "measured_x": measured_xyz[:, 0], "measured_y": measured_xyz[:, 1],
                   "measured_z": measured_xyz[:, 2], "dx": deviations_xy[:, 0], "dy": deviations_xy[:, 1],
                   "commanded_through_nominal_model": bool(through_nominal_model)},
        uncertainty=uncertainty)


def build_record(geometry: HeadGeometry, settings: ProcedureSettings, runs: Sequence[PlateRun],
                 models: Sequence[TrainedModel], existing_models: Sequence[Mapping],
                 chain_check: Optional[ChainCheck] = None) -> CalibrationRecord:
    """Build the record of a run from its trained ``models`` and its certificate's U map.

    The U map's chain term comes from ``chain_check`` when that was made with the run's plan and is
    assumed otherwise. Every trained type is covered (RBF/TPS alone and physics first); a budget that
    cannot be made (bad training data) leaves the map out: the file then serves NaN, as an older file does.

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    settings : ProcedureSettings
        The run's settings (ring radii for the calibrated region).
    runs : sequence of PlateRun
        The plates the models were trained on.
    models : sequence of TrainedModel
        The models trained now.
    existing_models : sequence of mapping
        The models of the calibration in use, applied first.
    chain_check : ChainCheck, optional
        The reference check of the chain.

    Returns
    -------
    CalibrationRecord
        The validated record.

    Raises
    ------
    CalibrationFileError
        If the record does not validate.
    """
    first = runs[0]
    region = calibrated_region(settings, float(np.mean(first.targets[:, 2])))
    try:
        uncertainty = run_budget(runs, models, settings, region.to_dict(), geometry.working_distance_mm,
                                 chain_check).to_dict()
    except (ValueError, KeyError) as error:
        _LOG.warning("no uncertainty map for this calibration: %s", error)
        uncertainty = None
    return calibration_record(
        geometry, plate_pose=runs[-1].plate_pose_gls,
        models=list(existing_models) + [model.model for model in models], trained=models,
        # The calibration plane: the mean height the first plate's targets were commanded at (the
        # plate's plane); targets off it are corrected through Q'.
        region=region, targets_xy=first.paired_targets_xy, measured_xyz=first.measured_gls,
        deviations_xy=first.deviations, through_nominal_model=not existing_models,
        metrics={"iterations": [run.metrics.to_dict() for run in runs]}, uncertainty=uncertainty)


def save_candidate(store: CalibrationStore, record: CalibrationRecord, geometry: HeadGeometry) -> Candidate:
    """Store ``record`` without activating it.

    Parameters
    ----------
    store : CalibrationStore
        The store.
    record : CalibrationRecord
        The validated record.
    geometry : HeadGeometry
        The nominal head.

    Returns
    -------
    Candidate
        The candidate's file, its record and the correction it describes.

    Raises
    ------
    ValueError
        If the record describes an unusable correction (checked before anything is saved).
    """
    correction = correction_from_record(record, geometry)   # refuses an unusable record before saving
    return Candidate(str(store.save(record, activate=False)), correction, record)


def certified_candidate(store: CalibrationStore, candidate: Candidate, geometry: HeadGeometry,
                        post_rms_mm: float, chain_check: Optional[ChainCheck], check_matches: bool) -> Candidate:
    """Return the candidate whose certificate holds what its validation showed: raised, a new file; or itself.

    After the validation plate, the candidate's U map is raised to the validation's measured RMS in
    quadrature with the reference check where it is below (``uncertainty.with_validation_floor``).
    A raised map is a new candidate in the history (the first stays there, inactive: files are
    written once), with the ``validation`` line in its budget; without a U map, a validated figure
    or a matching check the candidate is returned as it is.

    Parameters
    ----------
    store : CalibrationStore
        The store the candidate was saved in.
    candidate : Candidate
        The validated candidate.
    geometry : HeadGeometry
        The nominal head.
    post_rms_mm : float
        The validation plate's measured 2-D RMS after calibration.
    chain_check : ChainCheck, optional
        The reference check of the chain.
    check_matches : bool
        The check was made with the calibration's plan, placement and chain map.

    Returns
    -------
    Candidate
        The candidate to activate.

    Raises
    ------
    OSError
        If the new file cannot be written (nothing is activated; the first candidate stays).
    """
    stored = None if candidate.record is None else candidate.record.get(UNCERTAINTY_KEY)
    if stored is None:
        return candidate
    raised = with_validation_floor_stored(stored, post_rms_mm, chain_check, check_matches)
    if raised is None:
        return candidate
    record = CalibrationRecord({**dict(candidate.record), UNCERTAINTY_KEY: raised})
    return save_candidate(store, record, geometry)


def record_models(record: Mapping) -> list[dict]:
    """Return the model dicts of a record, in order of application.

    Parameters
    ----------
    record : mapping
        A validated calibration record.

    Returns
    -------
    list of dict
        Copies of its models' ``to_dict()`` forms.
    """
    return [dict(model) for model in record["models"]]


def correction_from_record(record: Mapping, geometry: HeadGeometry) -> Correction:
    """Build the correction a record describes.

    Parameters
    ----------
    record : mapping
        A validated calibration record.
    geometry : HeadGeometry
        The nominal head.

    Returns
    -------
    Correction
        Its models, region, taper and U map (when the record holds one).

    Raises
    ------
    ValueError
        When its models or region are unusable, or when its field is not finite or beyond the
        physical limit (:meth:`Correction.check_field`).
    """
    models = [model_from_dict(model) for model in record["models"]]
    region = CalibratedRegion.from_dict(record["calibrated_region"]) if models else None
    grid = None
    if UNCERTAINTY_KEY in record:
        grid = UncertaintyGrid.from_dict(record[UNCERTAINTY_KEY])
    elif models:
        _warn_no_uncertainty_once()
    correction = Correction(geometry, models, region, record["calibrated_region"].get("taper_mm", TAPER_MM),
                            uncertainty=grid)
    correction.check_field()
    return correction


_warned: list[bool] = []


def _warn_no_uncertainty_once() -> None:
    """One warning per process for calibrations without a U map (older files): served with NaN."""
    if not _warned:
        _warned.append(True)
        _LOG.warning("calibration without an uncertainty map (written before the certificate): "
                     "uncertainty_k2_mm is served as NaN")


def record_fiducials(record: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """Return the commanded targets and measured positions of a record's first plate.

    Parameters
    ----------
    record : mapping
        A validated calibration record.

    Returns
    -------
    commanded : numpy.ndarray, shape (N, 2)
        The targets, gls frame, mm.
    measured : numpy.ndarray, shape (N, 2)
        The measured centres, gls frame, mm.
    """
    fiducials = record["fiducials"]
    commanded = np.column_stack([fiducials["target_x"], fiducials["target_y"]]).astype(float)
    measured = np.column_stack([fiducials["measured_x"], fiducials["measured_y"]]).astype(float)
    return commanded, measured


def record_identity(record: Mapping) -> tuple[str, datetime]:
    """Return a record's content hash (sha256 of its YAML, 16 hex digits) and creation time.

    Which calibration a record is: what a correction answer names so that a client knows who answered.

    Parameters
    ----------
    record : mapping
        A validated calibration record.

    Returns
    -------
    content_hash : str
        16 hex digits.
    created : datetime.datetime
        Its creation time, UTC when the record names no zone.
    """
    content_hash = hashlib.sha256(dump_record(record).encode("utf-8")).hexdigest()[:16]
    created = datetime.fromisoformat(record["created_utc"])
    return content_hash, created if created.tzinfo else created.replace(tzinfo=timezone.utc)
