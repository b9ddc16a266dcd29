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
from gls_calibration.calibration.record_file import dump_record, new_record
from gls_calibration.calibration.stated_accuracy import ChainCheck
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.calibration.uncertainty import run_budget
from gls_calibration.correction.setpoints import CalibratedRegion, Correction
from gls_calibration.correction.uncertainty_grid import UNCERTAINTY_KEY, UncertaintyGrid
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.deviation_models import model_from_dict
from gls_calibration.models.training import TrainedModel


_LOG = logging.getLogger(__name__)
TAPER_MM = 10.0   # fade of the correction beyond the calibrated region (correction.taper_weight)


def calibrated_region(settings: ProcedureSettings, plane_z_mm: float = 0.0) -> CalibratedRegion:
    """The training grid's box, padded by the outer ring radius so whole rings stay inside, on the
    plane ``z = plane_z_mm`` where the plate was measured."""
    half = settings.grid_size_mm / 2.0 + max(settings.ring_radii_mm)
    return CalibratedRegion(-half, half, -half, half, plane_z_mm)


def build_record(geometry: HeadGeometry, settings: ProcedureSettings, runs: Sequence[PlateRun],
                 models: Sequence[TrainedModel], existing_models: Sequence[Mapping],
                 chain_check: Optional[ChainCheck] = None) -> dict:
    """The record of a run whose ``models`` were trained on ``runs`` (after ``existing_models``),
    with its certificate's U map (``uncertainty``; its chain term from ``chain_check`` when that
    was made with the run's plan, assumed otherwise). A model the certificate does not cover (physics
    first) leaves the map out: the file then serves NaN, as an older file does."""
    first = runs[0]
    region = calibrated_region(settings, float(np.mean(first.targets[:, 2]))).to_dict()
    try:
        uncertainty = run_budget(runs, models, settings, region, geometry.working_distance_mm, chain_check).to_dict()
    except (ValueError, KeyError) as error:
        _LOG.warning("no uncertainty map for this calibration: %s", error)
        uncertainty = None
    fiducials = {
        "target_x": first.paired_targets_xy[:, 0], "target_y": first.paired_targets_xy[:, 1],
        "measured_x": first.measured_gls[:, 0], "measured_y": first.measured_gls[:, 1],
        "measured_z": first.measured_gls[:, 2],
        "dx": first.deviations[:, 0], "dy": first.deviations[:, 1],
        # Whether the first plate was marked through the nominal model (what the discrepancy
        # workflow assumes) or through an earlier calibration.
        "commanded_through_nominal_model": not existing_models,
    }
    return new_record(
        head=geometry, plate_pose=runs[-1].plate_pose_gls,
        models=list(existing_models) + [model.model for model in models],
        # The calibration plane: the mean height the first plate's targets were commanded at (the
        # plate's plane); targets off it are corrected through Q'.
        calibrated_region={**region, "taper_mm": TAPER_MM},
        hyper_parameters={"trained_models": [
            {"method": model.method, "neurons": model.neurons, "spread_mm": model.spread_mm,
             "cv_rms_mm": model.cv_rms_mm} for model in models]},
        metrics={"iterations": [run.metrics.to_dict() for run in runs]},
        fiducials=fiducials, uncertainty=uncertainty)


def save_candidate(store: CalibrationStore, record: Mapping, geometry: HeadGeometry) -> Candidate:
    """Store ``record`` without activating it; the candidate's file and the correction it describes."""
    correction = correction_from_record(record, geometry)   # refuses an unusable record before saving
    return Candidate(str(store.save(record, activate=False)), correction)


def record_models(record: Mapping) -> list[dict]:
    """The model dicts of a record, in order of application."""
    return [dict(model) for model in record["models"]]


def correction_from_record(record: Mapping, geometry: HeadGeometry) -> Correction:
    """The correction a record describes (ValueError when its models or region are unusable, or
    when its field is not finite or beyond the physical limit: :meth:`Correction.check_field`)."""
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
    """Commanded targets (N, 2) and measured positions (N, 2) of a record's first plate."""
    fiducials = record["fiducials"]
    commanded = np.column_stack([fiducials["target_x"], fiducials["target_y"]]).astype(float)
    measured = np.column_stack([fiducials["measured_x"], fiducials["measured_y"]]).astype(float)
    return commanded, measured


def record_identity(record: Mapping) -> tuple[str, datetime]:
    """Which calibration a record is: a content hash (sha256 of its YAML, 16 hex digits) and its
    creation time (UTC); what a correction answer names so that a client knows who answered."""
    content_hash = hashlib.sha256(dump_record(record).encode("utf-8")).hexdigest()[:16]
    created = datetime.fromisoformat(record["created_utc"])
    return content_hash, created if created.tzinfo else created.replace(tzinfo=timezone.utc)
