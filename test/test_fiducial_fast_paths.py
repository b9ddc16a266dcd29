"""The fiducial measurement's faster array paths against plain references (issue 33 item 3).

The peak search along the rays and the detection image's binning were rewritten for CPU time; each
must give what the obvious per-candidate loop or block mean gives.
"""
import numpy as np
import pytest

from gls_calibration.fiducials.detection import _detection_image
from gls_calibration.fiducials.ring_fit import _peak


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
