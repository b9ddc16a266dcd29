"""The calibration manager's ``reference_check`` service scans the reference plate itself (issue 32).

The simulated cell's plate gets rings at known places by a calibration run (no validation: its
3 x 3 training plate stays on the bed); their true centres come from the simulated galvo's ground
truth (``sim/marked_paths``: where the marks landed, gls frame) and are written as the certificate.
The service then scans that plate with the calibration's plan and placement, as a real cell would
scan a certified plate, and writes the check the next calibration states its accuracy from.

One cell per preset: ``ideal`` (the check is micrometres) and ``paper_like`` (repeating robot error,
path wander, scanner noise: the check is many times larger). The core function the service runs,
``reference_check.scan_reference_check``, is also driven through ``DirectCell`` (no ROS) over a
5 x 5 plate of rings put at known places.
"""
from __future__ import annotations

import asyncio
import math
import threading

import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from gls_calibration.calibration.procedure import CalibrationError, true_fiducial_centres
from gls_calibration.calibration.reference_check import scan_reference_check
from gls_calibration.calibration.stated_accuracy import REFERENCE_BASIS, load_chain_check
from gls_calibration.fiducials.targets import RING_RADII_MM, rings_polylines
from gls_calibration.ros.conversions import marked_polylines
from gls_calibration_msgs.msg import CalibrationProgress
from gls_calibration_msgs.srv import Calibrate, GetMarkedPaths

from ros_helpers import running_cell, wait_for
from test_procedure import new_cell

CALIBRATE_TIMEOUT_S = 300.0
TIMEOUT_S = 10.0
FAST = {"sweep.plain_repeats": 1, "sweep.plan": "0+"}
GRID = 3
PLATE_NAME = "simulated plate, 3 x 3 rings of the first calibration"


def _set(cell, name: str, value) -> None:
    """Set one manager parameter as ``ros2 param set`` does; it must be accepted."""
    request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    answer = cell.call(SetParameters, "calibration_manager/set_parameters", request, TIMEOUT_S)
    assert answer.results[0].successful, answer.results[0].reason


def _check(cell):
    return cell.call(Trigger, "reference_check", Trigger.Request(), CALIBRATE_TIMEOUT_S)


def _true_centres(cell) -> np.ndarray:
    """The centres (N, 3, gls frame, mm) of the rings on the plate, from where the marks really landed."""
    paths = cell.call(GetMarkedPaths, "sim/marked_paths", GetMarkedPaths.Request(), TIMEOUT_S).paths
    return true_fiducial_centres(marked_polylines(paths), len(RING_RADII_MM))


def _write_certificate(path, centres: np.ndarray, header: str = "x,y,z") -> None:
    path.write_text(header + "\n" + "".join(",".join(f"{v:.6f}" for v in row) + "\n" for row in centres))


def _mark_plate(cell) -> np.ndarray:
    """Put rings on the plate with a calibration (its training plate stays); their true centres."""
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=False), CALIBRATE_TIMEOUT_S)
    assert answer.success, answer.message
    centres = _true_centres(cell)
    assert centres.shape == (GRID ** 2, 3)
    return centres


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    """Everything the ideal cell answers, recorded in one cell (stopped before the tests assert)."""
    folder = tmp_path_factory.mktemp("ideal")
    certificate, check_file = folder / "certificate.csv", folder / "reference_check.yaml"
    answers = {}
    parameters = {**FAST, "measurement_preset": "ideal", "reference_plate_certificate": str(certificate),
                  "reference_plate_name": PLATE_NAME}
    with running_cell(folder, grid=GRID, parameters=parameters) as cell:
        answers["no file"] = _check(cell)
        centres = _mark_plate(cell)     # before the file is set: a calibration refuses a file it cannot read
        answers["centres"] = centres
        _set(cell, "reference_check_file", str(check_file))
        answers["no certificate"] = _check(cell)
        _write_certificate(certificate, centres[:, :2], header="x,z")
        answers["missing column"] = _check(cell)
        answers["written before"] = check_file.exists()
        middle = centres.mean(axis=0)
        _write_certificate(certificate, middle + 0.9 * (centres - middle))     # a plate smaller than the grid
        answers["small plate"] = _check(cell)
        _write_certificate(certificate, centres)
        answers["check"] = _check(cell)
        written = check_file.read_bytes()
        _write_certificate(certificate, centres[:2])
        answers["too few"] = _check(cell)
        answers["untouched"] = check_file.read_bytes() == written
        # a calibration on a clean plate now states its accuracy from the check
        assert cell.call(Trigger, "sim/exchange_plate", Trigger.Request(), TIMEOUT_S).success
        answers["calibrate"] = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=True),
                                         CALIBRATE_TIMEOUT_S)
    return answers, certificate, check_file


def test_inputs_the_check_cannot_use_are_refused_and_nothing_is_written(ideal):
    answers, certificate, check_file = ideal
    assert not answers["no file"].success
    assert answers["no file"].message == ("request refused: reference_check_file is empty: the check would be lost; "
                                          "set it to the file the calibrations read the check from")
    assert not answers["no certificate"].success
    assert answers["no certificate"].message == (f"request refused: {certificate}: cannot be read: "
                                                 "No such file or directory")
    assert not answers["missing column"].success
    assert answers["missing column"].message == (f"request refused: {certificate}: the header names no column y "
                                                 "(found: x, z)")
    assert not answers["written before"]
    # a check of a plate that ends short of the grid could state no figure for it: refused before it scans
    assert not answers["small plate"].success
    assert answers["small plate"].message.startswith(f"request refused: {certificate}: the certified centres span x ")
    assert answers["small plate"].message.endswith("mm) at x min, x max, y min, y max: a check on them would state "
                                                   "no accuracy for that grid")
    assert not answers["too few"].success
    assert answers["too few"].message == (f"request refused: {certificate}: 2 certified centre(s); at least 3 "
                                          "are needed")
    assert answers["untouched"]


def test_the_check_of_an_ideal_chain_is_micrometres_and_is_what_calibrations_state_from(ideal):
    answers, _, check_file = ideal
    answer = answers["check"]
    assert answer.success, answer.message
    check = load_chain_check(check_file)
    assert (check.plan, check.placement, check.reference, check.chain_map) == ("0+", "pose", PLATE_NAME, "none")
    assert check.centres == GRID ** 2
    # where the plate was measured: the rings' true centres (the marks of an uncalibrated head, off the grid)
    centres = answers["centres"]
    assert np.allclose(check.extent_mm, (centres[:, 0].min(), centres[:, 0].max(), centres[:, 1].min(),
                                         centres[:, 1].max()), atol=0.01), check.extent_mm
    # The ideal chain measures rings to a few micrometres (as gls-reference-check's test on a bag): a
    # wrong frame, a mirrored axis or rings paired with the wrong centres would put tenths of a mm here.
    assert max(check.sigma_mm) < 0.004
    assert answer.message == (f"reference check written to {check_file}: sigma x {check.sigma_mm[0]:.4f} mm, "
                              f"y {check.sigma_mm[1]:.4f} mm (k = 1) from 9 of 9 certified centres; plan 0+, "
                              "placed by pose, chain map none")
    calibrated = answers["calibrate"]
    assert calibrated.success, calibrated.message
    assert calibrated.stated_basis == REFERENCE_BASIS, calibrated.message
    assert math.isfinite(calibrated.stated_rms_mm)
    assert calibrated.stated_rms_mm == pytest.approx(calibrated.post_rms_mm + check.rms_2d_mm)


def test_the_check_sees_the_chains_error_and_a_calibration_waits_for_it(ideal, tmp_path):
    """On `paper_like` the same kind of plate's check is many times the ideal chain's; while the check
    runs, a calibration and a second check are refused."""
    certificate, check_file = tmp_path / "certificate.csv", tmp_path / "reference_check.yaml"
    parameters = {**FAST, "measurement_preset": "paper_like", "reference_plate_certificate": str(certificate),
                  "reference_plate_name": PLATE_NAME}
    with running_cell(tmp_path, grid=GRID, parameters=parameters) as cell:
        _write_certificate(certificate, _mark_plate(cell))
        _set(cell, "reference_check_file", str(check_file))
        seen = threading.Event()
        cell.client_node.create_subscription(
            CalibrationProgress, "calibration/progress",
            lambda message: seen.set() if "reference plate" in message.text else None, 10)
        client = cell.client_node.create_client(Trigger, "reference_check")
        assert client.wait_for_service(timeout_sec=TIMEOUT_S)
        running = client.call_async(Trigger.Request())
        wait_for(seen.is_set, TIMEOUT_S, what="the reference check scanning")
        refused = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True), TIMEOUT_S)
        second = _check(cell)
        wait_for(running.done, CALIBRATE_TIMEOUT_S, what="the reference check ending")
        answer = running.result()
    assert not refused.success and refused.message == "a reference check is already running; request refused"
    assert not second.success and second.message == "a reference check is already running; request refused"
    assert answer.success, answer.message
    check = load_chain_check(check_file)
    assert check.centres == GRID ** 2
    ideal_check = load_chain_check(ideal[2])
    assert check.rms_2d_mm > 5 * ideal_check.rms_2d_mm


def _direct_plate(tmp_path):
    """A DirectCell (test_procedure's small ideal cell) whose plate carries 5 x 5 rings at 10 mm; their
    centres in the gls frame."""
    cell = new_cell(tmp_path)
    offsets = (np.arange(5) - 2) * 10.0
    known_uv = np.array([[x, y] for y in offsets for x in offsets])
    for ring in rings_polylines(known_uv, RING_RADII_MM):
        cell.sim.plate.add_mark_plate(ring)
    settings = cell.settings(grid_per_side=5, grid_size_mm=90.0, plain_sweeps=1, plain_sweep_step_mm=2.0)
    return cell, settings, cell.sim.plate.from_plate(known_uv)


def test_the_core_scans_as_a_calibration_scans_and_refuses_a_certificate_that_does_not_pair(tmp_path):
    cell, settings, known = _direct_plate(tmp_path)
    stages = []
    check = asyncio.run(scan_reference_check(cell, settings, known, " plate A ", lambda *item: stages.append(item)))
    assert (check.plan, check.placement, check.reference, check.chain_map, check.centres) == (
        "0+", "pose", "plate A", "none", 25)
    assert max(check.sigma_mm) < 0.004
    # the plain sweep, the stand-still height, one pass of the plan: as run_plate scans (no marking)
    assert (cell.sweeps, cell.standstills, len(cell.marks)) == (2, 1, 0)
    assert [stage for stage, _, _ in stages] == ["sweep_plain", "sweep_plain", "plate_pose", "sweep_marked",
                                                 "measurement", "measurement", "done"]
    assert stages[0][2] == "scanning the reference plate (1 of 1)"
    # A certificate at 1.3 times the pitch: every ring is found, only those near the middle pair (15).
    middle = known.mean(axis=0)
    with pytest.raises(CalibrationError, match=r"^paired \d+ of 25 certified centres with measured ones; at least 23 "
                                               r"are needed$"):
        asyncio.run(scan_reference_check(cell, settings, middle + 1.3 * (known - middle), "plate A",
                                         lambda *item: None))


@pytest.mark.parametrize("known, reference, message", [
    (np.zeros((2, 3)), "plate", "known_gls must be (N, 3) finite centres, N at least 3, got shape (2, 3)"),
    (np.zeros((4, 2)), "plate", "known_gls must be (N, 3) finite centres, N at least 3, got shape (4, 2)"),
    (np.eye(3), "  ", "reference must name the plate and its certificate"),
])
def test_the_core_refuses_bad_input_before_anything_moves(tmp_path, known, reference, message):
    cell, settings, _ = _direct_plate(tmp_path)
    with pytest.raises(ValueError) as error:
        asyncio.run(scan_reference_check(cell, settings, known, reference, lambda *item: None))
    assert str(error.value) == message
    assert (cell.sweeps, cell.standstills) == (0, 0)
