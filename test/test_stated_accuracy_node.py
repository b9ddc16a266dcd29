"""The calibrate answer and the report state the accuracy on the basis of the reference check file.

A small cell (3x3 grid, one pass, one plain sweep) so that a calibration takes seconds.
"""
import json
import math

import numpy as np
import pytest

from gls_calibration.calibration.stated_accuracy import REFERENCE_BASIS, SELF_CONSISTENCY, ChainCheck, save_chain_check
from gls_calibration.registration.chain_map import ChainMap, LineMap, load_chain_map, save_chain_map
from gls_calibration_msgs.srv import Calibrate

CALIBRATE_TIMEOUT_S = 300.0
FAST = {"sweep.plain_repeats": 1, "sweep.plan": "0+"}


def check_file(tmp_path, plan="0+", extent_mm=(-96, 96, -96, 96)):
    path = tmp_path / "reference_check.yaml"
    # the cell's 3x3 grid spans +-95 mm (config/gls.yaml's grid.size_mm)
    save_chain_check(path, ChainCheck((0.03, 0.04), plan, "pose", "test plate", 143, extent_mm=extent_mm))
    return path


def test_a_validated_calibration_states_its_accuracy_from_the_check(start_cell, tmp_path):
    cell = start_cell(grid=3, parameters={**FAST, "reference_check_file": str(check_file(tmp_path))})
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=True), CALIBRATE_TIMEOUT_S)
    assert answer.success, answer.message
    assert answer.stated_basis == REFERENCE_BASIS
    assert answer.stated_rms_mm == pytest.approx(answer.post_rms_mm + 0.05)
    summary = json.loads((cell.report_dir / "summary.json").read_text())
    assert summary["stated_rms_mm"] == pytest.approx(answer.stated_rms_mm)
    assert summary["reference_sigma_mm"] == [0.03, 0.04] and summary["stated_basis"] == REFERENCE_BASIS
    report = (cell.report_dir / "report.md").read_text()
    assert f"Stated accuracy: {answer.stated_rms_mm:.4f} mm RMS" in report and "SELF-CONSISTENCY" in report


@pytest.mark.parametrize("plan, extent, reason", [
    ("0+,90+", (-96, 96, -96, 96), "does not describe this chain"),
    ("0+", (-90, 90, -96, 96), "end short of the calibrated targets (x -95.0..95.0, y -95.0..95.0 mm) at x min, "
                               "x max: the chain's error at the field's edge is not checked"),
])
def test_a_check_of_another_plan_or_a_smaller_plate_states_nothing(start_cell, tmp_path, plan, extent, reason):
    cell = start_cell(grid=3, parameters={**FAST, "reference_check_file": str(check_file(tmp_path, plan, extent))})
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=True), CALIBRATE_TIMEOUT_S)
    assert answer.success, answer.message
    assert math.isnan(answer.stated_rms_mm) and answer.stated_basis == SELF_CONSISTENCY
    report = (cell.report_dir / "report.md").read_text()
    assert "No accuracy is stated" in report and reason in report


def test_an_unreadable_check_refuses_the_run_before_anything_moves(start_cell, tmp_path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("reference_check: {sigma_mm: [0.03], plan: '0+', placement: pose, reference: p, centres: 9}\n")
    cell = start_cell(grid=3, parameters={**FAST, "reference_check_file": str(broken)})
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=True), CALIBRATE_TIMEOUT_S)
    assert not answer.success
    assert str(broken) in answer.message and "reference_check.sigma_mm" in answer.message
    assert math.isnan(answer.stated_rms_mm) and answer.stated_basis == SELF_CONSISTENCY
    assert not (cell.calibration_dir / "active.yaml").exists() and not list(cell.report_dir.glob("*.md"))


def zero_chain_map_file(tmp_path):
    """A chain map of line 0+ that is zero everywhere the sweeps reach: it changes no centre, only
    which map the run and its check must share."""
    path = tmp_path / "chain_map.yaml"
    line = LineMap("0+", -400.0, 50.0, np.zeros(17), np.zeros(17))
    save_chain_map(path, ChainMap((line,), reference="zero map", sweeps_per_line=1, residual_rms_mm=(0.0, 0.0)))
    return path


def test_a_chain_map_is_applied_and_a_check_made_without_it_states_nothing(start_cell, tmp_path):
    map_file = zero_chain_map_file(tmp_path)
    cell = start_cell(grid=3, parameters={**FAST, "reference_check_file": str(check_file(tmp_path)),
                                          "chain_map_file": str(map_file)})
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=True), CALIBRATE_TIMEOUT_S)
    assert answer.success, answer.message
    identity = load_chain_map(map_file).identity
    summary = json.loads((cell.report_dir / "summary.json").read_text())
    assert summary["chain_map"] == identity
    assert math.isnan(answer.stated_rms_mm) and answer.stated_basis == SELF_CONSISTENCY
    assert summary["stated_explanation"] == (f"the reference check was measured with chain map none, the "
                                             f"calibration with {identity}: it does not describe this chain")


def test_an_unreadable_chain_map_refuses_the_run_before_anything_moves(start_cell, tmp_path):
    broken = tmp_path / "broken_map.yaml"
    broken.write_text("chain_map: {reference: x}\n")
    cell = start_cell(grid=3, parameters={**FAST, "chain_map_file": str(broken)})
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=True), CALIBRATE_TIMEOUT_S)
    assert not answer.success
    assert answer.message.startswith("calibration failed: ") and str(broken) in answer.message
    assert not (cell.calibration_dir / "active.yaml").exists() and not list(cell.report_dir.glob("*.md"))
