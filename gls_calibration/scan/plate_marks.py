"""Is the plain plate really plain? Old marks in the intensity of a sweep.

A clean plate's intensity varies by its texture and the sensor's speckle: close to Gaussian, a few
per cent. A marked line darkens (or brightens) the points on it, by tens of per cent on a clean
sensor. Two kinds of evidence, in robust standard deviations (1.4826 x the median absolute
deviation) from the median:

- many points far outside the texture (``sigmas``, 6 by default): on the ideal simulated chain none
  of 421 000 points of a 1 mm-step sweep of a clean plate lies beyond 5 sigma, one old fiducial
  gives about 24 points beyond 6 sigma, a 3x3 grid about 300;
- a fiducial-sized cluster of points moderately outside it (``cluster_sigmas``, 4 by default): the
  paper_like chain's speckle widens the texture so much that one old fiducial gives only 2-3 points
  beyond 6 sigma, but 20-21 beyond 4 sigma, all within one fiducial's extent, while the clean plate
  gives 0-2 such points scattered over the whole plate (2026-11-22, seeds 1 and 2; ideal: 8 scattered,
  39-40 with the fiducial). A mark is a connected line; texture and speckle outliers are not.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from gls_calibration.common.robust import robust_sigma
from gls_calibration.common.validation import as_positive_number

MAX_CLUSTER_CENTRES = 2000


@dataclass(frozen=True)
class MarkEvidence:
    """Points of a sweep whose intensity lies outside the plate's texture."""

    outlying_points: int          # beyond ``sigmas``
    finite_points: int
    sigmas: float
    largest_cluster: int = 0      # most points beyond ``cluster_sigmas`` within ``cluster_radius_mm`` of one of them
    cluster_sigmas: float = 0.0
    cluster_radius_mm: float = 0.0

    def marked(self, max_outlying_points: int, max_cluster_points: int | None = None) -> bool:
        """Tell whether the points outside the texture are too many or form too large a cluster.

        True when more points than ``max_outlying_points`` lie outside the texture, or more than
        ``max_cluster_points`` (when given) make one cluster.
        """
        return self.outlying_points > max_outlying_points or (
            max_cluster_points is not None and self.largest_cluster > max_cluster_points)


def existing_marks(intensity, sigmas: float = 6.0, *, points=None, cluster_sigmas: float = 4.0,
                   cluster_radius_mm: float = 6.0) -> MarkEvidence:
    """Count the points of ``intensity`` beyond ``sigmas`` robust deviations, and their clusters.

    Parameters
    ----------
    intensity : array_like
        Intensity of a sweep, any shape; NaN = no return.
    sigmas : float, default 6.0
        A point is outlying beyond this many robust deviations from the median; positive.
    points : array_like, optional
        The points, intensity's shape + (3,), mm. With them, also the largest cluster of points beyond
        ``cluster_sigmas`` within ``cluster_radius_mm`` (a fiducial's extent) of one of them.
    cluster_sigmas : float, default 4.0
        The threshold of a cluster's points, robust deviations; positive.
    cluster_radius_mm : float, default 6.0
        The radius of a cluster, mm; positive.

    Returns
    -------
    MarkEvidence
        The outlying and finite point counts, and the largest cluster (0 without ``points``).

    Raises
    ------
    ValueError
        If no intensity is finite, a number is not positive, or ``points`` has not the intensity's shape + (3,).

    Examples
    --------
    >>> intensity = np.ones((20, 30))
    >>> intensity[5, 7] = 10.0
    >>> existing_marks(intensity).outlying_points
    1
    """
    sigmas = as_positive_number(sigmas, "sigmas")
    values = np.asarray(intensity, dtype=np.float64)
    finite = np.isfinite(values)
    if not finite.any():
        raise ValueError("the sweep holds no finite intensity")
    median = float(np.median(values[finite]))
    spread = robust_sigma(values[finite] - median)
    with np.errstate(invalid="ignore"):
        distance = np.abs(values - median)
    if spread == 0.0:  # a quantized, perfectly uniform plate: any other value is an outlier
        outlying = int(np.count_nonzero(finite & (distance > 0.0)))
    else:
        outlying = int(np.count_nonzero(finite & (distance > sigmas * spread)))
    evidence = MarkEvidence(outlying_points=outlying, finite_points=int(finite.sum()), sigmas=float(sigmas))
    if points is None:
        return evidence
    cluster_sigmas = as_positive_number(cluster_sigmas, "cluster_sigmas")
    cluster_radius_mm = as_positive_number(cluster_radius_mm, "cluster_radius_mm")
    xyz = np.asarray(points, dtype=np.float64)
    if xyz.shape != values.shape + (3,):
        raise ValueError(f"points must have the intensity's shape {values.shape} + (3,), got {xyz.shape}")
    candidate = finite & (distance > cluster_sigmas * spread) & np.isfinite(xyz).all(axis=-1)
    found = xyz[candidate]
    largest = 0
    if len(found):
        # A plate covered with marks has many candidates: counting about a spread-out subset of them
        # bounds the time and still finds a cluster that large.
        centres = found[::max(1, len(found) // MAX_CLUSTER_CENTRES)]
        largest = int(max(cKDTree(found).query_ball_point(centres, cluster_radius_mm, return_length=True)))
    return replace(evidence, largest_cluster=largest, cluster_sigmas=float(cluster_sigmas),
                   cluster_radius_mm=float(cluster_radius_mm))
