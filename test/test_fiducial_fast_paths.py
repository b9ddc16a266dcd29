"""The fiducial measurement's faster array paths against plain references (issue 33 item 3).

The peak search along the rays, the detection image's binning, the correlation map's local maxima and
the rays' sample positions were rewritten for CPU time; each must give what the obvious
per-candidate loop, block mean, whole-map dilation or einsum gives.
"""
import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from gls_calibration.fiducials.detection import _correlation_peaks, _detection_image
from gls_calibration.fiducials.ring_fit import (_correlate_rows, _correlation_at, _peak, _ray_profiles, _sample_bicubic,
                                                _runs, _window_correlation, _window_profiles)


def _reference_peak(score: np.ndarray, low: np.ndarray, width: int):
    """Sub-sample argmax per candidate and ray, one candidate at a time."""
    count, rays, _ = score.shape
    index, ok = np.zeros((count, rays)), np.zeros((count, rays), bool)
    for m in range(count):
        window = score[m, :, low[m]:low[m] + width]
        best = np.argmax(window, axis=1)
        at = low[m] + best
        left, centre, right = (score[m, np.arange(rays), at + k] for k in (-1, 0, 1))
        curvature = left - 2 * centre + right
        delta = np.where(curvature < 0, 0.5 * (left - right) / np.where(curvature < 0, curvature, -1.0), 0.0)
        index[m] = at + np.clip(delta, -0.5, 0.5)
        ok[m] = (best > 0) & (best < width - 1) & (curvature < 0)
    return index, ok


@pytest.mark.parametrize("samples, width", [(81, 41), (71, 16), (20, 18)])
def test_peak_search_matches_a_loop_over_candidates(samples, width):
    rng = np.random.default_rng(samples)
    count, rays = 37, 64
    score = rng.normal(size=(count, rays, samples)).astype(np.float32)
    # Smooth peaks at random places, some at the window's ends, on top of the noise.
    score += np.exp(-0.5 * ((np.arange(samples) - rng.uniform(0, samples, (count, rays, 1))) / 2.0) ** 2)
    low = rng.integers(1, samples - width, count)            # keeps the window and a neighbour each side
    low[:2] = (1, samples - width - 1)                       # both extremes
    index, ok = _peak(score, low, width)
    expected_index, expected_ok = _reference_peak(score, low, width)
    np.testing.assert_array_equal(index, expected_index)
    np.testing.assert_array_equal(ok, expected_ok)
    assert ok.any() and not ok.all()


@pytest.mark.parametrize("pitch, factors", [((0.1, 0.1), (2, 2)), ((0.067, 0.15), (3, 1)), ((0.1, 0.05), (2, 4))])
def test_detection_image_is_the_block_mean(pitch, factors):
    rng = np.random.default_rng(3)
    image = rng.normal(size=(103, 98)).astype(np.float32)
    binned, found = _detection_image(image, pitch)
    assert found == factors
    rows, cols = image.shape[0] // factors[0], image.shape[1] // factors[1]
    expected = image[:rows * factors[0], :cols * factors[1]].astype(float).reshape(
        rows, factors[0], cols, factors[1]).mean(axis=(1, 3))
    assert binned.shape == expected.shape and binned.dtype == np.float32
    np.testing.assert_allclose(binned, expected, rtol=0, atol=1e-6)


def test_detection_image_at_the_detection_pitch_is_the_image_itself():
    image = np.arange(20, dtype=np.float32).reshape(4, 5)
    binned, factors = _detection_image(image, (0.2, 0.2))
    assert factors == (1, 1) and binned is image


def _reference_correlation_peaks(score: np.ndarray, distance_px: float, threshold: float) -> np.ndarray:
    """Local maxima through a dilation of the whole map (the code before issue 33's rewrite)."""
    size = 2 * int(np.ceil(distance_px)) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    rows, cols = np.nonzero((score >= cv2.dilate(score, kernel)) & (score > threshold))
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


@pytest.mark.parametrize("seed, distance_px, threshold", [(0, 13.5, 0.3), (1, 4.2, 0.0), (2, 2.0, 0.5), (3, 7.0, 2.0)])
def test_correlation_peaks_match_a_dilation_of_the_whole_map(seed, distance_px, threshold):
    rng = np.random.default_rng(seed)
    score = cv2.GaussianBlur(rng.normal(size=(157, 203)).astype(np.float32), (0, 0), 3.0)
    score /= score.std()
    # Plateaus (equal maxima) and maxima on the border, where the dilation ignores what is outside.
    score = np.round(score * 4) / 4
    score[0, 50:53] = score[:, -1] = score.max()
    peaks = _correlation_peaks(score, distance_px, threshold)
    expected = _reference_correlation_peaks(score, distance_px, threshold)
    np.testing.assert_array_equal(peaks, expected)
    assert len(expected) > 3 or threshold >= 2.0


def test_correlation_peaks_none_above_the_threshold():
    score = np.zeros((40, 50), np.float32)
    assert _correlation_peaks(score, 5.0, 0.1).shape == (0, 2)


def test_ray_profiles_sample_where_the_einsum_of_the_maps_puts_them():
    rng = np.random.default_rng(5)
    image = rng.normal(size=(120, 140)).astype(np.float32)
    count, rays = 9, 32
    centres = rng.uniform(4.0, 12.0, (count, 2))       # some rays leave the image
    offset = rng.uniform(-0.5, 0.5, (count, 2))
    inverse = np.linalg.inv(np.array([[0.1, 0.004], [-0.003, 0.15]]) + rng.normal(0, 0.005, (count, 2, 2)))
    angles = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)
    directions = np.stack([np.cos(angles), np.sin(angles)], -1)
    radial = np.linspace(1.0, 3.0, 41).astype(np.float32)
    start = np.einsum("mij,mj->mi", inverse, centres - offset).astype(np.float32)
    heading = np.einsum("mij,aj->mai", inverse, directions).astype(np.float32)
    maps = [heading[..., axis, None] * radial + start[:, None, None, axis] for axis in range(2)]
    expected = _sample_bicubic(image, *maps)
    np.testing.assert_array_equal(_ray_profiles(image, centres, offset, inverse, directions, radial), expected)
    assert np.isfinite(expected).any() and np.isnan(expected).any()


@pytest.mark.parametrize("samples, taps, outputs", [(71, 39, 18), (55, 27, 29), (40, 39, 5)])
def test_window_correlation_is_the_whole_profiles_correlation_there(samples, taps, outputs):
    rng = np.random.default_rng(taps)
    count, rays = 23, 32
    profiles = rng.normal(size=(count, rays, samples)).astype(np.float32)
    template = rng.normal(size=taps).astype(np.float32)
    whole = _correlate_rows(profiles, template)
    # Windows inside the profile and ones whose template reaches beyond either end (replicated border).
    first = rng.integers(0, samples - outputs + 1, count)
    first[:2] = (0, samples - outputs)
    window = _window_correlation(profiles, template, first, outputs)
    expected = np.take_along_axis(whole, np.broadcast_to(first[:, None, None] + np.arange(outputs), window.shape), -1)
    # The same sums; OpenBLAS on AVX-512 adds them in filter2D's order (equal to the bit there).
    np.testing.assert_allclose(window, expected, rtol=1e-5, atol=1e-5 * np.abs(whole).max())
    position = rng.integers(0, samples, (count, rays))
    np.testing.assert_allclose(_correlation_at(profiles, template, window, first, position),
                               np.take_along_axis(whole, position[..., None], -1)[..., 0],
                               rtol=1e-5, atol=1e-5 * np.abs(whole).max())


def test_runs_are_the_sliding_window_views_gather():
    rng = np.random.default_rng(5)
    values = rng.normal(size=(7, 11, 40)).astype(np.float32)
    first = rng.integers(0, 40 - 13 + 1, (7, 11))
    first[0, :2] = (0, 40 - 13)
    expected = np.lib.stride_tricks.sliding_window_view(values, 13, axis=-1)[
        np.arange(7)[:, None], np.arange(11)[None, :], first]
    np.testing.assert_array_equal(_runs(values, first, 13), expected)


def test_window_profiles_are_the_whole_profiles_there_also_at_the_border():
    rng = np.random.default_rng(8)
    image = rng.normal(size=(150, 170)).astype(np.float32)
    count, rays, length = 12, 64, 30
    # Half the candidates well inside, half with rays that reach or cross the border.
    centres = np.concatenate([rng.uniform(5.0, 10.0, (count // 2, 2)), rng.uniform(1.5, 3.0, (count // 2, 2))])
    offset = np.zeros((count, 2))
    inverse = np.linalg.inv(np.array([[0.1, 0.002], [-0.001, 0.1]]) + rng.normal(0, 0.002, (count, 2, 2)))
    angles = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)
    directions = np.stack([np.cos(angles), np.sin(angles)], -1)
    radial = np.linspace(2.0, 3.4, 71).astype(np.float32)
    first = rng.integers(0, len(radial) - length + 1, count)
    profiles, inside, whole = _window_profiles(image, centres, offset, inverse, directions, radial, first, length)
    expected = _ray_profiles(image, centres, offset, inverse, directions, radial)
    expected_inside = np.isfinite(expected[..., 0]) & np.isfinite(expected[..., -1])
    expected = np.where(np.isfinite(expected), expected, np.float32(0.0))
    np.testing.assert_array_equal(inside, expected_inside)
    assert not inside[count // 2:].all() and inside[:count // 2].all()
    np.testing.assert_array_equal(profiles, _runs(expected, np.broadcast_to(first[:, None], (count, rays)), length))
    mask = rng.random((count, rays)) < 0.2
    np.testing.assert_array_equal(whole(mask), expected[mask])
