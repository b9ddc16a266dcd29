"""Issue 31 item 6: the discrepancy workflow names only what the data separate, and states its conventions.

Two generators of an axis skew: the project's ray trace (optics.PhysicalHead, the table's convention:
only the X galvo's axis tilts) and an independent ray trace written here in which the whole X galvo
(axis and mirror) is turned about the beam that reaches it.
"""
import math

import numpy as np
import pytest

from gls_calibration.cli.discrepancy import main
from gls_calibration.discrepancy import SEPARABLE_AT, explain, fit_effects, separability
from gls_calibration.discrepancy.fitting import Predictor
from gls_calibration.geometry.effect_table import EFFECT_TABLE
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import HeadEffects, PhysicalHead

GEOMETRY = HeadGeometry()
AXIS = np.linspace(-95.0, 95.0, 19)
TARGETS = np.column_stack([np.meshgrid(AXIS, AXIS)[0].ravel(), np.meshgrid(AXIS, AXIS)[1].ravel()])
NOISE_MM = 0.015


def moved(landed_xy, rng):
    """Noise, then a random rigid motion of the measured frame."""
    angle = rng.uniform(-math.pi, math.pi)
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return (landed_xy + rng.normal(0.0, NOISE_MM, landed_xy.shape)) @ rotation.T + rng.uniform(-50.0, 50.0, 2)


def optics_skew(skew_rad, seed):
    joints = inverse(GEOMETRY, TARGETS[:, 0], TARGETS[:, 1])
    landed = PhysicalHead(GEOMETRY, {"axis_skew": [skew_rad]}).land(joints.alpha_x, joints.alpha_y)[:, :2]
    return moved(landed, np.random.default_rng(seed))


def _turn(axis, angle, vectors):
    """Rodrigues: ``vectors`` (N, 3) turned by ``angle`` (N,) about the unit ``axis``."""
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return vectors * cos + np.cross(axis, vectors) * sin + np.outer(vectors @ axis, axis) * (1.0 - cos)


def _mirror(points, directions, pivot, normals):
    """Hit points on the mirror planes through ``pivot`` and the reflected directions."""
    reach = ((pivot - points) * normals).sum(1) / (directions * normals).sum(1)
    hits = points + reach[:, None] * directions
    return hits, directions - 2.0 * (directions * normals).sum(1)[:, None] * normals


def whole_galvo_skew(turn_rad, seed):
    """An independent trace: the whole X galvo (axis and mirror) turned by ``turn_rad`` about gls x,
    the beam between the mirrors; commands from the nominal inverse kinematics written out here."""
    e, d = GEOMETRY.mirror_distance_mm, GEOMETRY.working_distance_mm
    x, y = TARGETS[:, 0], TARGETS[:, 1]
    alpha_x = 0.5 * np.arctan2(x, d)
    alpha_y = 0.5 * np.arctan2(y, e + np.hypot(d, x))
    count = len(TARGETS)
    start = np.tile([-e, 0.0, d], (count, 1))
    beam = np.tile([0.0, 1.0, 0.0], (count, 1))
    y_normals = _turn(np.array([0.0, 0.0, 1.0]), alpha_y, np.tile([1.0, -1.0, 0.0], (count, 1)) / math.sqrt(2.0))
    hits, beam = _mirror(start, beam, np.array([-e, 0.0, d]), y_normals)
    c, s = math.cos(turn_rad), math.sin(turn_rad)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    x_axis = turn @ np.array([0.0, -1.0, 0.0])
    x_normal = turn @ (np.array([-1.0, 0.0, -1.0]) / math.sqrt(2.0))
    x_normals = _turn(x_axis, alpha_x, np.tile(x_normal, (count, 1)))
    hits, beam = _mirror(hits, beam, np.array([0.0, 0.0, d]), x_normals)
    landed = hits - (hits[:, 2] / beam[:, 2])[:, None] * beam
    return moved(landed[:, :2], np.random.default_rng(seed))


def test_the_independent_trace_is_the_nominal_head_when_nothing_is_turned():
    rng_free = whole_galvo_skew(0.0, seed=0)
    aligned = explain(TARGETS, rng_free, GEOMETRY, sigma_mm=NOISE_MM)
    assert aligned.named_effects == () and aligned.rms_before_mm < 1.5 * aligned.noise_floor_mm


@pytest.mark.parametrize("skew_rad", [1e-3, 3e-3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_axis_skew_of_the_table_convention_is_named_alone_with_its_size(skew_rad, seed):
    result = explain(TARGETS, optics_skew(skew_rad, seed), GEOMETRY, sigma_mm=NOISE_MM)
    assert result.named_effects == ("axis_skew",) and result.named_groups == ()
    fitted, = result.model_effects.get("axis_skew")
    assert abs(fitted - skew_rad) < 4.0 * result.model_uncertainty["axis_skew"][0]


@pytest.mark.parametrize("turn_rad", [1e-3, 3e-3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_whole_galvo_turn_names_the_skew_at_the_documented_factor_and_no_lone_offset(turn_rad, seed):
    # Issue 31: this named axis_skew AND galvo_offset_y (correlation -1.00 with a y shift) with a skew
    # twice the generator's and no word on why.
    result = explain(TARGETS, whole_galvo_skew(turn_rad, seed), GEOMETRY, sigma_mm=NOISE_MM)
    assert result.named_effects == ("axis_skew",)
    assert "galvo_offset_y" not in result.named_effects
    # what else the turn does is real (a few standard errors beyond the rigid motion) but looks the
    # same as a beam tilt: named as a group, never as a lone galvo offset
    for group in result.named_groups:
        assert len(group) >= 2 and set(group) <= {"galvo_offset_y", "beam_tilt"}
    fitted, = result.model_effects.get("axis_skew")
    assert fitted / turn_rad == pytest.approx(2.0, rel=0.05)          # the factor the table's doc states
    assert "skew_rad = 2 s" in EFFECT_TABLE["axis_skew"].doc


def test_z_is_the_fitted_size_over_its_standard_error_from_an_independent_joint_fit():
    # galvo_offset_y with beam_tilt also fitted: the linear z must match value / standard error of the
    # least-squares fit (scipy's Jacobian at its solution, a separate code path)
    data = optics_skew(3e-3, seed=4)
    fitted = fit_effects(TARGETS, data, GEOMETRY, ("axis_skew",), sigma_axis_mm=NOISE_MM)
    records = separability(Predictor(GEOMETRY, TARGETS, None), fitted, HeadEffects(), ("galvo_offset_y",), NOISE_MM)
    value, = fitted.parameters("axis_skew").values()
    error, = fitted.uncertainty("axis_skew").values()
    assert records[0].z == pytest.approx(abs(value) / error, rel=0.02)
    assert records[0].separable_from_rigid and records[0].group == ("axis_skew",)


def test_an_effect_the_rigid_motion_absorbs_is_not_named_and_look_alikes_form_a_group():
    predict = Predictor(GEOMETRY, TARGETS, None)
    # a galvo offset of 1e-5 rad is a 10 um shift: what survives the alignment is far below the noise
    tiny = moved(predict(HeadEffects({"galvo_offset_y": [1e-5]})), np.random.default_rng(5))
    fitted = fit_effects(TARGETS, tiny, GEOMETRY, ("galvo_offset_y",), sigma_axis_mm=NOISE_MM)
    record, = separability(predict, fitted, HeadEffects(), ("beam_tilt",), NOISE_MM)
    assert record.z_rigid < SEPARABLE_AT and not record.separable_from_rigid
    # a large one is separable from the rigid motion, not from a beam tilt
    large = moved(predict(HeadEffects({"galvo_offset_y": [-0.015]})), np.random.default_rng(6))
    fitted = fit_effects(TARGETS, large, GEOMETRY, ("galvo_offset_y",), sigma_axis_mm=NOISE_MM)
    record, = separability(predict, fitted, HeadEffects(), ("beam_tilt", "galvo_gain_x"), NOISE_MM)
    assert record.z_rigid > 100.0 and record.group == ("galvo_offset_y", "beam_tilt")
    assert record.z_with["beam_tilt"] < 1.0


def test_the_report_prints_each_fitted_effect_with_its_definition_and_status(tmp_path, capsys):
    data = whole_galvo_skew(3e-3, seed=1)
    csv_path = tmp_path / "marks.csv"
    csv_path.write_text("x_cmd,y_cmd,x_meas,y_meas\n" + "\n".join(
        f"{q[0]:.6f},{q[1]:.6f},{m[0]:.6f},{m[1]:.6f}" for q, m in zip(TARGETS, data)) + "\n")
    out = tmp_path / "out"
    assert main(["--measured", str(csv_path), "--out", str(out), "--sigma", str(NOISE_MM)]) == 0
    printed = capsys.readouterr().out
    assert "named effects: axis_skew and one of galvo_offset_y / beam_tilt;" in printed
    lines = (out / "report.md").read_text().splitlines()
    skew = next(i for i, line in enumerate(lines) if line.startswith("- **axis_skew** (named; z = "))
    assert lines[skew + 1].startswith("  - axis_skew.skew_rad = 0.00")
    assert lines[skew + 2] == f"  - definition: {EFFECT_TABLE['axis_skew'].doc}"
    assert "Convention: only the axis tilts" in lines[skew + 2]
    offset = next(i for i, line in enumerate(lines) if line.startswith("- **galvo_offset_y** (named as a group"))
    assert lines[offset + 2] == f"  - definition: {EFFECT_TABLE['galvo_offset_y'].doc}"
