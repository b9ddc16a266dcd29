"""Tests of the setpoint correction: composition, calibrated region, taper and flags."""
import re

import numpy as np
import pytest

from gls_calibration.correction.setpoints import CalibratedRegion, Correction, taper_weight
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.models.rbf import OLSRBFNetwork, ThinPlateSplineModel

GEOMETRY = HeadGeometry()
GRID = grid_targets()
REGION = CalibratedRegion.from_points(GRID)


def field(points, scale=1.0):
    s, t = points[:, 0] / 95.0, points[:, 1] / 95.0
    return scale * np.column_stack([0.6 * s + 0.3 * s ** 3 + 0.1 * s * t, 0.3 * t - 0.2 * s * s])


@pytest.fixture(scope="module")
def first_model():
    return OLSRBFNetwork(GRID, field(GRID))


@pytest.fixture(scope="module")
def second_model():
    return ThinPlateSplineModel(GRID, field(GRID, -0.1) + 0.02, smoothing=10.0)


def test_region_from_grid_is_its_bounding_box():
    assert REGION == CalibratedRegion(-95.0, 95.0, -95.0, 95.0)
    assert CalibratedRegion.from_dict(REGION.to_dict()) == REGION
    np.testing.assert_array_equal(REGION.contains([95.0, 95.0 + 1e-6, 0.0], [0.0, 0.0, -96.0]), [True, False, False])


def test_inside_the_region_the_commanded_point_is_target_plus_model(first_model):
    correction = Correction(GEOMETRY, [first_model], REGION)
    points = np.random.default_rng(0).uniform(-95.0, 95.0, (200, 2))
    result = correction.correct(points[:, 0], points[:, 1])
    expected = points + first_model(points)
    np.testing.assert_allclose(np.column_stack([result.x, result.y]), expected, atol=1e-12)
    assert result.inside_calibrated_field.all()
    joints = inverse(GEOMETRY, expected[:, 0], expected[:, 1])
    np.testing.assert_allclose(result.alpha_x, joints.alpha_x, atol=1e-15)
    np.testing.assert_allclose(result.alpha_y, joints.alpha_y, atol=1e-15)
    np.testing.assert_allclose(result.focus_shift, joints.focus_shift, atol=1e-12)


def test_composition_of_two_models_is_their_sum(first_model, second_model):
    base = Correction(GEOMETRY, [first_model], REGION)
    both = base.with_model(second_model)
    assert len(base.models) == 1 and len(both.models) == 2          # the original is unchanged
    points = np.random.default_rng(1).uniform(-130.0, 130.0, (300, 2))
    dx, dy, inside = both.deviation(points[:, 0], points[:, 1])
    dx1, dy1, _ = base.deviation(points[:, 0], points[:, 1])
    dx2, dy2, _ = Correction(GEOMETRY, [second_model], REGION).deviation(points[:, 0], points[:, 1])
    np.testing.assert_allclose(dx, dx1 + dx2, atol=1e-12)
    np.testing.assert_allclose(dy, dy1 + dy2, atol=1e-12)
    np.testing.assert_array_equal(inside, REGION.contains(points[:, 0], points[:, 1]))


def test_with_model_intersects_regions(first_model):
    narrower = CalibratedRegion(-50.0, 80.0, -95.0, 60.0)
    combined = Correction(GEOMETRY, [first_model], REGION).with_model(first_model, narrower)
    assert combined.calibrated_region == narrower
    first = Correction(GEOMETRY).with_model(first_model, REGION)
    assert first.calibrated_region == REGION


def test_outside_the_region_the_correction_is_clamped_tapered_and_finite(first_model):
    correction = Correction(GEOMETRY, [first_model], REGION, taper_mm=10.0)
    far = np.array([[1e6, 0.0], [-1e9, 3e8], [120.0, -250.0], [0.0, 1e300]])
    result = correction.correct(far[:, 0], far[:, 1])
    for value in (result.x, result.y, result.alpha_x, result.alpha_y, result.focus_shift):
        assert np.all(np.isfinite(value))
    np.testing.assert_array_equal(result.x, far[:, 0])               # fully tapered off
    np.testing.assert_array_equal(result.y, far[:, 1])
    assert not result.inside_calibrated_field.any()
    assert not result.within_limits.any()


def test_tapered_correction_is_bounded_by_the_in_region_correction(first_model):
    correction = Correction(GEOMETRY, [first_model], REGION, taper_mm=10.0)
    axis = np.linspace(-95.0, 95.0, 191)
    inner = np.column_stack([grid.ravel() for grid in np.meshgrid(axis, axis)])
    inner_dx, inner_dy, _ = correction.deviation(inner[:, 0], inner[:, 1])
    largest = np.hypot(inner_dx, inner_dy).max()
    ring = np.random.default_rng(2).uniform(-110.0, 110.0, (2000, 2))
    ring = ring[~REGION.contains(ring[:, 0], ring[:, 1])]
    dx, dy, inside = correction.deviation(ring[:, 0], ring[:, 1])
    assert not inside.any()
    magnitude = np.hypot(dx, dy)
    assert magnitude.max() <= largest * (1 + 1e-9)
    boundary_dx, boundary_dy, _ = correction.deviation(*REGION.clamp(ring[:, 0], ring[:, 1]))
    assert np.all(magnitude <= np.hypot(boundary_dx, boundary_dy) + 1e-12)


def test_taper_is_continuous_at_both_ends():
    np.testing.assert_allclose(taper_weight(np.array([0.0, 1e-9, 5.0, 10.0 - 1e-9, 10.0, 50.0]), 10.0),
                               [1.0, 1.0, 0.5, 0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_array_equal(taper_weight(np.array([0.0, 1e-3]), 0.0), [1.0, 0.0])


def test_correction_is_continuous_across_the_boundary(first_model):
    correction = Correction(GEOMETRY, [first_model], REGION, taper_mm=10.0)
    x = np.array([95.0 - 1e-7, 95.0, 95.0 + 1e-7])
    dx, dy, inside = correction.deviation(x, np.full(3, 20.0))
    np.testing.assert_allclose(dx, dx[1], atol=1e-6)
    np.testing.assert_array_equal(inside, [True, True, False])


def test_without_models_it_is_the_nominal_kinematics():
    correction = Correction(GEOMETRY)
    x, y, z = np.array([0.0, 50.0, 300.0]), np.array([10.0, -80.0, 0.0]), np.array([0.0, 5.0, -2.0])
    result = correction.correct(x, y, z)
    joints = inverse(GEOMETRY, x, y, z)
    np.testing.assert_array_equal(result.x, x)
    np.testing.assert_array_equal(result.alpha_x, joints.alpha_x)
    np.testing.assert_array_equal(result.focus_shift, joints.focus_shift)
    assert not result.inside_calibrated_field.any()


def test_limit_flags_come_from_the_kinematics_of_the_commanded_point(first_model):
    correction = Correction(GEOMETRY, [first_model], REGION)
    x = np.array([0.0, 90.0, 170.0, 0.0, 150.0])
    y = np.array([0.0, 90.0, 0.0, -200.0, 150.0])
    z = np.array([0.0, 0.0, 0.0, 0.0, 0.0])           # last: mirrors reach it, the focus module does not
    result = correction.correct(x, y, z)
    joints = inverse(GEOMETRY, result.x, result.y, z)
    np.testing.assert_array_equal(result.within_limits, joints.within_limits)
    assert result.within_limits.tolist() == [True, True, False, False, False]


@pytest.mark.parametrize("kwargs, message", [
    ({"models": [lambda p: p]}, "calibrated_region is required when models are given"),
    ({"models": [1.0], "calibrated_region": REGION}, r"models\[0\] is not callable"),
    ({"taper_mm": -1.0}, "taper_mm must be a non-negative finite number"),
    ({"models": [lambda p: p], "calibrated_region": CalibratedRegion(-1.0, 1.0, -1.0, 1.0, plane_z_mm=490.0)},
     r"calibration plane z = 490 mm lies outside the head's focus range \(\+-25 mm\)"),
])
def test_correction_rejects_bad_configuration(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Correction(GEOMETRY, **kwargs)


def test_the_answer_is_the_same_whatever_the_number_of_workers(first_model, second_model):
    correction = Correction(GEOMETRY, [first_model, second_model], REGION)
    rng = np.random.default_rng(21)
    x, y, z = rng.uniform(-110.0, 110.0, 20_001), rng.uniform(-110.0, 110.0, 20_001), rng.uniform(-10.0, 10.0, 20_001)
    serial = correction.correct(x, y, z, workers=1)
    for workers in (2, 3, None):
        shared = correction.correct(x, y, z, workers=workers)
        for name in vars(serial):
            np.testing.assert_array_equal(getattr(shared, name), getattr(serial, name), err_msg=name)


def test_sharing_a_request_runs_blas_on_one_thread(first_model, monkeypatch):
    # Each worker's matrix products under a threaded BLAS would start BLAS threads of their own on the
    # CPUs the workers already use (a process started without OPENBLAS_NUM_THREADS=1).
    from threadpoolctl import threadpool_info, threadpool_limits
    import gls_calibration.correction.setpoints as correction_module

    def blas_threads() -> list[int]:
        return [info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"]

    monkeypatch.setattr(correction_module, "_shared_pool", [])      # the pool starts in this test
    with threadpool_limits(limits=2, user_api="blas"):
        if set(blas_threads()) != {2}:
            pytest.skip(f"BLAS here cannot run on two threads: {blas_threads()}")
        correction = Correction(GEOMETRY, [first_model], REGION)
        x = np.linspace(-100.0, 100.0, 20_000)
        correction.correct(x, x[::-1], workers=1)
        assert set(blas_threads()) == {2}               # nothing shared, nothing changed
        correction.correct(x, x[::-1], workers=2)
        assert set(blas_threads()) == {1}


@pytest.mark.parametrize("workers", [0, -1, 1.5, True])
def test_correct_rejects_a_bad_number_of_workers(workers):
    with pytest.raises(ValueError, match=f"workers must be an integer >= 1, got {workers!r}"):
        Correction(GEOMETRY).correct([0.0], [0.0], workers=workers)


def test_correct_rejects_bad_coordinates():
    with pytest.raises(ValueError, match="x and y must have the same length"):
        Correction(GEOMETRY).correct([0.0, 1.0], [0.0])
    with pytest.raises(ValueError, match="calibrated region is empty"):
        CalibratedRegion(1.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize("with_model", [False, True])
@pytest.mark.parametrize("z", [[490.0], [0.0, 490.0], [1e308], [-490.0]])
def test_correct_rejects_heights_at_or_beyond_the_working_distance(first_model, with_model, z):
    # At the mirrors' height the ray transfer divided by zero; far beyond it the focus shift was inf.
    correction = Correction(GEOMETRY, [first_model], REGION) if with_model else Correction(GEOMETRY)
    first = next(index for index, value in enumerate(z) if abs(value) >= 490.0)
    message = (f"z must lie within +-490 mm (the head's working distance): 1 target(s) outside, "
               f"first z = {z[first]:g} mm at index {first}")
    with pytest.raises(ValueError, match=re.escape(message)):
        correction.correct([10.0] * len(z), [10.0] * len(z), z)
