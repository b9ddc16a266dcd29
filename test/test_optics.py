"""Tests of the physical head model (vector ray trace with named effects)."""
import math

import numpy as np
import pytest

from gls_calibration.geometry.effect_table import EFFECT_TABLE
from gls_calibration.geometry.kinematics import HeadGeometry, forward, inverse
from gls_calibration.geometry.optics import (EFFECTS, HeadEffects, PhysicalHead, effect_names, parameter_count,
                                             parameter_labels)

GEOMETRY = HeadGeometry()
LIMIT = GEOMETRY.mirror_limit_rad


def field_angles(per_side: int = 21, limit: float = LIMIT) -> tuple[np.ndarray, np.ndarray]:
    """Mechanical angles on a square grid over the whole field."""
    angles = np.linspace(-limit, limit, per_side)
    alpha_x, alpha_y = np.meshgrid(angles, angles)
    return alpha_x.ravel(), alpha_y.ravel()


def displacement(effects: dict, t=None) -> tuple[np.ndarray, np.ndarray]:
    """Nominal landing points (N, 3) and their displacement (N, 3) caused by ``effects``."""
    alpha_x, alpha_y = field_angles()
    nominal = PhysicalHead(GEOMETRY).land(alpha_x, alpha_y)
    moved = PhysicalHead(GEOMETRY, effects).land(alpha_x, alpha_y, t)
    return nominal, moved - nominal


def test_zero_effects_equal_nominal_forward_over_the_field():
    alpha_x, alpha_y = field_angles(41)
    landed = PhysicalHead(GEOMETRY).land(alpha_x, alpha_y)
    x, y = forward(GEOMETRY, alpha_x, alpha_y)
    assert np.abs(landed[:, 0] - x).max() < 1e-6
    assert np.abs(landed[:, 1] - y).max() < 1e-6
    assert np.abs(landed[:, 2]).max() < 1e-9
    # explicit zeros are the same as no effects
    zeros = {name: (0.0,) * len(parameters) for name, parameters in EFFECTS.items()}
    assert np.array_equal(PhysicalHead(GEOMETRY, zeros).land(alpha_x, alpha_y), landed)


def test_sign_conventions_positive_angles_give_positive_coordinates():
    head = PhysicalHead(GEOMETRY)
    along_x = head.land(0.05, 0.0)[0]
    along_y = head.land(0.0, 0.05)[0]
    assert along_x[0] > 40.0 and abs(along_x[1]) < 1e-9
    assert along_y[1] > 40.0 and abs(along_y[0]) < 1e-9


def test_traced_path_length_gives_the_focus_shift_formula():
    geometry = HeadGeometry(working_distance_mm=400.0, mirror_distance_mm=22.0)
    alpha_x, alpha_y = field_angles(25)
    head = PhysicalHead(geometry)
    x, y = forward(geometry, alpha_x, alpha_y)
    expected = inverse(geometry, x, y).focus_shift
    traced = head.path_length(alpha_x, alpha_y) - (geometry.mirror_distance_mm + geometry.working_distance_mm)
    assert np.abs(traced - expected).max() < 1e-6
    assert np.allclose(head.focus_path_length(alpha_x, alpha_y), expected, atol=1e-6)
    assert expected.max() > 5.0     # the check is not vacuous


def test_galvo_gain_x_scales_x_only():
    nominal, moved = displacement({"galvo_gain_x": 0.01})
    # x grows outwards in proportion to x; y barely moves
    outer = np.abs(nominal[:, 0]) > 10.0
    ratio = moved[outer, 0] / nominal[outer, 0]
    assert np.all(ratio > 0.009) and np.all(ratio < 0.012)
    # y = (e + d / cos(theta_x)) tan(theta_y) feels theta_x only through 1/cos: small and even in x
    assert np.abs(moved[:, 1]).max() < 0.15 * np.abs(moved[:, 0]).max()
    on_axes = (np.abs(nominal[:, 0]) < 1e-9) | (np.abs(nominal[:, 1]) < 1e-9)
    assert np.abs(moved[on_axes, 1]).max() < 1e-9


def test_galvo_gain_y_scales_y_only():
    nominal, moved = displacement({"galvo_gain_y": -0.01})
    outer = np.abs(nominal[:, 1]) > 10.0
    ratio = moved[outer, 1] / nominal[outer, 1]
    assert np.all(ratio < -0.009) and np.all(ratio > -0.012)
    assert np.abs(moved[:, 0]).max() < 1e-9


@pytest.mark.parametrize("name, axis", [("galvo_offset_x", 0), ("galvo_offset_y", 1)])
def test_galvo_offsets_shift_the_field(name, axis):
    _, moved = displacement({name: 1e-3})
    expected = 2.0 * GEOMETRY.working_distance_mm * 1e-3     # optical angle is twice the mechanical
    assert np.all(moved[:, axis] > 0.9 * expected)
    assert np.all(moved[:, axis] < 1.3 * expected)
    assert np.std(moved[:, axis]) < 0.1 * expected


def test_working_distance_scales_both_axes_radially():
    nominal, moved = displacement({"working_distance": 5.0})
    assert np.allclose(moved[:, 2], -5.0)
    outer = np.hypot(nominal[:, 0], nominal[:, 1]) > 20.0
    planar, position = moved[outer, :2], nominal[outer, :2]
    cosine = np.einsum("ij,ij->i", planar, position) / (
        np.linalg.norm(planar, axis=1) * np.linalg.norm(position, axis=1))
    assert np.all(cosine > 0.999)
    relative = np.linalg.norm(planar, axis=1) / np.linalg.norm(position, axis=1)
    assert np.all(np.abs(relative - 5.0 / GEOMETRY.working_distance_mm) < 0.0015)


def test_mirror_distance_changes_y_only():
    nominal, moved = displacement({"mirror_distance": 3.0})
    assert np.abs(moved[:, 0]).max() < 1e-9
    # y = (e + ...) tan(theta_y): the change is 3 mm * tan(theta_y) = 3 mm * y / (e + d/cos)
    assert np.abs(moved[:, 1]).max() > 0.15
    assert np.all(np.sign(moved[np.abs(nominal[:, 1]) > 1.0, 1])
                  == np.sign(nominal[np.abs(nominal[:, 1]) > 1.0, 1]))


def test_axis_skew_shears_y_with_x():
    # the X mirror axis leans out of perpendicular to the Y mirror axis: turning the X mirror
    # also deflects in y, so y moves with x (a shear), nearly whatever y is, and x stays put
    nominal, moved = displacement({"axis_skew": 2e-3})
    grid_x = nominal[:, 0].reshape(21, 21)
    grid_dy = moved[:, 1].reshape(21, 21)          # rows: alpha_y, columns: alpha_x
    assert np.abs(grid_dy[:, 10]).max() < 1e-9     # no change on the x = 0 column
    assert np.all(np.sign(grid_dy[:, 15:]) == np.sign(grid_dy[0, -1]))
    assert np.all(np.sign(grid_dy[:, :6]) == -np.sign(grid_dy[0, -1]))
    slope = np.polyfit(grid_x.ravel(), grid_dy.ravel(), 1)[0]
    assert abs(slope) > 0.5 * 2e-3
    # the shear varies far more across x than across y
    assert np.ptp(grid_dy, axis=0).max() < 0.1 * np.ptp(grid_dy)
    assert np.abs(moved[:, 0]).max() < 0.4 * np.abs(moved[:, 1]).max()   # x only feels it via the y tilt of the beam


def test_plate_tilt_gives_a_keystone():
    nominal, moved = displacement({"plate_tilt": (0.02, 0.0)})
    # tilting about x brings the +y side nearer to the head: x scale depends on y
    outer = np.abs(nominal[:, 0]) > 20.0
    x_scale = moved[outer, 0] / nominal[outer, 0]
    slope = np.polyfit(nominal[outer, 1], x_scale, 1)[0]
    assert slope < -1e-5
    assert np.ptp(x_scale) > 1e-3
    # the landing points lie on the tilted plane
    head = PhysicalHead(GEOMETRY, {"plate_tilt": (0.02, 0.0)})
    landed = nominal + moved
    assert np.abs((landed - head.plate_origin) @ head.plate_normal).max() < 1e-9


def test_radial_distortion_is_radial_and_cubic():
    k1 = 1e-7
    nominal, moved = displacement({"radial_distortion": k1})
    radius = np.hypot(nominal[:, 0], nominal[:, 1])
    assert np.allclose(np.linalg.norm(moved, axis=1), k1 * radius ** 3, rtol=1e-9, atol=1e-12)
    assert np.allclose(moved[:, :2], nominal[:, :2] * (k1 * radius ** 2)[:, None], atol=1e-12)


def test_thermal_drift_is_zero_at_time_zero_and_grows_with_time():
    effects = {"thermal_drift": (1e-5, 1e-6)}
    _, at_zero = displacement(effects, t=0.0)
    _, at_ten = displacement(effects, t=10.0)
    _, at_hundred = displacement(effects, t=100.0)
    assert np.abs(at_zero).max() == 0.0
    assert 0.0 < np.abs(at_ten).max() < np.abs(at_hundred).max()
    assert np.abs(at_hundred).max() == pytest.approx(10.0 * np.abs(at_ten).max(), rel=0.02)
    # a time per point works too
    alpha_x, alpha_y = field_angles()
    per_point = PhysicalHead(GEOMETRY, effects).land(alpha_x, alpha_y, np.full(alpha_x.size, 10.0))
    scalar = PhysicalHead(GEOMETRY, effects).land(alpha_x, alpha_y, 10.0)
    assert np.array_equal(per_point, scalar)


@pytest.mark.parametrize("name", ["mirror_offset", "beam_tilt"])
def test_remaining_effects_move_the_marks_smoothly(name):
    values = (0.5, 0.5) if name == "mirror_offset" else (1e-3, 1e-3)
    _, moved = displacement({name: values})
    size = np.linalg.norm(moved[:, :2], axis=1)
    assert size.max() > 0.05
    # smooth: neighbouring grid points move alike
    grid = moved[:, :2].reshape(21, 21, 2)
    assert np.abs(np.diff(grid, axis=0)).max() < 0.2 * size.max()


def test_metadata_tables_cover_every_effect():
    assert effect_names() == tuple(EFFECTS)
    for name, parameters in EFFECTS.items():
        spec = EFFECT_TABLE[name]
        assert spec.parameter_names == parameters and len(spec.units) == len(parameters)
        assert spec.doc
        for parameter in spec.parameters:   # the typical size is itself plausible
            assert parameter.low < 0.0 < parameter.high
            assert parameter.per_run or parameter.plausible(parameter.typical)
    assert parameter_count(["mirror_offset", "galvo_gain_x"]) == 3
    assert parameter_labels(["beam_tilt"]) == ("beam_tilt.tilt_a_rad", "beam_tilt.tilt_b_rad")


def test_vector_round_trip_and_missing_effects_are_zero():
    names = ["thermal_drift", "galvo_gain_x", "plate_tilt"]
    vector = np.array([1e-5, 2e-6, 0.01, 0.003, -0.002])
    effects = HeadEffects.from_vector(names, vector)
    assert effects.get("plate_tilt") == (0.003, -0.002)
    assert np.array_equal(effects.to_vector(names), vector)
    assert np.array_equal(effects.to_vector(["axis_skew", "galvo_gain_x"]), [0.0, 0.01])
    assert effects == HeadEffects({**effects.values, "axis_skew": 0.0})
    assert effects.replace(galvo_gain_x=0.02).get("galvo_gain_x") == (0.02,)
    assert "galvo_gain_x" not in effects.without("galvo_gain_x").values


def test_unknown_effect_is_rejected():
    with pytest.raises(ValueError, match="unknown effect 'lens_wobble'; known effects: mirror_distance"):
        HeadEffects({"lens_wobble": 1.0})
    with pytest.raises(ValueError, match="unknown effect 'lens_wobble'"):
        PhysicalHead(GEOMETRY, {"lens_wobble": 1.0})
    with pytest.raises(ValueError, match="unknown effect 'foo'"):
        HeadEffects.from_vector(["foo"], [1.0])


def test_wrong_parameter_counts_are_rejected():
    with pytest.raises(ValueError,
                       match=r"effect 'plate_tilt' takes 2 parameter\(s\) \(tilt_x_rad, tilt_y_rad\), got 1"):
        HeadEffects({"plate_tilt": 0.01})
    with pytest.raises(ValueError, match=r"effect 'galvo_gain_x' takes 1 parameter\(s\)"):
        HeadEffects({"galvo_gain_x": (0.01, 0.02)})
    with pytest.raises(ValueError, match=r"vector must hold 3 value\(s\)"):
        HeadEffects.from_vector(["galvo_gain_x", "beam_tilt"], [0.1, 0.2])
    with pytest.raises(ValueError, match="effect 'axis_skew' contains 1 NaN"):
        HeadEffects({"axis_skew": math.nan})


def test_bad_angle_inputs_are_rejected():
    head = PhysicalHead(GEOMETRY)
    with pytest.raises(ValueError, match="alpha_x and alpha_y must be 1-D arrays of the same length"):
        head.land([0.0, 0.1], [0.0])
    with pytest.raises(ValueError, match="t must be a scalar or have the length of alpha_x"):
        head.land([0.0, 0.1], [0.0, 0.1], t=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="alpha_y contains 1 NaN"):
        head.land([0.0], [math.nan])


def test_plate_coordinates_round_trip():
    head = PhysicalHead(GEOMETRY, {"plate_tilt": (0.01, -0.02), "working_distance": 2.0})
    uv = np.random.default_rng(3).uniform(-100, 100, (50, 2))
    points = head.from_plate(uv)
    assert np.abs((points - head.plate_origin) @ head.plate_normal).max() < 1e-9
    assert np.allclose(head.to_plate(points), uv, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_the_rotation_of_a_mirror_normal_is_rodrigues_with_numpys_cross_product(seed):
    """_rotate's written-out cross product gives np.cross's numbers, bit for bit."""
    from gls_calibration.geometry.optics import _rotate

    rng = np.random.default_rng(seed)
    for _ in range(50):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        vector, angle = rng.normal(size=3), rng.uniform(-0.5, 0.5, 7)
        cos, sin = np.cos(angle), np.sin(angle)
        expected = (vector[:, None] * cos + np.cross(axis, vector)[:, None] * sin
                    + (axis * np.dot(axis, vector))[:, None] * (1.0 - cos))
        assert _rotate(vector, axis, angle).tobytes() == expected.tobytes()


def test_effects_given_as_float_tuples_are_taken_as_they_are_and_land_as_before():
    """The fits' fast path (float tuples, angles checked once) lands exactly where the checked path does."""
    values = {"galvo_gain_x": (0.004,), "mirror_offset": (0.2, -0.1), "plate_tilt": (0.003, -0.002)}
    fast = HeadEffects(values)
    assert fast == HeadEffects({name: list(value) for name, value in values.items()})
    assert fast.values["mirror_offset"] == (0.2, -0.1)
    for bad, problem in (({"galvo_gain_x": (math.nan,)}, "NaN or infinite"), ({"mirror_offset": (0.1,)}, "takes 2"),
                         ({"no_such_effect": (0.1,)}, "unknown effect")):
        with pytest.raises(ValueError, match=problem):
            HeadEffects(bad)
    alpha_x, alpha_y = field_angles(7)
    head = PhysicalHead(GEOMETRY, fast)
    landed = head.land_checked(*PhysicalHead.checked_angles(alpha_x, alpha_y, 2.0))
    assert np.array_equal(landed, head.land(alpha_x, alpha_y, 2.0))
    with pytest.raises(ValueError, match="alpha_x contains 1 NaN"):
        PhysicalHead.checked_angles(np.array([math.nan]), np.array([0.0]))
