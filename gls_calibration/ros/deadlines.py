"""Time limits of the calibration manager's calls, derived from the work each call asks for.

A sweep takes its length over the sensor speed; a marking job its path length over the marking
speed plus one jump per polyline. The limit is that time times ``deadline_factor`` plus
``deadline_margin_s`` (start-up, transport, a busy machine), so a long job is not cut short and a
dead device is not waited for longer than the job itself would take.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gls_calibration.common.validation import as_non_negative_number, as_positive_number


@dataclass(frozen=True)
class Deadlines:
    """Sweep and marking speeds as configured, and how much slack a job gets."""

    sweep_length_mm: float
    sweep_speed_mm_s: float
    marking_speed_mm_s: float
    jump_time_s: float
    factor: float
    margin_s: float

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        for name in ("sweep_length_mm", "sweep_speed_mm_s", "marking_speed_mm_s", "factor", "margin_s"):
            as_positive_number(getattr(self, name), name)
        as_non_negative_number(self.jump_time_s, "jump_time_s")
        if self.factor < 1.0:
            raise ValueError(f"factor must be at least 1, got {self.factor}")

    def limit_s(self, work_s: float) -> float:
        """Return the time limit of a job expected to take ``work_s``."""
        return self.factor * work_s + self.margin_s

    def sweep_s(self) -> float:
        """Time limit of one sweep over ``sweep_length_mm`` at ``sweep_speed_mm_s``."""
        return self.limit_s(self.sweep_length_mm / self.sweep_speed_mm_s)

    def marking_s(self, xy_mm: np.ndarray, polyline_starts) -> float:
        """Time limit of marking the polylines through ``xy_mm`` (N x 2, mm) that begin at ``polyline_starts``."""
        xy_mm = np.asarray(xy_mm, dtype=float)
        steps = np.linalg.norm(np.diff(xy_mm, axis=0), axis=1)
        starts = np.asarray(polyline_starts, dtype=int)
        # The step into the first point of a polyline is a jump, not a marked line.
        steps[starts[(starts > 0) & (starts < len(xy_mm))] - 1] = 0.0
        length_mm = float(np.sum(steps[np.isfinite(steps)]))
        return self.limit_s(length_mm / self.marking_speed_mm_s + len(starts) * self.jump_time_s)
