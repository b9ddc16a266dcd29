"""Robust spread: a normal sample's standard deviation read from the median absolute departure.

Robust spread: the standard deviation a normal sample would have, read from its median absolute
departure, so that the outliers being looked for do not set it.
"""
from __future__ import annotations

import numpy as np
from scipy.special import ndtri

NORMAL_MAD_SCALE = float(1.0 / ndtri(0.75))
"""Standard deviations per median absolute departure of a normal sample (1.4826)."""


def robust_sigma(departures) -> float:
    """Return ``NORMAL_MAD_SCALE`` x the median of ``|departures|``.

    ``departures`` may have any shape, are taken from a centre already, and must be finite.
    """
    return NORMAL_MAD_SCALE * float(np.median(np.abs(departures)))
