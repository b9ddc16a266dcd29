"""The procedure's ``Cell`` over the simulated cell, without ROS: the core functions called directly.

Runs ``procedure.calibrate`` and ``procedure.run_plate`` in one process, with the same core steps
the nodes wrap (plate pose, fiducial measurement, correction, training), so that tests and
benchmarks exercise the real calibrate flow in seconds. What differs from the ROS cell: clouds stay
numpy arrays (xyz, intensity) in the scanner base frame instead of PointCloud2 profiles.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np

from gls_calibration.calibration.procedure import CalibrationError, ProcedureSettings
from gls_calibration.calibration.record import correction_from_record
from gls_calibration.calibration.record_file import CalibrationFileError
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.correction.setpoints import CorrectedSetpoints, Correction
from gls_calibration.fiducials.measure import FiducialMeasurement, measure_fiducials
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.models.training import TrainedModel, TrainingOptions, train_correction
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.scan.plate_pose import PlatePose, estimate_plate_pose
from gls_calibration.simulation.world import SimulatedCell

Cloud = tuple[np.ndarray, np.ndarray]   # organized xyz (H, W, 3) and intensity (H, W), scanner base frame, mm


class DirectCell:
    """``procedure.Cell`` over a :class:`SimulatedCell`; calibrations are read from ``store``.

    ``ring_radii_mm`` must be those of the settings the procedure runs with; ``physics_first`` and
    ``training`` choose what ``train`` trains (see ``training.train_correction``). ``correction`` is
    what ``correct`` uses (set by ``load_calibration``/``reload_active``; a benchmark may set it to
    compare models); ``marks`` the polylines landed on the current plate. Clouds are in the scanner
    base frame, profiles placed by the robot's reported pose (``placed_by_pose``) or by time.
    ``sweeps`` and ``standstills`` count the acquisitions apart, each seeding its own draws.
    """

    def __init__(self, sim: SimulatedCell, store: CalibrationStore, *, ring_radii_mm=RING_RADII_MM,
                 physics_first: bool = False, training: TrainingOptions = TrainingOptions(),
                 placed_by_pose: bool = True) -> None:
        self.sim = sim
        self.placed_by_pose = placed_by_pose
        self.store = store
        self.ring_radii_mm = tuple(ring_radii_mm)
        self.physics_first = physics_first
        self.training = training
        self.correction = Correction(sim.config.geometry)
        self.sweeps = 0
        self.standstills = 0   # counted apart: a stand-still must not shift the sweeps' random draws
        self.marks: list[np.ndarray] = []    # landed polylines (gls, mm) on the current plate
        self.reload_active_now()

    def settings(self, **overrides) -> ProcedureSettings:
        """Procedure settings for this cell: its CAD scanner mounting and ring radii, then ``overrides``."""
        mounting = self.sim.config.scanner_to_gls
        base = ProcedureSettings(scanner_to_gls=RigidTransform(mounting[:3, :3].copy(), mounting[:3, 3].copy()),
                                 ring_radii_mm=self.ring_radii_mm)
        base = dataclasses.replace(base, profiles_placed_by_pose=self.placed_by_pose)
        return dataclasses.replace(base, **overrides)

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> Cloud:
        self.sweeps += 1   # each sweep its own robot path error and noise, as on the ROS cell
        data = _refusing(self.sim.sweep_data, step_mm=step_mm, seed=self.sim.config.seed * 100003 + self.sweeps,
                         direction=direction, orientation_deg=orientation_deg)
        xyz = data.placed_by_pose() if self.placed_by_pose else data.placed_by_time()
        return xyz.astype(np.float32), data.intensity

    async def acquire_standstill(self, profiles: int) -> Cloud:
        self.standstills += 1
        data = _refusing(self.sim.standstill_data, profiles, seed=self.sim.config.seed * 100003 + self.standstills)
        xyz = data.placed_by_pose() if self.placed_by_pose else data.placed_by_time()
        return xyz.astype(np.float32), data.intensity

    def points_and_intensities(self, cloud: Cloud) -> tuple[np.ndarray, np.ndarray]:
        return cloud

    async def estimate_plate_pose(self, cloud: Cloud) -> PlatePose:
        return _refusing(estimate_plate_pose, cloud[0].reshape(-1, 3), head_direction=(0.0, 0.0, -1.0))

    async def measure_fiducials(self, cloud: Cloud, pose: PlatePose, expected_count: int) -> FiducialMeasurement:
        return _refusing(measure_fiducials, cloud[0], cloud[1], pose, ring_radii_mm=self.ring_radii_mm,
                         expected_count=expected_count)

    async def correct(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> CorrectedSetpoints:
        return _refusing(self.correction.correct, x, y, z)

    async def mark(self, alpha_x: np.ndarray, alpha_y: np.ndarray, focus_shift: np.ndarray,
                   polyline_starts: np.ndarray) -> float:
        began = self.sim.head.clock_s
        starts = np.asarray(polyline_starts, dtype=int)
        for ax, ay in zip(np.split(np.asarray(alpha_x), starts[1:]), np.split(np.asarray(alpha_y), starts[1:])):
            self.marks.append(_refusing(self.sim.head.mark, ax, ay))
        return self.sim.head.clock_s - began

    async def train(self, landed_xy: np.ndarray, corrections: np.ndarray) -> TrainedModel:
        return _refusing(train_correction, landed_xy, corrections, self.sim.config.geometry,
                         physics_first=self.physics_first, options=self.training)

    async def load_calibration(self, path: str) -> None:
        self._load(Path(path))

    async def reload_active(self) -> None:
        self.reload_active_now()

    def reload_active_now(self) -> None:
        """Correct through the store's active calibration (the nominal model when there is none)."""
        try:
            path = self.store.active_path()
        except CalibrationFileError as error:
            raise CalibrationError(str(error)) from None
        if path is None:
            self.correction = Correction(self.sim.config.geometry)
        else:
            self._load(path)

    def _load(self, path: Path) -> None:
        try:
            self.correction = correction_from_record(self.store.load(path), self.sim.config.geometry)
        except (CalibrationFileError, ValueError, OSError) as error:
            raise CalibrationError(f"calibration file {path} is unusable: {error}") from None

    async def exchange_plate(self) -> None:
        self.sim.exchange_plate()
        self.marks.clear()

    async def true_marks(self) -> Optional[list[np.ndarray]]:
        return list(self.marks)


def _refusing(function, *args, **kwargs):
    """``function(*args, **kwargs)`` with a ValueError turned into CalibrationError, as a node answers."""
    try:
        return function(*args, **kwargs)
    except ValueError as error:
        raise CalibrationError(str(error)) from None
