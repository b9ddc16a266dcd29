"""Ring candidates in the plate image (step 2 of :mod:`gls_calibration.fiducials.measure`).

Ring candidates in the plate image: log intensity, prewhitening, normalised cross-correlation with
the double-ring template (step 2 of :mod:`gls_calibration.fiducials.measure`).
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from gls_calibration.common.robust import robust_sigma
from gls_calibration.fiducials.raster import HIGH_PASS_SIGMA_PX


DETECTION_SIGMAS = 4.0
"""Detection threshold on the correlation map, in robust standard deviations of bare steel."""

MIN_DETECTION_SCORE = 0.12
"""Lowest normalised correlation accepted as a candidate whatever the steel looks like."""

LOG_BLOCK_PIXELS = 1 << 16
"""Pixels of the intensity image clipped and logged at a time (``log_intensity_image``)."""

PREWHITENING_TILE_PX = 32
"""Side (pixels) of the bare-steel tiles whose averaged periodogram is the noise spectrum the centre
fit is prewhitened by (``prewhitening_kernel``): 1/32 cycle per pixel resolves speckle correlated
over 1-2 pixels, and a 19x19 plate at 0.1 mm holds about 1 100 such tiles clear of its rings."""

PREWHITENING_KERNEL_PX = 11
"""Side (pixels) of the prewhitening filter (the spectrum's inverse square root, truncated): it
spans the speckle's correlation several times over and stays cheap (``cv2.filter2D``)."""

PREWHITENING_MIN_TILES = 16
"""Bare-steel tiles needed for a noise spectrum; with fewer the centre fit keeps the high-passed image."""

PREWHITENING_FLOOR = 1e-3
"""Floor added to the noise spectrum, as a share of its mean: no frequency is boosted by more than
about 1 / sqrt(floor), so spectral bins the periodogram put near zero by chance stay bounded."""


def log_intensity_image(intensity: np.ndarray) -> np.ndarray:
    """Return the log intensity (H, W) float32: it makes the multiplicative speckle additive.

    Log intensity (H, W) float32: speckle is multiplicative, so it becomes additive and equal on
    steel and marks. Intensities below 1 % of the typical one are clipped there.
    """
    # Every 4th pixel per axis gives the median to ~0.1 % at a 16th of the cost.
    floor = 0.01 * max(float(np.median(intensity[::4, ::4])), 1e-12)
    logged = np.empty(intensity.shape, np.float32)
    # A band of rows at a time: the clipped intensities (float64 for a float64 image) stay in the
    # cache instead of an image-sized array, and the log is cast to float32 as it is written.
    rows = max(1, LOG_BLOCK_PIXELS // max(intensity.shape[1], 1))
    for start in range(0, len(intensity), rows):
        band = np.maximum(intensity[start:start + rows], floor)
        np.log(band, out=band)
        logged[start:start + rows] = band
    return logged


def refinement_image(log_intensity: np.ndarray) -> np.ndarray:
    """Return the whitened image for detection and ring tracking (a high-passed log intensity).

    Whitened image for detection and ring tracking: the log intensity minus its Gaussian blur of
    ``HIGH_PASS_SIGMA_PX`` (removes shading and the coarse part of correlated speckle, keeps the
    thin ring lines).
    """
    blurred = cv2.GaussianBlur(log_intensity, (0, 0), HIGH_PASS_SIGMA_PX)
    return np.subtract(log_intensity, blurred, out=blurred)      # into the blur: one image-sized array less


def prewhitening_kernel(log_intensity: np.ndarray, candidates_px: np.ndarray,
                        clear_radius_px: float) -> np.ndarray | None:
    """Filter (K, K) float32 that whitens the noise of bare steel, or None without enough of it.

    The noise spectrum is the mean periodogram (Hann window, each tile's mean removed) of the
    ``PREWHITENING_TILE_PX`` tiles of ``log_intensity`` that no candidate's disc of
    ``clear_radius_px`` (candidates as (column, row) pixels) touches, plus ``PREWHITENING_FLOOR``
    of its mean; the filter is its inverse square root without the mean, truncated to
    ``PREWHITENING_KERNEL_PX``. Correlated speckle puts most of its power at low spatial
    frequencies, one-pixel ring lines spread theirs up to the pixel pitch: after the filter every
    frequency carries the same noise, so the edge fit weighs each by its signal-to-noise ratio
    (a prewhitening matched filter). With white noise the filter is a mild high pass.
    """
    tile = PREWHITENING_TILE_PX
    height, width = log_intensity.shape
    rows, cols = height // tile, width // tile
    if rows * cols < PREWHITENING_MIN_TILES:
        return None
    covered = np.zeros((height, width), np.uint8)
    for column, row in np.rint(candidates_px).astype(int):
        cv2.circle(covered, (int(column), int(row)), int(np.ceil(clear_radius_px)), 1, -1)
    touched = covered[:rows * tile, :cols * tile].reshape(rows, tile, cols, tile).any(axis=(1, 3))
    tiles = log_intensity[:rows * tile, :cols * tile].reshape(rows, tile, cols, tile).swapaxes(1, 2)[~touched]
    if len(tiles) < PREWHITENING_MIN_TILES:
        return None
    window = np.outer(np.hanning(tile), np.hanning(tile)).astype(np.float32)
    spectrum = np.mean(np.abs(np.fft.rfft2((tiles - tiles.mean(axis=(1, 2), keepdims=True)) * window)) ** 2,
                       axis=0)
    mean_power = float(spectrum.mean())
    if not np.isfinite(mean_power) or mean_power <= 0:
        return None   # noiseless steel: nothing to whiten
    gain = 1.0 / np.sqrt(spectrum + PREWHITENING_FLOOR * mean_power)
    gain[0, 0] = 0.0
    kernel = np.fft.fftshift(np.fft.irfft2(gain, s=(tile, tile)))
    half = PREWHITENING_KERNEL_PX // 2
    kernel = kernel[tile // 2 - half:tile // 2 + half + 1, tile // 2 - half:tile // 2 + half + 1]
    kernel = kernel - kernel.mean()
    return (kernel / np.sqrt(np.sum(kernel**2))).astype(np.float32)


def _ring_template(pitch: tuple[float, float], radii: np.ndarray, line_sigma_mm: float) -> np.ndarray:
    """Return the negated darkness template of the rings (rows, cols) at the given pitch.

    Darkness template of the rings (rows, cols) at the given (row, column) pitch, negated: dark
    rings correlate positively. Gaussian lines of ``line_sigma_mm`` tolerate blur and tilt.
    """
    half = radii[-1] + 3 * line_sigma_mm
    rows = np.arange(-np.ceil(half / pitch[0]), np.ceil(half / pitch[0]) + 1) * pitch[0]
    cols = np.arange(-np.ceil(half / pitch[1]), np.ceil(half / pitch[1]) + 1) * pitch[1]
    radius = np.hypot(*np.meshgrid(cols, rows))
    darkness = sum(np.exp(-0.5 * ((radius - r) / line_sigma_mm) ** 2) for r in radii)
    return (-darkness).astype(np.float32)


def _correlation_peaks(score: np.ndarray, distance_px: float, threshold: float) -> np.ndarray:
    """(column, row) of local maxima of ``score`` above ``threshold``, at least ``distance_px`` apart."""
    half = int(np.ceil(distance_px))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * half + 1, 2 * half + 1)).astype(bool)
    # A local maximum is no lower than any pixel of the (symmetric) elliptical neighbourhood about it:
    # ``score >= cv2.dilate(score, kernel)``. Only pixels above the threshold are asked, and only a
    # pixel above it can be higher than one of them, so the comparison runs over the pairs of pixels
    # above the threshold within the kernel's reach (a few thousand), not a dilation of the whole map.
    rows, cols = np.nonzero(score > threshold)
    above = score[rows, cols]
    pairs = cKDTree(np.column_stack([rows, cols])).query_pairs(half, p=np.inf, output_type="ndarray")
    first, second = pairs[:, 0], pairs[:, 1]
    pairs = pairs[kernel[rows[second] - rows[first] + half, cols[second] - cols[first] + half]]
    first, second = pairs[:, 0], pairs[:, 1]
    beaten = np.zeros(len(rows), bool)
    beaten[first[above[second] > above[first]]] = True
    beaten[second[above[first] > above[second]]] = True
    rows, cols = rows[~beaten], cols[~beaten]
    # Plateaus give several equal maxima: keep one per neighbourhood, strongest first.
    order = np.argsort(-score[rows, cols], kind="stable")
    points = np.column_stack([cols, rows])[order].astype(float)
    if len(points) == 0:
        return points
    tree = cKDTree(points)
    taken = np.zeros(len(points), bool)
    keep = []
    for index in range(len(points)):
        if not taken[index]:
            keep.append(index)
            taken[tree.query_ball_point(points[index], distance_px)] = True
    return points[keep]


def _detection_image(image: np.ndarray, pitch: tuple[float, float]):
    """Image binned to about 0.2 mm pixels for detection (integer factors per axis) and the factors."""
    factor_rows = max(1, int(round(0.2 / pitch[0])))
    factor_cols = max(1, int(round(0.2 / pitch[1])))
    if factor_rows == factor_cols == 1:
        return image, (1, 1)
    height, width = image.shape[0] // factor_rows, image.shape[1] // factor_cols
    # Area interpolation at integer factors is the mean of each block (cv2: 0.002 s for a 2000 x 2000
    # image against 0.03 s for numpy's mean over two strided axes; the last bit may differ).
    binned = cv2.resize(np.ascontiguousarray(image[:height * factor_rows, :width * factor_cols], np.float32),
                        (width, height), interpolation=cv2.INTER_AREA)
    return binned, (factor_rows, factor_cols)


def detect_rings(image: np.ndarray, pitch: tuple[float, float], radii: np.ndarray, marks_darker: bool | None,
                 expected_count: int | None):
    """Candidate centres (M, 2) as (column, row) pixels of ``image``, their scores, and the polarity."""
    binned, (factor_rows, factor_cols) = _detection_image(image, pitch)
    binned_pitch = (pitch[0] * factor_rows, pitch[1] * factor_cols)
    template = _ring_template(binned_pitch, radii, max(0.6 * max(binned_pitch), 0.06))
    # Zero padding (the whitened image's mean) lets rings that touch the scan's border be found; the
    # fit then sees how much of them is there (coverage).
    pad_rows, pad_cols = (template.shape[0] - 1) // 2, (template.shape[1] - 1) // 2
    binned = cv2.copyMakeBorder(binned, pad_rows, pad_rows, pad_cols, pad_cols, cv2.BORDER_CONSTANT, value=0.0)
    score = cv2.matchTemplate(binned, template, cv2.TM_CCOEFF_NORMED)
    score = np.nan_to_num(score, nan=0.0)
    # Bare steel sets the spread of the correlation; marks cover a small share of the plate.
    sample = score[::2, ::2]
    median = float(np.median(sample))
    spread = robust_sigma(sample - median)
    threshold = max(MIN_DETECTION_SCORE, median + DETECTION_SIGMAS * spread,
                    -median + DETECTION_SIGMAS * spread)
    distance_px = radii[-1] / max(binned_pitch)
    found = {}      # peaks per polarity (True: dark marks)
    if marks_darker is None:
        # The polarity whose strongest peaks stand out more: bright marks correlate negatively.
        top = max(expected_count or 0, 4)
        strength = []
        for sign in (1.0, -1.0):
            values = found[sign > 0] = _correlation_peaks(sign * score, distance_px, threshold)
            scores = np.sort(sign * score[values[:, 1].astype(int), values[:, 0].astype(int)])[::-1][:top] \
                if len(values) else np.zeros(0)
            strength.append(float(np.sum(scores)))
        marks_darker = strength[0] >= strength[1]
    signed = score if marks_darker else -score
    # The chosen polarity's peaks were found already when it was decided here.
    peaks = found[marks_darker] if marks_darker in found else _correlation_peaks(signed, distance_px, threshold)
    if expected_count:
        peaks = peaks[:max(2 * expected_count, expected_count + 20)]
    values = signed[peaks[:, 1].astype(int), peaks[:, 0].astype(int)] if len(peaks) else np.empty(0)
    offset = np.array([(template.shape[1] - 1) / 2 - pad_cols, (template.shape[0] - 1) / 2 - pad_rows])
    binned_centre = peaks + offset
    # Binned pixel k covers full pixels k*f .. k*f + f - 1: centre at k*f + (f - 1) / 2.
    centres = binned_centre * np.array([factor_cols, factor_rows]) + np.array(
        [(factor_cols - 1) / 2, (factor_rows - 1) / 2])
    return centres, values, marks_darker
