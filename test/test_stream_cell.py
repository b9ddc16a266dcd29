"""The simulated streaming cell (sim_robot + sim_line_scanner + stream_acquisition) gives the clouds of
the direct cells for the same seed: those of RecordingCell (the same float32-metre streams assembled
by the same code) to 1e-6 mm after the answer's float32 metres, and DirectCell's to float32 precision."""
from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from std_srvs.srv import SetBool
from tf2_msgs.msg import TFMessage

from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.common.config_files import config_path
from gls_calibration.nodes.sim_line_scanner import SimLineScannerNode
from gls_calibration.nodes.sim_robot import SimRobotNode
from gls_calibration.nodes.stream_acquisition import StreamAcquisitionNode
from gls_calibration.ros import conversions
from gls_calibration.ros.stream_topics import static_qos, transform_msg
from gls_calibration.scan.bag_io import BagRecorder
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.recording_cell import SIM_FLANGE_TO_SENSOR, RecordingCell, base_to_gls
from gls_calibration.simulation.world import SimulatedCell, load_sim_config
from gls_calibration_msgs.srv import AcquireSweep

from ros_helpers import call_service, wait_for

PRESET, SEED = "paper_like", 1
STEP_MM = 1.0
PROFILE_RATE_HZ = 150.0
FLOAT32_MM = 1e-4          # float32 metres near 0.3 m: about 3e-5 mm


@pytest.fixture
def stream_cell(ros_context, add_node):
    """start(**acquisition_parameters) -> robot, scanner, acquisition and a client node, in-process."""
    def parameters(**values):
        return [Parameter(name, value=value) for name, value in values.items()]

    def start(**acquisition_parameters):
        # TF at twice the profile rate: a sample at every profile's stamp, so that interpolation adds nothing
        robot = add_node(SimRobotNode(context=ros_context, parameter_overrides=parameters(
            measurement_preset=PRESET, seed=SEED, tf_rate_hz=2 * PROFILE_RATE_HZ, profile_rate_hz=PROFILE_RATE_HZ)))
        scanner = add_node(SimLineScannerNode(robot, context=ros_context))
        acquisition = add_node(StreamAcquisitionNode(context=ros_context, parameter_overrides=parameters(
            profile_rate_hz=PROFILE_RATE_HZ, end_grace_s=0.5, **acquisition_parameters)))
        client_node = add_node(rclpy.create_node("stream_cell_test", namespace="gls", context=ros_context))
        return robot, scanner, acquisition, client_node
    return start


def _call(client_node, service: str, request, srv=AcquireSweep):
    return call_service(client_node, client_node.create_client(srv, service), request, timeout_s=60.0)


def test_streaming_cell_gives_the_direct_cells_clouds(stream_cell, tmp_path):
    robot, _, _, client_node = stream_cell()
    config = load_sim_config(preset=PRESET)
    assert config.seed == SEED
    direct = DirectCell(SimulatedCell(config), CalibrationStore(tmp_path / "direct"))
    profiles = round(config.sweep_length_mm / STEP_MM) + 1       # the sweeps of config/sim.yaml
    with BagRecorder(tmp_path / "bag", SIM_FLANGE_TO_SENSOR, base_to_gls(config)) as recorder:
        recording = RecordingCell(SimulatedCell(config), CalibrationStore(tmp_path / "recording"), recorder=recorder)
        for direction, orientation in ((1, 0.0), (-1, 90.0), (0, None)):
            if orientation is None:          # a stand-still: as many profiles as a sweep of its length
                answer = _call(client_node, "scan/acquire_standstill",
                               AcquireSweep.Request(length_mm=config.sweep_length_mm, step_mm=STEP_MM))
                expected, _ = asyncio.run(recording.acquire_standstill(profiles))
                reference, _ = asyncio.run(direct.acquire_standstill(profiles))
            else:
                answer = _call(client_node, "scan/acquire", AcquireSweep.Request(
                    length_mm=config.sweep_length_mm, step_mm=STEP_MM, direction=direction,
                    orientation_deg=orientation))
                expected, _ = asyncio.run(recording.acquire_sweep(STEP_MM, direction, orientation))
                reference, _ = asyncio.run(direct.acquire_sweep(STEP_MM, direction, orientation))
            assert answer.success, answer.message
            answered, _ = conversions.cloud_arrays_from_msg(answer.cloud)
            # RecordingCell's sweep through the same conversion to the answer's float32 metres
            expected_wire = conversions.cloud_to_msg(conversions.xyzi_array(expected, np.zeros(expected.shape[:2])),
                                                     "robot_base")
            expected, _ = conversions.cloud_arrays_from_msg(expected_wire)
            assert answered.shape == expected.shape == (profiles, 2101, 3)
            assert np.array_equal(np.isnan(answered), np.isnan(expected))
            assert np.nanmax(np.abs(answered - expected)) <= 1e-6
            assert np.array_equal(np.isnan(answered), np.isnan(reference))
            assert np.nanmax(np.abs(answered - reference)) <= FLOAT32_MM
    assert robot.refused == 0


def test_back_to_back_lines_do_not_overlap_in_time(stream_cell):
    # The simulation streams a motion faster than real time, so its stamps run ahead of the wall clock;
    # a line commanded at once after must still start after all the previous one streamed (seen: the
    # next motion stamped inside the last one, its profiles dropped as out of order).
    robot, _, acquisition, client_node = stream_cell()
    runs = []
    robot.run_listeners.append(runs.append)
    for _ in range(4):
        answer = _call(client_node, "scan/acquire", AcquireSweep.Request(length_mm=200.0, step_mm=10.0))
        assert answer.success, answer.message
        assert answer.cloud.height == 21, answer.message
        assert "0 out of order dropped" in answer.message, answer.message
    assert len(runs) == 4 and robot.refused == 0
    for previous, run in zip(runs, runs[1:]):
        assert previous.streamed_until_ns == previous.after_profiles()[0][-1]
        assert run.start_ns > previous.streamed_until_ns


def test_a_hand_eye_that_comes_after_the_request_is_waited_for(stream_cell):
    # /tf_static reaches a new subscriber after discovery: under load a request could come first (seen in
    # CI: "frame scanner_optical is not in the transform tree (frames: flange, robot_base)"). Here the
    # node has forgotten the hand-eye, which a separate static publisher (as a real cell's launch file
    # starts) sends 1 s after the request.
    robot, _, acquisition, client_node = stream_cell()
    wait_for(lambda: "scanner_optical" in acquisition.statics, 10.0, what="the robot's fixed frames")
    acquisition.statics.clear()
    client = client_node.create_client(AcquireSweep, "scan/acquire")
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(AcquireSweep.Request(length_mm=200.0, step_mm=10.0))
    time.sleep(1.0)
    assert not future.done() and "scanner_optical" not in acquisition.statics
    publisher = client_node.create_publisher(TFMessage, "/tf_static", static_qos())
    publisher.publish(TFMessage(transforms=[
        transform_msg(robot.frames.flange, robot.frames.sensor, robot.frames.flange_to_sensor, 0)]))
    wait_for(future.done, 60.0, what="the sweep's answer")
    answer = future.result()
    assert answer.success, answer.message
    assert answer.cloud.height == 21


def test_without_the_hand_eye_the_line_is_not_commanded(stream_cell, tmp_path):
    frames = config_path("cell_frames.yaml").read_text()
    assert "sensor: scanner_optical" in frames
    other = tmp_path / "cell_frames.yaml"
    other.write_text(frames.replace("sensor: scanner_optical", "sensor: other_optical"))
    robot, _, _, client_node = stream_cell(cell_frames=str(other))
    runs = []
    robot.run_listeners.append(runs.append)
    answer = _call(client_node, "scan/acquire", AcquireSweep.Request(length_mm=200.0, step_mm=10.0))
    assert not answer.success
    assert answer.message.startswith("no fixed transform from flange to other_optical on /tf_static within 5 s "
                                     "(fixed frames received: "), answer.message
    assert "flange -> scanner_optical" in answer.message and answer.message.endswith("; line not commanded")
    assert not runs


def test_scanner_off_and_a_line_the_robot_refuses_fail_the_sweep(stream_cell):
    # the simulation stands still at the middle of its 200 mm sweep only: an acquisition that takes the
    # marking pose at the middle of 100 mm commands a line the robot refuses
    robot, scanner, _, client_node = stream_cell(default_length_mm=100.0)
    off = _call(client_node, "scanner/enable", SetBool.Request(data=False), SetBool)
    assert off.success and not scanner.enabled
    silent = _call(client_node, "scan/acquire", AcquireSweep.Request(length_mm=200.0, step_mm=10.0, timeout_s=20.0))
    assert not silent.success and "0 profile(s) within the motion" in silent.message, silent.message
    assert _call(client_node, "scanner/enable", SetBool.Request(data=True), SetBool).success
    refused = _call(client_node, "scan/acquire_standstill",
                    AcquireSweep.Request(length_mm=100.0, step_mm=10.0, timeout_s=2.0))
    assert not refused.success
    assert refused.message == "the robot did not start the line within 2 s (nothing on /motion/start)"
    assert robot.refused == 1
    bad = _call(client_node, "scan/acquire", AcquireSweep.Request(length_mm=200.0, direction=2))
    assert not bad.success and bad.message == "direction must be +1, -1 or 0 (+1), got 2"


@pytest.mark.parametrize("extra, message", [
    ([], "--placement time needs --sweep-contract: the split cell places every profile through TF"),
    (["--streaming"], "--placement time needs --sweep-contract: the split cell places every profile through TF"),
    (["--sweep-contract", "--streaming"], "not allowed with argument"),
])
def test_sim_cell_places_by_time_only_on_the_sweep_contract(tmp_path, extra, message, capsys):
    from gls_calibration.cli.sim_cell import main as sim_cell_main

    with pytest.raises(SystemExit) as exit_:
        sim_cell_main(["--out", str(tmp_path / "out"), "--placement", "time"] + extra)
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("cell", ["--sweep-contract", "--streaming"])
@pytest.mark.parametrize("extra", [["--reference-plate"], ["--record", "BAG"]])
def test_sim_cell_refuses_a_cell_choice_where_no_ros_cell_runs(tmp_path, cell, extra, capsys):
    from gls_calibration.cli.sim_cell import main as sim_cell_main

    extra = [str(tmp_path / "bag") if item == "BAG" else item for item in extra]
    with pytest.raises(SystemExit) as exit_:
        sim_cell_main(["--out", str(tmp_path / "out"), cell] + extra)
    assert exit_.value.code == 2
    assert ("--sweep-contract and --streaming pick the ROS cell's scanner: not with --record or --reference-plate, "
            "which run no ROS cell") in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not (tmp_path / "bag").exists()


def test_sim_cell_runs_the_split_cell_by_default(tmp_path):
    """Without an option the ROS cell is the split one: its -p overrides ask sim_robot for the plate's marks."""
    from gls_calibration.cli import sim_cell

    split = sim_cell.parse_args(["--out", str(tmp_path / "out")])
    contract = sim_cell.parse_args(["--out", str(tmp_path / "out"), "--sweep-contract"])
    assert not split.sweep_contract and contract.sweep_contract
    assert '-p marks_service:="sim/marked_paths"' in " ".join(sim_cell.ros_arguments(split, tmp_path, tmp_path))
    assert "marks_service" not in " ".join(sim_cell.ros_arguments(contract, tmp_path, tmp_path))


@pytest.mark.slow
def test_sim_cell_split_cell_calibrates_as_the_sweep_contract_cell(tmp_path):
    """A whole (small) calibration through the split cell (the default) measures what the sweep-contract
    cell measures: the two differ by the float32 rounding of their streams only (3.4e-5 mm in RMS when
    written). Each cell runs as a user runs it, in a process of its own."""
    options = ["--grid", "3", "--no-validate", "--sweep-plan", "0+", "--measurement", "ideal", "--no-reference-check"]
    summaries = {}
    for name, extra in (("contract", ["--sweep-contract"]), ("split", [])):
        run = subprocess.run([sys.executable, "-m", "gls_calibration.cli.sim_cell", "--out", str(tmp_path / name)]
                             + options + extra, capture_output=True, text=True, timeout=240)
        assert run.returncode == 0, run.stderr[-3000:]
        summaries[name] = json.loads((tmp_path / name / "summary.json").read_text())
    today, streaming = summaries["contract"], summaries["split"]
    assert streaming["fiducials_found"] == today["fiducials_found"] == 9
    for key in ("pre_rms_mm", "pre_max_mm", "cv_rms_mm"):
        assert abs(streaming[key] - today[key]) < 1e-3, (key, streaming[key], today[key])


@pytest.mark.parametrize("serve", [False, True])
def test_a_one_shot_split_cell_keeps_its_streams_in_its_namespace(tmp_path, serve):
    # Two one-shot cells on one ROS domain met on /tf and the motion topics (a line refused, a sweep
    # without poses); a served cell keeps the absolute names that drivers and RViz use.
    from gls_calibration.cli import sim_cell

    args = sim_cell.parse_args(["--out", str(tmp_path)] + (["--serve"] if serve else []))
    namespace = sim_cell.cell_namespace(args)
    context = rclpy.Context()
    rclpy.init(args=sim_cell.ros_arguments(args, tmp_path / "store", tmp_path) + sim_cell.private_stream_remaps(args),
               context=context)
    try:
        node = rclpy.create_node("probe", namespace=namespace, context=context)
        for topic in ("/tf", "/tf_static", "/motion/line", "/motion/start", "/motion/end", "/scanner/profile"):
            assert node.resolve_topic_name(topic) == (topic if serve else f"/{namespace}{topic}")
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
