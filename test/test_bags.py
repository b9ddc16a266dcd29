"""Record a simulated calibration to a rosbag2 bag and replay it (bag_io, RecordingCell, gls-measure --bag)."""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import re
import sqlite3

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from gls_calibration.calibration import procedure
from gls_calibration.calibration.record import build_record, save_candidate
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.cli.sim_record import sweep_length_mm
from gls_calibration.cli.measure import csv_text, measure_cloud
from gls_calibration.cli.measure import main as measure_main
from gls_calibration.fiducials.measure import measure_fiducials
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.registration.sweep_plan import parse_plan
from gls_calibration.scan.bag_io import BagLayout, BagRecorder, ReplayLimits, read_sweeps
from gls_calibration.scan.plate_pose import estimate_plate_pose, mean_plate_pose, pose_at_height
from gls_calibration.simulation.recording_cell import SIM_FLANGE_TO_SENSOR, RecordingCell, base_to_gls
from gls_calibration.simulation.scanner import pose_matrix
from gls_calibration.simulation.world import SimulatedCell, load_sim_config

GRID = 3
GRID_SIZE_MM = 80.0
PLAIN_SWEEPS = 2
PLAN = "0+,90-"      # forward, then reversed with the sensor turned: the chain's rotations matter


def _small_config(preset: str):
    config = load_sim_config(preset=preset)
    # the sweep length of config/gls.yaml, which gls-train reads (the error separation measures from its middle)
    return dataclasses.replace(config, scanner=dataclasses.replace(config.scanner, line_length_mm=120.0),
                               sweep_length_mm=sweep_length_mm(), scanner_to_gls=None)


def _record(folder, preset: str, storage: str):
    """A one-iteration calibration of a 3x3 grid (plan ``PLAN``) on the direct cell, recorded into
    ``folder / 'bag'``."""
    config = _small_config(preset)
    with BagRecorder(folder / "bag", SIM_FLANGE_TO_SENSOR, base_to_gls(config), storage=storage) as recorder:
        cell = RecordingCell(SimulatedCell(config), CalibrationStore(folder / "store"), recorder=recorder)
        settings = cell.settings(grid_per_side=GRID, grid_size_mm=GRID_SIZE_MM, plain_sweeps=PLAIN_SWEEPS,
                                 plain_sweep_step_mm=2.0, sweep_plan=parse_plan(PLAN))

        def save(runs, models):
            return save_candidate(cell.store, build_record(config.geometry, settings, runs, models, []),
                                  config.geometry)
        asyncio.run(procedure.calibrate(cell, settings, iterations=1, validate=False, force=True, want_truth=False,
                                        progress=lambda *args: None, save_candidate=save))
    return cell, folder / "bag"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    return _record(tmp_path_factory.mktemp("recorded"), "paper_like", "sqlite3")


def _replay_as_the_procedure(bag, cell):
    """Plate pose from the plain sweeps, its height from the stand-still, fiducials of the marked sweeps,
    with the direct cell's own calls."""
    sweeps = read_sweeps(bag)
    assert [sweep.standstill for sweep in sweeps] == [False] * PLAIN_SWEEPS + [True] + [False] * len(parse_plan(PLAN))
    poses = [estimate_plate_pose(sweep.xyz_mm.reshape(-1, 3), head_direction=(0.0, 0.0, -1.0))
             for sweep in sweeps[:PLAIN_SWEEPS]]
    pose = pose_at_height(mean_plate_pose(poses), sweeps[PLAIN_SWEEPS].xyz_mm.reshape(-1, 3))
    found = [measure_fiducials(sweep.xyz_mm, sweep.intensity, pose,
                               ring_radii_mm=procedure.ProcedureSettings.ring_radii_mm, expected_count=GRID ** 2)
             for sweep in sweeps[PLAIN_SWEEPS + 1:]]
    return sweeps, poses, found


def test_replaying_the_bag_gives_the_live_fiducial_centres(recorded):
    cell, bag = recorded
    sweeps, poses, found = _replay_as_the_procedure(bag, cell)
    assert (cell.sweeps, cell.standstills) == (PLAIN_SWEEPS + len(cell.live_measurements), 1)
    assert len(sweeps) == cell.sweeps + cell.standstills
    for replayed, live in zip(poses, cell.live_poses):
        assert np.max(np.abs(replayed.centre - live.centre)) <= 1e-9
        assert np.max(np.abs(replayed.normal - live.normal)) <= 1e-12
    assert len(found) == len(cell.live_measurements) >= 1
    for replayed, live in zip(found, cell.live_measurements):
        assert len(live.centres) == GRID ** 2
        assert np.asarray(replayed.centres).shape == np.asarray(live.centres).shape
        assert np.max(np.abs(np.asarray(replayed.centres) - np.asarray(live.centres))) <= 1e-9    # mm
        assert np.max(np.abs(np.asarray(replayed.sigma_xy_mm) - np.asarray(live.sigma_xy_mm))) <= 1e-9


def test_the_bag_holds_only_standard_types_in_metres(recorded):
    _, bag = recorded
    store = get_typestore(Stores.ROS2_JAZZY)
    layout = BagLayout()
    with Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {layout.scan_topic: "sensor_msgs/msg/PointCloud2", "/tf": "tf2_msgs/msg/TFMessage",
                         "/tf_static": "tf2_msgs/msg/TFMessage", "/motion/start": "std_msgs/msg/Header",
                         "/motion/end": "std_msgs/msg/Header"}
        static = []
        profile = None
        for connection, _, raw in reader.messages([c for c in reader.connections
                                                   if c.topic in ("/tf_static", layout.scan_topic)]):
            message = store.deserialize_cdr(raw, connection.msgtype)
            if connection.topic == "/tf_static":
                static += [(t.header.frame_id, t.child_frame_id) for t in message.transforms]
            elif profile is None:
                profile = message
    assert sorted(static) == [("flange", "scanner_optical"), ("robot_base", "gls")]
    assert profile.header.frame_id == "scanner_optical" and profile.height == 1
    assert [(f.name, f.datatype) for f in profile.fields] == [(n, 7) for n in ("x", "y", "z", "intensity")]
    points = np.frombuffer(profile.data.tobytes(), dtype=np.float32).reshape(-1, 4)
    assert 0.2 < np.nanmedian(points[:, 2]) < 0.45      # the plate at about 325 mm, written in metres


def test_gls_measure_bag_measures_every_sweep(recorded, tmp_path, capsys):
    cell, bag = recorded
    out = tmp_path / "out"
    assert measure_main(["--bag", str(bag), "--grid", str(GRID), "--size", str(GRID_SIZE_MM),
                         "--out", str(out)]) == 0, capsys.readouterr().err
    folders = sorted(path.name for path in out.iterdir() if path.is_dir())
    # every motion but the stand-still (motion PLAIN_SWEEPS + 1: one line of profiles, nothing to measure)
    motions = cell.sweeps + cell.standstills
    assert folders == [f"sweep_{n:02d}" for n in range(1, motions + 1) if n != PLAIN_SWEEPS + 1]
    # each sweep measured as `gls-measure --cloud` measures one cloud (its own plate pose, polarity found)
    arguments = argparse.Namespace(grid=GRID, rings=RING_RADII_MM, pixel=0.1)
    sweeps = [sweep for sweep in read_sweeps(bag) if not sweep.standstill]
    for folder, sweep in zip(folders, sweeps):
        _, measurement, _ = measure_cloud(sweep.xyz_mm, sweep.intensity, arguments)
        assert (out / folder / "centres.csv").read_text() == csv_text(measurement)
    assert len((out / folders[-1] / "centres.csv").read_text().splitlines()) == 1 + GRID ** 2
    assert (out / "sweeps.json").is_file()


def test_an_mcap_bag_replays_like_sqlite(tmp_path):
    cell, bag = _record(tmp_path, "ideal", "mcap")
    assert any(path.suffix == ".mcap" for path in bag.iterdir())
    _, _, found = _replay_as_the_procedure(bag, cell)
    assert np.max(np.abs(np.asarray(found[0].centres) - np.asarray(cell.live_measurements[0].centres))) <= 1e-9


# ------------------------------------------------------------------------------------------ bad input

WIDTH, ROWS = 40, 30
PERIOD_NS = 10_000_000          # a 100 Hz scanner
START_NS = 1_000 * 1_000_000_000


def _synthetic_bag(path, *, profiles_scale=1.0, drop_profiles=(), flange_every=1, motions=1, end=True, stray=0):
    """A bag of ``motions`` short sweeps over a flat plate 0.3 m below the sensor, written with BagRecorder."""
    x = np.linspace(-0.02, 0.02, WIDTH)
    profiles = np.zeros((ROWS, WIDTH, 4))
    profiles[..., 0], profiles[..., 2], profiles[..., 3] = x, 0.3, 0.5
    profiles[..., :3] *= profiles_scale
    flange_to_sensor = pose_matrix([0.0, 0.0, 100.0], [0.0, 0.0, 0.0])
    recorder = BagRecorder(path, flange_to_sensor, np.eye(4))
    with recorder:
        for motion in range(motions):
            start = START_NS + motion * 10 * ROWS * PERIOD_NS
            stamps = start + PERIOD_NS * np.arange(ROWS)
            flange = np.repeat(np.eye(4)[None], ROWS, axis=0)
            flange[:, 1, 3] = np.arange(ROWS) * 0.1
            keep = [row for row in range(ROWS) if row not in drop_profiles]
            every = sorted(set(range(0, ROWS, flange_every)) | {ROWS - 1})
            recorder.write_sweep(int(stamps[0]), int(stamps[-1]), stamps[keep], profiles[keep],
                                 stamps[every], flange[every])
            if stray:    # the scanner keeps streaming after the motion, the robot keeps reporting
                after = stamps[-1] + PERIOD_NS * np.arange(1, stray + 1)
                recorder.write_stream(after, profiles[:stray] + 0.01, after, flange[-1:].repeat(stray, axis=0))
    if not end:      # the recording was cut before the last motion's end: delete that message
        db = next(path.glob("*.db3"))
        with sqlite3.connect(db) as connection:
            topic = connection.execute("SELECT id FROM topics WHERE name = '/motion/end'").fetchone()[0]
            connection.execute("DELETE FROM messages WHERE topic_id = ? AND timestamp = "
                               "(SELECT MAX(timestamp) FROM messages WHERE topic_id = ?)", (topic, topic))
    return path


def test_a_synthetic_bag_is_placed_through_the_chain(tmp_path):
    sweeps = read_sweeps(_synthetic_bag(tmp_path / "bag", motions=2, flange_every=3, stray=5))
    assert len(sweeps) == 2     # the profiles streamed between the motions belong to neither
    xyz = sweeps[0].xyz_mm
    assert xyz.shape == (ROWS, WIDTH, 3)
    # flange at y = 0.1 mm per row, sensor 100 mm below it along z, plate 300 mm further: exact positions
    np.testing.assert_allclose(xyz[:, :, 1], np.repeat((np.arange(ROWS) * 0.1)[:, None], WIDTH, 1), atol=1e-9)
    np.testing.assert_allclose(xyz[:, :, 2], 400.0, atol=1e-4)       # float32 metres -> about 0.03 um
    np.testing.assert_allclose(xyz[0, :, 0], np.linspace(-20.0, 20.0, WIDTH), atol=1e-4)


@pytest.mark.parametrize("build, layout, limits, message", [
    (dict(), BagLayout(scan_topic="/laser"), ReplayLimits(), "topic /laser is not in the bag"),
    (dict(), BagLayout(base_frame="world"), ReplayLimits(), "frame world is not in the transform tree"),
    (dict(flange_every=10), BagLayout(), ReplayLimits(max_pose_age_s=0.05),
     r"the newest pose of flange in robot_base is 0.06 s older than 1000060000000 ns \(limit 0.05 s\)"),
    (dict(drop_profiles=range(10, 20)), BagLayout(), ReplayLimits(), "the profile stream stops for 0.11 s"),
    (dict(drop_profiles=range(20, 30)), BagLayout(), ReplayLimits(), "before the motion ends"),
    (dict(profiles_scale=1000.0), BagLayout(), ReplayLimits(), "the cloud is not in metres"),
    (dict(motions=2, end=False), BagLayout(), ReplayLimits(), "has no end"),
])
def test_bad_bags_are_refused_with_the_problem_named(tmp_path, build, layout, limits, message):
    bag = _synthetic_bag(tmp_path / "bag", **build)
    with pytest.raises(ValueError, match=message):
        read_sweeps(bag, layout, limits)


def test_gls_measure_refuses_bad_bags_and_writes_nothing(tmp_path, capsys):
    bag = _synthetic_bag(tmp_path / "bag")
    out = tmp_path / "out"
    common = ["--grid", "3", "--size", "80", "--out", str(out)]
    assert measure_main(["--bag", str(bag), "--scan-topic", "/laser"] + common) == 2
    assert "topic /laser is not in the bag" in capsys.readouterr().err
    assert measure_main(["--bag", str(bag), "--sensor-frame", "camera"] + common) == 2
    assert "not 'camera'" in capsys.readouterr().err
    db = next(bag.glob("*.db3"))
    db.write_bytes(db.read_bytes()[: db.stat().st_size // 3])          # truncated
    assert measure_main(["--bag", str(bag)] + common) == 2
    assert "unreadable bag" in capsys.readouterr().err
    assert measure_main(["--bag", str(tmp_path / "none")] + common) == 2
    assert "no such bag" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("build, options, message", [
    (dict(), ["--scan-topic", "/laser"], "topic /laser is not in the bag"),
    (dict(), ["--base-frame", "world"], "frame world is not in the transform tree"),
    (dict(flange_every=10), [], r"is 0.06 s older than \d+ ns \(limit 0.05 s\)"),
    (dict(drop_profiles=range(20, 30)), [], "before the motion ends"),
    (dict(profiles_scale=1000.0), [], r"median point distance 300.2 m exceeds 10 m: the cloud is not in metres"),
    (dict(), ["TRUNCATE"], "unreadable bag"),
    (dict(), ["MISSING"], "no such bag"),
])
def test_gls_train_refuses_bad_bags_and_writes_nothing(tmp_path, capsys, build, options, message):
    """Each bad input of a recording (issue 28) is exit 2 with the problem named; no calibration, no report."""
    from gls_calibration.cli.train import main as train_main

    bag = _synthetic_bag(tmp_path / "bag", **build)
    if "TRUNCATE" in options:
        db = next(bag.glob("*.db3"))
        db.write_bytes(db.read_bytes()[: db.stat().st_size // 3])
    if "MISSING" in options:
        bag = tmp_path / "none"
    out = tmp_path / "calibration.yaml"
    given = [option for option in options if option not in ("TRUNCATE", "MISSING")]
    assert train_main(["--bag", str(bag), "--out", str(out), "--force"] + given) == 2
    assert re.search(message, capsys.readouterr().err)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["bag"]


def test_a_failed_recording_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with BagRecorder(tmp_path / "bag", np.eye(4), np.eye(4)):
            raise RuntimeError("the cell failed")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "bag").mkdir()
    with pytest.raises(ValueError, match="exists already"):
        BagRecorder(tmp_path / "bag", np.eye(4), np.eye(4))


@pytest.mark.slow
def test_gls_sim_cell_records_a_bag_that_replays(tmp_path, capsys):
    from gls_calibration.cli.sim_cell import main as sim_cell_main
    from gls_calibration.simulation.reference_plate import calibration_plan

    bag = tmp_path / "bag"
    assert sim_cell_main(["--out", str(tmp_path / "out"), "--record", str(bag), "--grid", "3", "--no-validate",
                          "--sweep-plan", "0+", "--measurement", "ideal"]) == 0, capsys.readouterr().err
    plain = calibration_plan().plain_sweeps     # sweep.plain_repeats of config/gls.yaml, as the cell reads it
    assert plain >= 1
    # the plain sweeps, the stand-still and 1 marked
    assert f"recorded {plain + 1} sweep(s) and 1 stand-still(s)" in capsys.readouterr().out
    sweeps = read_sweeps(bag)
    # sweeps of sweep.length_mm (config/gls.yaml): plain at 1 mm, marked at 0.1 mm; 20 profiles standing
    length = sweep_length_mm()
    profiles = [round(length) + 1] * plain + [20] + [round(length / 0.1) + 1]
    assert [sweep.xyz_mm.shape[0] for sweep in sweeps] == profiles
    assert [sweep.standstill for sweep in sweeps] == [False] * plain + [True, False]


@pytest.mark.parametrize("extra, message", [
    (["--serve"], "not with --serve"),
    (["--placement", "time"], "not with --placement time"),
])
def test_gls_sim_cell_record_refuses_bad_options(tmp_path, capsys, extra, message):
    from gls_calibration.cli.sim_cell import main as sim_cell_main

    with pytest.raises(SystemExit) as stopped:
        sim_cell_main(["--out", str(tmp_path / "out"), "--record", str(tmp_path / "bag")] + extra)
    assert stopped.value.code == 2
    assert message in capsys.readouterr().err
    (tmp_path / "bag").mkdir()
    with pytest.raises(SystemExit) as stopped:
        sim_cell_main(["--out", str(tmp_path / "out"), "--record", str(tmp_path / "bag")])
    assert stopped.value.code == 2
    assert "exists already" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_gls_train_bag_reproduces_the_recorded_calibration(recorded, tmp_path, capsys):
    from gls_calibration.cli.train import main as train_main

    cell, bag = recorded
    out = tmp_path / "replayed.yaml"
    arguments = ["--bag", str(bag), "--out", str(out), "--grid", str(GRID), "--grid-size", str(GRID_SIZE_MM),
                 "--sweep-plan", PLAN, "--plain-sweeps", str(PLAIN_SWEEPS), "--force"]
    assert train_main(arguments) == 0, capsys.readouterr().err
    (live,) = cell.store.history()

    def content(path):
        return [line for line in path.read_text().splitlines() if not line.startswith("created_utc:")]
    assert content(out) == content(live)          # the same calibration, number for number
    report = tmp_path / "replayed.yaml.report"
    assert {"report.md", "summary.json", "training.csv", "fiducials.csv"} <= {p.name for p in report.iterdir()}
    # a plate takes 5 motions (2 plain, the stand-still, 2 marked): with 3 plain sweeps the bag does not hold
    # whole plates
    again = tmp_path / "again.yaml"
    assert train_main(arguments[:2] + ["--out", str(again)] + arguments[4:10] + ["--plain-sweeps", "3"]) == 2
    assert "a plate takes 6 (3 plain, 1 stand-still and 2 marked)" in capsys.readouterr().err
    assert not again.exists() and not (tmp_path / "again.yaml.report").exists()
    # told the recording has no stand-still, the replay finds one where it expects the first marked sweep
    assert train_main(arguments[:2] + ["--out", str(again)] + arguments[4:] + ["--no-standstill-height",
                                                                               "--plain-sweeps", "3"]) == 1
    assert re.search(r"the bag's motion 3 travels 0\.\d+ mm: a stand-still where the calibration asks for a sweep",
                     capsys.readouterr().err)
    assert not again.exists() and not (tmp_path / "again.yaml.report").exists()


def test_gls_train_refuses_a_bag_swept_with_another_length(recorded, tmp_path, capsys, monkeypatch):
    """A recording is combined about its sweeps' middle: replayed with another sweep.length_mm, exit 2."""
    from gls_calibration.cli import sim_record
    from gls_calibration.cli.train import main as train_main

    _, bag = recorded
    length = sweep_length_mm()
    monkeypatch.setattr(sim_record, "sweep_length_mm", lambda: length + 10.0)     # gls.yaml edited since
    out = tmp_path / "replayed.yaml"
    assert train_main(["--bag", str(bag), "--out", str(out), "--grid", str(GRID), "--grid-size", str(GRID_SIZE_MM),
                       "--sweep-plan", PLAN, "--plain-sweeps", str(PLAIN_SWEEPS), "--force"]) == 2
    assert (f"motion 0 of the bag travels {length:.1f} mm, sweep.length_mm of config/gls.yaml is {length + 10:g} mm"
            in capsys.readouterr().err)
    assert not out.exists() and not (tmp_path / "replayed.yaml.report").exists()


def test_the_tf_buffer_interpolates_and_names_what_is_missing():
    from gls_calibration.scan.tf_buffer import TfBuffer

    buffer = TfBuffer()
    buffer.set_transform("base", "flange", 0, pose_matrix([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    buffer.set_transform("base", "flange", 100, pose_matrix([10.0, 20.0, 0.0], [0.0, 0.0, np.pi / 2]))
    buffer.set_transform("flange", "sensor", 0, pose_matrix([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]), static=True)
    buffer.set_transform("base", "gls", 0, pose_matrix([0.0, 0.0, 5.0], [0.0, 0.0, 0.0]), static=True)
    # a quarter of the way: translation (2.5, 5, 0), rotation 22.5 deg about z; the sensor 1 mm along x of it
    angle = np.pi / 8
    expected = pose_matrix([2.5 + np.cos(angle), 5.0 + np.sin(angle), 0.0], [0.0, 0.0, angle])
    np.testing.assert_allclose(buffer.lookup("base", "sensor", 25, max_age_ns=100), expected, atol=1e-12)
    # between two branches of the tree: gls -> base -> flange -> sensor
    in_gls = buffer.lookup("gls", "sensor", 25, max_age_ns=100)
    np.testing.assert_allclose(in_gls[:3, 3], expected[:3, 3] - [0.0, 0.0, 5.0], atol=1e-12)
    with pytest.raises(ValueError, match=r"is 2.5e-08 s older than 25 ns \(limit 1e-08 s\)"):
        buffer.lookup("base", "sensor", 25, max_age_ns=10)
    with pytest.raises(ValueError, match="no pose of flange in base after 150 ns"):
        buffer.lookup("base", "sensor", 150, max_age_ns=100)
    with pytest.raises(ValueError, match="frame camera is not in the transform tree"):
        buffer.lookup("base", "camera", 25, max_age_ns=100)
    with pytest.raises(ValueError, match="frame sensor has two parents"):
        buffer.set_transform("gls", "sensor", 0, np.eye(4), static=True)
    bent = np.eye(4)
    bent[0, 0] = 1.01
    with pytest.raises(ValueError, match="does not hold a proper rotation"):
        buffer.set_transform("base", "flange", 200, bent)
    buffer.set_transform("world", "table", 0, np.eye(4), static=True)
    with pytest.raises(ValueError, match="no transform from table to base"):
        buffer.lookup("base", "table", 25, max_age_ns=100)
