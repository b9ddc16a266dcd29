"""The discrepancy verdict for a calibration run's report: the workflow on the first plate's deviations."""
from __future__ import annotations

import numpy as np

from gls_calibration.discrepancy.residual_statistics import MIN_POINTS
from gls_calibration.discrepancy.selection import explain
from gls_calibration.discrepancy.verdict import verdict_lines
from gls_calibration.geometry.kinematics import HeadGeometry


def run_verdict_lines(targets_xy, deviations_xy, geometry: HeadGeometry | None = None,
                      sigma_mm=None) -> tuple[str, ...]:
    """Return report lines: the discrepancy verdict on ``deviations_xy = Q - P`` at the targets ``Q`` (gls, mm).

    Assumes the plate was marked through the nominal model (the first plate of a run without an
    active calibration). A data set the workflow cannot take gives one line saying why.

    Parameters
    ----------
    targets_xy : array_like, shape (N, 2)
        The targets Q, gls frame, mm.
    deviations_xy : array_like, shape (N, 2)
        ``Q - P``, mm.
    geometry : HeadGeometry, optional
        The nominal head; the default one when None.
    sigma_mm : float or array_like, shape (N,), optional
        Per-axis standard uncertainty of each measured point, mm.

    Returns
    -------
    tuple of str
        Markdown lines; one line saying why when the verdict was not computed (never raises for bad data).

    Examples
    --------
    >>> run_verdict_lines(np.zeros((3, 2)), np.zeros((3, 2)))[0][:40]
    'Discrepancy verdict: not computed (3 fid'
    """
    targets_xy = np.asarray(targets_xy, dtype=float)
    if len(targets_xy) < MIN_POINTS:
        return (f"Discrepancy verdict: not computed ({len(targets_xy)} fiducials, at least {MIN_POINTS} needed).",)
    try:
        result = explain(targets_xy, targets_xy - np.asarray(deviations_xy, dtype=float), geometry, sigma_mm=sigma_mm)
    except ValueError as error:
        return (f"Discrepancy verdict: not computed ({error}).",)
    return ("Discrepancy workflow on the first plate (assumes it was marked through the nominal model):",
            *verdict_lines(result))
