"""The procedure's ``Cell`` over the simulated cell, without ROS: the core functions called directly.

Runs ``procedure.calibrate`` and ``procedure.run_plate`` in one process, with the same core steps
the nodes wrap (plate pose, fiducial measurement, correction, training: :class:`CoreCell`), so that
tests and benchmarks exercise the real calibrate flow in seconds. What differs from the ROS cell:
clouds stay numpy arrays (xyz, intensity) in the scanner base frame instead of PointCloud2 profiles.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from gls_calibration.calibration.core_cell import Cloud, CoreCell, refusing
from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.models.training import TrainingOptions
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.registration.sweep_plan import CellTimeModel
from gls_calibration.simulation.world import SimulatedCell


class DirectCell(CoreCell):
    """``procedure.Cell`` over a :class:`SimulatedCell`; calibrations are read from ``store``.

    ``physics_first`` and ``training`` choose what ``train`` trains (see ``training.train_correction``);
    ``correction`` is what ``correct`` uses (set by ``use_candidate``/``reload_active``; a benchmark may
    set it to compare models); ``marks`` the polylines landed on the current plate. Clouds are in the
    scanner base frame, profiles placed by the robot's reported pose (``placed_by_pose``) or by time.
    ``sweeps`` and ``standstills`` count the acquisitions apart, each seeding its own draws.
    """

    def __init__(self, sim: SimulatedCell, store: CalibrationStore, *, physics_first: bool = False,
                 training: TrainingOptions = TrainingOptions(), placed_by_pose: bool = True) -> None:
        self.sim = sim
        self.placed_by_pose = placed_by_pose
        self.sweeps = 0
        self.standstills = 0   # counted apart: a stand-still must not shift the sweeps' random draws
        self.marks: list[np.ndarray] = []    # landed polylines (gls, mm) on the current plate
        super().__init__(sim.config.geometry, store, physics_first=physics_first, training=training)

    def settings(self, **overrides) -> ProcedureSettings:
        """Procedure settings for this cell: its CAD scanner mounting and sweep length, then ``overrides``."""
        mounting = self.sim.config.scanner_to_gls
        values = dict(scanner_to_gls=RigidTransform(mounting[:3, :3].copy(), mounting[:3, 3].copy()),
                      profiles_placed_by_pose=self.placed_by_pose,
                      # the simulated sweeps' length: where they turn the sensor (the lateral coordinate's origin)
                      cell_time=CellTimeModel(sweep_length_mm=self.sim.config.sweep_length_mm))
        return ProcedureSettings(**{**values, **overrides})

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> Cloud:
        """Simulate a sweep with its own robot path error and noise (see ``Cell.acquire_sweep``)."""
        self.sweeps += 1   # each sweep its own robot path error and noise, as on the ROS cell
        data = refusing(self.sim.sweep_data, step_mm=step_mm, seed=self.sim.config.seed * 100003 + self.sweeps,
                        direction=direction, orientation_deg=orientation_deg)
        xyz = data.placed_by_pose() if self.placed_by_pose else data.placed_by_time()
        return xyz.astype(np.float32), data.intensity

    async def acquire_standstill(self, profiles: int) -> Cloud:
        """Simulate profiles standing still (see ``Cell.acquire_standstill``)."""
        self.standstills += 1
        data = refusing(self.sim.standstill_data, profiles, seed=self.sim.config.seed * 100003 + self.standstills)
        xyz = data.placed_by_pose() if self.placed_by_pose else data.placed_by_time()
        return xyz.astype(np.float32), data.intensity

    async def mark(self, alpha_x: np.ndarray, alpha_y: np.ndarray, focus_shift: np.ndarray,
                   polyline_starts: np.ndarray) -> float:
        """Mark on the simulated plate; returns the simulated marking time, s."""
        began = self.sim.head.clock_s
        starts = np.asarray(polyline_starts, dtype=int)
        for ax, ay in zip(np.split(np.asarray(alpha_x), starts[1:]), np.split(np.asarray(alpha_y), starts[1:])):
            self.marks.append(refusing(self.sim.head.mark, ax, ay))
        return self.sim.head.clock_s - began

    async def exchange_plate(self) -> None:
        """Put a fresh simulated plate in (its marks forgotten)."""
        self.sim.exchange_plate()
        self.marks.clear()

    async def true_marks(self) -> Optional[list[np.ndarray]]:
        """Return the marks where they truly landed on the simulated plate."""
        return list(self.marks)
