"""The procedure's ``Cell`` over a recorded bag: the calibrate flow run again offline, training included.

Sweeps and stand-still acquisitions (the plate height at the marking pose: a motion without travel)
come from the bag in recorded order (:func:`gls_calibration.scan.bag_io.read_sweeps`); marking and
plate exchanges already happened in the recording, so they do nothing here. Everything else is the
core the nodes wrap, called as :class:`~gls_calibration.simulation.direct_cell.DirectCell` calls it:
plate pose, fiducial measurement, correction through the calibration in force, training.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from gls_calibration.calibration.procedure import CalibrationError
from gls_calibration.calibration.record import correction_from_record
from gls_calibration.calibration.record_file import CalibrationFileError
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.correction.setpoints import CorrectedSetpoints, Correction
from gls_calibration.fiducials.measure import FiducialMeasurement, measure_fiducials
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.training import TrainedModel, TrainingOptions, train_correction
from gls_calibration.scan.bag_io import ReplayedSweep
from gls_calibration.scan.plate_pose import PlatePose, estimate_plate_pose

Cloud = tuple[np.ndarray, np.ndarray]


class ReplayCell:
    """``procedure.Cell`` whose sweeps and stand-stills are ``sweeps`` in order (each checked to be the
    kind asked for); calibrations live in ``store``."""

    def __init__(self, sweeps: Sequence[ReplayedSweep], geometry: HeadGeometry, store: CalibrationStore, *,
                 ring_radii_mm=RING_RADII_MM, physics_first: bool = False,
                 training: TrainingOptions = TrainingOptions()) -> None:
        self.recorded = list(sweeps)
        self.geometry = geometry
        self.store = store
        self.ring_radii_mm = tuple(ring_radii_mm)
        self.physics_first = physics_first
        self.training = training
        self.correction = Correction(geometry)
        self.taken = 0    # recorded motions served so far (sweeps and stand-stills)

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> Cloud:
        return self._next(standstill=False)

    async def acquire_standstill(self, profiles: int) -> Cloud:
        return self._next(standstill=True)

    def _next(self, *, standstill: bool) -> Cloud:
        if self.taken >= len(self.recorded):
            raise CalibrationError(f"the bag holds {len(self.recorded)} motion(s); the calibration needs more "
                                   "(check the grid, sweep plan, plain sweeps, stand-still height and iterations "
                                   "of the recording)")
        sweep = self.recorded[self.taken]
        self.taken += 1
        if _refusing(lambda: sweep.standstill) != standstill:
            wanted, found = ("a stand-still", "a sweep") if standstill else ("a sweep", "a stand-still")
            raise CalibrationError(f"the bag's motion {self.taken} travels {sweep.travel_mm:.3g} mm: {found} where "
                                   f"the calibration asks for {wanted} (check --standstill-height and the plan of "
                                   "the recording)")
        return sweep.xyz_mm, sweep.intensity

    def points_and_intensities(self, cloud: Cloud) -> tuple[np.ndarray, np.ndarray]:
        return cloud

    async def estimate_plate_pose(self, cloud: Cloud) -> PlatePose:
        return _refusing(estimate_plate_pose, cloud[0].reshape(-1, 3), head_direction=(0.0, 0.0, -1.0))

    async def measure_fiducials(self, cloud: Cloud, pose: PlatePose, expected_count: int) -> FiducialMeasurement:
        return _refusing(measure_fiducials, cloud[0], cloud[1], pose, ring_radii_mm=self.ring_radii_mm,
                         expected_count=expected_count)

    async def correct(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> CorrectedSetpoints:
        return _refusing(self.correction.correct, x, y, z)

    async def mark(self, alpha_x, alpha_y, focus_shift, polyline_starts) -> float:
        return 0.0     # marked in the recording

    async def train(self, landed_xy: np.ndarray, corrections: np.ndarray) -> TrainedModel:
        return _refusing(train_correction, landed_xy, corrections, self.geometry, physics_first=self.physics_first,
                         options=self.training)

    async def load_calibration(self, path: str) -> None:
        try:
            self.correction = correction_from_record(self.store.load(Path(path)), self.geometry)
        except (CalibrationFileError, ValueError, OSError) as error:
            raise CalibrationError(f"calibration file {path} is unusable: {error}") from None

    async def reload_active(self) -> None:
        path = self.store.active_path()
        if path is None:
            self.correction = Correction(self.geometry)
        else:
            await self.load_calibration(str(path))

    async def exchange_plate(self) -> None:
        return None    # exchanged in the recording

    async def true_marks(self) -> Optional[list[np.ndarray]]:
        return None    # a recording has no ground truth


def _refusing(function, *args, **kwargs):
    try:
        return function(*args, **kwargs)
    except ValueError as error:
        raise CalibrationError(str(error)) from None
