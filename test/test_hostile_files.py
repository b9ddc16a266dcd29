"""Hostile calibration files: confinement to the store, non-regular files, size, YAML bombs.

Every refusal must be a CalibrationFileError naming the problem, well within a second.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from gls_calibration.calibration.record_file import (MAX_FILE_BYTES, MAX_YAML_DEPTH, CalibrationFileError, load_record,
                                                     read_bounded_text)
from gls_calibration.calibration.store import CalibrationStore
from test_persistence import make_record

REFUSE_WITHIN_S = 1.0


def refused(action, match: str) -> CalibrationFileError:
    began = time.monotonic()
    with pytest.raises(CalibrationFileError, match=match) as caught:
        action()
    elapsed = time.monotonic() - began
    assert elapsed < REFUSE_WITHIN_S, f"refusal took {elapsed:.2f} s"
    return caught.value


@pytest.fixture
def store(tmp_path) -> CalibrationStore:
    store = CalibrationStore(tmp_path / "store")
    store.save(make_record(), activate=True)
    return store


def test_a_file_of_the_store_loads_by_name_and_by_path(store):
    path = store.active_path()
    assert store.load(path.name) == store.load(path) == store.load_active()


def test_paths_outside_the_store_are_refused(store, tmp_path):
    outside = tmp_path / "elsewhere.yaml"
    outside.write_text(store.active_path().read_text())
    load_record(outside)                                  # a good file, only in the wrong place
    refused(lambda: store.load(outside), "outside the calibration directory")
    refused(lambda: store.load(f"../../{outside.name}"), "outside the calibration directory")
    refused(lambda: store.load("/etc/hostname"), "outside the calibration directory")


def test_a_path_outside_the_store_is_refused_the_same_way_whether_or_not_it_exists(store, tmp_path):
    # Issue 31: the answer must not tell whether a file exists outside the store (an existence oracle).
    existing = tmp_path / "elsewhere.yaml"
    existing.write_text(store.active_path().read_text())
    missing = tmp_path / "nothing_here.yaml"
    for there, absent in [(existing, missing), ("/etc/hostname", "/etc/no_such_file_here"),
                          (f"../../{existing.name}", f"../../{missing.name}")]:
        first = refused(lambda: store.load(there), "outside the calibration directory")
        second = refused(lambda: store.load(absent), "outside the calibration directory")
        assert first.problem == second.problem
    # the same through a symlink in the store pointing at an existing or a missing file outside
    (store.history_directory / "to_existing.yaml").symlink_to(existing)
    (store.history_directory / "to_missing.yaml").symlink_to(missing)
    assert (refused(lambda: store.load("to_existing.yaml"), "outside").problem
            == refused(lambda: store.load("to_missing.yaml"), "outside").problem)
    # a missing file inside the store is still named as missing
    refused(lambda: store.load("calibration_missing.yaml"), "cannot read file")


def test_a_symlink_leaving_the_store_is_refused_and_one_inside_it_is_followed(store, tmp_path):
    outside = tmp_path / "elsewhere.yaml"
    outside.write_text(store.active_path().read_text())
    (store.history_directory / "escape.yaml").symlink_to(outside)
    refused(lambda: store.load("escape.yaml"), "outside the calibration directory")
    (store.history_directory / "inside.yaml").symlink_to(store.active_path())
    assert store.load("inside.yaml") == store.load_active()


def test_devices_fifos_and_directories_are_refused_without_blocking(store, tmp_path):
    refused(lambda: read_bounded_text("/dev/zero"), "not a regular file")
    fifo = store.history_directory / "pipe.yaml"
    os.mkfifo(fifo)
    refused(lambda: store.load("pipe.yaml"), "not a regular file")  # no writer: open must not block
    (store.history_directory / "folder.yaml").mkdir()
    refused(lambda: store.load("folder.yaml"), "not a regular file|Is a directory")
    refused(lambda: store.load("missing.yaml"), "cannot read file")


def test_an_oversized_file_is_refused_before_it_is_read(store):
    big = store.history_directory / "big.yaml"
    with open(big, "wb") as handle:
        handle.truncate(MAX_FILE_BYTES + 1)               # sparse: costs no disk
    refused(lambda: store.load("big.yaml"), f"over the limit of {MAX_FILE_BYTES}")


def test_yaml_alias_bombs_and_deep_nesting_are_refused(store):
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(9))
    (store.history_directory / "bomb.yaml").write_text(bomb)
    refused(lambda: store.load("bomb.yaml"), "aliases are not allowed")
    (store.history_directory / "deep.yaml").write_text("[" * 100_000 + "]" * 100_000)
    refused(lambda: store.load("deep.yaml"), f"nested deeper than {MAX_YAML_DEPTH} levels")
    (store.history_directory / "deep_map.yaml").write_text("".join(" " * i + f"k{i}:\n" for i in range(200)))
    refused(lambda: store.load("deep_map.yaml"), f"nested deeper than {MAX_YAML_DEPTH} levels")


def test_a_hostile_pointer_file_is_refused(store):
    store.pointer_path.write_text("active: &x calibration_20250101T000000Z_0001.yaml\nagain: *x\n")
    refused(store.active_path, "aliases are not allowed")
    store.pointer_path.unlink()
    os.mkfifo(store.pointer_path)
    refused(store.active_path, "not a regular file")


def test_saved_files_carry_no_aliases_and_load_back(tmp_path):
    store = CalibrationStore(tmp_path / "store")
    record = make_record()
    path = store.save(record, activate=True)
    assert "&" not in Path(path).read_text() and "*id" not in Path(path).read_text()
    assert store.load_active()["head"] == store.load(path)["head"]
