"""Gross outliers: points that depart both from a smooth field and from their neighbours.

A physical effect leaves a smooth residual; a local defect (a plate bump) moves a patch of
neighbouring points alike; a gross outlier (a mis-detected or damaged fiducial) stands alone. A
point is an outlier when its residual departs from a robust smooth fit (polynomial of
:mod:`.residual_statistics`, refitted without the points already flagged) by more than
``threshold`` robust sigmas (1.4826 x median absolute departure, so the outliers do not set it)
AND no one of its nearest neighbours departs alike (within as much): a stripe or a bump shares
its departure with some neighbour, an outlier with none.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from gls_calibration.common.robust import robust_sigma
from gls_calibration.discrepancy.residual_statistics import smooth_basis, smooth_degree

#: Robust sigmas a gross outlier departs by (a 2-D Gaussian exceeds 5 sigma with p = 4e-6).
THRESHOLD = 5.0
NEIGHBOURS = 8
_PASSES = 4


def _robust_sigma(departures: np.ndarray) -> float:
    """Per-axis robust sigma of (N, 2) departures (1.4826 x MAD, both axes pooled)."""
    return robust_sigma(departures - np.median(departures, axis=0))


def find_outliers(points_xy: np.ndarray, residual_xy: np.ndarray, *, threshold: float = THRESHOLD,
                  min_sigma_mm: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Outlier mask (N,) and each point's departure size (N,, mm) from the smooth field.

    ``residual_xy`` is the rigidly aligned residual against the current model. The rigid alignment
    used for it includes the outliers; a gross outlier of size s moves it by about s / N, well below
    the noise for the grids this workflow sees.
    """
    count = len(points_xy)
    degree, _ = smooth_degree(count, False)
    basis = smooth_basis(points_xy, None, degree, False)
    inliers = np.ones(count, dtype=bool)
    departures = residual_xy
    for _ in range(_PASSES):
        coefficients = np.linalg.lstsq(basis[inliers], residual_xy[inliers], rcond=None)[0]
        departures = residual_xy - basis @ coefficients
        sigma = max(_robust_sigma(departures[inliers]), min_sigma_mm)
        size = np.hypot(*departures.T)
        flagged = size > threshold * sigma
        if np.array_equal(~flagged, inliers):
            break
        inliers = ~flagged
    size = np.hypot(*departures.T)
    if not np.any(~inliers) or count <= NEIGHBOURS:
        return np.zeros(count, dtype=bool), size
    # a neighbour with (nearly) the same departure means structure (a bump, a stripe), not an outlier
    _, nearest = cKDTree(points_xy).query(points_xy, k=NEIGHBOURS + 1)
    closest = np.min(np.hypot(*(departures[:, None, :] - departures[nearest[:, 1:]]).transpose(2, 0, 1)), axis=1)
    return ~inliers & (closest > threshold * sigma), size
