"""Nominal kinematics of the post-objective two-mirror galvo head.

The beam meets the Y mirror first and the X mirror last; ``d`` is the distance from the X mirror
axis to the work plane (z = 0 in the ``gls`` frame, z pointing towards the head) and ``e`` the
distance between the two mirror axes. Optical angles are twice the mechanical ones.

Forward model (published closed form)::

    x = (d - z) tan(theta_x)
    y = (e + (d - z) / cos(theta_x)) tan(theta_y)

The focus shift is the beam path beyond the nominal one: the traced length from the Y mirror to the
target minus ``e + d - z``.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gls_calibration.common.validation import as_coordinate_arrays


@dataclass(frozen=True)
class HeadGeometry:
    """Nominal parameters of the head (mm and rad).

    Parameters
    ----------
    working_distance_mm : float, default 490.0
        Distance ``d`` from the X mirror axis (the last mirror) to the work plane, mm; positive.
    mirror_distance_mm : float, default 15.0
        Distance ``e`` between the two mirror axes, mm; non-negative.
    mirror_limit_rad : float, default radians(10.5)
        Largest mechanical mirror angle, rad; positive.
    focus_range_mm : float, default 25.0
        Largest focus shift either way (+-), mm; positive.

    Raises
    ------
    ValueError
        If a field is not finite or out of its range (the first bad one is named).
    """

    working_distance_mm: float = 490.0
    mirror_distance_mm: float = 15.0
    mirror_limit_rad: float = math.radians(10.5)
    focus_range_mm: float = 25.0

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        for name in ("working_distance_mm", "mirror_limit_rad", "focus_range_mm"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not math.isfinite(self.mirror_distance_mm) or self.mirror_distance_mm < 0.0:
            raise ValueError(
                f"mirror_distance_mm must be a non-negative finite number, got {self.mirror_distance_mm!r}")


@dataclass(frozen=True)
class JointSetpoints:
    """Mechanical mirror angles (rad), focus shift (mm) and per-point limit flags."""

    alpha_x: np.ndarray
    alpha_y: np.ndarray
    focus_shift: np.ndarray
    within_mirror_limits: np.ndarray
    within_focus_range: np.ndarray

    @property
    def within_limits(self) -> np.ndarray:
        """Return True where both mirrors and the focus module can reach the target."""
        return self.within_mirror_limits & self.within_focus_range


def forward(geometry: HeadGeometry, alpha_x, alpha_y, z=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Cartesian landing point (mm) on the plane at height ``z`` for mechanical angles (rad).

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    alpha_x, alpha_y : array_like
        Mechanical mirror angles (rad); broadcast with ``z``.
    z : array_like, optional
        Height of the plane (mm, gls frame); 0 is the work plane.

    Returns
    -------
    x, y : ndarray
        Where the beam meets the plane (mm, gls frame).

    Examples
    --------
    >>> from gls_calibration.geometry.kinematics import HeadGeometry, forward, inverse
    >>> setpoints = inverse(HeadGeometry(), [10.0, -40.0], [20.0, 5.0])
    >>> x, y = forward(HeadGeometry(), setpoints.alpha_x, setpoints.alpha_y)
    >>> print(np.round(x, 9), np.round(y, 9))
    [ 10. -40.] [20.  5.]
    """
    alpha_x, alpha_y, z = np.broadcast_arrays(
        np.asarray(alpha_x, dtype=float), np.asarray(alpha_y, dtype=float), np.asarray(z, dtype=float))
    theta_x = 2.0 * alpha_x
    theta_y = 2.0 * alpha_y
    height = geometry.working_distance_mm - z
    x = height * np.tan(theta_x)
    y = (geometry.mirror_distance_mm + height / np.cos(theta_x)) * np.tan(theta_y)
    return x, y


def inverse(geometry: HeadGeometry, x, y, z=None) -> JointSetpoints:
    """Mechanical angles and focus shift that put the spot on (x, y, z) (mm).

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    x, y : array_like
        Targets (mm, gls frame).
    z : array_like, optional
        Target heights (mm); None: the work plane.

    Returns
    -------
    JointSetpoints
        Angles (rad), focus shift (mm) and per target whether it lies within the mirror limits and
        the focus range: targets beyond them are flagged, never clipped.

    Raises
    ------
    ValueError
        Coordinates that are not finite or do not match in length.

    Examples
    --------
    >>> from gls_calibration.geometry.kinematics import HeadGeometry, inverse
    >>> setpoints = inverse(HeadGeometry(), [10.0], [20.0])
    >>> print(np.round(setpoints.alpha_x, 6), np.round(setpoints.focus_shift, 4), setpoints.within_limits)
    [0.010203] [0.4978] [ True]
    """
    x, y, z = as_coordinate_arrays(x, y, z)
    height = geometry.working_distance_mm - z
    slant = np.hypot(height, x)          # X mirror to target, projected on the x-z plane
    beam = geometry.mirror_distance_mm + slant
    alpha_x = 0.5 * np.arctan2(x, height)
    alpha_y = 0.5 * np.arctan2(y, beam)
    focus_shift = np.hypot(beam, y) - (geometry.mirror_distance_mm + height)
    limit = geometry.mirror_limit_rad
    within_mirror = (np.abs(alpha_x) <= limit) & (np.abs(alpha_y) <= limit)
    within_focus = np.abs(focus_shift) <= geometry.focus_range_mm
    return JointSetpoints(alpha_x, alpha_y, focus_shift, within_mirror, within_focus)
