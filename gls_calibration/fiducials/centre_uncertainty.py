"""The standard uncertainty of a fitted ring centre (step 4 of the fiducial measurement).

Sector jackknife, the edge noise's spectrum and moderation towards the plate's typical variance:
step 4 of :mod:`gls_calibration.fiducials.measure`.
"""
from __future__ import annotations

import numpy as np
from scipy import optimize, special

from gls_calibration.fiducials.sector_jackknife import sector_jackknife, well_conditioned
from gls_calibration.scan.plate_pose import PlatePose


SECTORS = 24
"""Angular sectors for coverage (15 degrees each)."""

MODEL_SIGMA_MM = 0.001
"""Uncertainty of the method itself, added in quadrature: its error on noise-free renders is a
fraction of this (interpolation and the template's line shape)."""

SPECTRUM_FIT_HARMONICS = (3, 12)
"""Harmonics of the ring's residuals (the fit leaves 3 and up) whose straight line gives the edge
noise's power at harmonics 0-2 (``_spectral_covariance``); 8 or 16 as the last changed the stated
uncertainties under speckle by about 3 %."""

SPECTRUM_SAMPLE_MIN_SHARE = 0.9
"""Candidates with at least this share of their rays used give the plate's spectrum shape (gaps blur
a periodogram)."""

COVARIANCE_BLOCK = 32
"""Candidates whose rays' outer products are summed by sector at a time (``centre_covariance``):
about 1.6 MB of products, in the cache, instead of 19 MB for a 19x19 plate."""

MODERATION_MIN_REFERENCE = 10
"""Candidates a plate needs before their uncertainties are moderated towards its typical one."""


def harmonic_design(angles: np.ndarray) -> np.ndarray:
    """Radial model of a ring seen from near its centre: r(theta) = R + a cos + b sin + c cos 2 + d sin 2.

    (a, b) is the centre's offset from the ray origin (first order, exact at the fixed point of the
    passes); the second harmonic takes up ellipticity (tilt, unequal pixel pitch, an uncalibrated
    scanner's distortion) so that it neither enters the residuals nor the uncertainty.
    """
    return np.stack([np.ones_like(angles), np.cos(angles), np.sin(angles), np.cos(2 * angles),
                     np.sin(2 * angles)], axis=-1)


def sector_sums(values: np.ndarray, sector_of_ray: np.ndarray) -> np.ndarray:
    """Sum ``values`` (M, A, ...) over the rays of each sector (M, SECTORS, ...).

    Sums of ``values`` (M, A, ...) over the rays of each sector (M, SECTORS, ...); the rays of a
    sector are contiguous and ``sector_of_ray`` is sorted, so this is one ``reduceat``.
    """
    starts = np.searchsorted(sector_of_ray, np.arange(SECTORS))
    return np.add.reduceat(values, starts, axis=1)


def centre_covariance(design: np.ndarray, residual: np.ndarray, used: np.ndarray,
                      sector_of_ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the centre's covariance (M, 2, 2) from the radial residuals, and its dof (M,).

    Covariance (M, 2, 2) of the fitted centre (plate axes, mm^2) from the radial residuals, and its
    degrees of freedom (M,): per candidate the larger (by trace) of two estimates, each blind to
    what the other sees.

    - The delete-one-sector jackknife of the linearised circle fit (dof: sectors used - 1) follows a
      fiducial's own trouble, a scratch or a speckle grain on a few sectors.
    - The spectral estimate (``_spectral_covariance``) follows noise correlated around the whole ring,
      whose share in the first harmonic (the centre) no sector sees.
    """
    count, rays = residual.shape
    parameters = design.shape[-1]
    u = np.asarray(used, dtype=float)       # the fit's weight per ray, 0 where unused
    full_design = np.broadcast_to(design, (count, rays, parameters))
    # Every ray's weighted outer product as (x_i u) x_j, the order einsum multiplies in: the same values.
    # A block of candidates at a time: the products (block, A, P, P) stay in the cache.
    sector_normal = np.empty((count, SECTORS, parameters, parameters))
    for start in range(0, count, COVARIANCE_BLOCK):
        block = slice(start, start + COVARIANCE_BLOCK)
        sector_normal[block] = sector_sums((design * u[block, :, None])[..., :, None] * design[:, None, :],
                                           sector_of_ray)
    sector_score = sector_sums(full_design * (u * np.where(u > 0, residual, 0.0))[..., None], sector_of_ray)
    jackknife, groups = sector_jackknife(sector_normal, sector_score, sector_sums(u, sector_of_ray) > 0,
                                         total_right=np.zeros((count, parameters)))
    jackknife = jackknife[:, 1:3, 1:3]
    spectral, spectral_dof = _spectral_covariance(design, residual, used)
    larger = np.trace(jackknife, axis1=1, axis2=2) >= np.trace(spectral, axis1=1, axis2=2)
    return (np.where(larger[:, None, None], jackknife, spectral),
            np.where(larger, groups - 1.0, spectral_dof))


def _spectral_covariance(design: np.ndarray, residual: np.ndarray, used: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Return the centre's covariance (M, 2, 2) from the edge noise spectrum, and its dof (M,).

    Covariance (M, 2, 2) of the fitted centre from the edge noise's spectrum around the ring, and
    its degrees of freedom (M,).

    The edge errors of neighbouring rays are correlated (speckle grains span several rays), and their
    power falls with the harmonic number; the centre is the first harmonic, which the fit takes out of
    the residuals along with harmonics 0 and 2. So the spectrum's shape is pooled over the plate's
    well-seen candidates (residual periodograms, each over its own residual variance), fitted by a
    straight line over ``SPECTRUM_FIT_HARMONICS`` and extended by it to harmonics 0-2; each candidate
    scales it by its own residual variance s^2. With the rays' covariance C the circulant of that
    spectrum, the fit's covariance is the sandwich B^-1 (W X)^T C (W X) B^-1 (X the design, W the
    used rays, B = X^T W X). Degrees of freedom: the used rays over the noise's integrated
    correlation (the spectrum at harmonic 0 over its mean).
    """
    count, rays = residual.shape
    weight = np.asarray(used, dtype=float)      # the fit's weight per ray, 0 where unused
    kept = np.where(weight > 0, residual, 0.0)
    share = (weight > 0).mean(axis=1)
    variance = (weight * kept**2).sum(axis=1) / np.maximum(weight.sum(axis=1), 1e-12)
    periodogram = np.abs(np.fft.rfft(kept, axis=1)) ** 2 / rays                    # harmonics 0..A/2
    sample = (share >= SPECTRUM_SAMPLE_MIN_SHARE) & (variance > 0)
    if np.count_nonzero(sample) < MODERATION_MIN_REFERENCE:
        sample = variance > 0
    if not sample.any():
        return np.zeros((count, 2, 2)), np.full(count, 2.0)
    shape = (periodogram[sample] / (variance[sample] * share[sample])[:, None]).mean(axis=0)
    first, last = SPECTRUM_FIT_HARMONICS
    band = np.arange(first, last + 1)
    line = np.polyfit(band, shape[band], 1)
    shape[:first] = np.maximum(np.polyval(line, np.arange(first)), 0.0)
    weighted = weight[..., None] * design                                               # (M, A, P)
    correlated = np.fft.irfft(np.fft.rfft(weighted, axis=1) * shape[None, :, None], n=rays, axis=1)
    transposed = np.swapaxes(weighted, 1, 2)                                            # (M, P, A)
    meat = variance[:, None, None] * (transposed @ correlated)
    normal = transposed @ design
    normal[~well_conditioned(normal, 1e10)] = np.eye(design.shape[-1])
    inverse = np.linalg.inv(normal)
    covariance = inverse @ meat @ inverse
    # The mean over all A harmonics of the symmetric spectrum, from its half.
    full_mean = (2.0 * shape.sum() - shape[0] - shape[-1]) / rays
    correlation_time = max(shape[0] / max(full_mean, 1e-12), 1.0)
    return covariance[:, 1:3, 1:3], np.maximum(weight.sum(axis=1) / correlation_time, 2.0)


def moderated_covariance(covariance: np.ndarray, dof: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Raise each axis' variance of centre covariances (M, 2, 2) to its empirical-Bayes posterior.

    Centre covariances (M, 2, 2) with each axis' variance raised to its empirical-Bayes
    posterior, never lowered.

    A variance estimated from ~24 sectors (``dof`` (M,) degrees of freedom) comes out well below the
    true one now and then, so in units of the stated uncertainty the errors of a plate are
    heavy-tailed (Student t, not normal). The fiducials of one plate share most of their noise:
    per plate axis, each variance is combined with the plate's typical one as in moderated
    statistics (Smyth 2004): the prior's degrees of freedom d0 and variance s0^2 by the method of
    moments on the log variances of the ``reference`` candidates, posterior (d s^2 + d0 s0^2) /
    (d + d0). Only raised: a fiducial with a genuinely larger uncertainty (scratched, partly seen)
    keeps its own. Fewer than ``MODERATION_MIN_REFERENCE`` references: unchanged.
    """
    usable = reference & (dof >= 2) & np.all(np.diagonal(covariance, axis1=1, axis2=2) > 0, axis=1)
    if np.count_nonzero(usable) < MODERATION_MIN_REFERENCE:
        return covariance
    half = dof[usable] / 2.0
    factors = np.ones((len(covariance), 2))
    for axis in range(2):
        variance = covariance[:, axis, axis]
        # log s^2 - E[log chi2_d / d] is centred on the log of the prior's scale (both have digammas)
        centred = np.log(variance[usable]) - special.digamma(half) + np.log(half)
        excess = np.var(centred, ddof=1) - np.mean(special.polygamma(1, half))
        if excess > 0:
            prior_dof = 2.0 * optimize.brentq(lambda x: special.polygamma(1, x) - excess, 1e-8, 1e8)
            prior = np.exp(np.mean(centred) + special.digamma(prior_dof / 2) - np.log(prior_dof / 2))
            posterior = (dof * variance + prior_dof * prior) / np.maximum(dof + prior_dof, 1e-12)
        else:   # no spread beyond the sampling's: one variance for the whole plate
            posterior = np.full(len(variance), np.exp(np.mean(centred)))
        with np.errstate(divide="ignore", invalid="ignore"):
            factors[:, axis] = np.where(variance > 0, np.maximum(posterior / variance, 1.0), 1.0)
    scale = np.sqrt(factors)
    return covariance * scale[:, :, None] * scale[:, None, :]


def plane_to_cloud_sigma(covariance: np.ndarray, pose: PlatePose) -> np.ndarray:
    """Per-axis standard uncertainty (M, 2) along the cloud's x and y of plate-axis covariances."""
    in_plane = np.asarray(pose.rotation, dtype=float)[:, :2]
    cloud = np.einsum("ij,mjk,lk->mil", in_plane, covariance, in_plane)
    return np.sqrt(np.stack([cloud[:, 0, 0], cloud[:, 1, 1]], axis=-1))
