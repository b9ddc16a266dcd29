"""Delete-one-sector jackknife of least-squares fits around a ring, many candidates at once."""
from __future__ import annotations

import numpy as np


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
    removal leaves an ill-posed fit do not enter; g is at least 2.
    """
    parameters = sector_normal.shape[-1]
    total = sector_right.sum(axis=1) if total_right is None else total_right
    left_out = sector_normal.sum(axis=1, keepdims=True) - sector_normal            # (M, S, P, P)
    # Condition number of the symmetric positive semi-definite systems (their eigenvalues are their
    # singular values), at two thirds of the cost of an SVD.
    eigenvalues = np.linalg.eigvalsh(left_out)
    solvable = eigenvalues[..., 0] > 1e-10 * eigenvalues[..., -1]
    left_out[~solvable] = np.eye(parameters)
    partial = np.linalg.solve(left_out, (total[:, None] - sector_right)[..., None])[..., 0]
    keep = present & solvable
    groups = np.maximum(keep.sum(axis=1), 2)
    mean = np.where(keep[..., None], partial, 0.0).sum(axis=1) / groups[:, None]
    deviation = np.where(keep[..., None], partial - mean[:, None], 0.0)
    covariance = ((groups - 1) / groups)[:, None, None] * np.einsum("msi,msj->mij", deviation, deviation)
    return covariance, groups
