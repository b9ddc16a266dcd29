"""Delete-one-sector jackknife of least-squares fits around a ring, many candidates at once.

Also the conditioning check of such fits' normal equations (``well_conditioned``).
"""
from __future__ import annotations

import numpy as np

MIN_EIGENVALUE_RATIO = 1e-10
"""A left-out system is solved when its smallest eigenvalue exceeds this share of its largest."""


def well_conditioned(normal: np.ndarray, limit: float) -> np.ndarray:
    """Return ``np.linalg.cond(normal) < limit`` for positive semi-definite normal matrices, mostly without an SVD.

    The eigenvalues of a positive semi-definite P x P matrix are its singular values, the largest
    at most its trace t and the smallest at least det / t^(P - 1); so t^P / det bounds its condition
    number from above. Where that bound is below half the limit (det's rounding is far smaller) the
    matrix passes; the rest (ill-conditioned, singular, non-finite) get ``np.linalg.cond`` as before.
    Meant for small P (a handful of parameters), where the bound is seldom loose by more than 10^4.

    Parameters
    ----------
    normal : numpy.ndarray, shape (M, P, P)
        Positive semi-definite matrices (weighted normal matrices, weights non-negative).
    limit : float
        Largest condition number (2-norm) accepted, exclusive.

    Returns
    -------
    numpy.ndarray of bool, shape (M,)
        True where the condition number is below ``limit``.
    """
    parameters = normal.shape[-1]
    trace = np.trace(normal, axis1=-2, axis2=-1)
    determinant = np.linalg.det(normal)
    with np.errstate(invalid="ignore", over="ignore"):
        passed = (determinant > 0) & (trace**parameters < 0.5 * limit * determinant)
    unproven = ~passed
    if unproven.any():
        with np.errstate(divide="ignore", invalid="ignore"):    # a singular matrix's condition is inf
            passed[unproven] = np.linalg.cond(normal[unproven]) < limit
    return passed


def _well_posed(total_normal: np.ndarray, sector_normal: np.ndarray, left_out: np.ndarray) -> np.ndarray:
    """Return the mask (M, S) of left-out systems whose eigenvalue ratio exceeds ``MIN_EIGENVALUE_RATIO``.

    The same test as the eigenvalues of every left-out system, mostly without computing them: each
    sector's share N_g (M, S, P, P) is positive semi-definite, so with the full system N (M, P, P),
    N - N_g >= (1 - mu_g) N in the Loewner order for mu_g = lambda_max(N^-1 N_g) <= trace(N^-1 N_g),
    and lambda_max(N - N_g) <= lambda_max(N). Where (1 - trace(N^-1 N_g)) lambda_min(N) / lambda_max(N)
    exceeds twice the limit (N itself conditioned better than 1e8, so that its inverse and this bound
    are exact to far below that margin), the ratio is proven above the limit. The systems left
    unproven (a few with sectors that carry much of the fit, or an ill-posed N) get their own
    eigenvalues (``numpy.linalg.eigvalsh``), as before.

    Parameters
    ----------
    total_normal : numpy.ndarray, shape (M, P, P)
        The full normal matrix of every candidate, the sum of its sectors' shares.
    sector_normal : numpy.ndarray, shape (M, S, P, P)
        Each sector's share, positive semi-definite.
    left_out : numpy.ndarray, shape (M, S, P, P)
        ``total_normal`` less each sector's share.

    Returns
    -------
    numpy.ndarray, shape (M, S)
        True where the left-out system's smallest eigenvalue exceeds ``MIN_EIGENVALUE_RATIO`` times its largest.
    """
    parameters = total_normal.shape[-1]
    eigenvalues = np.linalg.eigvalsh(total_normal)
    largest = eigenvalues[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(largest > 0, eigenvalues[:, 0] / largest, 0.0)
    invertible = ratio > 1e-8
    inverse = np.linalg.inv(np.where(invertible[:, None, None], total_normal, np.eye(parameters)))
    # trace(N^-1 N_g): the sector's leverage, its share of the fit's information (P over all sectors).
    leverage = np.einsum("mij,msji->ms", inverse, sector_normal)
    solvable = invertible[:, None] & ((1.0 - leverage) * ratio[:, None] > 2 * MIN_EIGENVALUE_RATIO)
    unproven = ~solvable
    if unproven.any():
        # Eigenvalues of symmetric positive semi-definite systems are their singular values.
        doubtful = np.linalg.eigvalsh(left_out[unproven])
        solvable[unproven] = doubtful[:, 0] > MIN_EIGENVALUE_RATIO * doubtful[:, -1]
    return solvable


def sector_jackknife(sector_normal: np.ndarray, sector_right: np.ndarray, present: np.ndarray,
                     total_right: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Return the delete-one-sector jackknife covariance (M, P, P) of a fit and its sector count.

    Delete-one-sector jackknife of a least-squares fit given per sector (the rays of a ring are
    correlated, whole sectors much less): covariance (M, P, P) of the solution and the number of
    sectors g (M,) that entered it.

    ``sector_normal`` (M, S, P, P) and ``sector_right`` (M, S, P) are each sector's share of the
    normal equations N x = r, ``present`` (M, S) the sectors with data. Leaving out sector g gives
    (N - N_g)^-1 (r - r_g), with r the sum of ``sector_right`` unless ``total_right`` (M, P) is
    given (0 for a fit already solved, whose residuals' scores are ``sector_right``). Sectors whose
    removal leaves an ill-posed fit (``_well_posed``) do not enter; g is at least 2.
    """
    parameters = sector_normal.shape[-1]
    total = sector_right.sum(axis=1) if total_right is None else total_right
    total_normal = sector_normal.sum(axis=1, keepdims=True)
    left_out = total_normal - sector_normal                                         # (M, S, P, P)
    solvable = _well_posed(total_normal[:, 0], sector_normal, left_out)
    left_out[~solvable] = np.eye(parameters)
    partial = np.linalg.solve(left_out, (total[:, None] - sector_right)[..., None])[..., 0]
    keep = present & solvable
    groups = np.maximum(keep.sum(axis=1), 2)
    mean = np.where(keep[..., None], partial, 0.0).sum(axis=1) / groups[:, None]
    deviation = np.where(keep[..., None], partial - mean[:, None], 0.0)
    covariance = ((groups - 1) / groups)[:, None, None] * np.einsum("msi,msj->mij", deviation, deviation)
    return covariance, groups
