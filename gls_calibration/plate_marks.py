"""Is the plain plate really plain? Old marks in the intensity of a sweep.

A clean plate's intensity varies by its texture and the sensor's speckle: close to Gaussian, a few
per cent. A marked line darkens (or brightens) the points on it by tens of per cent, far outside
that spread. Points further than ``sigmas`` robust standard deviations (1.4826 x the median
absolute deviation) from the median are counted; on the simulated clean plate none of 421 000
points of a 1 mm-step sweep is beyond 5 sigma, while a single old fiducial gives about 24 beyond
6 sigma and a 3x3 grid about 300.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gls_calibration.validation import as_positive_number


@dataclass(frozen=True)
class MarkEvidence:
    """Points of a sweep whose intensity lies outside the plate's texture."""

    outlying_points: int
    finite_points: int
    sigmas: float

    def marked(self, max_outlying_points: int) -> bool:
        """True when more points than ``max_outlying_points`` lie outside the texture."""
        return self.outlying_points > max_outlying_points


def existing_marks(intensity, sigmas: float = 6.0) -> MarkEvidence:
    """Count the points of ``intensity`` (any shape; NaN = no return) beyond ``sigmas`` robust deviations."""
    sigmas = as_positive_number(sigmas, "sigmas")
    values = np.asarray(intensity, dtype=np.float64).reshape(-1)
    values = values[np.isfinite(values)]
    if values.size == 0:
        raise ValueError("the sweep holds no finite intensity")
    median = float(np.median(values))
    spread = 1.4826 * float(np.median(np.abs(values - median)))
    if spread == 0.0:  # a quantized, perfectly uniform plate: any other value is an outlier
        outlying = int(np.count_nonzero(values != median))
    else:
        outlying = int(np.count_nonzero(np.abs(values - median) > sigmas * spread))
    return MarkEvidence(outlying_points=outlying, finite_points=int(values.size), sigmas=float(sigmas))
