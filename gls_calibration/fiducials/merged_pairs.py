"""Two fiducials marked a fraction of a millimetre apart, told from one: the pair's signature in the image.

Two double rings offset by s (about 0.1-0.3 mm) are found as one candidate about s / 2 from either,
with ring radii and ellipticity an uncalibrated head can also produce. Along the offset their lines
split, across it they coincide, so the pair darkens and broadens its lines by an amount that
varies as cos 2(theta - phi) around the ring, and broadens them on average by as much; one ring
seen through a distorted head changes its radius (first and second harmonics of the edge), not its
line profile.

The test works on the pixels themselves (no interpolation: resampling the prewhitened image's
sharp lines along rays would put its own phase-dependent width pattern on every fiducial):

1. Template: the plate's mean line profile g(rho) of the image against the signed distance rho from
   each reference candidate's fitted mid-ring (mean radius plus elliptical second harmonic), in bins
   of a fifth of a pixel, and its first and second derivatives (Savitzky-Golay). It holds whatever
   the real lines, optics and prewhitening filter make of a mark; nothing is assumed about them.
2. Per candidate, least squares over the pixels within ``band_mm`` of its rings: the single mark,
   linearised about the fit (amplitude g, centre shift g' n, radius g', ellipse g' cos 2theta /
   g' sin 2theta, shading g cos theta / g sin theta, offset), plus the pair's signature (line width
   g'', g'' and g times cos 2theta and sin 2theta), per angular sector. Its five coefficients over
   the amplitude, minus the plate's median (the part every mark shares: spot shape, unequal pixel
   pitch).
3. Their covariance: the candidate's delete-one-sector jackknife (the pixels' misfit is correlated
   along the ring; a covariance from the residuals as if independent made single marks look like
   pairs) plus the variance by which the plate's single marks truly differ (a marking laser's power
   and focus wander along the path). Hotelling's T^2 against F(5, g - 5) with g sectors.
"""
from __future__ import annotations

import numpy as np
from scipy.special import fdtrc
from scipy.signal import savgol_filter

from gls_calibration.common.robust import robust_sigma
from gls_calibration.fiducials.sector_jackknife import sector_jackknife

SIGNATURE_DOF = 5
"""Coefficients of the pair's signature: the mean line width, and line width and darkness each as
cos 2theta and sin 2theta."""

PROFILE_BIN_PX = 0.2
"""Bin of the plate's line profile, in pixels: pixel centres fall at every phase against the rings."""

SECTORS = 24
"""Angular sectors of the jackknife (as for the centres: a sector holds a stretch of ring whose
misfit is shared, sectors much less)."""

MIN_PIXELS = 200
"""Pixels a candidate needs within the band for its own fit; fewer (at the scan's border): no test."""

CANDIDATE_BLOCK = 32
"""Candidates per batched least-squares product (bounds the work arrays to some tens of MB)."""

GEOMETRY_BLOCK = 16
"""Candidates whose window pixels' geometry is computed at a time (``_pixel_geometry``): their dozen
temporaries, about 0.3 MB each, stay in the cache."""


def _profile_tables(rho: np.ndarray, values: np.ndarray, bin_mm: float, band_mm: float):
    """Return bin centres (B,) and the mean profile of ``values`` against ``rho`` with derivatives.

    The derivatives are the first and second, each (B,); ``rho`` is 1-D, mm, within +-``band_mm``.
    Empty bins take their neighbours' values.
    """
    edges = np.arange(-band_mm - 3 * bin_mm, band_mm + 3 * bin_mm + 0.5 * bin_mm, bin_mm)
    index = _even_interval(rho, edges, within=True) + 1         # np.digitize(rho, edges)
    counts = np.bincount(index, minlength=len(edges) + 1)[1:-1]
    sums = np.bincount(index, values, minlength=len(edges) + 1)[1:-1]
    centres = 0.5 * (edges[1:] + edges[:-1])
    filled = counts > 0
    profile = np.interp(centres, centres[filled], sums[filled] / counts[filled])
    window = 7
    return (centres, savgol_filter(profile, window, 3), savgol_filter(profile, window, 3, deriv=1, delta=bin_mm),
            savgol_filter(profile, window + 2, 3, deriv=2, delta=bin_mm))


def _even_interval(position: np.ndarray, abscissae: np.ndarray, *, within: bool = False) -> np.ndarray:
    """Return ``np.searchsorted(abscissae, position, side="right") - 1`` for evenly spaced abscissae.

    The interval from the spacing, then moved by one where rounding put it next door: the interval
    a search finds (abscissae[i] <= position < abscissae[i + 1]; -1 before the first, B - 1 at or
    beyond the last or NaN) without a binary search per position, which in no order costs a full one.

    Parameters
    ----------
    position : numpy.ndarray
        Positions to place.
    abscissae : numpy.ndarray, shape (B,)
        Increasing, evenly spaced (to well within a spacing) positions, B >= 2.
    within : bool
        Every position is known to lie between the first and last abscissae (not at the last): the
        passes for NaN and for positions beyond either end are skipped.

    Returns
    -------
    numpy.ndarray of int, shaped as ``position``
        The interval of every position.
    """
    last = len(abscissae) - 1
    first, spacing = abscissae[0], (abscissae[-1] - abscissae[0]) / last
    scaled = np.subtract(position, first)
    scaled /= spacing                   # in place: the same quotient, one temporary less
    guess = np.clip(scaled if within else np.nan_to_num(scaled, copy=False), 0, last - 1, out=scaled).astype(int)
    # np.take, and the next abscissa from the shifted view: no index array built per pass.
    guess -= (position < np.take(abscissae, guess)) & (guess > 0)
    guess += (position >= np.take(abscissae[1:], guess)) & (guess < last - 1)
    if not within:
        guess[(position >= abscissae[-1]) | np.isnan(position)] = last
        guess[position < first] = -1
    return guess


class _LinearLookup:
    """``np.interp`` of several tables on the same abscissae, the interval found once for all of them.

    Each value is ``np.interp``'s own (the same slope per interval, the same expression), so the
    results are identical; positions not ``used`` read 0 instead of being multiplied by 0 afterwards.
    """

    def __init__(self, abscissae: np.ndarray, tables: tuple[np.ndarray, ...]):
        """Keep the tables' slopes and values per interval, with constant ones beyond either end and 0 for unused.

        Parameters
        ----------
        abscissae : numpy.ndarray, shape (B,)
            Increasing positions of the tables' entries.
        tables : tuple of numpy.ndarray, each shape (B,)
            Values at ``abscissae``.
        """
        self.abscissae = abscissae
        width = np.diff(abscissae)
        # Intervals 0..B-2, then B-1 (at or beyond the last abscissa), B (before the first), B + 1 (unused).
        self.slopes = [np.concatenate([(table[1:] - table[:-1]) / width, np.zeros(3)]) for table in tables]
        self.values = [np.concatenate([table[:-1], [table[-1], table[0], 0.0]]) for table in tables]

    def __call__(self, position: np.ndarray, used: np.ndarray) -> list[np.ndarray]:
        """Return every table at ``position`` where ``used``, 0 elsewhere.

        Parameters
        ----------
        position : numpy.ndarray
            Where to interpolate, strictly between the first and last abscissae wherever ``used``.
        used : numpy.ndarray of bool, same shape
            The positions that read the tables.

        Returns
        -------
        list of numpy.ndarray
            One array per table, shaped as ``position``.
        """
        abscissae = self.abscissae
        last = len(abscissae) - 1
        # The used positions lie between the ends; the others are moved to the first abscissa and
        # read the unused interval: no passes for positions beyond the ends or NaN.
        within = np.where(used, position, abscissae[0])
        interval = _even_interval(within, abscissae, within=True)
        offset = within - np.take(abscissae, interval)
        interval = np.where(used, interval, last + 2)
        # np.take: the same gathers as indexing, a good part cheaper on these (m, S, L) arrays.
        return [np.take(slope, interval) * offset + np.take(value, interval)
                for slope, value in zip(self.slopes, self.values)]


def _window(pitch_mm: tuple[float, float], jacobian: np.ndarray, inner_mm: float, outer_mm: float):
    """Return the pixel offsets around a candidate's centre within the annulus, and a sector index.

    Pixel offsets (N, 2) as (column, row) around a candidate's centre pixel that can fall between
    ``inner_mm`` and ``outer_mm`` of it (the plate's typical pixel map, a pixel of slack), and an
    index (S, L) of them per angular sector, padded with N (a row of zeros is appended there).
    """
    half_rows, half_cols = int(np.ceil(outer_mm / pitch_mm[0])) + 1, int(np.ceil(outer_mm / pitch_mm[1])) + 1
    rows, cols = np.mgrid[-half_rows:half_rows + 1, -half_cols:half_cols + 1]
    offsets = np.stack([cols.ravel(), rows.ravel()], -1)
    uv = offsets @ np.median(jacobian, axis=0).T
    distance = np.hypot(uv[:, 0], uv[:, 1])
    slack = 1.5 * max(pitch_mm)
    keep = (distance >= inner_mm - slack) & (distance <= outer_mm + slack)
    offsets = offsets[keep]
    sector = ((np.arctan2(uv[keep, 1], uv[keep, 0]) + np.pi) / (2 * np.pi) * SECTORS).astype(int) % SECTORS
    members = [np.nonzero(sector == k)[0] for k in range(SECTORS)]
    longest = max(len(m) for m in members)
    by_sector = np.full((SECTORS, longest), len(offsets))
    for k, m in enumerate(members):
        by_sector[k, :len(m)] = m
    return offsets, by_sector


def _pixel_geometry(image: np.ndarray, centre_px: np.ndarray, offsets: np.ndarray, by_sector: np.ndarray,
                    shift_mm: np.ndarray, jacobian: np.ndarray, mid_radius_mm: np.ndarray,
                    harmonic_mm: np.ndarray, reference: np.ndarray, band_mm: float):
    """Return every candidate's window pixels by sector and the reference candidates' pixels.

    Per block of ``GEOMETRY_BLOCK`` candidates, whose temporaries stay in the cache: the pixels at
    ``offsets`` (N, 2; column, row) about each candidate's centre pixel ``centre_px`` (M, 2), their
    plate position relative to the fitted centre (``shift_mm`` (M, 2) plus J times the offset), the
    angle's cosine and sine, the signed distance rho from the fitted mid-ring, and whether a pixel
    enters the fit (inside the image, finite, within ``band_mm`` of the mid-ring).

    Returns
    -------
    rho, cos1, sin1, values : numpy.ndarray, each (M, S, L)
        The window's pixels gathered by sector (``by_sector``; the padding reads pixel N - 1); the
        values in the image's dtype.
    usable : numpy.ndarray of bool, (M, S, L)
        The pixels that enter the fit (padding excluded).
    reference_rho, reference_values : numpy.ndarray, each (K,)
        rho and value of the ``reference`` candidates' usable pixels, candidate by candidate and in
        window order: the order the plate's line profile sums them in.
    """
    count = len(centre_px)
    height, width = image.shape
    layout = (count,) + by_sector.shape
    rho_s, cos_s, sin_s = (np.empty(layout) for _ in range(3))
    values_s = np.empty(layout, image.dtype)        # the image's own values: cast where they enter a product
    usable_s = np.empty(layout, bool)
    padding = by_sector >= len(offsets)
    # A window wholly inside the image (nearly every candidate) reads its pixels at one flat offset
    # each from its centre pixel: no bounds per pixel.
    low, high = offsets.min(axis=0), offsets.max(axis=0)
    whole = np.all((centre_px + low >= 0) & (centre_px + high < (width, height)), axis=1)
    flat_offsets = offsets[:, 1] * width + offsets[:, 0]
    offsets_mm = np.ascontiguousarray(offsets.T, dtype=float)                              # (2, N)
    taken_rho, taken_values = [], []
    for start in range(0, count, GEOMETRY_BLOCK):
        block = slice(start, min(start + GEOMETRY_BLOCK, count))
        centre = centre_px[block]
        if whole[block].all():
            inside = True
            values = np.take(image, (centre[:, 1] * width + centre[:, 0])[:, None] + flat_offsets)
        else:
            col = centre[:, 0, None] + offsets[:, 0]                                         # (m, N)
            row = centre[:, 1, None] + offsets[:, 1]
            inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
            # One flat index per pixel: a single gather instead of numpy's two-axis fancy indexing.
            values = np.take(image, np.clip(row, 0, height - 1) * width + np.clip(col, 0, width - 1))
        # Each pixel's plate position relative to the centre, u and v in rows of their own: one
        # product of the block's Jacobians (2m, 2) with the offsets (2, N), the same sums of two
        # products per pixel as J @ offset (on this OpenBLAS the same to the bit, checked on the
        # plates of benchmarks/fiducial_identity.py), then the shift.
        relative = jacobian[block].reshape(-1, 2) @ offsets_mm                             # (2m, N)
        u, v = relative[0::2], relative[1::2]
        u += shift_mm[block, 0, None]
        v += shift_mm[block, 1, None]
        # The angle's cosines and sines from the coordinates (no trigonometric calls on ~10^6 pixels).
        distance = np.maximum(np.hypot(u, v), 1e-12)
        cos1, sin1 = u / distance, v / distance
        cos2, sin2 = cos1 * cos1 - sin1 * sin1, 2 * cos1 * sin1
        harmonic = harmonic_mm[block]
        rho = distance - (mid_radius_mm[block, None] + harmonic[:, 0, None] * cos2 + harmonic[:, 1, None] * sin2)
        usable = inside & (np.abs(rho) <= band_mm) & np.isfinite(values)
        taken = usable[reference[block]]
        if taken.size:
            taken_rho.append(rho[reference[block]][taken])
            taken_values.append(values[reference[block]][taken])
        # Gathered by sector here, while the block is in the cache (the padding reads pixel N - 1).
        for source, target in ((rho, rho_s), (cos1, cos_s), (sin1, sin_s), (values, values_s), (usable, usable_s)):
            np.take(source, by_sector, axis=1, mode="clip", out=target[block])
        usable_s[block] &= ~padding
    concatenated = [np.concatenate(parts) if parts else np.empty(0) for parts in (taken_rho, taken_values)]
    return rho_s, cos_s, sin_s, values_s, usable_s, concatenated[0], concatenated[1]


def pair_signature(image: np.ndarray, centres_uv: np.ndarray, offset: np.ndarray, jacobian: np.ndarray,
                   mid_radius_mm: np.ndarray, harmonic_mm: np.ndarray, reference: np.ndarray,
                   pitch_mm: tuple[float, float], band_mm: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit each candidate's pair signature (M, 5) with its jackknife covariance and sector count.

    Each candidate's pair signature over its amplitude (M, 5), its delete-one-sector jackknife
    covariance (M, 5, 5) and the number of sectors that entered it (M,); NaN where it cannot be fitted.

    ``image`` (H, W) is the image the centres were fitted on, marks positive or negative alike;
    ``centres_uv`` (M, 2) the fitted centres in plate mm, ``offset`` (M, 2) and ``jacobian``
    (M, 2, 2) each candidate's local map uv = offset + J (column, row); ``mid_radius_mm`` (M,) the
    fitted mean radius between the rings and ``harmonic_mm`` (M, 2) its cos 2theta / sin 2theta
    terms; ``reference`` (M,) the candidates the plate's line profile is taken from; ``pitch_mm``
    the (row, column) pixel pitch.
    """
    count = len(centres_uv)
    signature = np.full((count, SIGNATURE_DOF), np.nan)
    covariance = np.full((count, SIGNATURE_DOF, SIGNATURE_DOF), np.nan)
    groups = np.zeros(count, int)
    if count == 0 or not reference.any():
        return signature, covariance, groups
    radii = mid_radius_mm[reference]
    offsets, by_sector = _window(pitch_mm, jacobian, float(radii.min()) - band_mm, float(radii.max()) + band_mm)
    centre_px = np.rint(np.einsum("mij,mj->mi", np.linalg.inv(jacobian), centres_uv - offset)).astype(int)
    shift_mm = offset - centres_uv + np.einsum("mij,mj->mi", jacobian, centre_px.astype(float))
    rho_s, cos_s, sin_s, values_s, usable_s, reference_rho, reference_values = _pixel_geometry(
        image, centre_px, offsets, by_sector, shift_mm, jacobian, mid_radius_mm, harmonic_mm, reference, band_mm)

    # 1. The plate's line profile from its reference candidates.
    bin_mm = PROFILE_BIN_PX * min(pitch_mm)
    if len(reference_rho) < MIN_PIXELS:
        return signature, covariance, groups
    centres, g0, g1, g2 = _profile_tables(reference_rho, reference_values, bin_mm, band_mm)

    # 2. Each candidate's fit, the single mark linearised about it plus the pair's signature, per sector.
    # The pixels were gathered by sector (the padded index N reads the last pixel, unused) and the
    # design is built in that layout, a row per parameter: no copy of the design to transpose.
    lookup = _LinearLookup(centres, (g0, g1, g2))
    for start in range(0, count, CANDIDATE_BLOCK):
        block = slice(start, min(start + CANDIDATE_BLOCK, count))
        use_s, rho, c1, s1 = usable_s[block], rho_s[block], cos_s[block], sin_s[block]
        c2, s2 = c1 * c1 - s1 * s1, 2 * c1 * s1
        target = np.where(use_s, values_s[block].astype(float), 0.0)
        # Every column has one of these four factors: zeroed there, a pixel left out weighs nothing.
        profile, slope, bend = lookup(rho, use_s)
        columns = ((profile, None), (slope, c1), (slope, s1), (slope, None), (slope, c2), (slope, s2),
                   (profile, c1), (profile, s1), (use_s, None), (bend, None),
                   (bend, c2), (bend, s2), (profile, c2), (profile, s2))
        parameters = len(columns)
        # Each product written straight into its row of the design: no temporaries stacked after.
        design = np.empty(profile.shape[:2] + (parameters,) + profile.shape[2:])              # (m, S, P, L)
        for column, (factor, angle) in enumerate(columns):
            if angle is None:
                design[:, :, column] = factor
            else:
                np.multiply(factor, angle, out=design[:, :, column])
        sector_normal = np.matmul(design, np.swapaxes(design, 2, 3))                           # (m, S, P, P)
        sector_right = np.matmul(design, target[..., None])[..., 0]                            # (m, S, P)
        sector_pixels = use_s.sum(axis=2)
        normal = sector_normal.sum(axis=1)
        fit = (sector_pixels.sum(axis=1) >= MIN_PIXELS) & (np.linalg.cond(normal) < 1e12)
        normal[~fit] = np.eye(parameters)
        solution = np.linalg.solve(normal, sector_right.sum(axis=1)[..., None])[..., 0]
        jackknife, sectors = sector_jackknife(sector_normal, sector_right, sector_pixels >= parameters)
        fit &= solution[:, 0] > 0
        amplitude = np.where(fit, solution[:, 0], np.nan)
        signature[block] = solution[:, -SIGNATURE_DOF:] / amplitude[:, None]
        covariance[block] = jackknife[:, -SIGNATURE_DOF:, -SIGNATURE_DOF:] / amplitude[:, None, None] ** 2
        groups[block] = sectors
    return signature, covariance, groups


def merged(signature: np.ndarray, covariance: np.ndarray, groups: np.ndarray, reference: np.ndarray,
           false_alarm: float, min_reference: int) -> np.ndarray:
    """Mask (M,) of candidates whose pair signature (``pair_signature``) stands out from the plate's.

    The signature minus the ``reference`` candidates' median (what every mark shares: spot shape,
    unequal pixel pitch) against its covariance: its own jackknife covariance plus, per coefficient,
    the variance by which the plate's single marks truly differ (a laser's power and focus wander
    along the marking path; robust: the references' squared MAD less their median own variance,
    never negative). Hotelling's T^2 with g sectors, F(5, g - 5) distributed for a single fiducial;
    merged where that puts it beyond ``false_alarm``. With fewer than ``min_reference`` usable
    references nothing is called merged.
    """
    flagged = np.zeros(len(signature), bool)
    finite = np.all(np.isfinite(signature), axis=1) & np.all(np.isfinite(covariance), axis=(1, 2))
    usable = reference & finite
    if np.count_nonzero(usable) < min_reference:
        return flagged
    excess = np.nan_to_num(signature - np.median(signature[usable], axis=0))
    own_variance = np.diagonal(covariance[usable], axis1=1, axis2=2)
    between = np.maximum(np.array([robust_sigma(excess[usable, k]) ** 2 for k in range(SIGNATURE_DOF)])
                         - np.median(own_variance, axis=0), 0.0)
    total = np.where(finite[:, None, None], covariance, np.eye(SIGNATURE_DOF)) + np.diag(between)
    check = finite & (np.linalg.cond(total) < 1e12) & (groups > SIGNATURE_DOF + 1)
    if not check.any():
        return flagged
    t_squared = np.einsum("mi,mij,mj->m", excess[check], np.linalg.inv(total[check]), excess[check])
    dof = groups[check].astype(float)
    statistic = t_squared * (dof - SIGNATURE_DOF) / (SIGNATURE_DOF * (dof - 1))
    flagged[check] = fdtrc(SIGNATURE_DOF, dof - SIGNATURE_DOF, statistic) < false_alarm
    return flagged
