"""Error separation over reversed and turned sweeps, on synthetic sweeps whose errors are known."""
import math

import numpy as np
import pytest
from scipy import sparse

from gls_calibration.registration.separation import TIME_PLACED, SeparationSettings, _weighted_design, separate

LINE_HALF_MM = 105.0


def linearity(u):
    """A smooth linearity shape of the sensor, peak ~0.07 mm."""
    return 0.06 * np.sin(1.5 * np.pi * u / LINE_HALF_MM) + 0.02 * np.cos(2.5 * np.pi * u / LINE_HALF_MM)


def lateral_truth(u):
    """The linearity shape without a lateral scale over the marks' span: with the line's scale
    trusted, that is all a separation can see (a scale of every sweep is a scale of the plate)."""
    span = np.linspace(-91.0, 91.0, 2001)
    slope, offset = np.polyfit(span, linearity(span), 1)
    return linearity(u) - slope * u - offset


def smooth_process(rng, amplitude_mm, length_mm):
    """A random smooth function of the travel (a few sines), as robot wander or speed ripple."""
    waves = rng.uniform(1.0 / 200.0, 1.0 / length_mm, 6)
    phases = rng.uniform(0, 2 * np.pi, 6)
    weights = rng.normal(0, amplitude_mm / math.sqrt(3), 6)
    return lambda v: sum(w * np.sin(2 * np.pi * f * v + p) for w, f, p in zip(weights, waves, phases))


def true_marks(rng):
    axis = np.linspace(-90.0, 90.0, 19)
    x, y = np.meshgrid(axis, axis)
    grid = np.column_stack([x.ravel(), y.ravel()])
    # a galvo-like smooth field of about 1 mm plus the marks' own scatter
    field = np.column_stack([0.8 * np.sin(grid[:, 1] / 60.0), 0.6 * np.cos(grid[:, 0] / 70.0)])
    return grid + field + rng.normal(0, 0.01, grid.shape)


def rotation(angle):
    return np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])


def measure(rng, marks, plan, noise_mm=0.003, lateral=linearity, motion_mm=0.03, along_mm=0.0, scale=0.0,
            yaw=0.0):
    """One (N, 2) sweep-frame table per (orientation deg, direction) of ``plan``, plus the truth.

    ``motion_mm``: path wander across the travel; ``along_mm`` and ``scale``: placement along it
    (zero with a pose stream; speed ripple and scale when profiles are placed by time); ``yaw``: the
    std of each sweep's own path yaw (a cross-track error growing along the travel, rad). A 45 deg
    sweep sees only the marks inside the grid's square turned with it (NaN elsewhere).
    """
    sweeps, truth = [], []
    for orientation_deg, direction in plan:
        # the plate seen from the sensor: turned, and for a reversed sweep the travel starts at the other end
        placed = marks @ rotation(-math.radians(orientation_deg)).T
        hidden = np.any(np.abs(placed) > 92.0, axis=1)
        placed = placed + rng.normal(0, 0.5, 2) + np.array([0.0, 100.0 if direction > 0 else -100.0])
        across, along = smooth_process(rng, motion_mm, 40.0), smooth_process(rng, along_mm, 40.0)
        v = placed[:, 1]
        slope = rng.normal(0, yaw) if yaw else 0.0
        error = np.column_stack([lateral(placed[:, 0]) + across(v) + slope * v, along(v) + scale * direction * v])
        seen = placed + error + rng.normal(0, noise_mm, placed.shape)
        seen[hidden] = np.nan
        sweeps.append(seen)
        truth.append(error)
    return sweeps, truth


def rigid_residual_rms(estimate, truth):
    """RMS of ``estimate`` - ``truth`` after the best 2-D rigid alignment."""
    a, b = estimate - estimate.mean(0), truth - truth.mean(0)
    u, _, vt = np.linalg.svd(b.T @ a)
    r = u @ np.diag([1, np.sign(np.linalg.det(u @ vt))]) @ vt
    return float(np.sqrt(np.mean(np.sum((a @ r.T - b) ** 2, axis=1))))


def plain_average(sweeps):
    """Each sweep rigidly aligned onto sweep 0, then averaged: what repeating alone gives."""
    reference = sweeps[0]
    aligned = [reference]
    for sweep in sweeps[1:]:
        a, b = sweep - sweep.mean(0), reference - reference.mean(0)
        u, _, vt = np.linalg.svd(b.T @ a)
        r = u @ np.diag([1, np.sign(np.linalg.det(u @ vt))]) @ vt
        aligned.append(a @ r.T + reference.mean(0))
    return np.mean(aligned, axis=0)


FULL_PLAN = [(0, 1), (0, -1), (90, 1), (90, -1)]


def test_turned_and_reversed_sweeps_remove_the_scanner_frame_error():
    rng = np.random.default_rng(4)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, FULL_PLAN)
    averaged = rigid_residual_rms(plain_average(sweeps), marks)
    result = separate(sweeps, [np.full(len(marks), 0.003)] * len(sweeps))
    separated = rigid_residual_rms(result.centres_mm, marks)
    assert averaged > 0.025                 # the structured errors do not average out
    assert separated < 0.005                # noise alone: 0.002
    assert result.scanner_rms_mm > 0.02 and result.motion_rms_mm > 0.01


@pytest.mark.parametrize("seed", range(6))
def test_a_45_deg_pass_separates_the_sweeps_path_yaw_from_a_shear_of_the_marks(seed):
    """Each sweep's path yaw (random, 1e-3 rad) is a shear in its own frame; at 0 and 90 deg the part
    that differs between the turned sweeps cannot be told from a symmetric shear of the marks and
    stays in them (the ridge splits it), while a 45 deg pass sees that shear as a stretch along its
    lines and travel and pins it."""
    marks = true_marks(np.random.default_rng(seed))
    residual = {}
    for name, plan in (("0/90", FULL_PLAN), ("0/90 + 45", FULL_PLAN + [(45, 1)])):
        for yaw in (0.0, 1e-3):
            rng = np.random.default_rng(100 + seed)     # the same noise with and without the yaw
            sweeps, _ = measure(rng, marks, plan, yaw=yaw)
            residual[name, yaw] = rigid_residual_rms(separate(sweeps).centres_mm, marks)
    assert residual["0/90 + 45", 1e-3] < 1.15 * residual["0/90 + 45", 0.0]
    assert residual["0/90 + 45", 0.0] < 0.003                  # noise alone: ~0.002
    # the 45 deg sweep misses the grid's corners (72 of 361 marks); those come from the 0/90 sweeps alone
    assert 50 <= np.isnan(sweeps[-1]).any(axis=1).sum() <= 100


def test_without_a_45_deg_pass_the_path_yaw_leaks_into_the_marks():
    """Over the seeds of the test above, the 0/90 plan carries the yaw into the marks on some."""
    worst = 0.0
    for seed in range(6):
        marks = true_marks(np.random.default_rng(seed))
        with_yaw, without = (rigid_residual_rms(separate(measure(np.random.default_rng(100 + seed), marks, FULL_PLAN,
                                                                 yaw=yaw)[0]).centres_mm, marks)
                             for yaw in (1e-3, 0.0))
        worst = max(worst, with_yaw / without)
    assert worst > 4.0          # measured: 8.4 (seed 1)


def test_profiles_placed_by_time_are_helped_less():
    rng = np.random.default_rng(4)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, FULL_PLAN, lateral=lateral_truth, along_mm=0.03, scale=0.0015)
    averaged = rigid_residual_rms(plain_average(sweeps), marks)
    separated = rigid_residual_rms(separate(sweeps, settings=TIME_PLACED).centres_mm, marks)
    assert separated < 0.5 * averaged
    # trusting the travel when it carries a speed error is wrong
    assert rigid_residual_rms(separate(sweeps).centres_mm, marks) > separated


def test_the_lateral_shape_is_recovered():
    rng = np.random.default_rng(7)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, FULL_PLAN)
    result = separate(sweeps)
    u = np.linspace(-80.0, 80.0, 161)
    error = result.lateral(u) - linearity(u)
    error -= error.mean()
    assert np.sqrt(np.mean(error ** 2)) < 0.1 * np.sqrt(np.mean(linearity(u) ** 2))


def test_trusting_the_line_leaves_its_scale_error_in_the_plate():
    rng = np.random.default_rng(3)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, FULL_PLAN)
    trusting_line = rigid_residual_rms(separate(sweeps, settings=TIME_PLACED).centres_mm, marks)
    assert trusting_line > 2 * rigid_residual_rms(separate(sweeps).centres_mm, marks)


def test_one_orientation_cannot_see_the_lateral_shape_and_falls_back_to_averaging():
    rng = np.random.default_rng(11)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, [(0, 1), (0, -1), (0, 1)], motion_mm=0.0)
    result = separate(sweeps)
    assert np.all(result.lateral(np.linspace(-80, 80, 50)) == 0.0)
    # no worse than averaging: the lateral shape stays in the marks, it is not invented
    assert rigid_residual_rms(result.centres_mm, marks) < 1.1 * rigid_residual_rms(plain_average(sweeps), marks)


def test_without_scanner_errors_the_separation_averages_the_noise():
    rng = np.random.default_rng(2)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, FULL_PLAN, noise_mm=0.004, lateral=lambda u: 0.0 * u, motion_mm=0.0)
    result = separate(sweeps, [np.full(len(marks), 0.004)] * 4)
    error = rigid_residual_rms(result.centres_mm, marks)
    # four sweeps: sqrt(2) * 0.004 / 2 per point (two axes), a little more for the shapes fitted
    assert error < 1.4 * math.sqrt(2) * 0.004 / 2
    assert np.nanmedian(result.sigma_mm) == pytest.approx(0.002, rel=0.35)


def test_uncertainty_follows_the_spread_of_a_noisy_fiducial():
    rng = np.random.default_rng(5)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, FULL_PLAN, noise_mm=0.002)
    for sweep in sweeps:
        sweep[17] += rng.normal(0, 0.05, 2)          # one fiducial measured badly, its ring fit unaware
    result = separate(sweeps, [np.full(len(marks), 0.002)] * 4)
    assert result.sigma_mm[17] > 5 * np.median(result.sigma_mm)
    assert np.all(result.ring_sigma_mm == pytest.approx(0.001))


def test_missing_fiducials_are_allowed_and_reported():
    rng = np.random.default_rng(9)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, FULL_PLAN)
    sweeps[1][[3, 40]] = np.nan
    sweeps[2][3] = np.nan
    result = separate(sweeps)
    assert result.sweeps_seen[3] == 2 and result.sweeps_seen[40] == 3 and result.sweeps_seen[0] == 4
    assert np.all(np.isfinite(result.centres_mm))


def test_a_single_sweep_gives_its_own_centres():
    rng = np.random.default_rng(1)
    marks = true_marks(rng)
    sweeps, _ = measure(rng, marks, [(0, 1)], motion_mm=0.0)
    result = separate(sweeps)
    assert np.allclose(result.centres_mm, sweeps[0], atol=1e-6)
    assert np.all(np.isnan(result.spread_sigma_mm))


@pytest.mark.parametrize("centres, sigmas, message", [
    ([], None, "at least one sweep"),
    ([np.zeros((5, 3))], None, r"shape \(N, 2\)"),
    ([np.zeros((5, 2)), np.zeros((4, 2))], None, "same fiducials"),
    ([np.full((5, 2), np.inf)], None, "infinite"),
    ([np.ones((5, 2))], [np.ones(5), np.ones(5)], "one array per sweep"),
    ([np.ones((5, 2))], [-np.ones(5)], "non-negative"),
])
def test_bad_input_is_refused(centres, sigmas, message):
    with pytest.raises(ValueError, match=message):
        separate(centres, sigmas)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="lateral_knot_spacing_mm"):
        SeparationSettings(lateral_knot_spacing_mm=0.0)
    with pytest.raises(ValueError, match="scale_from must be one of travel, line"):
        SeparationSettings(scale_from="robot")


@pytest.mark.parametrize("seed", range(4))
def test_the_weighted_design_is_the_sparse_matrix_of_the_dense_one(seed):
    """The same entries, order and index type as ``csr_matrix`` of the dense design, so the same normal matrix."""
    rng = np.random.default_rng(seed)
    rows, n_marks, n_rest = 2 * int(rng.integers(3, 200)), 2 * int(rng.integers(2, 60)), int(rng.integers(0, 30))
    mark_column = rng.integers(0, n_marks, rows)
    rest = rng.normal(size=(rows, n_rest))
    rest[rng.uniform(size=rest.shape) < 0.6] = 0.0
    rest[rng.uniform(size=rest.shape) < 0.05] = -0.0
    row_weight = rng.uniform(0.1, 1e3, rows)
    dense = np.zeros((rows, n_marks + n_rest))
    dense[np.arange(rows), mark_column] = 1.0
    dense[:, n_marks:] = rest
    expected = sparse.csr_matrix(dense * row_weight[:, None])
    got = _weighted_design(mark_column, rest, row_weight, n_marks + n_rest)
    assert got.shape == expected.shape
    for name in ("data", "indices", "indptr"):
        assert getattr(got, name).dtype == getattr(expected, name).dtype, name
        assert getattr(got, name).tobytes() == getattr(expected, name).tobytes(), name
    assert ((got.T @ got).toarray().tobytes() == (expected.T @ expected).toarray().tobytes())
