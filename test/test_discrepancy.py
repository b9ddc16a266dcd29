"""Discrepancy workflow on data from the truth head (optics.PhysicalHead with hidden effects)."""
import json
import math

import numpy as np
import pytest

from gls_calibration.discrepancy import (
    align_rigid_2d, estimate_noise_floor, explain, fit_effects, observability_report, physical_prediction,
    structure_test)
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import EFFECTS, PhysicalHead

GEOMETRY = HeadGeometry()
AXIS = np.linspace(-95.0, 95.0, 19)
TARGETS = np.column_stack([np.meshgrid(AXIS, AXIS)[0].ravel(), np.meshgrid(AXIS, AXIS)[1].ravel()])
MARKING_TIME = np.arange(len(TARGETS)) * 1.0     # 1 s per mark, row-major


def rotation(angle):
    return np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])


def measure(effects, seed, noise_mm=0.015, t=None, targets=TARGETS):
    """Marks of the truth head for the nominal commands, with noise, in a randomly moved frame."""
    rng = np.random.default_rng(seed)
    joints = inverse(GEOMETRY, targets[:, 0], targets[:, 1])
    landed = PhysicalHead(GEOMETRY, effects).land(joints.alpha_x, joints.alpha_y, t)[:, :2]
    landed = landed + rng.normal(0.0, noise_mm, landed.shape)
    return landed @ rotation(rng.uniform(-math.pi, math.pi)).T + rng.uniform(-60.0, 60.0, 2)


def found(result, name):
    """Named alone, named in a group the data cannot split, or reported as indistinguishable from the one named."""
    return (name in result.named_effects or any(name in group for group in result.named_groups)
            or any(name in step.indistinguishable_from for step in result.steps))


# one observable defect each, sized to leave 0.2-0.35 mm RMS after rigid alignment (>= 10x the noise
# floor at 0.01 mm per axis, so a 90 % shrink of the gap is possible)
SINGLE_DEFECTS = [
    ("mirror_distance", [2.0]),
    ("working_distance", [2.0]),
    ("galvo_gain_x", [5e-3]),
    ("galvo_gain_y", [-5e-3]),
    ("galvo_offset_x", [0.012]),
    ("galvo_offset_y", [-0.015]),
    ("axis_skew", [1e-2]),
    ("mirror_offset", [1.0, 1.0]),
    ("beam_tilt", [0.02, 0.02]),
    ("plate_tilt", [0.015, -0.015]),
    ("radial_distortion", [3e-7]),
]


def test_align_rigid_2d_recovers_a_rigid_motion():
    rng = np.random.default_rng(1)
    source = rng.uniform(-100, 100, (50, 2))
    target = source @ rotation(2.5).T + np.array([30.0, -7.0])
    alignment, moved = align_rigid_2d(source, target)
    assert moved == pytest.approx(target, abs=1e-9)
    assert alignment.apply(source) == pytest.approx(target, abs=1e-9)
    assert alignment.rotation_rad == pytest.approx(2.5)


@pytest.mark.parametrize("structured", [False, True])
def test_noise_floor_estimates_the_noise_with_or_without_structure(structured):
    sigma = 0.02
    for seed in range(5):
        rng = np.random.default_rng(seed)
        residual = rng.normal(0.0, sigma, TARGETS.shape)
        if structured:   # smooth field of 0.5 mm, as a physical effect leaves
            residual += 0.5 * np.column_stack([(TARGETS[:, 0] / 95) ** 3, TARGETS[:, 0] * TARGETS[:, 1] / 95 ** 2])
        noise = estimate_noise_floor(TARGETS, residual)
        assert noise.sigma_axis_mm == pytest.approx(sigma, rel=0.12)
        assert noise.noise_floor_mm == pytest.approx(math.sqrt(2) * noise.sigma_axis_mm)
        test = structure_test(TARGETS, residual, noise)
        assert test.is_structure == structured


def test_no_defect_names_nothing_in_at_least_19_of_20_seeds():
    named = [explain(TARGETS, measure({}, seed, noise_mm=0.02), GEOMETRY).named_effects for seed in range(20)]
    assert sum(1 for names in named if names) <= 1
    result = explain(TARGETS, measure({}, 99), GEOMETRY)
    assert result.rms_after_mm == result.rms_before_mm
    assert result.rms_before_mm <= 1.2 * result.noise_floor_mm


@pytest.mark.parametrize("name,values", SINGLE_DEFECTS, ids=[name for name, _ in SINGLE_DEFECTS])
def test_single_defect_is_named_and_explains_the_gap(name, values):
    result = explain(TARGETS, measure({name: values}, seed=7, noise_mm=0.01), GEOMETRY)
    assert 0.15 <= result.rms_before_mm <= 1.0
    assert found(result, name), (result.named_effects, [s.indistinguishable_from for s in result.steps])
    first = result.steps[0]
    assert first.rms_after_mm <= 0.2 * result.rms_before_mm          # >= 80 % in one step
    assert result.rms_after_mm <= 0.1 * result.rms_before_mm         # >= 90 % at the end
    assert result.rms_after_mm <= 1.5 * result.noise_floor_mm
    assert not result.structure_after.is_structure
    if result.named_effects == (name,):
        fitted = [result.model_effects.get(name)[i] for i in range(len(values))]
        assert fitted == pytest.approx(values, rel=0.05, abs=5 * max(result.model_uncertainty[name]))


def test_confusable_single_defect_is_reported_with_its_look_alike():
    # mirror distance only scales y, as a Y gain does: the workflow must not pretend to know which
    result = explain(TARGETS, measure({"mirror_distance": [1.0]}, seed=3), GEOMETRY)
    step = result.steps[0]
    assert {step.name, *step.indistinguishable_from} >= {"mirror_distance", "galvo_gain_y"}
    assert any("indistinguishable" in note for note in result.notes)


@pytest.mark.parametrize("defects", [
    {"working_distance": [1.5], "radial_distortion": [2e-7]},
    {"galvo_gain_x": [3e-3], "axis_skew": [8e-3]},
    {"mirror_distance": [2.0], "plate_tilt": [0.01, 0.005]},
    {"galvo_gain_x": [2e-3], "galvo_gain_y": [-2e-3]},
], ids=lambda defects: "+".join(defects))
def test_pairs_of_defects_are_both_found(defects):
    result = explain(TARGETS, measure(defects, seed=11, noise_mm=0.01), GEOMETRY)
    for name in defects:
        assert found(result, name), (name, result.named_effects)
    assert result.rms_after_mm <= 1.5 * result.noise_floor_mm
    assert result.rms_after_mm <= 0.1 * result.rms_before_mm
    assert result.gap_per_step_mm == tuple(sorted(result.gap_per_step_mm, reverse=True))


@pytest.mark.parametrize("order", ["raster", "shuffled"])
def test_thermal_drift_is_found_with_marking_time_only(order):
    defects = {"thermal_drift": [5e-6, 5e-6]}
    t = MARKING_TIME if order == "raster" else np.random.default_rng(3).permutation(MARKING_TIME)
    measured = measure(defects, seed=5, t=t)
    with_time = explain(TARGETS, measured, GEOMETRY, t=t)
    assert with_time.named_effects[0] == "thermal_drift"
    assert with_time.rms_after_mm <= 1.5 * with_time.noise_floor_mm
    rates = with_time.model_effects.get("thermal_drift")
    assert rates == pytest.approx((5e-6, 5e-6), rel=0.05)
    if order == "shuffled":     # time separable from position: the location test sees it
        assert with_time.location_before.time_p_value < 1e-3
        assert with_time.location_after.time_p_value > 1e-3
    else:                       # raster order: time is linear in position, the location test says so
        assert with_time.location_before.time_p_value is None
        assert any("raster" in finding for finding in with_time.location_before.findings)
        assert any("Marking time follows the position" in note for note in with_time.notes)
    without_time = explain(TARGETS, measured, GEOMETRY)
    assert "thermal_drift" not in without_time.named_effects


def test_known_effects_are_part_of_the_model():
    measured = measure({"galvo_gain_x": [3e-3]}, seed=2)
    result = explain(TARGETS, measured, GEOMETRY, known_effects={"galvo_gain_x": [3e-3]})
    assert result.named_effects == ()
    assert result.rms_before_mm <= 1.2 * result.noise_floor_mm


def test_result_does_not_depend_on_the_measured_frame():
    measured = measure({"radial_distortion": [2e-7]}, seed=4)
    moved = measured @ rotation(1.0).T + np.array([-200.0, 35.0])
    a = explain(TARGETS, measured, GEOMETRY)
    b = explain(TARGETS, moved, GEOMETRY)
    assert a.named_effects == b.named_effects
    assert a.rms_after_mm == pytest.approx(b.rms_after_mm, rel=1e-6)
    assert a.residual_after_xy == pytest.approx(b.residual_after_xy, abs=1e-6)


def test_physical_prediction_leaves_the_final_residual():
    measured = measure({"working_distance": [1.5], "radial_distortion": [2e-7]}, seed=8)
    result = explain(TARGETS, measured, GEOMETRY)
    predicted = physical_prediction(result, TARGETS)
    aligned = result.alignment_after.apply(measured)
    assert aligned - predicted == pytest.approx(result.residual_after_xy, abs=1e-9)


def test_fit_effects_recovers_noise_free_parameters():
    truth = {"mirror_offset": [0.8, -0.4], "plate_tilt": [0.004, 0.006]}
    joints = inverse(GEOMETRY, TARGETS[:, 0], TARGETS[:, 1])
    measured = PhysicalHead(GEOMETRY, truth).land(joints.alpha_x, joints.alpha_y)[:, :2] @ rotation(0.3).T + 5.0
    fit = fit_effects(TARGETS, measured, GEOMETRY, ["mirror_offset", "plate_tilt"], sigma_axis_mm=0.01)
    assert fit.vector == pytest.approx([0.8, -0.4, 0.004, 0.006], rel=1e-4)
    assert fit.rms_mm < 1e-6
    assert fit.alignment.rotation_rad == pytest.approx(-0.3, abs=1e-9)
    assert all(value > 0 for value in fit.uncertainty("plate_tilt").values())


def test_to_dict_is_json_with_the_contract_keys():
    result = explain(TARGETS, measure({"axis_skew": [4e-3]}, seed=1), GEOMETRY)
    document = json.loads(json.dumps(result.to_dict()))
    for key in ("named_effects", "effects", "rms_before_mm", "rms_after_mm", "noise_floor_mm"):
        assert key in document
    step = document["effects"][0]
    for key in ("name", "parameters", "uncertainty", "indistinguishable_from", "rms_after_mm"):
        assert key in step
    assert set(step["parameters"]) == set(EFFECTS[step["name"]])
    assert document["named_effects"] == ["axis_skew"]


def test_observability_report_finds_rigid_like_and_confusable_effects():
    report = observability_report(GEOMETRY)
    kept = {(effect, parameter): aligned / raw for effect, parameter, _, raw, aligned in report.parameters}
    for key in [("galvo_offset_x", "offset_x_rad"), ("galvo_offset_y", "offset_y_rad"),
                ("beam_tilt", "tilt_a_rad"), ("beam_tilt", "tilt_b_rad")]:
        assert kept[key] < 0.05            # mostly a shift / rotation of the whole field
    for key in [("galvo_gain_x", "gain_error_x"), ("working_distance", "delta_d_mm"),
                ("radial_distortion", "k1_per_mm2")]:
        assert kept[key] > 0.95            # a scale or distortion survives alignment
    pairs = {(a, b) for a, b, _ in report.confusable_pairs(0.99)}
    assert ("mirror_distance", "galvo_gain_y") in pairs
    assert ("galvo_offset_x", "plate_tilt") in pairs
    assert ("galvo_gain_x", "galvo_gain_y") not in pairs
    assert np.allclose(report.similarity, report.similarity.T)
    assert "confusable" in report.summary()


@pytest.mark.parametrize("kwargs,message", [
    ({"commanded_xy": TARGETS[:9], "measured_xy": TARGETS[:9]}, r"commanded_xy must hold at least 10 point"),
    ({"measured_xy": TARGETS[:20]}, r"measured_xy must have the shape of commanded_xy"),
    ({"measured_xy": np.where(np.arange(361)[:, None] == 3, np.nan, TARGETS)}, r"measured_xy contains 2 NaN"),
    ({"t": np.zeros(5)}, r"t must hold one marking time per point \(361\), got 5"),
    ({"known_effects": {"lens_wobble": [1.0]}}, r"unknown effect 'lens_wobble'"),
    ({"candidates": ["galvo_gain_x", "wobble"]}, r"unknown effect 'wobble'"),
    ({"criterion": "dic"}, r"criterion must be one of bic, aic, got 'dic'"),
])
def test_bad_input_is_rejected(kwargs, message):
    arguments = {"commanded_xy": TARGETS, "measured_xy": TARGETS.copy(), "geometry": GEOMETRY}
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=message):
        explain(**arguments)
