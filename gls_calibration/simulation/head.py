"""The simulated galvo head: the physical model with the true effects and a marking clock.

The clock advances per polyline by a jump time plus the polyline's nominal length over the
marking speed; each vertex gets its own time, which the ``thermal_drift`` effect uses. The head's
work plane is the plate: when a plate is given, its pose sets the ``plate_tilt`` and
``working_distance`` effects.

Straight rays (``straight_rays``, on unless switched off): the beam is a straight line after the
last mirror. The head's in-plane terms (today ``radial_distortion``, which the physical model
applies in the plate plane) are turned into a deviation of that ray: the ray runs from the X
mirror's reflection point (the exit point) through the distorted landing point on the calibration
plane (the configured plate plane), so a target above or below that plane lands where a real beam
would. The plane actually marked may differ from the calibration plane: by the plate's
``marking_pose_error`` (the robot-held head's repeatability; height and tilts) or by
:meth:`TruthHead.land` ``plane_offset_mm``.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Iterable, Mapping

import numpy as np

from gls_calibration.common.validation import as_finite_array
from gls_calibration.geometry.kinematics import HeadGeometry, forward
from gls_calibration.geometry.optics import HeadEffects, PhysicalHead, plate_frame
from gls_calibration.simulation.plate import Plate


@dataclass(frozen=True)
class MarkRecord:
    """One marked polyline: its order, start and end time (s), vertex count and each vertex's time."""

    index: int
    start_s: float
    end_s: float
    vertex_count: int
    plate_id: int | None
    vertex_times: np.ndarray    # marking time of each vertex (s), by the commanded path length


class TruthHead:
    """Marks joint-space polylines with the true (defective) head and keeps a marking log.

    Parameters
    ----------
    geometry : HeadGeometry, optional
        The nominal head; the default one when None.
    effects : HeadEffects or mapping, optional
        The true head's effects.
    plate : Plate, optional
        The plate marked; its pose sets the plate_tilt and working_distance effects.
    mark_speed_mm_s : float, default 500.0
        Marking speed, mm/s; positive.
    jump_time_s : float, default 0.005
        Time of a jump between polylines, s; non-negative.
    straight_rays : bool, optional
        Trace straight rays; None: the plate's measurement chain decides (True without a plate).

    Raises
    ------
    ValueError
        If a speed or time is out of range, or an effect contradicts the plate pose.
    """

    def __init__(self, geometry: HeadGeometry | None = None,
                 effects: HeadEffects | Mapping[str, object] | None = None, *,
                 plate: Plate | None = None, mark_speed_mm_s: float = 500.0, jump_time_s: float = 0.005,
                 straight_rays: bool | None = None) -> None:
        if not (math.isfinite(mark_speed_mm_s) and mark_speed_mm_s > 0.0):
            raise ValueError(f"mark_speed_mm_s must be positive, got {mark_speed_mm_s!r}")
        if not (math.isfinite(jump_time_s) and jump_time_s >= 0.0):
            raise ValueError(f"jump_time_s must be non-negative, got {jump_time_s!r}")
        self.geometry = geometry if geometry is not None else HeadGeometry()
        effects = effects if isinstance(effects, HeadEffects) else HeadEffects(effects or {})
        if plate is not None:
            for name, values in plate.settings.pose_effects.items():
                given = effects.get(name)
                if any(given) and not np.allclose(given, values, rtol=0.0, atol=1e-12):
                    raise ValueError(
                        f"effect {name!r} = {given} contradicts the plate pose {values}; "
                        "the plate pose sets it")
            effects = effects.replace(**plate.settings.pose_effects)
        self.physical = PhysicalHead(self.geometry, effects)
        self.plate = plate
        if straight_rays is None:
            straight_rays = bool(plate.chain.straight_rays) if plate is not None else True
        self.straight_rays = bool(straight_rays)
        self.mark_speed_mm_s = float(mark_speed_mm_s)
        self.jump_time_s = float(jump_time_s)
        self.clock_s = 0.0
        self.log: list[MarkRecord] = []

    @property
    def effects(self) -> HeadEffects:
        """Return the true effects (including the plate pose)."""
        return self.physical.effects

    def reset_clock(self) -> None:
        """Start the marking clock (and the log) again at zero, e.g. after a cool-down."""
        self.clock_s = 0.0
        self.log.clear()

    def mark(self, alpha_x, alpha_y) -> np.ndarray:
        """Mark one joint-space polyline (mechanical angles, rad); returns the landed points (M, 3), gls."""
        alpha_x = np.atleast_1d(as_finite_array(alpha_x, "alpha_x"))
        alpha_y = np.atleast_1d(as_finite_array(alpha_y, "alpha_y"))
        if alpha_x.ndim != 1 or alpha_x.shape != alpha_y.shape:
            raise ValueError(
                f"alpha_x and alpha_y must be 1-D arrays of the same length, got {alpha_x.shape} and {alpha_y.shape}")
        # the clock runs on the commanded (nominal) path length
        x, y = forward(self.geometry, alpha_x, alpha_y)
        travelled = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
        start = self.clock_s + self.jump_time_s
        times = start + travelled / self.mark_speed_mm_s
        landed = self.land(alpha_x, alpha_y, times)
        self.clock_s = float(times[-1])
        plate_id = None
        if self.plate is not None:
            self.plate.add_mark(landed)
            plate_id = self.plate.plate_id
        self.log.append(MarkRecord(len(self.log), float(start), self.clock_s, int(alpha_x.size), plate_id, times))
        return landed

    def land(self, alpha_x, alpha_y, t=None, plane_offset_mm: float = 0.0) -> np.ndarray:
        """Return where commanded mechanical angles (rad) land (N, 3, gls) on the plane marked now.

        That plane is the calibration plane moved by the plate's marking-pose error and by
        ``plane_offset_mm`` along gls z (towards the head when > 0).
        """
        height, tilt_x, tilt_y = self.plate.marking_pose_error if self.plate is not None else (0.0, 0.0, 0.0)
        height += plane_offset_mm
        if not self.straight_rays:
            if height or tilt_x or tilt_y:
                raise ValueError("landing off the calibration plane needs straight_rays")
            return self.physical.land(alpha_x, alpha_y, t)
        reference = self.physical.land(alpha_x, alpha_y, t).T            # on the calibration plane
        if not (height or tilt_x or tilt_y):
            return np.ascontiguousarray(reference.T)
        _, exit_points, _ = self.physical._trace(alpha_x, alpha_y, t)   # reflection points on the X mirror
        base_tilt_x, base_tilt_y = self.effects.get("plate_tilt")
        rotation, origin = plate_frame(base_tilt_x + tilt_x, base_tilt_y + tilt_y,
                                       self.effects.get("working_distance")[0] - height)
        normal = rotation[:, 2:3]
        direction = reference - exit_points
        gap = np.sum((origin[:, None] - exit_points) * normal, axis=0)
        hits = exit_points + direction * (gap / np.sum(direction * normal, axis=0))
        return np.ascontiguousarray(hits.T)

    def mark_polylines(self, polylines: Iterable) -> list[np.ndarray]:
        """Mark joint-space polylines in order, each (M, 2) of (alpha_x, alpha_y); returns landed (M, 3) each."""
        landed = []
        for number, polyline in enumerate(polylines):
            polyline = as_finite_array(polyline, f"polyline {number}", ndim=2)
            if polyline.shape[1] != 2:
                raise ValueError(f"polyline {number} must have shape (M, 2), got {polyline.shape}")
            landed.append(self.mark(polyline[:, 0], polyline[:, 1]))
        return landed
