"""The calibrate action, as gls-calibrate sends it, against a robot and a line scanner played by a
separate process that imports nothing of this package (test/_cell_peer.py: plain rclpy, PointCloud2
profiles in metres in the optical frame, /tf, /tf_static and the motion contract). The galvo is the
package's sim_galvo (its contract is separate); the peer burns nothing: it renders the rings where a
galvo with a KNOWN smooth distortion would have put them, so the deviations the calibration measures
must be that distortion, in closed form."""
from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rclpy.action import ActionClient

from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.nodes.calibration_manager import CalibrationManager
from gls_calibration.nodes.correction import CorrectionNode
from gls_calibration.nodes.fiducial_measurement import FiducialMeasurementNode
from gls_calibration.nodes.plate_pose import PlatePoseNode
from gls_calibration.nodes.rbf_trainer import RbfTrainerNode
from gls_calibration.nodes.sim_galvo import SimGalvoNode
from gls_calibration.nodes.stream_acquisition import StreamAcquisitionNode
from gls_calibration_msgs.action import Calibrate

from ros_helpers import default_sigint, stop_process, wait_for
from test_stream_peer import imported_modules

PEER = Path(__file__).with_name("_cell_peer.py")
GRID, SIZE_MM = 5, 40.0
FIELD_A = 5e-4            # 1/mm: the peer's field reaches a * 20 * 20 = 0.2 mm at the grid's corners
RATE_HZ = 150.0           # the acquisition's default profile rate: 0.1 mm steps at 15 mm/s
PIXEL_MM = 0.1            # the peer's point spacing along the line, and the marked sweep's step
# The rendering is noise-free, so what is left is how well a ring centre is found on a 0.1 mm raster
# of 0.1 mm-wide lines: a fraction of a pixel per ring point, averaged over the ~330 raster cells a
# 2.5-2.7 mm ring crosses. A tenth of a pixel bounds it with room (1/20 of the field's 0.2 mm), and a
# distortion measured wrongly by even 10 % (0.02 mm at the corners) fails.
TOLERANCE_MM = 0.1 * PIXEL_MM


def peer_field_mm(xy_mm: np.ndarray) -> np.ndarray:
    """The peer's field (test/_cell_peer.py, ``field_mm``), restated here: d = a (x y, (x^2 - y^2) / 2)."""
    x, y = xy_mm[:, 0], xy_mm[:, 1]
    return FIELD_A * np.column_stack([x * y, 0.5 * (x * x - y * y)])


def test_the_cell_peer_imports_nothing_of_the_package():
    """Its imports name no module of the package (and at run time it asserts none got loaded); the
    helpers it takes from the acquisition's peer are held to the same rule (test_stream_peer.py)."""
    modules = imported_modules(PEER)
    ours = ("gls_calibration", "gls_calibration_msgs", "ros_helpers")
    assert "rclpy" in modules and not any(name.split(".")[0] in ours for name in modules)
    assert {name for name in modules if name.startswith("_") and name != "__future__"} == {"_stream_peer"}


def test_the_field_has_no_rigid_part_on_the_grid():
    """The calibration removes a rigid motion of the whole field before it reports deviations; the
    field is chosen without one on the symmetric grid, so the reported deviations are -d itself."""
    offsets = np.linspace(-0.5 * SIZE_MM, 0.5 * SIZE_MM, GRID)
    grid = np.column_stack([c.ravel() for c in np.meshgrid(offsets, offsets, indexing="xy")])
    d = peer_field_mm(grid)
    assert np.allclose(d.mean(axis=0), 0.0, atol=1e-15)
    assert abs(np.sum(grid[:, 0] * d[:, 1] - grid[:, 1] * d[:, 0])) < 1e-12      # no rotation
    assert np.sqrt(np.mean(np.sum(d ** 2, axis=1))) > 0.05      # above the manager's tolerance: it trains


def _fiducial_rows(report_dir: Path, stage: str) -> list[dict]:
    with (report_dir / "fiducials.csv").open() as handle:
        return [row for row in csv.DictReader(handle) if row["stage"] == stage]


def _calibrate(start_cell, tmp_path, fault: list[str]):
    """Start the peer (``fault``: its extra options) and the package's nodes; send calibrate as
    gls-calibrate does; the result, the peer's log and the cell."""
    log = tmp_path / "peer.log"
    with log.open("w") as handle:
        peer = subprocess.Popen([sys.executable, str(PEER), "--rate", str(RATE_HZ), "--grid", str(GRID),
                                 "--size-mm", str(SIZE_MM), "--field-a", str(FIELD_A), "--lifetime", "300"] + fault,
                                stdout=handle, stderr=subprocess.STDOUT, preexec_fn=default_sigint)
    try:
        cell = start_cell(grid=GRID, node_types=(SimGalvoNode, StreamAcquisitionNode, PlatePoseNode,
                                                 FiducialMeasurementNode, RbfTrainerNode, CorrectionNode,
                                                 CalibrationManager),
                          parameters={"grid.size_mm": SIZE_MM, "sweep.plan": "0+", "ground_truth_service": "",
                                      "profile_rate_hz": RATE_HZ})
        wait_for(lambda: "peer ready" in log.read_text(), 30.0, what="the peer's start")
        client = ActionClient(cell.client_node, Calibrate, "calibrate")
        assert client.wait_for_server(timeout_sec=30.0)
        sent = client.send_goal_async(Calibrate.Goal(iterations=1, validate=False, force=False))
        wait_for(sent.done, 30.0, what="the goal's acceptance")
        handle = sent.result()
        assert handle.accepted
        result = handle.get_result_async()
        wait_for(result.done, 240.0, what="the calibration's result")
        return result.result().result, log.read_text(), cell
    finally:
        stop_process(peer)


@pytest.mark.slow
def test_calibrate_action_against_a_peer_robot_and_scanner(start_cell, tmp_path):
    answer, log, cell = _calibrate(start_cell, tmp_path, [])
    assert answer.success, f"{answer.message}\npeer log:\n{log}"
    assert CalibrationStore(cell.calibration_dir).active_path() is not None

    assert answer.fiducials_found == GRID * GRID and answer.neurons > 0
    rows = _fiducial_rows(Path(answer.report_dir), "before")
    assert len(rows) == GRID * GRID
    targets = np.array([[float(row["target_x_mm"]), float(row["target_y_mm"])] for row in rows])
    measured = np.array([[float(row["dx_mm"]), float(row["dy_mm"])] for row in rows])
    # deviation = commanded minus landed (docs/interfaces.md, sign conventions): the peer's rings landed at Q + d(Q)
    expected = -peer_field_mm(targets)
    error = np.abs(measured - expected)
    assert error.max() <= TOLERANCE_MM, (error.max(), np.column_stack([targets, measured, expected]))
    rms = np.sqrt(np.mean(np.sum(expected ** 2, axis=1)))
    assert answer.pre_rms_mm == pytest.approx(rms, abs=TOLERANCE_MM)


@pytest.mark.slow
@pytest.mark.parametrize("fault, problem", [
    ("mm", "median point distance 325.3 m exceeds 10 m: the cloud is not in metres (millimetres?)"),
    ("stops", "the profile stream stops"),
])
def test_a_broken_stream_fails_the_calibration_and_activates_nothing(start_cell, tmp_path, fault, problem):
    """The first marked sweep broken by the peer's driver: the action answers success=false naming the
    problem, no fiducial is measured from that sweep and no calibration becomes active."""
    answer, log, cell = _calibrate(start_cell, tmp_path, ["--fault", fault])
    assert not answer.success and problem in answer.message, f"{answer.message}\npeer log:\n{log}"
    assert answer.fiducials_found == 0
    store = CalibrationStore(cell.calibration_dir)
    assert store.active_path() is None and store.history() == []
