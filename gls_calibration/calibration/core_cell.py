"""The steps of the procedure's ``Cell`` that are the core itself, called in-process without ROS.

Plate pose, fiducial measurement, correction, training and the candidate in use are the same for
every cell that runs the core directly: the simulated cell of tests and benchmarks
(:class:`~gls_calibration.simulation.direct_cell.DirectCell`) and the replay of a recorded bag
(:class:`~gls_calibration.calibration.replay_cell.ReplayCell`). A subclass supplies what differs:
its sweeps and stand-stills, marking, plate exchange and the ground truth. A core ValueError becomes
a CalibrationError, as a node answers ``success=false``.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from gls_calibration.calibration.outcome import Candidate
from gls_calibration.calibration.procedure import CalibrationError
from gls_calibration.calibration.record import correction_from_record
from gls_calibration.calibration.record_file import CalibrationFileError
from gls_calibration.calibration.reference_check import plate_plane
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.correction.setpoints import CorrectedSetpoints, Correction
from gls_calibration.fiducials.measure import FiducialMeasurement, measure_fiducials
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.training import TrainedModel, TrainingOptions, train_correction
from gls_calibration.scan.plate_pose import PlatePose

Cloud = tuple[np.ndarray, np.ndarray]   # xyz (H, W, 3) or (N, 3) and intensity, scanner base frame, mm


class CoreCell:
    """The core steps of ``procedure.Cell`` over arrays; calibrations live in ``store``.

    ``correction`` is what ``correct`` uses: the store's active calibration at start, a candidate
    once ``use_candidate`` hands one over (as it is, not its file read again).

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    store : CalibrationStore
        Where calibrations are saved and the active one is read from.
    physics_first : bool, default False
        ``train`` fits a physical model of the head before the data-driven one
        (``training.train_correction``).
    training : TrainingOptions, optional
        The grid search of the data-driven part.

    Raises
    ------
    CalibrationError
        If the store's active calibration cannot be read or is unusable.
    """

    def __init__(self, geometry: HeadGeometry, store: CalibrationStore, *, physics_first: bool = False,
                 training: TrainingOptions = TrainingOptions()) -> None:
        self.geometry = geometry
        self.store = store
        self.physics_first = physics_first
        self.training = training
        self.correction = Correction(geometry)
        self.reload_active_now()

    def points_and_intensities(self, cloud: Cloud) -> tuple[np.ndarray, np.ndarray]:
        """Return the cloud as it is: it is already (points, intensities) in this cell."""
        return cloud

    async def estimate_plate_pose(self, cloud: Cloud) -> PlatePose:
        """Plate pose fitted in process (see ``Cell.estimate_plate_pose``)."""
        return refusing(plate_plane, cloud[0])

    async def measure_fiducials(self, cloud: Cloud, pose: PlatePose, expected_count: int,
                                ring_radii_mm: Sequence[float]) -> FiducialMeasurement:
        """Fiducial centres measured in process (see ``Cell.measure_fiducials``)."""
        return refusing(measure_fiducials, cloud[0], cloud[1], pose, ring_radii_mm=ring_radii_mm,
                        expected_count=expected_count)

    async def correct(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> CorrectedSetpoints:
        """Correct setpoints by the correction in use (see ``Cell.correct``)."""
        return refusing(self.correction.correct, x, y, z)

    async def train(self, landed_xy: np.ndarray, corrections: np.ndarray) -> TrainedModel:
        """Train a correction in process (see ``Cell.train``)."""
        return refusing(train_correction, landed_xy, corrections, self.geometry, physics_first=self.physics_first,
                        options=self.training)

    def start(self, step):
        """Return the step itself: in process the steps compute when awaited, one after the other (``Cell.start``)."""
        return step

    async def use_candidate(self, candidate: Candidate) -> None:
        """Correct by ``candidate`` from now on (see ``Cell.use_candidate``)."""
        self.correction = candidate.correction

    async def reload_active(self) -> None:
        """Correct by the store's active calibration again (see ``Cell.reload_active``)."""
        self.reload_active_now()

    def reload_active_now(self) -> None:
        """Correct through the store's active calibration (the nominal model when there is none)."""
        try:
            path = self.store.active_path()
        except CalibrationFileError as error:
            raise CalibrationError(str(error)) from None
        if path is None:
            self.correction = Correction(self.geometry)
            return
        try:
            self.correction = correction_from_record(self.store.load(path), self.geometry)
        except (CalibrationFileError, ValueError, OSError) as error:
            raise CalibrationError(f"calibration file {path} is unusable: {error}") from None


def refusing(function, *args, **kwargs):
    """Call ``function(*args, **kwargs)`` with a ValueError turned into CalibrationError, as a node answers.

    Parameters
    ----------
    function : callable
        The core step.
    *args, **kwargs
        Its arguments.

    Returns
    -------
    object
        What ``function`` returns.

    Raises
    ------
    CalibrationError
        With the message of the ValueError that ``function`` raised.
    """
    try:
        return function(*args, **kwargs)
    except ValueError as error:
        raise CalibrationError(str(error)) from None
