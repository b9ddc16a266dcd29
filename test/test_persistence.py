"""Tests of calibration persistence: atomic writes, the store's history/active pointer, validation."""
from __future__ import annotations

import copy
import math
import os
from pathlib import Path
import re

import numpy as np
import pytest
import yaml

import gls_calibration
from gls_calibration.calibration import record_file as persistence
from gls_calibration.calibration.record_file import (CalibrationFileError, dump_record, head_geometry, load_record,
                                                     new_record, validate_record)
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.common.files import atomic_write_text
from gls_calibration.geometry.kinematics import HeadGeometry


def make_record(seed: int = 0, count: int = 5) -> dict:
    """A complete, valid record with random float64 content, as a plain dict (tests change it)."""
    rng = np.random.default_rng(seed)
    targets = rng.uniform(-95.0, 95.0, (count, 2))
    deviations = rng.normal(0.0, 0.5, (count, 2))
    metrics = {"count": count, "max_abs_mm": float(np.max(np.hypot(*deviations.T))), "rms_abs_mm": 0.5}
    return new_record(
        head=HeadGeometry(),
        plate_pose={"normal": np.array([0.0, 0.0, 1.0]), "centre": rng.normal(size=3),
                    "rotation": np.eye(3), "flatness_rms_mm": 0.01},
        models=[{"type": "ols_rbf", "centres": rng.normal(size=(4, 2)), "weights": rng.normal(size=(4, 2)),
                 "bias": rng.normal(size=2), "spread_mm": 35.0}],
        calibrated_region={"type": "box", "x_min": -95.0, "x_max": 95.0, "y_min": -95.0, "y_max": 95.0},
        hyper_parameters={"spread_mm": 35.0, "mse_goal_mm2": 0.0005},
        metrics={"before": {"full": metrics},
                 "after": {"full": metrics, "50x50": {"count": 0, "rms_abs_mm": math.nan}}},
        fiducials={"target_x": targets[:, 0], "target_y": targets[:, 1],
                   "measured_x": targets[:, 0] + deviations[:, 0], "measured_y": targets[:, 1] + deviations[:, 1],
                   "measured_z": np.zeros(count), "dx": deviations[:, 0], "dy": deviations[:, 1]},
    ).to_dict()


def leftover_temp_files(directory: Path) -> list[Path]:
    return [path for path in directory.rglob("*") if path.name.endswith(".tmp")]


# ------------------------------------------------------------------------------- atomic writes


def test_atomic_write_creates_and_replaces(tmp_path):
    target = tmp_path / "file.yaml"
    atomic_write_text(target, "first\n")
    atomic_write_text(target, "second\n")
    assert target.read_text() == "second\n"
    assert leftover_temp_files(tmp_path) == []
    assert target.stat().st_mode & 0o777 == 0o644


def test_atomic_write_failure_keeps_old_file_and_removes_temp(tmp_path, monkeypatch):
    target = tmp_path / "file.yaml"
    target.write_text("old content\n")

    def failing_replace(source, destination):
        # The temp file exists and holds the full new text when the rename fails.
        assert Path(source).read_text() == "new content\n"
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(persistence.os, "replace", failing_replace)
    with pytest.raises(OSError, match="No space left on device"):
        atomic_write_text(target, "new content\n")
    assert target.read_text() == "old content\n"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["file.yaml"]


def test_atomic_write_failure_during_write_leaves_no_target(tmp_path, monkeypatch):
    target = tmp_path / "new.yaml"

    def failing_fsync(descriptor):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(persistence.os, "fsync", failing_fsync)
    with pytest.raises(OSError, match="Input/output error"):
        atomic_write_text(target, "text")
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_keeps_existing_mode(tmp_path):
    target = tmp_path / "private.yaml"
    target.write_text("x")
    target.chmod(0o600)
    atomic_write_text(target, "y")
    assert target.stat().st_mode & 0o777 == 0o600


# ------------------------------------------------------------------------------------- records


def test_new_record_fills_version_and_time():
    record = make_record()
    assert record["format_version"] == 2
    assert record["software_version"] == gls_calibration.__version__
    assert re.match(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{6}\+00:00$", record["created_utc"])
    assert record["head"] == {"working_distance_mm": 490.0, "mirror_distance_mm": 15.0,
                              "mirror_limit_rad": math.radians(10.5), "focus_range_mm": 25.0}
    # A metric that cannot be computed is stored as null, not NaN.
    assert record["metrics"]["after"]["50x50"]["rms_abs_mm"] is None
    assert head_geometry(record) == HeadGeometry()


def test_new_record_accepts_plate_pose_object():
    class Pose:  # stands in for plate_pose.PlatePose (same attribute names)
        normal = np.array([0.0, 0.0, 1.0])
        centre = np.zeros(3)
        rotation = np.eye(3)
        flatness_rms_mm = np.float64(0.02)
        inlier_count = 10

    base = make_record()
    record = new_record(head=base["head"], plate_pose=Pose(), models=[], calibrated_region=base["calibrated_region"],
                        hyper_parameters={}, metrics={}, fiducials=base["fiducials"])
    assert record["plate_pose"] == {"normal": [0.0, 0.0, 1.0], "centre": [0.0, 0.0, 0.0],
                                    "rotation": np.eye(3).tolist(), "flatness_rms_mm": 0.02}


def test_floats_survive_save_and_load_bit_for_bit(tmp_path):
    rng = np.random.default_rng(7)
    awkward = np.concatenate([rng.normal(size=50) * 10.0 ** rng.integers(-300, 300, 50),
                              [5e-324, 1e-5, 1e16, 0.1, 1.0 / 3.0, -0.0, 2.0 ** 0.5, np.finfo(float).max]])
    record = make_record()
    record["models"][0]["weights"] = awkward.tolist()
    store = CalibrationStore(tmp_path)
    loaded = store.load(store.save(record))
    restored = np.array(loaded["models"][0]["weights"], dtype=np.float64)
    assert restored.view(np.uint64).tolist() == awkward.view(np.uint64).tolist()
    assert loaded == record


def test_dump_uses_insertion_order_and_flow_lists():
    text = dump_record(make_record())
    keys = [line.split(":")[0] for line in text.splitlines() if re.match(r"^[a-z_]+:", line)]
    assert keys == list(persistence.REQUIRED_KEYS)
    assert "normal: [0.0, 0.0, 1.0]" in text


# --------------------------------------------------------------------------------------- store


def test_store_round_trip_history_and_active_switch(tmp_path):
    store = CalibrationStore(tmp_path / "cell")
    assert store.active_path() is None
    assert store.history() == []
    first, second = make_record(1), make_record(2)
    first_path = store.save(first)
    assert store.active_path() == first_path
    assert store.load_active() == first
    second_path = store.save(second)
    assert store.history() == [first_path, second_path]
    assert store.active_path() == second_path
    assert store.load_active() == second
    assert store.load(first_path) == first
    assert store.load(first_path.name) == first  # bare names are taken inside the history
    assert re.match(r"^calibration_\d{8}T\d{6}Z_0002\.yaml$", second_path.name)
    assert yaml.safe_load((tmp_path / "cell" / "active.yaml").read_text())["active"] == second_path.name
    assert leftover_temp_files(tmp_path) == []


def test_a_store_opened_by_a_relative_directory_hands_out_paths_it_can_load(tmp_path, monkeypatch):
    # `make sim` opens reports/sim-cell/calibrations: the saved candidate's path came back relative,
    # and loading it took it as a name inside the history (.../history/reports/sim-cell/...), so the
    # main job failed from a fresh clone (2026-11-22 17:10 to 2026-11-23).
    monkeypatch.chdir(tmp_path)
    store = CalibrationStore(Path("reports") / "cell")
    record = make_record(1)
    saved = store.save(record, activate=False)
    assert saved.is_absolute() and saved == tmp_path / "reports" / "cell" / "history" / saved.name
    assert store.load(saved) == record
    store.activate(saved)
    assert store.active_path() == saved and store.load_active() == record


def test_history_sorted_by_sequence_number(tmp_path):
    store = CalibrationStore(tmp_path)
    paths = [store.save(make_record(seed)) for seed in range(3)]
    (tmp_path / "history" / "notes.txt").write_text("ignored")
    assert store.history() == paths
    assert [int(path.stem.split("_")[-1]) for path in paths] == [1, 2, 3]


def test_invalid_record_does_not_replace_active(tmp_path):
    store = CalibrationStore(tmp_path)
    good = store.save(make_record(1))
    bad = make_record(2)
    del bad["models"]
    with pytest.raises(CalibrationFileError, match=r"^calibration record: missing key 'models'$"):
        store.save(bad)
    assert store.active_path() == good
    assert store.history() == [good]


def test_write_error_during_pointer_switch_keeps_previous_active(tmp_path, monkeypatch):
    store = CalibrationStore(tmp_path)
    first = make_record(1)
    good = store.save(first)
    real_replace = os.replace

    def replace_failing_for_pointer(source, destination):
        if Path(destination).name == "active.yaml":
            raise OSError(28, "No space left on device")
        real_replace(source, destination)

    monkeypatch.setattr(persistence.os, "replace", replace_failing_for_pointer)
    with pytest.raises(OSError):
        store.save(make_record(2))
    assert store.active_path() == good
    assert store.load_active() == first
    assert len(store.history()) == 2  # the unreferenced new history file is harmless
    assert leftover_temp_files(tmp_path) == []


def test_write_error_on_history_file_keeps_previous_active(tmp_path, monkeypatch):
    store = CalibrationStore(tmp_path)
    good = store.save(make_record(1))
    monkeypatch.setattr(persistence.os, "replace", lambda source, destination: (_ for _ in ()).throw(OSError("boom")))
    with pytest.raises(OSError, match="boom"):
        store.save(make_record(2))
    assert store.active_path() == good
    assert store.history() == [good]
    assert leftover_temp_files(tmp_path) == []


def test_load_active_without_calibration(tmp_path):
    store = CalibrationStore(tmp_path)
    expected = f"calibration file {tmp_path / 'active.yaml'}: no active calibration (nothing saved yet)"
    with pytest.raises(CalibrationFileError, match=f"^{re.escape(expected)}$"):
        store.load_active()


def test_bad_pointer_is_reported(tmp_path):
    store = CalibrationStore(tmp_path)
    (tmp_path / "active.yaml").write_text("active: ../../etc/passwd\n")
    with pytest.raises(CalibrationFileError, match=r"active\.yaml: key 'active' must name a history file"):
        store.active_path()
    (tmp_path / "active.yaml").write_text("- just a list\n")
    with pytest.raises(CalibrationFileError, match=r"active\.yaml: missing key 'active'$"):
        store.load_active()


def test_pointer_to_missing_file(tmp_path):
    store = CalibrationStore(tmp_path)
    path = store.save(make_record())
    path.unlink()
    expected = f"calibration file {path}: cannot read file: No such file or directory"
    with pytest.raises(CalibrationFileError, match=f"^{re.escape(expected)}$"):
        store.load_active()


# ------------------------------------------------------------------------------ corrupt files


def write_active(tmp_path: Path, text: str) -> tuple[CalibrationStore, Path]:
    """Save a valid record, then overwrite the active file with ``text``."""
    store = CalibrationStore(tmp_path)
    path = store.save(make_record())
    path.write_text(text)
    return store, path


def test_invalid_yaml_is_reported_with_location(tmp_path):
    store, path = write_active(tmp_path, "format_version: 1\nhead: [1, 2\n")
    with pytest.raises(CalibrationFileError) as caught:
        store.load_active()
    assert str(caught.value).startswith(f"calibration file {path}: invalid YAML at line 3, column 1: ")
    assert isinstance(caught.value, ValueError)
    assert caught.value.source == str(path)


def test_truncated_file_is_reported_as_incomplete(tmp_path):
    store, path = write_active(tmp_path, "")
    with pytest.raises(CalibrationFileError, match=f"^{re.escape(f'calibration file {path}: file is empty')}$"):
        store.load_active()
    full = dump_record(make_record())
    cut = full[: full.index("\nmetrics:")]  # a file cut off mid-way that is still valid YAML
    path.write_text(cut)
    with pytest.raises(CalibrationFileError, match=f"^{re.escape(f'calibration file {path}: missing key')} 'metrics'$"):
        store.load_active()


def test_nan_in_file_is_reported_with_its_location(tmp_path):
    record = make_record()
    record["models"][0]["weights"][2][1] = math.nan
    store, path = write_active(tmp_path, yaml.safe_dump(record, sort_keys=False))
    expected = f"calibration file {path}: NaN or infinite number at 'models[0].weights[2][1]'"
    with pytest.raises(CalibrationFileError, match=f"^{re.escape(expected)}$"):
        store.load_active()


def test_save_stores_nan_metrics_as_null(tmp_path):
    record = make_record()
    record["metrics"]["before"]["50x50"] = {"count": 0, "max_abs_mm": np.float64("nan")}
    store = CalibrationStore(tmp_path)
    loaded = store.load(store.save(record))
    assert loaded["metrics"]["before"]["50x50"] == {"count": 0, "max_abs_mm": None}
    assert math.isnan(record["metrics"]["before"]["50x50"]["max_abs_mm"])  # caller's record untouched


def test_save_refuses_nan(tmp_path):
    record = make_record()
    record["fiducials"]["dx"][0] = np.float64("inf")
    with pytest.raises(CalibrationFileError,
                       match=r"^calibration record: NaN or infinite number at 'fiducials\.dx\[0\]'$"):
        CalibrationStore(tmp_path).save(record)
    assert not (tmp_path / "active.yaml").exists()


@pytest.mark.parametrize("mutate, problem", [
    (lambda r: r.pop("models"), "missing key 'models'"),
    (lambda r: r.pop("format_version"), "missing key 'format_version'"),
    (lambda r: r.update(format_version=3), "format_version 3 is newer than this software reads (up to 2); "
                                           "update gls_calibration"),
    (lambda r: r.update(format_version=0), "unsupported format_version 0 (this software reads versions 1, 2)"),
    (lambda r: r.update(format_version="1"), "key 'format_version' must be an integer, got str"),
    (lambda r: r.update(created_utc="yesterday"), "key 'created_utc' is not an ISO 8601 time: 'yesterday'"),
    (lambda r: r.update(head=[490.0]), "key 'head' must be a mapping, got list"),
    (lambda r: r["head"].pop("mirror_distance_mm"), "missing key 'head.mirror_distance_mm'"),
    (lambda r: r["head"].update(working_distance_mm="490"), "key 'head.working_distance_mm' must be a number, got str"),
    (lambda r: r["head"].update(working_distance_mm=-1.0),
     "key 'head': working_distance_mm must be a positive finite number, got -1.0"),
    (lambda r: r["plate_pose"].update(normal=[0.0, 1.0]), "key 'plate_pose.normal' must hold 3 numbers, got 2"),
    (lambda r: r["plate_pose"].update(rotation=[[1.0, 0.0, 0.0]]),
     "key 'plate_pose.rotation' must be a 3x3 list of numbers, got list"),
    (lambda r: r["plate_pose"].update(flatness_rms_mm=True),
     "key 'plate_pose.flatness_rms_mm' must be a number, got bool"),
    (lambda r: r.update(models={"type": "ols_rbf"}), "key 'models' must be a list, got dict"),
    (lambda r: r["models"][0].pop("type"), "missing key 'models[0].type'"),
    (lambda r: r["models"][0].update(type=""), "key 'models[0].type' must be a non-empty string, got str"),
    (lambda r: r.update(calibrated_region={"x_min": 0.0}), "missing key 'calibrated_region.type'"),
    (lambda r: r.update(metrics=None), "key 'metrics' must be a mapping, got null"),
    (lambda r: r["fiducials"].pop("measured_z"), "missing key 'fiducials.measured_z'"),
    (lambda r: r["fiducials"].update(dx=["a"]), "key 'fiducials.dx' must be a list of numbers, got list"),
    (lambda r: r["fiducials"]["dy"].pop(),
     "fiducial lists must have equal lengths, got target_x: 5, target_y: 5, measured_x: 5, measured_y: 5, "
     "measured_z: 5, dx: 5, dy: 4"),
])
def test_validate_record_messages(mutate, problem):
    record = copy.deepcopy(make_record())
    mutate(record)
    expected = f"calibration file /x/y.yaml: {problem}"
    with pytest.raises(CalibrationFileError, match=f"^{re.escape(expected)}$"):
        validate_record(record, "/x/y.yaml")


def test_validate_record_top_level_and_good_record():
    with pytest.raises(CalibrationFileError, match=r"^calibration record: top level must be a mapping, got list$"):
        validate_record([1, 2])
    validate_record(make_record())  # no exception for a complete record
    record = make_record()
    record["models"] = []  # no model: identity correction, still a valid file
    validate_record(record)


def test_load_record_unreadable_file(tmp_path):
    path = tmp_path / "binary.yaml"
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(CalibrationFileError, match=f"^{re.escape(f'calibration file {path}: cannot read file: ')}"):
        load_record(path)


def test_candidate_save_does_not_replace_the_active_calibration_until_activated(tmp_path):
    store = CalibrationStore(tmp_path)
    first = store.save(make_record())
    candidate = store.save(make_record(), activate=False)
    assert store.active_path() == first
    store.activate(candidate)
    assert store.active_path() == candidate


def test_activate_refuses_a_file_outside_the_history(tmp_path):
    store = CalibrationStore(tmp_path / "store")
    outside = tmp_path / "calibration_20260101T000000Z_0001.yaml"
    outside.write_text("x: 1\n")
    with pytest.raises(CalibrationFileError, match="only a file of this store's history can be activated"):
        store.activate(outside)
