"""Centres of the double-ring fiducials marked on the plate, measured in a laser-line scanner cloud.

Pipeline (after the published method, with a sub-pixel stage of our own):

1. Image: an organized cloud (H, W, 3) maps straight to pixels (row = profile, column = point); an
   unorganized one is rasterised on the plate plane at ``pixel_size_mm`` (bilinear splatting: a
   weighted mean intensity per pixel).
   Missing pixels are filled by normalised convolution, marks are made dark, the image is stretched
   to 8 bits.
2. Detection: median filter, Gaussian smoothing (the first stage of the classic Canny detector),
   Canny with thresholds scaled to the steel texture, morphological closing and hole filling (a
   double ring becomes one filled disc), circle Hough transform (``cv2.HOUGH_GRADIENT``) with radii
   around the outer ring.
   An image with anisotropic pixels (> 5 %) is resized to square pixels for this step only.
3. Sub-pixel centres: for each candidate, the *unbinarised* intensity is sampled along 256 rays laid
   out in plate millimetres (through a local pixel -> plane affine map fitted to the cloud, so tilted
   plates and unequal pixel pitches need no resampling). Along each ray the darkness-weighted mean
   radius of a band holding both rings is an edge point; a linear least-squares (Kasa) circle fit
   to these points, with one robust trimming round, moves the centre, and the band follows it
   (four passes, the first with a wide band). Both rings enter every fit, and since the band is
   centred on the current estimate, symmetric disturbances (noise, blur, background level) cannot
   shift the fixed point. Each ring's radius is then measured about the final centre; the RMS of
   those per-ring residuals is the quality figure.
4. Candidates whose radii do not match the nominal ones are rejected; centres closer than the outer
   radius are merged (one fiducial, one centre). Centres are returned in plate coordinates and, via
   ``PlatePose.from_plane``, as 3-D points on the fitted plane.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from gls_calibration.plate_pose import PlatePose
from gls_calibration.validation import as_finite_array

RAY_COUNT = 256
"""Rays per fiducial: about 1.5 rays per pixel of outer-ring circumference at 0.1 mm pixels."""

RADIAL_STEP_PX = 0.2
"""Sample spacing along a ray, in pixels."""

REFINEMENT_PASSES = 4
"""One coarse pass with a wide band, then passes with a band just around the rings."""

COARSE_MARGIN_PX = 4.0
"""How far (pixels) the coarse window reaches beyond the rings: the start may be this far off."""
MIN_VALID_RAY_FRACTION = 0.6
"""A candidate needs this share of its rays inside the image and usable on every ring."""

ANISOTROPY_LIMIT = 0.05
"""Relative difference of row and column pitch above which detection runs on a resized image."""


@dataclass(frozen=True)
class FiducialMeasurement:
    """Measured fiducial centres (mm) and what happened on the way.

    ``centres`` (K, 3) lie on the fitted plate plane in the cloud's frame, ``centres_plane`` (K, 2)
    are the same points in plate coordinates (``PlatePose.to_plane``). ``quality`` (K,) is the RMS
    residual of the ring fit in mm, ``radii`` (K,) the fitted outer-ring radius and ``inner_radii``
    (K,) the fitted inner-ring radius. ``merged`` counts candidates folded into a neighbour,
    ``rejected`` candidates whose rings did not fit. ``missing`` is ``expected_count - K`` (negative
    for extra centres) or None. ``image_shape`` is (rows, columns) of the analysed image and
    ``pixel_pitch_mm`` its (row, column) pitch.
    """

    centres: np.ndarray
    centres_plane: np.ndarray
    quality: np.ndarray
    radii: np.ndarray
    inner_radii: np.ndarray
    merged: int
    rejected: int
    missing: int | None
    image_shape: tuple[int, int]
    pixel_pitch_mm: tuple[float, float]


@dataclass(frozen=True)
class _PlateImage:
    """Intensity image with a per-pixel plane position: uv = offset + pixel_to_plane @ (col, row)."""

    intensity: np.ndarray          # (H, W) float32, marks dark, no NaN
    plane_uv: np.ndarray | None    # (H, W, 2) plane coordinates per pixel (organized clouds), NaN allowed
    raster_origin: np.ndarray | None  # (2,) plane coordinates of pixel (0, 0) (rasterised clouds)
    pitch: tuple[float, float]     # (row, column) pixel pitch in mm


def _fill_missing(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill invalid pixels with the mean of valid neighbours, growing the neighbourhood as needed."""
    if valid.all():
        return image
    weights = valid.astype(np.float32)
    values = np.where(valid, image, 0.0).astype(np.float32)
    filled = values.copy()
    missing = ~valid
    for size in (3, 5, 9, 17, 33):
        # Normalised convolution: box-sum of values over box-sum of weights.
        sums = cv2.boxFilter(values, -1, (size, size), normalize=False, borderType=cv2.BORDER_REFLECT)
        counts = cv2.boxFilter(weights, -1, (size, size), normalize=False, borderType=cv2.BORDER_REFLECT)
        ready = missing & (counts > 0.5)
        filled[ready] = sums[ready] / counts[ready]
        missing &= ~ready
        if not missing.any():
            return filled
    filled[missing] = np.median(image[valid])
    return filled


def _median_spacing(uv: np.ndarray, axis: int) -> float:
    """Median distance between neighbouring pixels' plane positions along an image axis (mm)."""
    # Every 8th line across the axis is plenty for a median and eight times cheaper.
    lines = uv[:, ::8] if axis == 0 else uv[::8]
    steps = np.diff(lines, axis=axis)
    lengths = np.hypot(steps[..., 0], steps[..., 1]).ravel()
    lengths = lengths[np.isfinite(lengths)]
    if lengths.size == 0:
        raise ValueError("organized cloud has no two neighbouring finite points")
    return float(np.median(lengths))


def _organized_image(xyz: np.ndarray, intensity: np.ndarray, pose: PlatePose) -> _PlateImage:
    """Image of an organized cloud: one pixel per point."""
    height, width = intensity.shape
    uv = pose.to_plane(xyz.reshape(-1, 3)).reshape(height, width, 2)
    valid = np.isfinite(intensity) & np.isfinite(uv).all(axis=2)
    if np.count_nonzero(valid) == 0:
        raise ValueError("intensity image has no finite pixels")
    pitch = (_median_spacing(uv, 0), _median_spacing(uv, 1))
    return _PlateImage(_fill_missing(intensity, valid), uv, None, pitch)


def _rasterised_image(xyz: np.ndarray, intensity: np.ndarray, pose: PlatePose,
                      pixel_size_mm: float) -> _PlateImage:
    """Image of an unorganized cloud: mean intensity of the points falling in each plane pixel."""
    keep = np.isfinite(xyz).all(axis=1) & np.isfinite(intensity)
    if np.count_nonzero(keep) == 0:
        raise ValueError("cloud has no finite point with a finite intensity")
    uv = pose.to_plane(xyz[keep])
    values = intensity[keep]
    origin = np.floor(uv.min(axis=0) / pixel_size_mm) * pixel_size_mm
    position = (uv - origin) / pixel_size_mm
    corner = np.floor(position).astype(np.int64)
    fraction = position - corner
    width, height = (int(v) + 2 for v in corner.max(axis=0))
    if width * height > 10_000 * 10_000:
        raise ValueError(f"rasterised plate image would have {height}x{width} pixels; "
                         f"check pixel_size_mm ({pixel_size_mm})")
    # Bilinear splatting: every point spreads over its four nearest pixels. On a regular scan this is
    # bilinear resampling, so marks keep their sub-pixel position (nearest-pixel binning would shift
    # whole regions by up to half a pixel where the scan and raster grids are out of phase).
    sums = np.zeros(width * height)
    weights = np.zeros(width * height)
    for d_col, d_row in ((0, 0), (1, 0), (0, 1), (1, 1)):
        weight = ((fraction[:, 0] if d_col else 1 - fraction[:, 0])
                  * (fraction[:, 1] if d_row else 1 - fraction[:, 1]))
        index = (corner[:, 1] + d_row) * width + corner[:, 0] + d_col
        sums += np.bincount(index, weights=weight * values, minlength=width * height)
        weights += np.bincount(index, weights=weight, minlength=width * height)
    covered = weights > 1e-3
    mean = np.divide(sums, weights, out=np.zeros_like(sums), where=covered).reshape(height, width)
    image = _fill_missing(mean, covered.reshape(height, width))
    return _PlateImage(image, None, origin, (pixel_size_mm, pixel_size_mm))


def _stretch(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image scaled so its robust extremes (0.5 and 99.5 percentiles) span 0..255: float32 and 8-bit."""
    sample = image[::4, ::4] if image.size > 1_000_000 else image
    low, high = np.percentile(sample, (0.5, 99.5))
    scaled = ((image - low) * (255.0 / max(high - low, 1e-12))).astype(np.float32)
    return scaled, np.clip(scaled, 0, 255).astype(np.uint8)


def _detect(image8: np.ndarray, pitch: tuple[float, float], ring_radii_mm: tuple[float, ...]) -> np.ndarray:
    """Candidate centres (M, 2) as (column, row) pixel coordinates of the analysed image."""
    scale_rows = 1.0
    detect_pitch = pitch[1]
    if abs(pitch[0] - pitch[1]) > ANISOTROPY_LIMIT * min(pitch):
        # Square pixels for the Hough transform: rows are resampled to the column pitch.
        scale_rows = pitch[0] / pitch[1]
        image8 = cv2.resize(image8, (image8.shape[1], int(round(image8.shape[0] * scale_rows))),
                            interpolation=cv2.INTER_LINEAR)
    gap_px = (ring_radii_mm[-1] - ring_radii_mm[0]) / detect_pitch
    outer_px = ring_radii_mm[-1] / detect_pitch

    # Median against speckle, then the Gaussian stage of the classic Canny detector (OpenCV's Canny
    # has none): at about the ring gap it turns the two thin lines into one dark band.
    smoothed = cv2.GaussianBlur(cv2.medianBlur(image8, 3), (0, 0), max(1.0, 0.75 * gap_px))
    # Canny thresholds scale with the background texture (noise, speckle): the median gradient
    # magnitude is set by the steel, as marks cover a small share of the plate.
    gradient = cv2.magnitude(cv2.Sobel(smoothed, cv2.CV_32F, 1, 0), cv2.Sobel(smoothed, cv2.CV_32F, 0, 1))
    texture = float(np.median(gradient[::2, ::2]))
    edges = cv2.Canny(smoothed, max(1.5 * texture, 20.0), max(3.0 * texture, 40.0), L2gradient=True)
    kernel_size = 2 * int(np.ceil(gap_px / 2 + 1)) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kernel_size, kernel_size))
    closed = cv2.morphologyEx(edges, cv2.MORPH_CLOSE, kernel)
    discs = ndimage.binary_fill_holes(closed > 0).astype(np.uint8) * 255
    # Opening drops thin edge clutter (speckle, scratches) that is not part of a filled disc.
    discs = cv2.morphologyEx(discs, cv2.MORPH_OPEN, kernel)
    # Smooth disc borders give the gradient Hough transform consistent edge directions to vote along.
    discs = cv2.GaussianBlur(discs, (0, 0), 2.0)
    circles = cv2.HoughCircles(discs, cv2.HOUGH_GRADIENT, dp=1, minDist=max(outer_px / 2, 2.0),
                               param1=100, param2=max(8.0, 0.3 * np.pi * outer_px),
                               minRadius=int(np.floor(0.85 * outer_px)),
                               maxRadius=int(np.ceil(1.2 * outer_px + kernel_size / 2)))
    if circles is None:
        return np.empty((0, 2))
    centres = circles[0, :, :2].astype(float)
    if scale_rows != 1.0:
        # cv2.resize aligns pixel areas: centre coordinates map through (y + 0.5) / scale - 0.5.
        centres[:, 1] = (centres[:, 1] + 0.5) / scale_rows - 0.5
    return centres


def _local_affines(plate: _PlateImage, centres_px: np.ndarray, half_px: int):
    """Per candidate: plane offset (M, 2) and 2x2 Jacobian (M, 2, 2) with uv = offset + J @ (col, row)."""
    count = len(centres_px)
    if plate.plane_uv is None:
        jacobian = np.broadcast_to(np.diag([plate.pitch[1], plate.pitch[0]]), (count, 2, 2)).copy()
        return np.broadcast_to(plate.raster_origin, (count, 2)).copy(), jacobian, np.ones(count, bool)
    # Least-squares affine fit of the cloud's plane coordinates over a window around each candidate:
    # smoother than interpolating four noisy neighbours, and it carries tilt and pitch.
    height, width = plate.intensity.shape
    offsets_1d = np.arange(-half_px, half_px + 1)
    base = np.rint(centres_px).astype(np.int64)
    cols = base[:, 0, None, None] + offsets_1d[None, None, :]
    rows = base[:, 1, None, None] + offsets_1d[None, :, None]
    cols, rows = np.broadcast_arrays(cols, rows)
    inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    uv = plate.plane_uv[np.clip(rows, 0, height - 1), np.clip(cols, 0, width - 1)]
    weight = (inside & np.isfinite(uv).all(axis=-1)).astype(float)
    uv = np.where(weight[..., None] > 0, uv, 0.0)
    # Design matrix relative to the candidate pixel for conditioning.
    design = np.stack([np.ones_like(cols, dtype=float), (cols - base[:, 0, None, None]).astype(float),
                       (rows - base[:, 1, None, None]).astype(float)], axis=-1).reshape(count, -1, 3)
    weight = weight.reshape(count, -1)
    uv = uv.reshape(count, -1, 2)
    weighted = design * weight[..., None]
    normal_matrix = np.matmul(weighted.transpose(0, 2, 1), design)
    right = np.matmul(weighted.transpose(0, 2, 1), uv)
    usable = weight.sum(axis=1) >= 10
    normal_matrix[~usable] = np.eye(3)
    solution = np.linalg.solve(normal_matrix, right)            # (M, 3, 2)
    jacobian = np.transpose(solution[:, 1:, :], (0, 2, 1))      # (M, 2 [u,v], 2 [col,row])
    offset = solution[:, 0, :] - np.einsum("mij,mj->mi", jacobian, base.astype(float))
    return offset, jacobian, usable


def _ray_darkness(image: np.ndarray, centres: np.ndarray, offset: np.ndarray, inverse: np.ndarray,
                  directions: np.ndarray, radial: np.ndarray, steel: np.ndarray):
    """Darkness below the local steel level along rays (M, A, S) and which rays stay inside the image.

    Rays are laid out in plane mm from ``centres`` and mapped to pixels through each candidate's
    inverse affine map (pixel = J^-1 (uv - offset), linear in the radius). ``steel`` marks the radial
    samples that see bare steel; their median per candidate is the background level.
    """
    count = len(centres)
    start = np.einsum("mij,mj->mi", inverse, centres - offset).astype(np.float32)      # (M, 2)
    heading = np.einsum("mij,aj->mai", inverse, directions).astype(np.float32)          # (M, A, 2)
    map_x = start[:, None, None, 0] + heading[..., 0, None] * radial                    # (M, A, S)
    map_y = start[:, None, None, 1] + heading[..., 1, None] * radial
    profiles = _sample_bilinear(image, map_x, map_y)                                    # (M, A, S)
    inside = np.isfinite(profiles).all(axis=2)                                          # (M, A)
    # Median of the steel samples; NaN (outside the image) sorts last, so index by the finite count.
    samples = np.sort(profiles[:, :, steel].reshape(count, -1), axis=1)
    finite = np.isfinite(samples).sum(axis=1)
    background = samples[np.arange(count), np.maximum(finite - 1, 0) // 2]
    darkness = np.clip(background[:, None, None] - np.nan_to_num(profiles), 0.0, None)
    darkness[~inside] = 0.0
    return darkness, inside


def _window_centroid(darkness: np.ndarray, radial: np.ndarray, low: np.ndarray, high: np.ndarray,
                     step: float) -> tuple[np.ndarray, np.ndarray]:
    """Darkness-weighted mean radius (M, A) between low and high (broadcastable), and where defined.

    A linear taper one sample wide at each end keeps the estimate continuous as the window moves.
    """
    taper = np.clip(np.minimum(radial - low, high - radial) / step + 0.5, 0.0, 1.0).astype(np.float32)
    weight = darkness * taper
    total = weight.sum(axis=2)
    moment = (weight * radial).sum(axis=2)
    return moment / np.where(total > 0, total, 1.0), total > 0


def _refine(image: np.ndarray, centres_uv: np.ndarray, offset: np.ndarray, jacobian: np.ndarray,
            ring_radii_mm: tuple[float, ...], pitch_mm: float):
    """Sub-pixel ring fit per candidate: centres (M, 2), radii (M, R), RMS (M,), usable (M,).

    Every pass takes, along each ray, the darkness centroid of a band that holds all rings with
    margin, and fits one circle to these edge points (all rings together: the double ring acts as
    one thick line). The band is centred on the current estimate, so anything that biases the
    centroid symmetrically (noise, a background error, the rings' blur) only pulls towards that
    estimate and the iteration's fixed point is the true centre. The first pass reaches
    ``COARSE_MARGIN_PX`` beyond the rings so a start that far off still sees them whole.
    The last pass also splits the band at the mid-radii to measure each ring's radius about the
    final centre; the reported RMS is over these per-ring residuals.
    """
    count = len(centres_uv)
    radii_nominal = np.asarray(ring_radii_mm)
    half_gap = (float(np.min(np.diff(radii_nominal))) if len(radii_nominal) > 1 else 4 * pitch_mm) / 2
    angles = np.linspace(0.0, 2 * np.pi, RAY_COUNT, endpoint=False)
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=-1)        # (A, 2)
    inverse = np.linalg.inv(jacobian)                                       # (M, 2, 2)
    centres = centres_uv.copy()
    usable = np.ones(count, bool)

    for refinement in range(REFINEMENT_PASSES):
        # Marks are looked for in [low, high]; 2 pixels of steel beyond each end give the background.
        margin = (COARSE_MARGIN_PX if refinement == 0 else 1.5) * pitch_mm
        step = (2 if refinement == 0 else 1) * RADIAL_STEP_PX * pitch_mm
        low, high = radii_nominal[0] - half_gap - margin, radii_nominal[-1] + half_gap + margin
        radial = np.arange(low - 2 * pitch_mm, high + 2 * pitch_mm + step / 2, step).astype(np.float32)
        darkness, ray_ok = _ray_darkness(image, centres, offset, inverse, directions, radial,
                                         (radial < low) | (radial > high))
        band_radius, defined = _window_centroid(darkness, radial, low, high, step)
        ray_ok &= defined
        new_centres, _, _, fit_ok = _fit_shared_centre(centres, directions, band_radius[:, None], ray_ok)
        usable &= fit_ok & (ray_ok.mean(axis=1) >= MIN_VALID_RAY_FRACTION)
        sampled_at, centres = centres, np.where(usable[:, None], new_centres, centres)

    # Per-ring edge points from the last profiles: windows split at the mid-radii between rings.
    bounds = np.concatenate([[low], (radii_nominal[1:] + radii_nominal[:-1]) / 2, [high]])
    edge_points = []
    for ring in range(len(radii_nominal)):
        ring_radius, defined = _window_centroid(darkness, radial, bounds[ring], bounds[ring + 1], step)
        ray_ok &= defined
        edge_points.append(sampled_at[:, None, :] + ring_radius[..., None] * directions[None])  # (M, A, 2)
    points = np.stack(edge_points, axis=1)                                   # (M, R, A, 2)
    distance = np.linalg.norm(points - centres[:, None, None, :], axis=-1)   # (M, R, A)
    used = ray_ok[:, None, :]
    counts = np.maximum(used.sum(axis=2), 1)
    radii = np.where(used, distance, 0.0).sum(axis=2) / counts            # least-squares radius per ring
    residual = np.where(used, distance - radii[..., None], 0.0)
    rms = np.sqrt((residual**2).sum(axis=(1, 2)) / counts.sum(axis=1))
    return centres, radii, rms, usable


def _sample_bilinear(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at float32 (column, row) positions (M, ...); NaN outside."""
    count = len(map_x)
    shape = map_x.shape
    map_x, map_y = map_x.reshape(count, -1), map_y.reshape(count, -1)
    # cv2.remap limits every image side to SHRT_MAX: one row per candidate, in blocks of rows.
    block = 16_384
    samples = np.empty(map_x.shape, np.float32)
    for start in range(0, count, block):
        rows = slice(start, start + block)
        samples[rows] = cv2.remap(image, map_x[rows], map_y[rows], interpolation=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return samples.reshape(shape)


def _fit_shared_centre(centres: np.ndarray, directions: np.ndarray, edge_radius: np.ndarray,
                       ray_ok: np.ndarray):
    """Kasa fit of concentric circles to edge points, one radius per ring, with one trimming round."""
    count, ring_count, ray_count = edge_radius.shape
    # Edge points relative to the current centre (mm): conditioning and a near-zero solution.
    px = edge_radius * directions[None, None, :, 0]
    py = edge_radius * directions[None, None, :, 1]
    weight = np.broadcast_to(ray_ok[:, None, :], edge_radius.shape).astype(float)
    for trimming in range(2):
        # Unknowns: a, b (centre shift) and k_r per ring with x^2 + y^2 = 2 a x + 2 b y + k_r.
        design = np.zeros((count, ring_count, ray_count, 2 + ring_count))
        design[..., 0] = 2 * px
        design[..., 1] = 2 * py
        for ring in range(ring_count):
            design[:, ring, :, 2 + ring] = 1.0
        target = px**2 + py**2
        design = design.reshape(count, -1, 2 + ring_count)
        w = weight.reshape(count, -1)
        weighted = (design * w[..., None]).transpose(0, 2, 1)
        normal_matrix = np.matmul(weighted, design)
        right = np.matmul(weighted, target.reshape(count, -1, 1))[..., 0]
        well_posed = np.linalg.cond(normal_matrix) < 1e12
        normal_matrix[~well_posed] = np.eye(2 + ring_count)
        solution = np.linalg.solve(normal_matrix, right[..., None])[..., 0]
        shift = solution[:, :2]
        radii = np.sqrt(np.clip(solution[:, 2:] + (shift**2).sum(axis=1, keepdims=True), 0.0, None))
        residual = np.hypot(px - shift[:, None, None, 0], py - shift[:, None, None, 1]) - radii[..., None]
        used = weight > 0
        counts = used.sum(axis=(1, 2))
        rms = np.sqrt((np.where(used, residual, 0.0) ** 2).sum(axis=(1, 2)) / np.maximum(counts, 1))
        if trimming == 0:
            # Rays hit by speckle or a scratch: drop edge points beyond 3 robust sigmas and refit.
            abs_res = np.where(used, np.abs(residual), np.nan)
            mad = np.nanmedian(abs_res.reshape(count, -1), axis=1)
            limit = np.maximum(3.0 * 1.4826 * mad, 1e-6)
            weight = weight * (np.abs(residual) <= limit[:, None, None])
    fit_ok = well_posed & (counts >= 8)
    return centres + shift, radii, rms, fit_ok


def _merge(centres: np.ndarray, rms: np.ndarray, distance: float) -> np.ndarray:
    """Indices kept after folding every centre within ``distance`` of a better-fitting one."""
    order = np.argsort(rms)
    tree = cKDTree(centres)
    dropped = np.zeros(len(centres), bool)
    keep = []
    for index in order:
        if dropped[index]:
            continue
        keep.append(index)
        dropped[tree.query_ball_point(centres[index], distance)] = True
    return np.array(sorted(keep), dtype=int)


def measure_fiducials(xyz, intensity, pose: PlatePose, *, ring_radii_mm=(2.5, 2.7),
                      pixel_size_mm: float = 0.1,
                      expected_count: int | None = None, marks_darker: bool = True,
                      radius_tolerance_mm: float = 0.08) -> FiducialMeasurement:
    """Measure the double-ring fiducials of a plate scan; see the module docstring for the method.

    ``xyz`` is organized (H, W, 3) with ``intensity`` (H, W), or unorganized (N, 3) with (N,); NaNs
    are allowed. ``pose`` is the plate pose from ``estimate_plate_pose``. ``pixel_size_mm`` is the
    raster pitch for unorganized clouds. A candidate is kept when every fitted ring radius is within
    ``radius_tolerance_mm`` of its nominal value. Raises ValueError when no fiducial is found.
    """
    radii_nominal = tuple(sorted(float(r) for r in as_finite_array(ring_radii_mm, "ring_radii_mm", ndim=1)))
    if radii_nominal[0] <= 0 or len(set(radii_nominal)) != len(radii_nominal):
        raise ValueError(f"ring_radii_mm must be distinct positive radii, got {list(ring_radii_mm)}")
    if not np.isfinite(pixel_size_mm) or pixel_size_mm <= 0:
        raise ValueError(f"pixel_size_mm must be positive, got {pixel_size_mm!r}")
    if expected_count is not None and expected_count < 0:
        raise ValueError(f"expected_count must be non-negative, got {expected_count}")
    try:
        xyz = np.asarray(xyz, dtype=float)
        intensity = np.asarray(intensity, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f"xyz and intensity must be numeric: {error}") from None
    if xyz.ndim == 3 and xyz.shape[2] == 3 and intensity.shape == xyz.shape[:2]:
        plate = _organized_image(xyz, intensity, pose)
    elif xyz.ndim == 2 and xyz.shape[1] == 3 and intensity.shape == xyz.shape[:1]:
        plate = _rasterised_image(xyz, intensity, pose, pixel_size_mm)
    else:
        raise ValueError("xyz must be (H, W, 3) with intensity (H, W), or (N, 3) with intensity (N,); "
                         f"got {xyz.shape} and {intensity.shape}")

    image = plate.intensity if marks_darker else -plate.intensity
    scaled, image8 = _stretch(image)
    height, width = image8.shape
    candidates = _detect(image8, plate.pitch, radii_nominal)
    if len(candidates) == 0:
        raise ValueError(f"no fiducials found in a {width}x{height} image")

    pitch = min(plate.pitch)
    half_px = int(np.ceil((radii_nominal[-1] + 0.5) / pitch))
    offset, jacobian, affine_ok = _local_affines(plate, candidates, half_px)
    start_uv = offset + np.einsum("mij,mj->mi", jacobian, candidates)
    # The refinement samples the stretched image before 8-bit rounding and clipping, neither binarised
    # nor median filtered: a median would round off the one-pixel-wide ring lines.
    centres_uv, radii, rms, usable = _refine(scaled, start_uv, offset, jacobian,
                                             radii_nominal, pitch)
    radius_ok = np.all(np.abs(radii - np.asarray(radii_nominal)) <= radius_tolerance_mm, axis=1)
    accepted = np.nonzero(usable & affine_ok & radius_ok)[0]
    rejected = len(candidates) - len(accepted)
    if len(accepted) == 0:
        raise ValueError(f"no fiducials found in a {width}x{height} image "
                         f"({rejected} circle candidate(s) rejected by the ring fit)")
    kept = accepted[_merge(centres_uv[accepted], rms[accepted], radii_nominal[-1])]
    merged = len(accepted) - len(kept)
    # Row-major order in plate coordinates (v, then u) for reproducible output.
    kept = kept[np.lexsort((centres_uv[kept, 0], centres_uv[kept, 1]))]
    centres_plane = centres_uv[kept]
    return FiducialMeasurement(
        centres=pose.from_plane(centres_plane), centres_plane=centres_plane, quality=rms[kept],
        radii=radii[kept, -1], inner_radii=radii[kept, 0], merged=int(merged), rejected=int(rejected),
        missing=None if expected_count is None else int(expected_count) - len(kept),
        image_shape=(height, width), pixel_pitch_mm=plate.pitch)
