"""Fiducial targets: the nominal grid of target centres and the ring polylines marked on them."""
from __future__ import annotations

from collections.abc import Sequence
import math

import numpy as np

from gls_calibration.common.validation import as_finite_array, as_integer_at_least, as_points, as_positive_number

RING_RADII_MM = (2.5, 2.7)
"""Radii of the published double-ring fiducial (mm): the default of every function and node that
marks or measures rings. A cell sets its own once, as ``grid.ring_radii_mm`` in config/gls.yaml, and
the calibration manager carries it to the marking and, in every MeasureFiducials request, to the
measurement."""


def grid_targets(per_side: int = 19, size_mm: float = 190.0, centre_xy=(0.0, 0.0)) -> np.ndarray:
    """Return a square grid of ``per_side`` x ``per_side`` target centres spanning ``size_mm`` (gls frame, mm).

    Row-major: y is the outer (slow) index and x the inner one, both increasing, so point
    ``row * per_side + column`` sits at ``(x[column], y[row])``.

    Parameters
    ----------
    per_side : int, default 19
        Targets per side; at least 2.
    size_mm : float, default 190.0
        Distance between the first and the last target of a side, mm; positive.
    centre_xy : array_like, shape (2,), default (0, 0)
        Centre of the grid, mm.

    Returns
    -------
    numpy.ndarray, shape (per_side ** 2, 2)
        The target centres, mm.

    Raises
    ------
    ValueError
        If ``per_side`` is below 2, ``size_mm`` not positive, or ``centre_xy`` not 2 finite numbers.

    Examples
    --------
    >>> grid_targets(per_side=2, size_mm=10.0, centre_xy=(1.0, 0.0))
    array([[-4., -5.],
           [ 6., -5.],
           [-4.,  5.],
           [ 6.,  5.]])
    """
    per_side = as_integer_at_least(per_side, "per_side", 2)
    size_mm = as_positive_number(size_mm, "size_mm")
    centre = as_finite_array(centre_xy, "centre_xy", ndim=1)
    if centre.shape != (2,):
        raise ValueError(f"centre_xy must hold 2 numbers, got shape {centre.shape}")
    offsets = np.linspace(-0.5 * size_mm, 0.5 * size_mm, per_side)
    grid_x, grid_y = np.meshgrid(offsets + centre[0], offsets + centre[1], indexing="xy")
    return np.column_stack([grid_x.ravel(), grid_y.ravel()])


def ring_segment_count(radius_mm: float, max_chord_error_mm: float) -> int:
    """Fewest chords (at least 3) whose sagitta ``r (1 - cos(pi / n))`` stays within the error."""
    radius_mm = as_positive_number(radius_mm, "radius_mm")
    max_chord_error_mm = as_positive_number(max_chord_error_mm, "max_chord_error_mm")
    if max_chord_error_mm >= radius_mm:
        return 3
    half_angle = math.acos(1.0 - max_chord_error_mm / radius_mm)
    return max(3, math.ceil(math.pi / half_angle - 1e-9))


def ring_polyline(centre_xy, radius_mm: float, max_chord_error_mm: float = 0.005) -> np.ndarray:
    """Return a closed polyline (M, 2) approximating a circle; the first vertex is repeated at the end.

    Vertices lie on the circle, so the chord error is the sagitta of each segment; the segment
    count is the smallest that keeps it within ``max_chord_error_mm``.
    """
    centre = as_finite_array(centre_xy, "centre_xy", ndim=1)
    if centre.shape != (2,):
        raise ValueError(f"centre_xy must hold 2 numbers, got shape {centre.shape}")
    segments = ring_segment_count(radius_mm, max_chord_error_mm)
    angles = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    polyline = centre + float(radius_mm) * np.column_stack([np.cos(angles), np.sin(angles)])
    polyline[-1] = polyline[0]  # exact closure, not cos(2 pi) rounding
    return polyline


def rings_polylines(centres, radii: Sequence[float] = RING_RADII_MM,
                    max_chord_error_mm: float = 0.005) -> list[np.ndarray]:
    """Return the ring polylines of every target, in marking order: target by target, radii in the given order.

    Parameters
    ----------
    centres : array_like, shape (N, 2)
        Target centres, mm.
    radii : sequence of float, default RING_RADII_MM
        Ring radii, mm; positive.
    max_chord_error_mm : float, default 0.005
        Largest distance between a chord of the polyline and its circle, mm.

    Returns
    -------
    list of numpy.ndarray, each shape (M, 2)
        N x len(radii) closed polylines, mm.

    Raises
    ------
    ValueError
        If ``centres`` is not (N, 2) finite or a radius is not positive.

    Examples
    --------
    >>> rings = rings_polylines([[0.0, 0.0], [10.0, 0.0]], radii=(2.5, 2.7))
    >>> len(rings), bool(np.allclose(np.hypot(*(rings[3] - [10.0, 0.0]).T), 2.7))
    (4, True)
    """
    centres = as_points(centres, "centres", 2)
    radii = as_finite_array(radii, "radii", ndim=1)
    for radius in radii:
        as_positive_number(radius, "radii")
    return [ring_polyline(centre, radius, max_chord_error_mm) for centre in centres for radius in radii]
