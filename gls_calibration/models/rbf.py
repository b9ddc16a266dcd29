"""Deviation models: the OLS-trained Gaussian RBF network, a thin-plate spline, cross-validation.

The public namespace of the data-driven models; each idea lives in a module of its own:
:mod:`~gls_calibration.models.ols_rbf`, :mod:`~gls_calibration.models.thin_plate_spline`,
:mod:`~gls_calibration.models.model_selection` and :mod:`~gls_calibration.models.evaluation_blocks`.

A deviation model maps target positions ``Q`` (M, 2) in mm to deviations ``delta`` (M, 2) in mm:
it is built from training data in its constructor (like ``scipy.interpolate.RBFInterpolator``),
evaluated with ``model(points)`` and stored with ``to_dict()`` / ``from_dict`` (every stored type:
:mod:`gls_calibration.models.deviation_models`).

Spread convention (the one of MATLAB's ``newrb``, in which the published spread of 35 mm is
given): a unit's output is ``exp(-(sqrt(ln 2) r / spread)^2)``, i.e. 0.5 at ``r = spread``
(MATLAB writes the constant as 0.8326). In the ``exp(-r^2 / (2 sigma^2))`` form,
``sigma = spread / sqrt(2 ln 2) ~= 0.8493 spread``.
"""

from gls_calibration.models.evaluation_blocks import BLOCK_ROWS, TILED_MIN_ROWS
from gls_calibration.models.model_selection import (CandidateScore, CrossValidation, DeviationModel, ModelSelection,
                                                    cross_validate, select_model)
from gls_calibration.models.ols_rbf import LN2, OLSRBFNetwork, gaussian_design, sigma_from_spread
from gls_calibration.models.thin_plate_spline import ThinPlateSplineModel, tps_kernel

__all__ = ["BLOCK_ROWS", "LN2", "TILED_MIN_ROWS", "CandidateScore", "CrossValidation", "DeviationModel",
           "ModelSelection", "OLSRBFNetwork", "ThinPlateSplineModel", "cross_validate", "gaussian_design",
           "select_model", "sigma_from_spread", "tps_kernel"]
