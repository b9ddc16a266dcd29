"""Every service of the package refuses bad requests with a message and keeps serving.

For each service: NaN, infinite, negative, absurdly large values and empty lists get
``success=false`` and a message naming the problem; a good request right after must succeed.
"""
from __future__ import annotations

import math
import os
import re
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2, PointField

from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.geometry import kinematics
from gls_calibration.nodes.calibration_manager import CalibrationManager
from gls_calibration.nodes.correction import CorrectionNode
from gls_calibration.nodes.fiducial_measurement import FiducialMeasurementNode
from gls_calibration.nodes.plate_pose import PlatePoseNode
from gls_calibration.nodes.rbf_trainer import RbfTrainerNode
from gls_calibration.nodes.scan_acquisition import ScanAcquisitionNode
from gls_calibration.nodes.sim_galvo import SimGalvoNode
from gls_calibration.nodes.sim_scanner import SimScannerNode
from gls_calibration.ros.conversions import array_to_pointcloud2, cloud_to_msg, plate_pose_to_msg, xyzi_array
from gls_calibration.scan.plate_pose import estimate_plate_pose
from gls_calibration_msgs.msg import PlatePose, SweepDone
from gls_calibration_msgs.srv import (AcquireSweep, Calibrate, CorrectSetpoints, EstimatePlatePose,
                                      ExplainDeviations, LandingPositions, LoadCalibration, MarkPolylines,
                                      MeasureFiducials, StartSweep, TrainCorrection)

from rendering import render_plate_scan
from ros_helpers import call_service
from test_nodes import PROFILES, FakeScanner, trained_record
from test_persistence import make_record

NAMESPACE = "gls"
TIMEOUT_S = 20.0
GEOMETRY = kinematics.HeadGeometry()
NAN, INF = math.nan, math.inf


class Caller:
    """Calls one service of a node under test from a client node."""

    def __init__(self, node: Node, srv_type, name: str) -> None:
        self.node, self.client = node, node.create_client(srv_type, name)

    def __call__(self, request, timeout_s: float = TIMEOUT_S):
        return call_service(self.node, self.client, request, timeout_s)

    def refuses(self, request, match: str) -> str:
        response = self(request)
        assert not response.success, f"accepted: {request}"
        assert match in response.message, response.message
        return response.message


@pytest.fixture
def client(ros_context, add_node):
    node = add_node(Node("bad_request_client", namespace=NAMESPACE, context=ros_context))
    return lambda srv_type, name: Caller(node, srv_type, name)


# --- correction -------------------------------------------------------------------------------------

@pytest.mark.parametrize("service", ["correct_setpoints", "correct_setpoints_batch"])
def test_correct_setpoints_refuses_bad_and_oversized_requests_and_keeps_serving(ros_context, add_node, client,
                                                                                tmp_path, service):
    """Both services (the batch one is served by the companion node) validate the same way."""
    add_node(CorrectionNode(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(tmp_path / "store")), Parameter("max_targets", value=10)]))
    correct = client(CorrectSetpoints, service)
    correct.refuses(CorrectSetpoints.Request(x=[NAN], y=[0.0]), "x")
    correct.refuses(CorrectSetpoints.Request(x=[0.0], y=[INF]), "y")
    correct.refuses(CorrectSetpoints.Request(x=[0.0, 1.0], y=[0.0]), "same length")
    correct.refuses(CorrectSetpoints.Request(x=[0.0], y=[0.0], z=[-1e308, 2.0]), "z must be empty")
    correct.refuses(CorrectSetpoints.Request(x=[0.0], y=[0.0], z=[NAN]), "z")
    message = correct.refuses(CorrectSetpoints.Request(x=[0.0] * 11, y=[0.0] * 11), "11 targets refused")
    assert "at most 10 per request" in message
    beyond = correct(CorrectSetpoints.Request(x=[0.0, 1e6], y=[0.0, 0.0], z=[0.0, 0.0]))
    assert not beyond.success and list(beyond.within_limits) == [True, False]
    high = correct(CorrectSetpoints.Request(x=[0.0], y=[0.0], z=[100.0]))     # 4x the focus range
    assert not high.success and list(high.within_limits) == [False]
    good = correct(CorrectSetpoints.Request(x=[0.0] * 10, y=[1.0] * 10))
    assert good.success, good.message


@pytest.mark.parametrize("service", ["correct_setpoints", "correct_setpoints_batch"])
def test_correct_setpoints_refuses_heights_beyond_the_working_distance_and_keeps_serving(ros_context, add_node,
                                                                                         client, tmp_path, service):
    """A target at the mirrors' height divided by zero in the ray transfer: the node's thread died and
    no request was answered again. Now refused, one target (scalar path) or many, and served after."""
    store_dir = tmp_path / "store"
    CalibrationStore(store_dir).save(trained_record()[0], activate=True)
    add_node(CorrectionNode(context=ros_context,
                            parameter_overrides=[Parameter("calibration_dir", value=str(store_dir))]))
    correct = client(CorrectSetpoints, service)
    distance = GEOMETRY.working_distance_mm
    for z in ([distance], [0.0, distance], [1e308], [-1e308]):
        correct.refuses(CorrectSetpoints.Request(x=[10.0] * len(z), y=[10.0] * len(z), z=z), "working distance")
    good = correct(CorrectSetpoints.Request(x=[10.0], y=[10.0], z=[0.0]))
    assert good.success, good.message


def test_correct_setpoints_in_chunks_equals_one_piece(ros_context, add_node, client, tmp_path):
    store_dir = tmp_path / "store"
    record, _ = trained_record()
    CalibrationStore(store_dir).save(record, activate=True)
    add_node(CorrectionNode(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(store_dir)), Parameter("chunk_targets", value=100)]))
    x = np.linspace(-90.0, 90.0, 1001)
    y = np.cos(x / 30.0) * 80.0
    answer = client(CorrectSetpoints, "correct_setpoints")(CorrectSetpoints.Request(x=x, y=y))
    assert answer.success, answer.message
    from gls_calibration.calibration.record import correction_from_record
    expected = correction_from_record(CalibrationStore(store_dir).load_active(), GEOMETRY).correct(x, y)
    np.testing.assert_array_equal(np.asarray(answer.alpha_x), expected.alpha_x)
    np.testing.assert_array_equal(np.asarray(answer.y), expected.y)
    assert list(answer.inside_calibrated_field) == expected.inside_calibrated_field.tolist()


def test_correction_load_refuses_hostile_files_and_keeps_the_serving_calibration(ros_context, add_node, client,
                                                                                 tmp_path):
    store = CalibrationStore(tmp_path / "store")
    good = store.save(make_record(), activate=True)
    other = store.save(make_record(seed=1), activate=False)
    add_node(CorrectionNode(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(store.directory))]))
    load = client(LoadCalibration, "correction/load")
    outside = tmp_path / "outside.yaml"
    outside.write_text(good.read_text())
    fifo = store.history_directory / "pipe.yaml"
    os.mkfifo(fifo)
    (store.history_directory / "bomb.yaml").write_text("a: &a [1, 1]\nb: [*a, *a]\n")
    nan_text = re.sub(r"format_version: \d+", "format_version: .nan", good.read_text())
    assert nan_text != good.read_text()
    (store.history_directory / "nan.yaml").write_text(nan_text)
    # Only the active calibration is ever served: any other file named is refused, hostile or not.
    for path in [str(outside), "../../outside.yaml", "/dev/zero", str(fifo), "bomb.yaml", "nan.yaml",
                 str(store.history_directory), other.name]:
        message = load.refuses(LoadCalibration.Request(file=path), "is not the active calibration")
    served = client(CorrectSetpoints, "correct_setpoints")(CorrectSetpoints.Request(x=[0.0], y=[0.0]))
    assert served.success and served.message == "corrected"
    # A hostile ACTIVE file (the pointer written behind the node's back): the reload is refused with the
    # reason, within the bounds of the one reading function, and the serving calibration stays.
    pointer = store.pointer_path.read_text()
    for content, problem in [("a: &a [1, 1]\nb: [*a, *a]\n", "aliases are not allowed"), (nan_text, "format_version")]:
        hostile = store.history_directory / "calibration_20991231T000000Z_9999.yaml"
        hostile.write_text(content)
        store.pointer_path.write_text(f"active: {hostile.name}\n")
        message = load.refuses(LoadCalibration.Request(file=""), problem)
        assert message.endswith(f"still serving {good}"), message
        kept = client(CorrectSetpoints, "correct_setpoints")(CorrectSetpoints.Request(x=[0.0], y=[0.0]))
        assert kept.success and kept.calibration_id not in ("", "nominal"), kept.message
    store.pointer_path.write_text(pointer)
    store.activate(other)
    switched = load(LoadCalibration.Request(file=""))
    assert switched.success and Path(switched.file).resolve() == other.resolve(), switched.message


def test_a_bad_active_file_at_start_leaves_the_node_up_and_refusing_with_the_reason(ros_context, add_node, client,
                                                                                    tmp_path):
    store = CalibrationStore(tmp_path / "store")
    good = store.save(make_record(), activate=True)
    good.write_text("[" * 100_000 + "]" * 100_000)      # deep nesting: once a RecursionError at start-up
    add_node(CorrectionNode(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(store.directory))]))
    for service in ("correct_setpoints", "correct_setpoints_batch"):
        message = client(CorrectSetpoints, service).refuses(CorrectSetpoints.Request(x=[0.0], y=[0.0]),
                                                            "corrections refused")
        assert "nested deeper than" in message
    replacement = store.save(make_record(seed=2), activate=True)
    loaded = client(LoadCalibration, "correction/load")(LoadCalibration.Request(file=""))
    assert loaded.success and loaded.file == str(replacement), loaded.message
    for service in ("correct_setpoints", "correct_setpoints_batch"):
        assert client(CorrectSetpoints, service)(CorrectSetpoints.Request(x=[0.0], y=[0.0])).success


# --- scan acquisition, plate pose, fiducials, trainer ------------------------------------------------------

@pytest.mark.parametrize("field, value", [("timeout_s", -1.0), ("timeout_s", 1e10), ("timeout_s", 1e308),
                                          ("timeout_s", NAN), ("timeout_s", INF), ("length_mm", -1.0),
                                          ("speed_mm_s", NAN), ("step_mm", 1e308)])
def test_scan_acquire_refuses_bad_numbers_and_then_acquires(ros_context, add_node, client, field, value):
    add_node(ScanAcquisitionNode(context=ros_context))
    FakeScanner(add_node(Node("fake_scanner", namespace=NAMESPACE, context=ros_context)), "complete")
    acquire = client(AcquireSweep, "scan/acquire")
    request = AcquireSweep.Request(timeout_s=5.0)
    setattr(request, field, value)
    acquire.refuses(request, f"request refused: {field} must be 0 (the default) or a positive number up to")
    good = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))
    assert good.success, good.message


def plane_cloud(points: int = 2000) -> PointCloud2:
    rng = np.random.default_rng(3)
    xy = rng.uniform(-50.0, 50.0, (points, 2))
    z = 300.0 + 0.01 * xy[:, 0] + rng.normal(0.0, 0.01, points)
    return cloud_to_msg(xyzi_array(np.column_stack([xy, z]), rng.random(points)), "scanner")


def malformed_clouds() -> dict[str, PointCloud2]:
    good = plane_cloud()
    clouds = {}
    empty_huge = PointCloud2(height=1, width=2 ** 31, fields=good.fields, point_step=good.point_step,
                             row_step=good.point_step * 2 ** 31 % 2 ** 32, data=[])
    clouds["huge width, empty data"] = empty_huge
    short = plane_cloud()
    short.data = short.data[: len(short.data) // 2]
    clouds["short data"] = short
    step = plane_cloud()
    step.point_step = 3
    clouds["wrong point_step"] = step
    fields = plane_cloud()
    fields.fields = [field for field in fields.fields if field.name != "z"]
    clouds["missing field"] = fields
    nan_only = xyzi_array(np.full((50, 3), np.nan), np.zeros(50))
    clouds["NaN only"] = cloud_to_msg(nan_only, "scanner")
    counted = plane_cloud()
    counted.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=2 if f.name == "x" else 1)
                      for f in counted.fields]
    clouds["field count 2"] = counted
    return clouds


def test_plate_pose_refuses_malformed_clouds_and_then_fits(ros_context, add_node, client):
    add_node(PlatePoseNode(context=ros_context))
    estimate = client(EstimatePlatePose, "plate_pose/estimate")
    for name, cloud in malformed_clouds().items():
        response = estimate(EstimatePlatePose.Request(cloud=cloud))
        assert not response.success and response.message, name
    good = estimate(EstimatePlatePose.Request(cloud=plane_cloud()))
    assert good.success, good.message


def test_fiducial_measurement_refuses_bad_clouds_and_poses_and_then_measures(ros_context, add_node, client):
    add_node(FiducialMeasurementNode(context=ros_context))
    measure = client(MeasureFiducials, "fiducials/measure")
    centres = np.array([[-10.0, -10.0], [10.0, -10.0], [0.0, 10.0]])
    xyz, intensity = render_plate_scan(centres, size_mm=(40.0, 40.0), offset_mm=(0.0, 0.0, 300.0))
    pose = estimate_plate_pose(xyz)
    scan = cloud_to_msg(xyzi_array(xyz, intensity), "scanner")
    pose_msg = plate_pose_to_msg(pose)
    for name, cloud in malformed_clouds().items():
        response = measure(MeasureFiducials.Request(cloud=cloud, pose=pose_msg))
        assert not response.success and response.message, name
    nan_pose = PlatePose(normal=[NAN, 0.0, 1.0], centre=[0.0, 0.0, NAN], rotation=[NAN] * 9)
    measure.refuses(MeasureFiducials.Request(cloud=scan, pose=nan_pose), "rotation")
    bad_centre = plate_pose_to_msg(pose)
    bad_centre.centre = [0.0, INF, 300.0]
    measure.refuses(MeasureFiducials.Request(cloud=scan, pose=bad_centre), "centre")
    good = measure(MeasureFiducials.Request(cloud=scan, pose=pose_msg, expected_count=3))
    assert good.success and len(good.x) == 3, good.message
    # an unorganized cloud: rasterised at its own point spacing (pixel_size_mm 0, the default)
    loose = cloud_to_msg(xyzi_array(xyz.reshape(-1, 3), intensity.reshape(-1)), "scanner")
    good = measure(MeasureFiducials.Request(cloud=loose, pose=pose_msg, expected_count=3))
    assert good.success and len(good.x) == 3, good.message


def test_fiducial_measurement_logs_a_surplus_and_answers_missing_never_negative(ros_context, add_node, client,
                                                                                monkeypatch):
    node = add_node(FiducialMeasurementNode(context=ros_context))
    warnings = []
    monkeypatch.setattr(node.get_logger(), "warning", lambda message, **_: warnings.append(message))
    measure = client(MeasureFiducials, "fiducials/measure")
    centres = np.array([[-10.0, -10.0], [10.0, -10.0], [0.0, 10.0]])
    xyz, intensity = render_plate_scan(centres, size_mm=(40.0, 40.0), offset_mm=(0.0, 0.0, 300.0))
    request = MeasureFiducials.Request(cloud=cloud_to_msg(xyzi_array(xyz, intensity), "scanner"),
                                       pose=plate_pose_to_msg(estimate_plate_pose(xyz)))
    for expected_count, missing in ((4, 1), (3, 0), (0, 0)):   # 0: nothing expected
        request.expected_count = expected_count
        response = measure(request)
        assert response.success and len(response.x) == 3 and response.missing == missing, response.message
    assert warnings == []
    request.expected_count = 1
    response = measure(request)
    assert response.success and len(response.x) == 3 and response.missing == 0, response.message
    assert warnings == ["3 fiducials found, 2 more than the 1 expected: check expected_count or the scan for "
                        "spurious rings"]


def test_trainer_refuses_bad_training_data_and_then_trains(ros_context, add_node, client):
    add_node(RbfTrainerNode(context=ros_context, parameter_overrides=[Parameter("max_points", value=100)]))
    train = client(TrainCorrection, "rbf/train")
    train.refuses(TrainCorrection.Request(), "")
    train.refuses(TrainCorrection.Request(x=[0.0, 1.0], y=[0.0], dx=[0.0, 0.0], dy=[0.0, 0.0]), "same length")
    train.refuses(TrainCorrection.Request(x=[NAN] * 3, y=[0.0] * 3, dx=[0.0] * 3, dy=[0.0] * 3), "")
    train.refuses(TrainCorrection.Request(x=[0.0] * 3, y=[0.0] * 3, dx=[INF] * 3, dy=[0.0] * 3), "")
    many = np.linspace(0.0, 1.0, 101)
    train.refuses(TrainCorrection.Request(x=many, y=many, dx=many, dy=many), "101 points refused: at most 100")
    grid = np.stack(np.meshgrid(np.linspace(-90, 90, 7), np.linspace(-90, 90, 7)), axis=-1).reshape(-1, 2)
    field = 0.001 * grid[:, ::-1]
    good = train(TrainCorrection.Request(x=grid[:, 0], y=grid[:, 1], dx=field[:, 0], dy=field[:, 1]))
    assert good.success, good.message


# --- simulated devices ----------------------------------------------------------------------------------

def test_sim_scanner_refuses_absurd_sweeps_and_then_sweeps(ros_context, add_node, client):
    add_node(SimScannerNode(context=ros_context))
    start = client(StartSweep, "scanner/start_sweep")
    for request in (StartSweep.Request(length_mm=-1.0), StartSweep.Request(length_mm=NAN),
                    StartSweep.Request(length_mm=1e308), StartSweep.Request(speed_mm_s=INF),
                    StartSweep.Request(length_mm=200.0, step_mm=1e-9)):
        start.refuses(request, "")
    # No galvo here: the marks cannot be loaded, which the scanner says (and it keeps serving).
    started = start(StartSweep.Request(length_mm=10.0))
    assert not started.success and "marks" in started.message


def test_sim_galvo_refuses_bad_commands_and_then_marks(ros_context, add_node, client):
    add_node(SimGalvoNode(context=ros_context))
    mark = client(MarkPolylines, "galvo/mark")
    mark.refuses(MarkPolylines.Request(), "no points to mark")
    mark.refuses(MarkPolylines.Request(alpha_x=[NAN, 0.0], alpha_y=[0.0, 0.0], focus_shift=[0.0, 0.0],
                                       polyline_starts=[0]), "NaN")
    mark.refuses(MarkPolylines.Request(alpha_x=[0.0], alpha_y=[0.0, 0.0], focus_shift=[0.0],
                                       polyline_starts=[0]), "same length")
    mark.refuses(MarkPolylines.Request(alpha_x=[0.0, 0.01], alpha_y=[0.0, 0.0], focus_shift=[0.0, 0.0],
                                       polyline_starts=[0, 5]), "polyline_starts")
    landing = client(LandingPositions, "sim/landing_positions")
    landing.refuses(LandingPositions.Request(alpha_x=[NAN], alpha_y=[0.0]), "")
    landing.refuses(LandingPositions.Request(alpha_x=[0.0], alpha_y=[0.0], t=[-INF]), "")
    good = mark(MarkPolylines.Request(alpha_x=[0.0, 0.01], alpha_y=[0.0, 0.0], focus_shift=[0.0, 0.0],
                                      polyline_starts=[0]))
    assert good.success, good.message
    assert landing(LandingPositions.Request(alpha_x=[0.0], alpha_y=[0.0])).success


# --- the manager: calibrate and explain_deviations ------------------------------------------------------------

def test_manager_refuses_bad_requests_and_hostile_files_and_then_serves(start_cell, tmp_path):
    cell = start_cell(grid=4, parameters={"sweep.plain_repeats": 1})   # explain needs >= 10 fiducials
    for iterations in (255, 4):
        refused = cell.call(Calibrate, "calibrate", Calibrate.Request(iterations=iterations), TIMEOUT_S)
        assert not refused.success
        assert refused.message == f"request refused: iterations must be 0 (the default, 1) or 1 to 3, got {iterations}"
    good = cell.call(Calibrate, "calibrate", Calibrate.Request(iterations=1), 300.0)
    assert good.success, good.message

    history = CalibrationStore(cell.calibration_dir).history_directory
    outside = tmp_path / "outside.yaml"
    outside.write_text(Path(good.calibration_file).read_text())
    os.mkfifo(history / "pipe.yaml")
    (history / "bomb.yaml").write_text("a: &a [1, 1]\nb: [*a, *a]\n")
    for path, problem in [(str(outside), "outside the calibration directory"), ("/dev/zero", "outside the"),
                          ("pipe.yaml", "not a regular file"), ("bomb.yaml", "aliases are not allowed")]:
        explained = cell.call(ExplainDeviations, "explain_deviations",
                              ExplainDeviations.Request(calibration_file=path), TIMEOUT_S)
        assert not explained.success and problem in explained.message, explained.message
    explained = cell.call(ExplainDeviations, "explain_deviations", ExplainDeviations.Request(), 120.0)
    assert explained.success, explained.message


# --- parameters ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("node_type, name, value, match", [
    (FiducialMeasurementNode, "grid.ring_radii_mm", [-2.5, 2.7], "parameter grid.ring_radii_mm"),
    (FiducialMeasurementNode, "pixel_size_mm", 0.001, r"parameter pixel_size_mm must be 0 \(from the point "
     r"spacing\) or at least 0.005 mm, got 0.001"),
    (RbfTrainerNode, "spreads_mm", [35.0, NAN], "parameter spreads_mm"),
    (RbfTrainerNode, "mse_goals_mm2", [0.0], "parameter mse_goals_mm2"),
    (RbfTrainerNode, "tps_smoothings", [-1.0], "parameter tps_smoothings"),
    (CalibrationManager, "grid.ring_radii_mm", [2.7, 2.5], "ring_radii_mm must be one or more positive finite"),
    (CalibrationManager, "grid.ring_radii_mm", [-2.5, 2.7], "ring_radii_mm must be one or more positive finite"),
])
def test_bad_list_parameters_stop_a_node_at_start_with_the_reason(ros_context, tmp_path, node_type, name, value,
                                                                  match):
    with pytest.raises(ValueError, match=match):
        node_type(context=ros_context, parameter_overrides=[Parameter(name, value=value)])


@pytest.mark.parametrize("name, value", [("max_iterations", 0), ("service_timeout_s", 1e308),
                                         ("deadline_margin_s", -1.0), ("sweep.speed_mm_s", 0.0)])
def test_out_of_range_manager_parameters_are_refused_at_start(ros_context, name, value):
    from rclpy.exceptions import InvalidParameterValueException
    with pytest.raises(InvalidParameterValueException):
        CalibrationManager(context=ros_context, parameter_overrides=[Parameter(name, value=value)])


# --- hostile topics: malformed profiles, spoofed ends of sweep -------------------------------------------------

class HostileScanner(FakeScanner):
    """Streams malformed profiles and a foreign end of sweep before the real sweep."""

    def stream(self) -> None:
        for cloud in malformed_clouds().values():
            self.points.publish(cloud)
        negative = cloud_to_msg(self.profiles[0], "scanner")
        negative.header.stamp.sec = -5
        self.points.publish(negative)
        self.done.publish(SweepDone(sweep_id=99, profiles=3, step_mm=1.0, speed_mm_s=15.0,
                                    direction=[0.0, 1.0, 0.0], complete=True))
        time.sleep(0.2)
        super().stream()


WIDE_LIMIT = 60   # max_points_per_profile for the junk test; the fake scanner's profiles have 50


def stamped(cloud: PointCloud2, seconds: float) -> PointCloud2:
    cloud.header.stamp.sec, cloud.header.stamp.nanosec = int(seconds), int(round((seconds % 1.0) * 1e9))
    return cloud


class JunkScanner(FakeScanner):
    """Issue 31 item 8: well-formed junk in the middle of a sweep placed by pose."""

    def junk(self) -> list[PointCloud2]:
        profile = self.profiles[0]
        xyz = np.column_stack([profile["x"], profile["y"], profile["z"]]) * 1e-3        # metres
        wide = xyzi_array(np.column_stack([np.linspace(-30.0, 30.0, 2 * WIDE_LIMIT), np.zeros(2 * WIDE_LIMIT),
                                           np.full(2 * WIDE_LIMIT, 325.0)]))      # mm: cloud_to_msg sends metres
        near = 1000.05                                        # a stamp inside the sweep
        big_endian = stamped(cloud_to_msg(profile, "scanner_sensor"), near)
        big_endian.is_bigendian = True
        float64 = [(name, "f8") for name in ("x", "y", "z", "intensity")]
        return [
            stamped(array_to_pointcloud2(xyzi_array(np.zeros((50, 3))).astype(float64), "scanner_sensor"),
                    near),                                      # float64 zeros
            stamped(array_to_pointcloud2(xyzi_array(xyz).astype(float64), "scanner_sensor"),
                    near),                                      # float64 metres, plausible: another layout
            big_endian,
            stamped(cloud_to_msg(profile, "scanner_sensor"), 0.0),      # stamp zero
            stamped(cloud_to_msg(profile, "scanner_sensor"), 2.1e9),    # far in the future (int32 seconds)
        ] + [stamped(cloud_to_msg(wide, "scanner_sensor"), near) for _ in range(5)]   # wider than the bound

    def stream(self) -> None:
        junk = self.junk()
        original = self.points.publish
        count = [0]

        def publish(message):
            original(message)
            count[0] += 1
            if count[0] == 5:                                   # in the middle of the sweep
                for cloud in junk:
                    original(cloud)
        self.points.publish = publish
        try:
            super().stream()
        finally:
            self.points.publish = original


def test_well_formed_junk_in_a_sweep_is_dropped_by_layout_stamp_and_width(ros_context, add_node, client):
    add_node(ScanAcquisitionNode(context=ros_context, parameter_overrides=[
        Parameter("max_points_per_profile", value=WIDE_LIMIT)]))
    JunkScanner(add_node(Node("fake_scanner", namespace=NAMESPACE, context=ros_context)), "posed")
    acquire = client(AcquireSweep, "scan/acquire")
    response = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))
    assert response.success, response.message
    assert response.cloud.height == PROFILES                      # 20 rows, not 30
    assert response.placed_by_pose                                # the junk stamps did not switch to time
    assert response.cloud.header.stamp.sec == 1000                # stamped with the sweep's first profile
    dropped = {why: int(count) for count, why in re.findall(
        r"(\d+) profile\(s\) (malformed|wider|not of|not in the scanner's declared format)", response.message)}
    assert dropped["wider"] == 5, response.message
    # float64 zeros, float64 metres, the big-endian flag: not the format the scanner declares (float32, little-endian)
    assert dropped["not in the scanner's declared format"] == 3, response.message
    assert "(float32, little-endian; parameters profile_field_type, profile_big_endian)" in response.message
    assert dropped["not of"] == 2, response.message             # stamp zero, stamp 2.1e9: outside the time window
    assert "malformed" not in dropped, response.message
    again = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))
    assert again.success and again.cloud.height == PROFILES, again.message


class SpoofingScanner(FakeScanner):
    """Issue 31 item 8: ends of sweep with the running sweep's id that contradict it, sent early."""

    def stream(self) -> None:
        original = self.points.publish
        count = [0]

        def publish(message):
            original(message)
            count[0] += 1
            if count[0] == 1:      # complete after one profile: contradicts the announced 20
                self.done.publish(SweepDone(sweep_id=7, profiles=1, step_mm=0.15, speed_mm_s=15.0,
                                            direction=[0.0, 1.0, 0.0], complete=True))
            if count[0] == 2:      # cut short after 5, sent after 2: contradicted by the profiles that follow
                self.done.publish(SweepDone(sweep_id=7, profiles=5, step_mm=0.15, speed_mm_s=15.0,
                                            direction=[0.0, 1.0, 0.0], complete=False))
            if count[0] == 10:     # cut short after 3: contradicts the 10 received
                self.done.publish(SweepDone(sweep_id=7, profiles=3, step_mm=0.15, speed_mm_s=15.0,
                                            direction=[0.0, 1.0, 0.0], complete=False))
            time.sleep(0.02)       # a sweep that takes a while: the spoofs come long before its end
        self.points.publish = publish
        try:
            super().stream()
        finally:
            self.points.publish = original
            self.finished = time.monotonic()


def test_an_end_of_sweep_that_contradicts_the_sweep_is_ignored_and_the_real_end_awaited(ros_context, add_node,
                                                                                        client):
    add_node(ScanAcquisitionNode(context=ros_context))
    scanner = SpoofingScanner(add_node(Node("fake_scanner", namespace=NAMESPACE, context=ros_context)), "complete")
    acquire = client(AcquireSweep, "scan/acquire")
    response = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))
    answered = time.monotonic()
    assert response.success, response.message
    assert response.cloud.height == PROFILES
    assert answered >= scanner.finished          # not before the scanner's own end: it is not left running
    again = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))
    assert again.success and again.cloud.height == PROFILES, again.message


class BusyScanner(FakeScanner):
    """Refuses a sweep while one runs (as the simulated scanner does); a new id per sweep; slow."""

    def __init__(self, node: Node, script: str, period_s: float) -> None:
        super().__init__(node, script)
        self.period_s, self.running, self.refused = period_s, False, 0

    def on_start(self, request, response):
        if self.running:
            self.refused += 1
            response.success, response.message = False, "a sweep is running; request refused"
            return response
        self.running = True
        response = super().on_start(request, response)
        response.sweep_id = 7 + len(self.requests)
        return response

    def stream(self) -> None:
        sweep_id = 7 + len(self.requests)
        for index in range(PROFILES):
            stamp_s = 100.0 * sweep_id + index * 0.01
            self.points.publish(stamped(cloud_to_msg(self.profiles[index], "scanner_sensor"), stamp_s))
            time.sleep(self.period_s)
        self.running = False
        self.done.publish(SweepDone(sweep_id=sweep_id, profiles=PROFILES, step_mm=0.15, speed_mm_s=15.0,
                                    direction=[0.0, 1.0, 0.0], complete=True))


def test_a_sweep_left_running_by_a_failed_acquisition_does_not_get_the_next_one_refused(ros_context, add_node,
                                                                                        client):
    # Issue 31 item 8: an acquisition that fails before its sweep ended left the scanner sweeping, and
    # the next sweep was refused ("a sweep is running"). The next acquisition now awaits that end.
    add_node(ScanAcquisitionNode(context=ros_context))
    scanner = BusyScanner(add_node(Node("fake_scanner", namespace=NAMESPACE, context=ros_context)), "complete",
                          period_s=0.1)
    acquire = client(AcquireSweep, "scan/acquire")
    failed = acquire(AcquireSweep.Request(timeout_s=0.5))           # the sweep takes ~2 s
    assert not failed.success and failed.message.startswith("sweep not complete after 0.5 s"), failed.message
    again = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))
    assert again.success, again.message
    assert again.cloud.height == PROFILES and scanner.refused == 0


def test_an_announcement_that_contradicts_the_requested_length_and_step_is_said(ros_context, add_node, client):
    add_node(ScanAcquisitionNode(context=ros_context))
    FakeScanner(add_node(Node("fake_scanner", namespace=NAMESPACE, context=ros_context)), "complete")
    acquire = client(AcquireSweep, "scan/acquire")
    # 20 profiles announced for 30 mm every 0.15 mm (201): the scanner's count is used, the mismatch said
    response = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S, length_mm=30.0, step_mm=0.15))
    assert response.success and response.cloud.height == PROFILES, response.message
    assert response.message.endswith("; the scanner announced 20 profiles for 30 mm every 0.15 mm, which gives 201")
    again = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S, length_mm=2.85, step_mm=0.15))   # 20 profiles
    assert again.success and again.message.endswith("by time at the nominal speed"), again.message


def test_malformed_profiles_and_foreign_ends_of_sweep_are_dropped_counted_and_survived(ros_context, add_node,
                                                                                       client):
    add_node(ScanAcquisitionNode(context=ros_context))
    HostileScanner(add_node(Node("fake_scanner", namespace=NAMESPACE, context=ros_context)), "complete")
    acquire = client(AcquireSweep, "scan/acquire")
    response = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))
    assert response.success, response.message
    assert response.cloud.height == PROFILES                      # all good profiles, none of the others
    assert response.message.endswith(f"; dropped {len(malformed_clouds()) + 1} profile(s) malformed")
    again = acquire(AcquireSweep.Request(timeout_s=TIMEOUT_S))   # the node still serves
    assert again.success, again.message
