"""Time limits of the calibration manager's calls, derived from the work each call asks for.

A sweep takes its length over the sensor speed; a marking job its path length over the marking
speed plus one jump per polyline. The limit is that time times ``deadline_factor`` plus
``deadline_margin_s`` (start-up, transport, a busy machine), so a long job is not cut short and a
dead device is not waited for longer than the job itself would take.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gls_calibration.validation import as_non_negative_number, as_positive_number


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
        for name in ("sweep_length_mm", "sweep_speed_mm_s", "marking_speed_mm_s", "factor", "margin_s"):
            as_positive_number(getattr(self, name), name)
        as_non_negative_number(self.jump_time_s, "jump_time_s")
        if self.factor < 1.0:
            raise ValueError(f"factor must be at least 1, got {self.factor}")

    def limit_s(self, work_s: float) -> float:
        """The time limit of a job expected to take ``work_s``."""
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


def declare_deadlines(node) -> Deadlines:
    """Declare the manager's parameters of the job sizes and slack; return them."""
    return Deadlines(
        sweep_length_mm=node.declare("sweep.length_mm", 200.0, "length of each sweep (mm), sent to the scanner",
                                     minimum=1.0, maximum=5000.0),
        sweep_speed_mm_s=node.declare("sweep.speed_mm_s", 15.0, "sensor speed of each sweep (mm/s), sent to "
                                      "the scanner", minimum=0.1, maximum=10000.0),
        marking_speed_mm_s=node.declare("marking.speed_mm_s", 500.0, "the galvo's marking speed (mm/s), for "
                                        "the marking time limit", minimum=1.0, maximum=100000.0),
        jump_time_s=node.declare("marking.jump_time_s", 0.005, "time of one jump between polylines (s), for "
                                 "the marking time limit", minimum=0.0, maximum=10.0),
        factor=node.declare("deadline_factor", 2.0, "a sweep or marking job may take this many times its "
                            "expected duration", minimum=1.0, maximum=100.0),
        margin_s=node.declare("deadline_margin_s", 10.0, "added to every job's time limit (s)",
                              minimum=0.1, maximum=600.0))
