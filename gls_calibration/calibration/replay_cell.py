"""The procedure's ``Cell`` over a recorded bag: the calibrate flow run again offline, training included.

Sweeps and stand-still acquisitions (the plate height at the marking pose: a motion without travel)
come from the bag in recorded order (:func:`gls_calibration.scan.bag_io.read_sweeps`); marking and
plate exchanges already happened in the recording, so they do nothing here. Everything else is the
core the nodes wrap (:class:`~gls_calibration.calibration.core_cell.CoreCell`, as the simulated
cell runs it): plate pose, fiducial measurement, correction through the calibration in force, training.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from gls_calibration.calibration.core_cell import Cloud, CoreCell, refusing
from gls_calibration.calibration.procedure import CalibrationError
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.training import TrainingOptions
from gls_calibration.scan.bag_io import ReplayedSweep


class ReplayCell(CoreCell):
    """A ``procedure.Cell`` that replays recorded sweeps and stand-stills in order.

    Each recorded motion is checked to be the kind asked for; calibrations live in ``store``.

    Parameters
    ----------
    sweeps : sequence of ReplayedSweep
        The recorded motions, in the order the flow asks for them.
    geometry : HeadGeometry
        The nominal head.
    store : CalibrationStore
        Where calibrations are saved and the active one is read from.
    physics_first : bool, default False
        ``train`` fits a physical model of the head first.
    training : TrainingOptions, optional
        The grid search of the data-driven part.

    Raises
    ------
    CalibrationError
        If the store's active calibration cannot be read or is unusable.
    """

    def __init__(self, sweeps: Sequence[ReplayedSweep], geometry: HeadGeometry, store: CalibrationStore, *,
                 physics_first: bool = False, training: TrainingOptions = TrainingOptions()) -> None:
        self.recorded = list(sweeps)
        self.taken = 0    # recorded motions served so far (sweeps and stand-stills)
        super().__init__(geometry, store, physics_first=physics_first, training=training)

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> Cloud:
        """Return the recording's next sweep, whatever the request (the recording fixed the plan)."""
        return self._next(standstill=False)

    async def acquire_standstill(self, profiles: int) -> Cloud:
        """Return the recording's next stand-still acquisition."""
        return self._next(standstill=True)

    def _next(self, *, standstill: bool) -> Cloud:
        if self.taken >= len(self.recorded):
            raise CalibrationError(f"the bag holds {len(self.recorded)} motion(s); the calibration needs more "
                                   "(check the grid, sweep plan, plain sweeps, stand-still height and iterations "
                                   "of the recording)")
        sweep = self.recorded[self.taken]
        self.taken += 1
        if refusing(lambda: sweep.standstill) != standstill:
            wanted, found = ("a stand-still", "a sweep") if standstill else ("a sweep", "a stand-still")
            raise CalibrationError(f"the bag's motion {self.taken} travels {sweep.travel_mm:.3g} mm: {found} where "
                                   f"the calibration asks for {wanted} (check --standstill-height and the plan of "
                                   "the recording)")
        return sweep.xyz_mm, sweep.intensity

    async def mark(self, alpha_x, alpha_y, focus_shift, polyline_starts) -> float:
        """Nothing to mark: the recording holds the plate as it was marked."""
        return 0.0

    async def exchange_plate(self) -> None:
        """Nothing to exchange: the recording holds each plate."""
        return None

    async def true_marks(self) -> Optional[list[np.ndarray]]:
        """None: a recording has no ground truth."""
        return None
