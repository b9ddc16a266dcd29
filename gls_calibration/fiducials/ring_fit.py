"""Sub-pixel double-ring centres (step 3 of :mod:`gls_calibration.fiducials.measure`).

Sub-pixel double-ring centres: rays in plate millimetres, edge points, the ring model's weighted fit
(step 3 of :mod:`gls_calibration.fiducials.measure`).
"""
from __future__ import annotations

import cv2
import numpy as np

from gls_calibration.common.robust import NORMAL_MAD_SCALE
from gls_calibration.fiducials.centre_uncertainty import SECTORS, centre_covariance, harmonic_design, sector_sums
from gls_calibration.fiducials.sector_jackknife import well_conditioned


RAY_COUNT = 256
"""Rays per fiducial: about 1.5 rays per pixel of outer-ring circumference at 0.1 mm pixels."""

RADIAL_STEP_PX = 0.2
"""Radial sample step of the fine passes and the fit pass, pixels."""

COARSE_MARGIN_PX = 4.0
"""How far (pixels) the first pass looks for the rings: the detection may be this far off."""

FINE_MARGIN_PX = 1.5
"""How far later passes look for the rings around the current circle."""

PASSES = 3
"""Coarse pass (every ``COARSE_RAY_STRIDE``-th ray), fine pass on all rays, fine pass on the rays of
sectors where the rings are seen."""

COARSE_RAY_STRIDE = 2
"""The coarse pass follows every second ray (128) at ``COARSE_RADIAL_STEP_PX``: it only brings each
candidate within about a pixel of its rings for the fine passes, which follow all rays at
``RADIAL_STEP_PX`` and decide coverage, radii and centre (issue 33 item 3: a third of the coarse
pass's samples; 64 rays lost a fiducial of the independent renderer's 0.3 speckle plate)."""

COARSE_RADIAL_STEP_PX = 0.3
"""Radial sample step of the coarse pass, pixels (0.4 px in all three tracking passes lost 27 of
the 172 fiducials of the 85 % marks + 0.1 speckle plate, most as ``fit``)."""

SECTOR_SEEN_FRACTION = 0.4
"""A sector sees the rings when its amplitude reaches this share of the fiducial's typical one."""

MIN_VALID_RAY_FRACTION = 0.5
"""A fit needs this share of all rays usable."""

EDGE_WEIGHT_POWER = 2.0
"""A ray's weight in the ring fit grows as the square of its rings' contrast (``_edge_weights``): the
edge point's variance falls as the contrast's square, at equal noise."""

EDGE_WEIGHT_MAX = 2.0
"""Relative contrast beyond which a ray weighs no more: a speckle grain or a scratch that adds to a
ray's contrast does not take over the fit."""

FIT_PASSES = 1
"""Passes of the centre fit on the prewhitened image, from the high-passed image's result: that
start is within about 20 um, where the ring model's first-order centre is exact to well below 1 nm
(a second pass changed the 19x19 speckle plate's RMS by 0.04 um)."""


RAY_PROFILE_CHUNK = 16
"""Candidates whose sample positions are built and sampled at a time (``_ray_profiles``): their maps,
about a megabyte, are still in the cache when ``cv2.remap`` reads them (about 10 % faster than all at once)."""

REMAP_CLEAR_PX = 8
"""Distance (pixels) from the image's border beyond which every bicubic sample of ``cv2.remap`` is
finite, whatever its neighbours in the map (``_window_profiles``): its stencil reaches 2 pixels, and
a sample near the border makes its vector of neighbours NaN."""

WINDOW_OUTPUT_BLOCK = 16
"""Samples of the rings' correlation are computed in windows of a multiple of this many
(``_window_correlation``): the width of OpenBLAS's single-precision kernel on AVX-512, whose
narrower remainders sum in another order."""


def _sample_bicubic(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray,
                    out: np.ndarray | None = None) -> np.ndarray:
    """Sample ``image`` bicubically at float32 (column, row) positions (M, ...); NaN outside.

    Bicubic samples (``cv2.INTER_CUBIC``) of ``image`` at float32 (column, row) positions (M, ...);
    NaN outside. Written into ``out`` (contiguous float32, the maps' shape) when given.
    """
    count = len(map_x)
    shape = map_x.shape
    map_x, map_y = map_x.reshape(count, -1), map_y.reshape(count, -1)
    # cv2.remap limits every image side to SHRT_MAX: one row per candidate, in blocks of rows.
    block = 16_384
    samples = np.empty(map_x.shape, np.float32) if out is None else out.reshape(map_x.shape)
    for start in range(0, count, block):
        rows = slice(start, start + block)
        # Written in place (``dst``): no copy of each block's samples into the result.
        cv2.remap(image, map_x[rows], map_y[rows], dst=samples[rows], interpolation=cv2.INTER_CUBIC,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return samples.reshape(shape)


def _profile_template(step: float, offsets: np.ndarray, line_sigma_mm: float) -> np.ndarray:
    """Radial profile of dark lines at ``offsets`` (mm from the template centre), zero mean, negated."""
    half = float(np.max(np.abs(offsets))) + 3 * line_sigma_mm
    positions = np.arange(-np.ceil(half / step), np.ceil(half / step) + 1) * step
    darkness = sum(np.exp(-0.5 * ((positions - offset) / line_sigma_mm) ** 2) for offset in offsets)
    template = -darkness
    return (template - template.mean()).astype(np.float32)


def _correlate_rows(profiles: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Correlation of every profile (..., S) with a centred odd-length template, same length."""
    shape = profiles.shape
    flat = np.ascontiguousarray(profiles.reshape(-1, shape[-1]), dtype=np.float32)
    out = np.empty_like(flat)
    # cv2.filter2D correlates (no flip) with the anchor at the kernel centre; limited to 32767 rows.
    block = 32_000
    for start in range(0, len(flat), block):
        # Written in place (``dst``, same shape and type): no copy of each block's result.
        cv2.filter2D(flat[start:start + block], cv2.CV_32F, template[None, :], dst=out[start:start + block],
                     borderType=cv2.BORDER_REPLICATE)
    return out.reshape(shape)


def _window_correlation(profiles: np.ndarray, template: np.ndarray, first: np.ndarray, outputs: int) -> np.ndarray:
    """Correlation (M, A, J) of profiles (M, A, S) with ``template`` at samples first[m] .. first[m] + J - 1.

    As ``_correlate_rows`` (replicated border) at only the samples the peak search reads, a few
    times cheaper when they are a fraction of the profile. Where the template stays inside the
    profile, one matrix product per candidate with the shifted template as the matrix's columns (one
    matrix per distinct ``first``); windows reaching beyond the profile's ends are taken from their
    whole profile's correlation.

    The product is padded to a multiple of ``WINDOW_OUTPUT_BLOCK`` columns (the padding is left
    out of the result): OpenBLAS's single-precision kernel then sums every sample as
    ``cv2.filter2D`` does (the template's taps in order, fused multiply-adds), so on an AVX-512 host
    the correlation is the same to the bit; on another CPU the two may differ in the last bit of
    float32 (test_fiducial_fast_paths allows 1e-5).
    """
    length = profiles.shape[-1]
    half = (len(template) - 1) // 2
    span = -(-outputs // WINDOW_OUTPUT_BLOCK) * WINDOW_OUTPUT_BLOCK
    inner = (first >= half) & (first + outputs - 1 <= length - 1 - half)
    window = np.empty(profiles.shape[:2] + (span,), np.float32)
    if inner.any():
        starts, which = np.unique(first[inner], return_inverse=True)
        matrices = np.zeros((len(starts), length, span), np.float32)
        columns = np.broadcast_to(np.arange(span)[:, None], (span, len(template)))
        values = np.broadcast_to(template, columns.shape)
        for matrix, origin in zip(matrices, starts):
            rows = origin + columns + np.arange(len(template)) - half
            kept = rows < length        # the padding columns may run past the profile: they are dropped
            matrix[rows[kept], columns[kept]] = values[kept]
        if inner.all() and len(starts) == 1:     # windows sampled alone: one matrix for every candidate
            np.matmul(profiles, matrices[0], out=window)
        elif inner.all():   # the usual case: no copy of the profiles in or of the window out
            np.matmul(profiles, matrices[which.reshape(-1)], out=window)
        else:
            window[inner] = np.matmul(profiles[inner], matrices[which.reshape(-1)])
    if not inner.all():
        whole = _correlate_rows(profiles[~inner], template)
        samples = np.broadcast_to(first[~inner, None, None] + np.arange(outputs), whole.shape[:2] + (outputs,))
        window[~inner, :, :outputs] = np.take_along_axis(whole, samples, -1)
    # Contiguous: the peak search gathers from it several times (a view would be copied each time).
    return np.ascontiguousarray(window[..., :outputs])


def _correlation_at(profiles, template: np.ndarray, window: np.ndarray, first: np.ndarray,
                    position: np.ndarray) -> np.ndarray:
    """Correlation (M, A) of every profile (M, A, S) with ``template`` at its own sample index ``position``.

    Taken from the window's correlation (M, A, J; ``_window_correlation`` from index ``first`` (M,))
    where the position falls inside it; the few rays whose position is elsewhere are correlated whole.
    ``profiles`` is the profiles (M, A, S), or a function that returns the whole profiles (K, S) of
    the rays of a mask (M, A) when only their windows were sampled.
    """
    offset = position - first[:, None]
    within = (offset >= 0) & (offset < window.shape[-1])
    values = _along_last(window, np.clip(offset, 0, window.shape[-1] - 1))
    if not within.all():
        outside = ~within
        rows = profiles(outside) if callable(profiles) else profiles[outside]
        values[outside] = _along_last(_correlate_rows(rows, template), position[outside])
    return values


def _along_last(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Return ``values`` (..., S) at ``index`` (...; 0 <= index < S) along the last axis.

    ``np.take_along_axis(values, index[..., None], -1)[..., 0]`` as one gather at flat positions:
    take_along_axis builds an index array per axis and costs several times as much.
    """
    values = np.ascontiguousarray(values)
    length = values.shape[-1]
    flat = np.arange(0, index.size * length, length).reshape(index.shape) + index
    return np.take(values.reshape(-1), flat)


def _peak(score: np.ndarray, low: np.ndarray, width: int):
    """Sub-sample argmax of ``score`` (M, A, S) within sample indices [low, low + width) per candidate.

    ``low`` (M,) must keep the window and one neighbour on each side inside the profile. Returns
    the fractional index (M, A) and whether the maximum is interior (a real peak, not an end).
    """
    count, rays, _ = score.shape
    # Each candidate's window with one neighbour on either side, gathered as contiguous runs of a
    # sliding-window view (an index per sample cost twice the time).
    runs = np.lib.stride_tricks.sliding_window_view(score, width + 2, axis=-1)           # (M, A, S - W - 1, W + 2)
    return _window_peak(runs[np.arange(count)[:, None], np.arange(rays)[None, :], (low - 1)[:, None]], low)


def _window_peak(padded: np.ndarray, low: np.ndarray):
    """Sub-sample argmax of window scores (M, A, W + 2), samples low - 1 .. low + W of each candidate.

    The maximum is searched among the inner W samples [low, low + W), the outer two are its
    neighbours for the parabola. Returns the fractional index (M, A) along the whole profile and
    whether the maximum is interior (a real peak, not an end).
    """
    width = padded.shape[-1] - 2
    best = np.argmax(padded[..., 1:-1], axis=-1)
    interior = (best > 0) & (best < width - 1)
    at = low[:, None] + best
    left, centre, right = (_along_last(padded, best + k) for k in range(3))
    curvature = left - 2 * centre + right
    delta = np.where(curvature < 0, 0.5 * (left - right) / np.where(curvature < 0, curvature, -1.0), 0.0)
    return at + np.clip(delta, -0.5, 0.5), interior & (curvature < 0)


def _runs(values: np.ndarray, first: np.ndarray, length: int) -> np.ndarray:
    """Return ``values`` (M, A, S) at samples first .. first + length - 1 along the last axis (M, A, length).

    ``first`` (M, A) keeps every run inside its row. Each run is copied as one item of a view whose
    items are ``length`` samples long, one starting at every sample: a third of the time of a
    sliding-window view's three-index gather, which copies sample by sample.
    """
    values = np.ascontiguousarray(values)
    count, rays, samples = values.shape
    flat = values.reshape(-1)
    runs = np.ndarray((flat.size - length + 1,), dtype=np.dtype((np.void, length * flat.itemsize)), buffer=flat,
                      strides=(flat.itemsize,))
    starts = (np.arange(0, count * rays * samples, samples).reshape(count, rays) + first).reshape(-1)
    return runs[starts].view(values.dtype).reshape(count, rays, length)


def _row_nanquantile(values: np.ndarray, quantile: float) -> np.ndarray:
    """Return per row of ``values`` (M, N) the ``quantile`` (0-1) of its finite entries.

    Linear interpolation; NaN for a row without any finite entry. Works as ``np.nanpercentile``
    along rows, with one sort for all rows instead of numpy's loop over the rows that hold a NaN.
    """
    ordered = np.sort(np.where(np.isfinite(values), values, np.nan), axis=1)      # NaN sorts last
    last = np.isfinite(values).sum(axis=1) - 1
    position = np.maximum(last, 0) * quantile
    low = np.floor(position).astype(int)
    high = np.minimum(low + 1, np.maximum(last, 0))
    rows = np.arange(len(values))
    lower, upper = ordered[rows, low], ordered[rows, high]
    return np.where(last >= 0, lower + (upper - lower) * (position - low), np.nan)


def _row_median(values: np.ndarray) -> np.ndarray:
    """Return ``np.median(values, axis=-1)``: the same values from one sort of the short last axis.

    ``np.median`` partitions each of the ~10^5 short rows in its own call; a sort along the axis
    does them all at once (NaN sorts last, and a row holding one has a NaN median, as in numpy).
    """
    ordered = np.sort(values, axis=-1)
    count = ordered.shape[-1]
    middle = (ordered[..., count // 2] if count % 2
              else np.mean(ordered[..., count // 2 - 1:count // 2 + 1], axis=-1))
    return np.where(np.isnan(ordered[..., -1]), ordered[..., -1], middle)


def _fit_ring(edge_radius: np.ndarray, design: np.ndarray, usable: np.ndarray, strength: np.ndarray | None = None):
    """Fit the radial model to edge radii (M, A) by weighted least squares over the usable rays.

    Weighted least-squares fit of the radial model to edge radii (M, A) over the ``usable`` rays,
    each weighted by its ``strength`` (M, A; default 1), with one 3-sigma trimming round.

    Returns the centre shift (M, 2), mean radius (M,), the fitted radius along every ray (M, A),
    residuals (M, A), rays used (M, A) and fit_ok (M,).
    """
    used = usable.copy()
    parameters = design.shape[-1]
    for trimming in range(2):
        w = used * (1.0 if strength is None else strength)
        normal_matrix = np.einsum("ai,ma,aj->mij", design, w, design)
        right = np.einsum("ai,ma->mi", design, w * edge_radius)
        well_posed = well_conditioned(normal_matrix, 1e10)
        normal_matrix[~well_posed] = np.eye(parameters)
        solution = np.linalg.solve(normal_matrix, right[..., None])[..., 0]
        residual = edge_radius - solution @ design.T
        if trimming == 0:
            # Rays hit by speckle, a scratch or a neighbour's mark: beyond 3 robust sigmas.
            mad = _row_nanquantile(np.where(used, np.abs(residual), np.nan), 0.5)
            limit = np.maximum(3.0 * NORMAL_MAD_SCALE * np.nan_to_num(mad, nan=0.0), 1e-6)
            used = used & (np.abs(residual) <= limit[:, None])
    fit_ok = well_posed & (used.sum(axis=1) >= 16)
    return solution[:, 1:3], solution[:, 0], edge_radius - residual, residual, used, fit_ok


def _edge_weights(peak_score: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Return the weight (M, A) of every ray's edge point in the ring fit.

    Weight (M, A) of every ray's edge point in the ring fit: its darkness contrast (the profile's
    correlation with the rings at the edge) over the candidate's median one, to the power
    ``EDGE_WEIGHT_POWER``, at most ``EDGE_WEIGHT_MAX``.

    A ray's edge error grows as its rings' contrast falls (marks fainter along the path, a line
    sampled between points), so rays are weighed by how clearly they see the rings, relative to the
    same fiducial's other rays rather than against a fixed threshold.
    """
    median = _row_nanquantile(np.where(usable, peak_score, np.nan), 0.5)
    relative = peak_score / np.where(median > 0, median, np.inf)[:, None]
    return np.clip(relative, 0.0, EDGE_WEIGHT_MAX) ** EDGE_WEIGHT_POWER


def _second_harmonic(radius_per_ray: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Return cos/sin 2theta amplitudes (M, 2) of radii (M, A) at evenly spaced ``angles`` (A,)."""
    return np.stack([radius_per_ray @ np.cos(2 * angles), radius_per_ray @ np.sin(2 * angles)], -1) * (
        2.0 / len(angles))


def refine_ring_centres(image: np.ndarray, centres_uv: np.ndarray, offset: np.ndarray, jacobian: np.ndarray,
                        radii_nominal: np.ndarray, pitch_mm: float, fit_image: np.ndarray | None = None) -> dict:
    """Sub-pixel double-ring fit per candidate (see the module docstring, step 3 and 4).

    ``PASSES`` passes on ``image`` follow the rings and give the coverage and the rings' radii; with
    a ``fit_image`` (the prewhitened image), ``FIT_PASSES`` more passes on it, over the sectors seen,
    give the centres and their covariance.
    Returns centres (M, 2), covariance (M, 2, 2) with its degrees of freedom (M,), per-ring radii
    (M, R), edge RMS (M,), coverage (M,), ellipticity (M,), the last fit's mean radius (M,) and
    elliptical second harmonic (M, 2), and fit_ok (M,).
    """
    count = len(centres_uv)
    mid = float(np.mean(radii_nominal))
    offsets = radii_nominal - mid
    line_sigma = max(0.9 * pitch_mm, 0.05)
    # Radial step and ring template of the coarse pass [0] and of the fine passes [1].
    steps = (COARSE_RADIAL_STEP_PX * pitch_mm, RADIAL_STEP_PX * pitch_mm)
    templates = tuple(_profile_template(value, offsets, line_sigma) for value in steps)
    angles = np.linspace(0.0, 2 * np.pi, RAY_COUNT, endpoint=False)
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=-1)         # (A, 2)
    design = harmonic_design(angles)                                        # (A, 5)
    sector_of_ray = (np.arange(RAY_COUNT) * SECTORS) // RAY_COUNT
    inverse = np.linalg.inv(jacobian)
    centres = centres_uv.copy()
    visible = np.ones((count, RAY_COUNT), bool)
    fit_ok = np.ones(count, bool)
    coverage = np.zeros(count)
    schedule = [image] * PASSES + ([fit_image] * FIT_PASSES if fit_image is not None else [])
    # On a finite image a sample is NaN only where its bicubic stencil reaches past the border,
    # and the positions where it does not form a rectangle: a straight ray is whole when both its
    # ends are (no pass over every sample).
    finite_image = {id(pass_image): bool(np.isfinite(pass_image).all()) for pass_image in (image, fit_image)
                    if pass_image is not None}
    tracked = None
    for refinement, pass_image in enumerate(schedule):
        fitting_only = refinement >= PASSES
        if fitting_only and refinement == PASSES:
            # What the rings' tracking found is kept: radii and coverage are measured on the
            # high-passed image, whose line shape the templates describe.
            tracked = dict(profiles=profiles, used=used, at=at,  # noqa: F821 (set by the previous pass)
                           sampled_at=sampled_at, radial=radial, step=step, half=half)  # noqa: F821
        rays = slice(None, None, COARSE_RAY_STRIDE if refinement == 0 else 1)
        step, pair_template = steps[int(refinement != 0)], templates[int(refinement != 0)]
        half = (len(pair_template) - 1) / 2 * step
        margin = (COARSE_MARGIN_PX if refinement == 0 else FINE_MARGIN_PX) * pitch_mm
        reach = half + (margin if refinement == 0 else 2 * margin) + step
        radial = (mid + np.arange(-np.ceil(reach / step), np.ceil(reach / step) + 1) * step).astype(np.float32)
        # Search window (indices along the ray): +- margin about the nominal mid radius, then about
        # the last fitted one (rings of the wrong size stay in view and fail the radius check).
        centre_radius = (np.full(count, mid) if refinement == 0
                         else np.clip(radius, mid - margin, mid + margin))  # noqa: F821 (set by the previous pass)
        width = int(np.floor(2 * margin / step)) + 1
        low = np.clip(np.ceil((centre_radius - margin - radial[0]) / step).astype(int), 1, len(radial) - width - 1)
        # The samples the window's correlation reads: the window and a neighbour on either side, and
        # the template's reach beyond them.
        taps = (len(pair_template) - 1) // 2
        first_sample = low - 1 - taps
        window_samples = width + 2 + 2 * taps
        # The fine passes whose profiles are read in the window only (not the last tracking pass,
        # whose whole profiles give the rings' radii) sample just that part of each ray: about a
        # fifth fewer samples (``_window_profiles``).
        windowed = (refinement > 0 and refinement != PASSES - 1 and finite_image[id(pass_image)]
                    and first_sample.min() >= 0 and first_sample.max() + window_samples <= len(radial))
        if windowed:
            profiles, inside, whole = _window_profiles(pass_image, centres, offset, inverse, directions[rays], radial,
                                                       first_sample, window_samples)
        else:
            profiles = _ray_profiles(pass_image, centres, offset, inverse, directions[rays], radial)
            inside = (np.isfinite(profiles[..., 0]) & np.isfinite(profiles[..., -1]) if finite_image[id(pass_image)]
                      else np.isfinite(profiles).all(axis=2))
            if not inside.all():
                # Only rays leaving the image hold NaN: zeroed in place (a fresh array of this pass).
                leaving = profiles[~inside]
                profiles[~inside] = np.where(np.isfinite(leaving), leaving, np.float32(0.0))
            whole = profiles
        # The rings' correlation over the window and one neighbour on either side.
        score = (_window_correlation(profiles, pair_template, np.full(count, taps), width + 2) if windowed
                 else _window_correlation(profiles, pair_template, low - 1, width + 2))
        index, peak_ok = _window_peak(score, low)
        edge = radial[0] + index * step
        ray_ok = inside & peak_ok & (visible[:, rays] if refinement >= 2 else True)
        strength = _edge_weights(_along_last(score, np.rint(index).astype(int) - (low - 1)[:, None]),
                                 ray_ok)
        shift, radius, at, residual, used, ok = _fit_ring(edge, design[rays], ray_ok, strength)
        ok &= ray_ok.mean(axis=1) >= MIN_VALID_RAY_FRACTION * (coverage if refinement >= 2 else 1.0)
        fit_ok = ok if refinement == 0 else fit_ok & ok
        if fitting_only or refinement == 0:
            # The coarse pass's coverage would not be used: the fine pass measures it again.
            centres = np.where(fit_ok[:, None], centres + shift, centres)
            continue
        # Ring amplitude of every ray at the fitted circle: erased arcs read about zero there.
        position = np.clip(np.rint((at - radial[0]) / step).astype(int), 0, len(radial) - 1)
        amplitude = np.where(inside, _correlation_at(whole, pair_template, score, low - 1, position), np.nan)
        sector_sum = sector_sums(np.where(np.isfinite(amplitude), amplitude, 0.0), sector_of_ray)
        sector_n = sector_sums(np.isfinite(amplitude).astype(float), sector_of_ray)
        with np.errstate(invalid="ignore", divide="ignore"):
            sector = np.where(sector_n > 0, sector_sum / sector_n, np.nan)
        reference = _row_nanquantile(sector, 0.75)
        seen = np.nan_to_num(sector) > SECTOR_SEEN_FRACTION * np.where(reference > 0, reference, np.inf)[:, None]
        coverage = seen.mean(axis=1)
        visible = seen[:, sector_of_ray]
        sampled_at = centres
        centres = np.where(fit_ok[:, None], centres + shift, centres)
    final_residual, final_used, final_weight = residual, used, used * strength
    # The fitted ring about the final centre: mean radius and elliptical second harmonic.
    mid_radius = radius
    harmonic = _second_harmonic(at, angles)
    if tracked is not None:
        profiles, used, at, sampled_at, radial, step, half = (
            tracked[key] for key in ("profiles", "used", "at", "sampled_at", "radial", "step", "half"))
    # Second harmonic of the tracked ring (half the difference of its axes): a ring on the plate is a
    # circle, so this is small; the envelope of two offset rings (a merged detection) is not.
    ellipticity = np.hypot(*_second_harmonic(at, angles).T)
    covariance, dof = centre_covariance(design, final_residual, final_weight, sector_of_ray)

    # Each ring's radius about the final centre: darkness centroid in a window of +- half the ring
    # gap around its expected position on every used ray (a check of the ring sizes, not the centre).
    ring_radii = np.full((count, len(radii_nominal)), np.nan)
    gap = float(np.min(np.diff(radii_nominal))) if len(radii_nominal) > 1 else 4 * pitch_mm
    outside = np.abs(radial - mid) > half + margin
    background = _row_median(profiles[:, :, outside]) if outside.any() else np.zeros(profiles.shape[:2])
    at = at.astype(np.float32)
    # The window is zero beyond half the gap and half a sample from the expected radius: only the
    # ``span`` samples from ``first`` on each ray enter, gathered as runs (``_runs``).
    window_reach = gap / 2 + step / 2
    span = min(int(np.ceil(2 * window_reach / step)) + 2, len(radial))
    radial_runs = np.lib.stride_tricks.sliding_window_view(radial, span)                    # (S - K + 1, K)
    for ring, ring_offset in enumerate(offsets):
        expected = at + np.float32(ring_offset)                                             # (M, A)
        first = np.clip(np.floor((np.nan_to_num(expected) - window_reach - radial[0]) / step), 0,
                        len(radial) - span).astype(int)
        near = radial_runs[first]                                                           # (M, A, K)
        window = np.clip((np.float32(gap / 2) - np.abs(near - expected[..., None])) / np.float32(step)
                         + np.float32(0.5), 0.0, 1.0)
        weight = np.clip(background[..., None] - _runs(profiles, first, span), 0.0, None) * window
        total = weight.sum(axis=2)
        centroid = (weight * near).sum(axis=2) / np.where(total > 0, total, 1.0)
        points = sampled_at[:, None, :] + centroid[..., None] * directions
        distance = np.linalg.norm(points - centres[:, None, :], axis=-1)
        good = used & (total > 0)
        counts = good.sum(axis=1)
        ring_radii[:, ring] = np.where(counts > 0, np.where(good, distance, 0.0).sum(axis=1)
                                       / np.maximum(counts, 1), np.nan)
    rms = np.sqrt((np.where(final_used, final_residual, 0.0) ** 2).sum(axis=1) / np.maximum(final_used.sum(axis=1), 1))
    return dict(centres=centres, covariance=covariance, dof=dof, radii=ring_radii, rms=rms, coverage=coverage,
                ellipticity=ellipticity, mid_radius=mid_radius, harmonic=harmonic,
                fit_ok=fit_ok & np.isfinite(ring_radii).all(axis=1))


def _ray_maps(centres: np.ndarray, offset: np.ndarray, inverse: np.ndarray, directions: np.ndarray):
    """Return the rays' pixel start (M, 2) and heading along each pixel axis (2 arrays (M, A)), float32.

    Rays map to pixels through each candidate's inverse affine map (pixel = J^-1 (uv - offset)): a
    sample at radius r lies at start + heading r, one float32 product and one sum per axis.
    """
    start = np.einsum("mij,mj->mi", inverse, centres - offset).astype(np.float32)      # (M, 2)
    # Heading of every ray along each pixel axis (M, A), contiguous: J^-1 times the ray's direction.
    headings = [(inverse[:, axis, 0, None] * directions[:, 0] + inverse[:, axis, 1, None] * directions[:, 1]
                 ).astype(np.float32) for axis in range(2)]
    return start, headings


def _ray_profiles(image: np.ndarray, centres: np.ndarray, offset: np.ndarray, inverse: np.ndarray,
                  directions: np.ndarray, radial: np.ndarray) -> np.ndarray:
    """Image samples along rays (M, A, S) laid out in plate mm from ``centres``; NaN outside.

    Rays map to pixels through each candidate's inverse affine map (``_ray_maps``).
    """
    return _sample_rays(image, *_ray_maps(centres, offset, inverse, directions), radial)


def _sample_rays(image: np.ndarray, start: np.ndarray, headings: list, radial: np.ndarray) -> np.ndarray:
    """Return samples (M, A, S) at start + heading r (``_ray_maps``) for the float32 radii ``radial``.

    ``radial`` is (S,), the same for every candidate, or (M, S), each candidate's own.
    """
    count, rays = headings[0].shape
    length = radial.shape[-1]
    samples = np.empty((count, rays, length), np.float32)
    # A few candidates at a time, their maps built in place (heading times radius, plus the start:
    # the same float32 values) and sampled while they are still in the cache.
    maps = np.empty((2, min(count, RAY_PROFILE_CHUNK), rays, length), np.float32)
    for first in range(0, count, RAY_PROFILE_CHUNK):
        rows = slice(first, min(first + RAY_PROFILE_CHUNK, count))
        chunk = maps[:, :rows.stop - first]
        for axis in range(2):
            if radial.ndim == 1:
                # An outer product (each map value one float32 product, as broadcasting gives), in a
                # third less time than a broadcast multiply's short inner loops.
                np.einsum("i,j->ij", headings[axis][rows].reshape(-1), radial,
                          out=chunk[axis].reshape(-1, length))                           # (m, A, S)
            else:
                np.multiply(headings[axis][rows, :, None], radial[rows, None, :], out=chunk[axis])
            chunk[axis] += start[rows, None, None, axis]
        _sample_bicubic(image, chunk[0], chunk[1], out=samples[rows])
    return samples


def _window_profiles(image: np.ndarray, centres: np.ndarray, offset: np.ndarray, inverse: np.ndarray,
                     directions: np.ndarray, radial: np.ndarray, first: np.ndarray, length: int):
    """Return samples ``first`` .. ``first`` + ``length`` - 1 (M,) of every ray's profile on ``radial``.

    The values ``_ray_profiles`` on the whole ``radial`` (S,) gives there, NaN of rays leaving the image
    zeroed as the passes do, for a finite ``image``. A bicubic sample of ``cv2.remap`` is the same
    value wherever its position stands in the map, but near the image's border whether it is NaN
    depends on its neighbours in the map (a vector of samples with one beyond the border is all
    NaN). So a candidate whose rays stay ``REMAP_CLEAR_PX`` inside the image is sampled over its
    windows only (every sample finite, every ray whole); one nearer the border has its whole
    profiles sampled, as before, and cut.

    Returns
    -------
    profiles : numpy.ndarray, (M, A, length)
        The samples.
    inside : numpy.ndarray of bool, (M, A)
        Rays that stay inside the image (both ends of the whole profile finite).
    whole : callable
        Given a mask (M, A), the whole profiles (K, S) of its rays, NaN of rays leaving the image zeroed.
    """
    height, width = image.shape
    start, headings = _ray_maps(centres, offset, inverse, directions)
    ends = radial[[0, -1]]
    # The rays' ends as the maps hold them (float32 product and sum): a ray's samples lie between.
    reach = [headings[axis][..., None] * ends + start[:, None, None, axis] for axis in range(2)]
    clear = np.ones(len(centres), bool)
    for axis, size in enumerate((width, height)):
        clear &= ((reach[axis].min(axis=(1, 2)) >= REMAP_CLEAR_PX)
                  & (reach[axis].max(axis=(1, 2)) <= size - 1 - REMAP_CLEAR_PX))
    # Every candidate's windows (no copy of the clear ones' samples), the few near the border
    # replaced by the cut of their whole profiles.
    profiles = _sample_rays(image, start, headings, radial[first[:, None] + np.arange(length)])
    inside = np.ones(headings[0].shape, bool)
    near, full = np.flatnonzero(~clear), None
    if len(near):
        full = _sample_rays(image, start[near], [heading[near] for heading in headings], radial)
        inside[near] = np.isfinite(full[..., 0]) & np.isfinite(full[..., -1])
        full = np.where(np.isfinite(full), full, np.float32(0.0))
        profiles[near] = _runs(full, np.broadcast_to(first[near, None], full.shape[:2]), length)

    def whole(mask: np.ndarray) -> np.ndarray:
        """Whole profiles (K, S) of the rays of ``mask`` (M, A), in its order."""
        candidate, ray = np.nonzero(mask)
        rows = np.empty((len(candidate), len(radial)), np.float32)
        from_full = ~clear[candidate]
        if from_full.any():
            rows[from_full] = full[np.searchsorted(near, candidate[from_full]), ray[from_full]]
        sampled = ~from_full
        if sampled.any():
            # Each ray a row of the map (at least 8 samples: shorter rows of cv2.remap come out NaN).
            maps = [headings[axis][candidate[sampled], ray[sampled], None] * radial
                    + start[candidate[sampled], axis, None] for axis in range(2)]
            rows[sampled] = _sample_bicubic(image, *maps)
        return rows

    return profiles, inside, whole
