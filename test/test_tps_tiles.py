"""Tests of the tiled thin-plate kernel sum: accuracy against the exact sum, the box, the fallback."""
import numpy as np
import pytest

from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.models import tps_tiles
from gls_calibration.models.rbf import TILED_MIN_ROWS, ThinPlateSplineModel

GRID = grid_targets()


def wavy_field(points):
    """A smooth ~1 mm field with short-wave structure, so the weights are not small."""
    x, y = points[:, 0] / 95.0, points[:, 1] / 95.0
    return np.column_stack([0.6 * np.sin(3.0 * x) + 0.2 * x * y, 0.4 * np.cos(2.5 * y) * x + 0.1 * y ** 3])


@pytest.fixture(scope="module")
def spline():
    noise = np.random.default_rng(3).normal(0.0, 0.02, GRID.shape)
    return ThinPlateSplineModel(GRID, wavy_field(GRID) + noise)


def kernel_formula(spline, points):
    """The spline's kernel sum straight from its formula, sum_i w_i r^2 ln r."""
    squared = np.sum((points[:, None, :] - spline.centres) ** 2, axis=2)
    return (0.5 * squared * np.log(np.where(squared > 0.0, squared, 1.0))) @ spline.weights


def test_tiles_agree_with_the_exact_sum_everywhere_in_the_box(spline):
    evaluator = tps_tiles.build(spline.centres, 0.5 * spline.weights)
    assert evaluator is not None
    rng = np.random.default_rng(4)
    low, high = evaluator.origin, evaluator.origin + evaluator.tiles * evaluator.tile_size
    edges = low + np.arange(evaluator.tiles)[:, None] * evaluator.tile_size        # tiles' lower edges
    along_edges = np.column_stack([np.repeat(edges[:, 0], 50), np.tile(rng.uniform(low[1], high[1], 50),
                                                                       evaluator.tiles)])
    points = np.vstack([GRID, rng.uniform(low, high, (20_000, 2)), along_edges, along_edges[:, ::-1],
                        low + 1e-12, np.nextafter(high, low)])
    assert evaluator.inside(points).all()
    np.testing.assert_allclose(evaluator(points), kernel_formula(spline, points), rtol=0.0,
                               atol=tps_tiles.TOLERANCE_MM)


def test_a_large_batch_through_the_tiles_matches_the_exact_spline_inside_and_outside_the_box(spline):
    rng = np.random.default_rng(5)
    points = rng.uniform(-130.0, 130.0, (3 * TILED_MIN_ROWS, 2))        # about a third beyond the box
    expected = kernel_formula(spline, points) + spline.affine[0] + points @ spline.affine[1:]
    assert spline._tiled() is not None
    np.testing.assert_allclose(spline(points), expected, rtol=0.0, atol=tps_tiles.TOLERANCE_MM)


def test_a_targets_value_does_not_depend_on_the_rest_of_the_batch(spline):
    rng = np.random.default_rng(6)
    points = rng.uniform(-95.0, 95.0, (2 * TILED_MIN_ROWS, 2))
    whole = spline(points)
    shuffled = rng.permutation(points.shape[0])
    np.testing.assert_array_equal(spline(points[shuffled]), whole[shuffled])
    np.testing.assert_array_equal(spline(points[:TILED_MIN_ROWS]), whole[:TILED_MIN_ROWS])


def test_an_evaluator_that_fails_its_check_is_not_built_and_the_spline_stays_exact(spline, monkeypatch):
    # Degree 2 cannot follow the far field to 1e-10 mm: the check must refuse it.
    assert tps_tiles.build(spline.centres, 0.5 * spline.weights, degree=2) is None
    refused = ThinPlateSplineModel.from_dict(spline.to_dict())
    monkeypatch.setattr(tps_tiles, "DEGREE", 2)
    monkeypatch.setattr(tps_tiles.build, "__defaults__", (tps_tiles.TILES, 2))
    points = np.random.default_rng(7).uniform(-95.0, 95.0, (TILED_MIN_ROWS, 2))
    values = refused(points)
    assert refused._tiled() is None
    expected = kernel_formula(spline, points) + spline.affine[0] + points @ spline.affine[1:]
    np.testing.assert_allclose(values, expected, rtol=0.0, atol=5e-12)


@pytest.mark.parametrize("centres", [np.column_stack([np.linspace(0.0, 10.0, 20), np.zeros(20)]),
                                     np.zeros((3, 2))])
def test_centres_that_span_no_area_get_no_evaluator(centres):
    assert tps_tiles.build(centres, np.ones((centres.shape[0], 2))) is None


def test_a_correction_prepares_its_splines_tiles_before_the_first_large_request():
    from gls_calibration.correction.setpoints import CalibratedRegion, Correction
    from gls_calibration.geometry.kinematics import HeadGeometry

    spline = ThinPlateSplineModel(GRID, wavy_field(GRID))
    correction = Correction(HeadGeometry(), [spline], CalibratedRegion.from_points(GRID))
    assert spline._tiles is None                   # loading builds nothing
    correction.prepare()
    assert spline._tiles is not None and spline._tiles[0] is not None


def test_a_spline_with_its_tiles_built_survives_pickling(spline):
    import pickle

    points = np.random.default_rng(8).uniform(-95.0, 95.0, (TILED_MIN_ROWS, 2))
    values = spline(points)
    assert spline._tiles is not None
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(spline))(points), values)
