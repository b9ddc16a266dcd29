"""Validated once, never re-read (issue 29): in the manager's process a calibration record is validated
when it is built, saved and activated as it is, and the candidate's file is not read back by the manager
(the correction node, a node of its own, reads what it serves)."""
import traceback

from gls_calibration.calibration import record_file
from gls_calibration.calibration.record_file import CalibrationRecord
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration_msgs.srv import Calibrate

import pytest

from test_persistence import make_record

CALIBRATE_TIMEOUT_S = 300.0
FAST = {"sweep.plain_repeats": 1, "sweep.plan": "0+"}
CORRECTION_NODE = "gls_calibration/nodes/correction.py"


def by_the_correction_node() -> bool:
    return any(frame.filename.endswith(CORRECTION_NODE) for frame in traceback.extract_stack())


@pytest.fixture
def counted(monkeypatch):
    """Validations and file reads outside the correction node, as (what, source) pairs."""
    seen = []
    validate, read = record_file.validate_record, record_file.read_calibration_yaml

    def counting_validate(record, source=None):
        if not by_the_correction_node():
            seen.append(("validate", None if source is None else str(source)))
        return validate(record, source)

    def counting_read(path):
        if not by_the_correction_node():
            seen.append(("read", str(path)))
        return read(path)

    monkeypatch.setattr(record_file, "validate_record", counting_validate)
    monkeypatch.setattr(record_file, "read_calibration_yaml", counting_read)
    return seen


def test_a_calibration_is_validated_once_in_the_manager_and_its_candidate_never_read_back(start_cell, counted):
    cell = start_cell(grid=3, parameters=FAST)
    counted.clear()     # start-up (the correction node's first load) is not the run
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=False), CALIBRATE_TIMEOUT_S)
    assert answer.success, answer.message
    candidate = CalibrationStore(cell.calibration_dir).active_path()
    assert candidate is not None
    assert counted == [("validate", None)]    # built once; saved and activated without a second look


def test_the_store_saves_a_built_record_as_it_is_and_checks_a_plain_one(tmp_path, counted):
    store = CalibrationStore(tmp_path / "store")
    plain = make_record()
    counted.clear()
    built = CalibrationRecord(plain)
    assert counted == [("validate", None)]
    path = store.save(built, activate=False)
    store.activate(path)
    assert counted == [("validate", None)]            # this store wrote it and it is unchanged
    plain = built.to_dict()
    assert plain == built and plain is not built
    plain["head"]["d"] = float("nan")
    with pytest.raises(record_file.CalibrationFileError, match="head"):
        store.save(plain)
    # A file changed behind the store's back is read and validated again before it is activated.
    path.write_text(path.read_text().replace("format_version: 2", "format_version: 99"))
    with pytest.raises(record_file.CalibrationFileError, match="format_version"):
        store.activate(path)
