"""sim_scanner's hooks for sweep plans: direction, orientation and the reported pose per profile."""
from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from gls_calibration.nodes.scan_acquisition import ScanAcquisitionNode
from gls_calibration.nodes.sim_galvo import SimGalvoNode
from gls_calibration.nodes.sim_scanner import LISTENER_WAIT_S, SimScannerNode
from gls_calibration.ros import conversions
from gls_calibration.simulation.world import load_sim_config
from gls_calibration_msgs.msg import SweepDone
from gls_calibration_msgs.srv import AcquireSweep, StartSweep

from ros_helpers import wait_for


def test_sweep_direction_orientation_and_reported_pose_stream(start_cell):
    cell = start_cell(node_types=(SimGalvoNode, SimScannerNode), parameters={"measurement_preset": "paper_like"})
    poses, stamps, done = [], [], []
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    cell.client_node.create_subscription(PoseStamped, "scan/pose", poses.append, qos)
    cell.client_node.create_subscription(PointCloud2, "scan/points", lambda m: stamps.append(m.header.stamp), qos)
    cell.client_node.create_subscription(SweepDone, "scan/sweep_done", done.append, qos)
    refused = cell.call(StartSweep, "scanner/start_sweep", StartSweep.Request(length_mm=2.0, orientation_deg=30.0),
                        10.0)
    assert not refused.success and "orientation_deg 0, 45 or 90" in refused.message
    refused = cell.call(StartSweep, "scanner/start_sweep", StartSweep.Request(length_mm=2.0, direction=2), 10.0)
    assert not refused.success and "direction must be +1 or -1" in refused.message
    started = cell.call(StartSweep, "scanner/start_sweep",
                        StartSweep.Request(length_mm=2.0, step_mm=0.1, direction=-1, orientation_deg=90.0), 10.0)
    assert started.success and started.expected_profiles == 21
    wait_for(lambda: done and len(poses) == 21 and len(stamps) == 21, 20.0, what="the sweep, its poses and profiles")
    assert list(done[0].direction) == [0.0, -1.0, 0.0]
    # one pose per profile, stamped like it, in the scanner base frame (metres)
    assert [(p.header.stamp.sec, p.header.stamp.nanosec) for p in poses] == [(s.sec, s.nanosec) for s in stamps]
    assert all(p.header.frame_id == "scanner_base" for p in poses)
    x = np.array([p.pose.position.x for p in poses]) * 1e3
    y = np.array([p.pose.position.y for p in poses]) * 1e3
    # turned 90 deg and running backwards: the sensor moves along base +x, about 0.1 mm per profile
    # (the paper_like robot's speed error and ripple make the reported steps uneven)
    assert np.allclose(y, 1.0, atol=1e-9) and abs(x[0] + 1.0) < 0.4
    assert np.all(np.diff(x) > 0.05) and abs(x[-1] - x[0] - 2.0) < 0.2
    q = poses[0].pose.orientation
    assert np.allclose([q.x, q.y, abs(q.z), abs(q.w)], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])


def test_a_sweep_waits_for_its_listeners_before_publishing(start_cell):
    """Profiles published before the scanner's writers know the acquisition's readers would be lost
    (volatile topics): a sweep nobody listens to is held back LISTENER_WAIT_S, then goes out; with
    matched listeners every profile arrives."""
    cell = start_cell(node_types=(SimGalvoNode, SimScannerNode))
    asked = time.monotonic()
    started = cell.call(StartSweep, "scanner/start_sweep", StartSweep.Request(length_mm=2.0, step_mm=0.1), 20.0)
    assert started.success and time.monotonic() - asked >= LISTENER_WAIT_S - 0.05
    stamps, done = [], []
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    subscriptions = [
        cell.client_node.create_subscription(PointCloud2, "scan/points", lambda m: stamps.append(m.header.stamp), qos),
        cell.client_node.create_subscription(PoseStamped, "scan/pose", lambda m: None, qos),
        cell.client_node.create_subscription(SweepDone, "scan/sweep_done", done.append, qos)]
    # As scan_acquisition does: ask for a sweep once this side has matched the scanner's writers.
    wait_for(lambda: all(subscription.get_publisher_count() for subscription in subscriptions), 20.0,
             what="the scanner's publishers")
    time.sleep(0.5)   # the first sweep's profiles, if any were still in flight
    stamps.clear()
    started = cell.call(StartSweep, "scanner/start_sweep", StartSweep.Request(length_mm=2.0, step_mm=0.1), 20.0)
    assert started.success and started.expected_profiles == 21
    wait_for(lambda: any(end.sweep_id == started.sweep_id for end in done), 20.0, what="the end of the sweep")
    # The end of sweep travels on its own topic and may overtake the last profiles.
    wait_for(lambda: len(stamps) >= 21, 20.0, what="every profile of the sweep")
    assert len(stamps) == 21


def test_a_standstill_is_placed_where_the_sensor_stands_and_leaves_the_sweep_ids_alone(start_cell):
    """Issue 31 item 5: profiles taken standing still at the marking pose, through scan_acquisition;
    an earlier attempt numbered them as sweeps and every later sweep's draws moved."""
    cell = start_cell(node_types=(SimGalvoNode, SimScannerNode, ScanAcquisitionNode))
    still = cell.call(AcquireSweep, "scan/acquire_standstill", AcquireSweep.Request(length_mm=2.0, step_mm=0.1), 60.0)
    assert still.success and still.placed_by_pose, still.message
    points, intensity = conversions.cloud_arrays_from_msg(still.cloud)
    assert points.shape[0] == 21
    finite = np.all(np.isfinite(points), axis=-1)
    # no travel: every profile on the line over the middle of the sweep (scanner base frame, mm)
    middle_mm = 0.5 * load_sim_config().sweep_length_mm
    assert finite.sum() > 1000 and np.allclose(points[finite][:, 1], middle_mm, atol=1e-3)
    refused = cell.call(StartSweep, "scanner/start_standstill", StartSweep.Request(length_mm=2.0, orientation_deg=90.0),
                        10.0)
    assert not refused.success and "a stand-still is taken at orientation 0" in refused.message
    started = cell.call(StartSweep, "scanner/start_sweep", StartSweep.Request(length_mm=2.0, step_mm=0.1), 20.0)
    assert started.success and started.sweep_id == 1


def test_a_standstill_without_the_pose_stream_is_refused(start_cell):
    """Without travel the time cannot place the profiles: only the reported pose can."""
    cell = start_cell(node_types=(SimGalvoNode, SimScannerNode, ScanAcquisitionNode),
                      node_parameters={"scan_acquisition": {"use_pose_stream": False}})
    refused = cell.call(AcquireSweep, "scan/acquire_standstill", AcquireSweep.Request(length_mm=2.0, step_mm=0.1), 30.0)
    assert not refused.success
    assert refused.message == ("a stand-still acquisition needs the reported pose (use_pose_stream is false): "
                               "without travel the time cannot place its profiles")


def test_the_scanner_sees_the_galvos_plate_whatever_the_process_simulated_before(start_cell):
    """The scanner rebuilds the galvo's plate from the id the galvo reports: the same texture and the
    same per-plate draws (marking-pose error, thermal scale, warp), on the first plate and after an
    exchange. An in-process cell used to seed its copy from a count of every plate the process had
    made, so it saw another plate than the galvo's, and a different one after other tests had run
    (test_record_once found 8 of 9 fiducials after test_bags and test_stream_calibrate)."""
    for _ in range(3):      # plates of earlier cells in this process must not matter
        load_sim_config(preset="paper_like").make_plate()
    cell = start_cell(node_types=(SimGalvoNode, SimScannerNode), parameters={"measurement_preset": "paper_like"})
    galvo, scanner = cell.nodes["sim_galvo"].plate, cell.nodes["sim_scanner"].plate
    uv = np.stack(np.meshgrid(np.linspace(-100.0, 100.0, 41), np.linspace(-100.0, 100.0, 41)), axis=-1).reshape(-1, 2)
    for plate_id in (0, 1):
        if plate_id:
            assert cell.call(Trigger, "sim/exchange_plate", Trigger.Request(), 10.0).success
        # a sweep loads the galvo's plate into the scanner (nobody listens: it goes out after the wait)
        started = cell.call(StartSweep, "scanner/start_sweep", StartSweep.Request(length_mm=0.2, step_mm=0.1),
                            LISTENER_WAIT_S + 10.0)
        assert started.success, started.message
        wait_for(lambda: cell.nodes["sim_scanner"].job is None, 20.0, what="the end of the sweep")
        assert galvo.marking_pose_error == scanner.marking_pose_error and galvo.marking_pose_error != (0.0, 0.0, 0.0)
        assert galvo.thermal_scale == scanner.thermal_scale != 0.0
        np.testing.assert_array_equal(scanner.warp(uv), galvo.warp(uv))
        np.testing.assert_array_equal(scanner.reflectivity(uv), galvo.reflectivity(uv))
        assert galvo.plate_id == scanner.plate_id == plate_id
