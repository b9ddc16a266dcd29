"""The calibration record as a file: its schema and validation, hardened YAML reading, exact writing.

A calibration record is a plain dict that round-trips through YAML (see :func:`validate_record`
for the keys). Floats are written with ``repr`` precision, so every float64 is read back bit for
bit. NaN and infinity are refused anywhere in a record; a metric that could not be computed (for
example an empty sub-field) is stored as ``null``.
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
import copy
import dataclasses
from datetime import datetime, timezone
import math
import os
from pathlib import Path
import stat
from typing import Any

import numpy as np
import yaml

import gls_calibration
from gls_calibration.common.bounded_yaml import load_bounded_yaml
from gls_calibration.common.files import nan_to_none, to_plain
from gls_calibration.correction.uncertainty_grid import UNCERTAINTY_KEY, UncertaintyGrid
from gls_calibration.geometry.kinematics import HeadGeometry

FORMAT_VERSION = 2
# Version 1 stored a thin-plate spline as its training data (refitted when loaded) and had no
# calibration plane or taper in the region (z = 0 and 10 mm); such files still load.
READABLE_FORMAT_VERSIONS = (1, 2)
_SafeDumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
REQUIRED_KEYS = (
    "format_version", "software_version", "created_utc", "head", "plate_pose", "models",
    "calibrated_region", "hyper_parameters", "metrics", "fiducials",
)
FIDUCIAL_KEYS = ("target_x", "target_y", "measured_x", "measured_y", "measured_z", "dx", "dy")
HEAD_KEYS = tuple(field.name for field in dataclasses.fields(HeadGeometry))
_NUMBER_TYPES = {int, float}    # the exact types of YAML numbers (bool and numpy scalars: one by one)
_FLOAT_TYPE = {float}


class CalibrationRecord(Mapping):
    """A calibration record validated once, when it was built or read; read-only.

    Built by :func:`new_record` or read by :func:`load_record`. Code that holds one need not
    validate it again (the store saves it as it is); ``to_dict`` gives a plain copy to modify, which
    is validated again wherever it is used.
    """

    __slots__ = ("_data", "_text")

    def __init__(self, plain: dict, source: str | os.PathLike | None = None) -> None:
        validate_record(plain, source)
        self._data = plain
        self._text: str | None = None

    def __getitem__(self, key: str) -> Any:
        """Return the record's value of ``key``."""
        return self._data[key]

    def __iter__(self) -> Iterator[str]:
        """Iterate over the record's top-level keys."""
        return iter(self._data)

    def __len__(self) -> int:
        """Return the number of top-level keys."""
        return len(self._data)

    def __repr__(self) -> str:
        """Show the record's creation time."""
        return f"CalibrationRecord(created_utc={self._data.get('created_utc')!r})"

    def to_dict(self) -> dict:
        """Return a deep plain copy (to change and save as a new record)."""
        return copy.deepcopy(self._data)

    def yaml_text(self) -> str:
        """Return the record's YAML text (:func:`dump_record`), made once.

        A run dumps its record to save it and again for its content hash (``record.record_identity``),
        a correction node twice for its hash: each dump of a 19x19 record was ~50 ms. The record is
        read-only, so its text stays what it was.

        Returns
        -------
        str
            The YAML text.
        """
        if self._text is None:
            self._text = _yaml_text(self)
        return self._text


class CalibrationFileError(ValueError):
    """A calibration file (or record) that cannot be used; the message names the file and the problem.

    Parameters
    ----------
    source : str or os.PathLike or None
        The file; None for a record not read from a file.
    problem : str
        What is wrong.
    """

    def __init__(self, source: str | os.PathLike | None, problem: str) -> None:
        self.source = None if source is None else str(source)
        self.problem = problem
        prefix = "calibration record" if source is None else f"calibration file {source}"
        super().__init__(f"{prefix}: {problem}")


def new_record(*, head: HeadGeometry | Mapping, plate_pose: Any, models: list, calibrated_region: Mapping,
               hyper_parameters: Mapping, metrics: Mapping, fiducials: Mapping,
               created_utc: str | None = None, uncertainty: Mapping | None = None) -> CalibrationRecord:
    """Build a calibration record from the run's objects and fill the version and time stamp.

    ``head`` is a HeadGeometry or its dict; ``plate_pose`` a PlatePose (or any object/mapping with
    normal, centre, rotation, flatness_rms_mm); ``models`` the list of model ``to_dict()`` results in
    order of application; ``fiducials`` a mapping with the lists in FIDUCIAL_KEYS (arrays welcome).
    Non-finite metric values become None. The result is validated (once: it is a CalibrationRecord).
    """
    head_dict = dataclasses.asdict(head) if dataclasses.is_dataclass(head) else dict(head)
    pose_keys = ("normal", "centre", "rotation", "flatness_rms_mm")
    if isinstance(plate_pose, Mapping):
        pose_dict = {key: plate_pose[key] for key in pose_keys if key in plate_pose}
    else:
        pose_dict = {key: getattr(plate_pose, key) for key in pose_keys if hasattr(plate_pose, key)}
    record = {
        "format_version": FORMAT_VERSION,
        "software_version": gls_calibration.__version__,
        "created_utc": created_utc or datetime.now(timezone.utc).isoformat(timespec="microseconds"),
        "head": head_dict,
        "plate_pose": pose_dict,
        "models": list(models),
        "calibrated_region": calibrated_region,
        "hyper_parameters": hyper_parameters,
        "metrics": nan_to_none(to_plain(metrics)),
        "fiducials": dict(fiducials),
    }
    if uncertainty is not None:
        record[UNCERTAINTY_KEY] = dict(uncertainty)     # optional: older files have none
    return CalibrationRecord(to_plain(record))


def _type_name(value: Any) -> str:
    return "null" if value is None else type(value).__name__


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _all_numbers(values: list) -> bool:
    """Whether every item of ``values`` is a number (:func:`_is_number`)."""
    # the item types in one pass in C; subclasses (bool, numpy scalars) one by one
    return set(map(type, values)) <= _NUMBER_TYPES or all(_is_number(item) for item in values)


def validate_record(record: Any, source: str | os.PathLike | None = None) -> None:
    """Raise CalibrationFileError naming ``source`` and the first problem found in ``record``.

    Checks: a mapping with every key of REQUIRED_KEYS; format_version in READABLE_FORMAT_VERSIONS
    (a newer one is named as such); software_version and
    created_utc (ISO 8601) strings; head with the HeadGeometry fields as valid numbers; plate_pose
    with normal/centre (3 numbers), rotation (3x3) and flatness_rms_mm; models a list of mappings
    with a non-empty string 'type'; calibrated_region a mapping with a string 'type';
    hyper_parameters and metrics mappings; fiducials with equal-length number lists FIDUCIAL_KEYS;
    no NaN or infinite number anywhere.
    """
    def fail(problem: str) -> None:
        raise CalibrationFileError(source, problem)

    def require_mapping(value: Any, key: str) -> None:
        if not isinstance(value, Mapping):
            fail(f"key '{key}' must be a mapping, got {_type_name(value)}")

    def require_number(value: Any, key: str) -> None:
        if not _is_number(value):
            fail(f"key '{key}' must be a number, got {_type_name(value)}")

    def require_numbers(value: Any, key: str, length: int | None = None) -> None:
        if not isinstance(value, list) or not _all_numbers(value):
            fail(f"key '{key}' must be a list of numbers, got {_type_name(value)}")
        if length is not None and len(value) != length:
            fail(f"key '{key}' must hold {length} numbers, got {len(value)}")

    if not isinstance(record, Mapping):
        fail(f"top level must be a mapping, got {_type_name(record)}")
    for key in REQUIRED_KEYS:
        if key not in record:
            fail(f"missing key '{key}'")

    version = record["format_version"]
    if not isinstance(version, int) or isinstance(version, bool):
        fail(f"key 'format_version' must be an integer, got {_type_name(version)}")
    if version > FORMAT_VERSION:
        fail(f"format_version {version} is newer than this software reads (up to {FORMAT_VERSION}); "
             "update gls_calibration")
    if version not in READABLE_FORMAT_VERSIONS:
        fail(f"unsupported format_version {version} (this software reads versions "
             f"{', '.join(map(str, READABLE_FORMAT_VERSIONS))})")
    for key in ("software_version", "created_utc"):
        if not isinstance(record[key], str):
            fail(f"key '{key}' must be a string, got {_type_name(record[key])}")
    try:
        datetime.fromisoformat(record["created_utc"])
    except ValueError:
        fail(f"key 'created_utc' is not an ISO 8601 time: {record['created_utc']!r}")

    head = record["head"]
    require_mapping(head, "head")
    for key in HEAD_KEYS:
        if key not in head:
            fail(f"missing key 'head.{key}'")
        require_number(head[key], f"head.{key}")

    pose = record["plate_pose"]
    require_mapping(pose, "plate_pose")
    for key in ("normal", "centre", "rotation", "flatness_rms_mm"):
        if key not in pose:
            fail(f"missing key 'plate_pose.{key}'")
    require_numbers(pose["normal"], "plate_pose.normal", 3)
    require_numbers(pose["centre"], "plate_pose.centre", 3)
    rotation = pose["rotation"]
    if not isinstance(rotation, list) or len(rotation) != 3:
        fail(f"key 'plate_pose.rotation' must be a 3x3 list of numbers, got {_type_name(rotation)}")
    for row_index, row in enumerate(rotation):
        require_numbers(row, f"plate_pose.rotation[{row_index}]", 3)
    require_number(pose["flatness_rms_mm"], "plate_pose.flatness_rms_mm")

    models = record["models"]
    if not isinstance(models, list):
        fail(f"key 'models' must be a list, got {_type_name(models)}")
    for index, model in enumerate(models):
        require_mapping(model, f"models[{index}]")
        if "type" not in model:
            fail(f"missing key 'models[{index}].type'")
        if not isinstance(model["type"], str) or not model["type"]:
            fail(f"key 'models[{index}].type' must be a non-empty string, got {_type_name(model['type'])}")

    region = record["calibrated_region"]
    require_mapping(region, "calibrated_region")
    if "type" not in region:
        fail("missing key 'calibrated_region.type'")
    if not isinstance(region["type"], str) or not region["type"]:
        fail(f"key 'calibrated_region.type' must be a non-empty string, got {_type_name(region['type'])}")

    require_mapping(record["hyper_parameters"], "hyper_parameters")
    require_mapping(record["metrics"], "metrics")

    fiducials = record["fiducials"]
    require_mapping(fiducials, "fiducials")
    for key in FIDUCIAL_KEYS:
        if key not in fiducials:
            fail(f"missing key 'fiducials.{key}'")
        require_numbers(fiducials[key], f"fiducials.{key}")
    lengths = {key: len(fiducials[key]) for key in FIDUCIAL_KEYS}
    if len(set(lengths.values())) > 1:
        listed = ", ".join(f"{key}: {length}" for key, length in lengths.items())
        fail(f"fiducial lists must have equal lengths, got {listed}")

    if UNCERTAINTY_KEY in record:
        try:
            UncertaintyGrid.from_dict(record[UNCERTAINTY_KEY])
        except ValueError as error:
            fail(str(error))

    bad_path = _first_non_finite(record, "")
    if bad_path is not None:
        fail(f"NaN or infinite number at '{bad_path}'")

    # HeadGeometry knows which values are physically valid (positive distances, ...).
    try:
        HeadGeometry(**{key: head[key] for key in HEAD_KEYS})
    except ValueError as error:
        fail(f"key 'head': {error}")


def _first_non_finite(value: Any, path: str) -> str | None:
    """Dotted/indexed path of the first NaN or infinite float inside ``value``, or None."""
    if isinstance(value, Mapping):
        for key, item in value.items():
            found = _first_non_finite(item, f"{path}.{key}" if path else str(key))
            if found is not None:
                return found
    elif isinstance(value, (list, tuple)):
        if value and set(map(type, value)) == _FLOAT_TYPE:    # a list of floats checked in one go
            finite = np.isfinite(np.array(value, dtype=float))
            return None if finite.all() else f"{path}[{int(np.argmin(finite))}]"
        for index, item in enumerate(value):
            found = _first_non_finite(item, f"{path}[{index}]")
            if found is not None:
                return found
    elif isinstance(value, float) and not math.isfinite(value):
        return path
    return None


def head_geometry(record: Mapping) -> HeadGeometry:
    """Return the HeadGeometry stored in a (validated) record.

    Parameters
    ----------
    record : mapping
        A validated calibration record.

    Returns
    -------
    HeadGeometry
        Its ``head`` block.
    """
    return HeadGeometry(**{key: record["head"][key] for key in HEAD_KEYS})


def dump_record(record: Mapping) -> str:
    """Return the YAML text of a record: keys in insertion order, short lists inline, floats at full precision.

    Parameters
    ----------
    record : mapping
        The record (numpy values are converted to plain ones).

    Returns
    -------
    str
        The YAML text.
    """
    return record.yaml_text() if isinstance(record, CalibrationRecord) else _yaml_text(record)


def _yaml_text(record: Mapping) -> str:
    """Return the YAML text of ``record`` (see :func:`dump_record`)."""
    return yaml.dump(to_plain(record), Dumper=_NoAliasDumper, sort_keys=False, default_flow_style=None,
                     allow_unicode=True)


class _NoAliasDumper(_SafeDumper):
    """Writes a repeated object in full: the reader refuses aliases (see ``bounded_yaml``)."""

    def ignore_aliases(self, data):  # noqa: D102 (PyYAML's hook)
        return True


MAX_FILE_BYTES = 4 * 1024 * 1024   # a 19x19 calibration is ~0.1 MB; bounds memory and parsing time
MAX_YAML_DEPTH = 32                # a calibration file nests 5 levels deep


def read_bounded_text(path: str | os.PathLike, limit_bytes: int = MAX_FILE_BYTES) -> str:
    """Return the text of the regular file ``path``, read with a bound; CalibrationFileError otherwise.

    Devices, FIFOs and directories are refused without blocking (opened non-blocking, checked with
    fstat on the open descriptor), and so is a file over ``limit_bytes``.
    """
    path = Path(path)
    try:
        descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as error:
        raise CalibrationFileError(path, f"cannot read file: {error.strerror or error}") from None
    try:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            raise CalibrationFileError(path, "not a regular file")
        if status.st_size > limit_bytes:
            raise CalibrationFileError(path, f"file of {status.st_size} bytes is over the limit of {limit_bytes}")
        with os.fdopen(descriptor, "rb", closefd=False) as handle:
            data = handle.read(limit_bytes + 1)
    except OSError as error:
        raise CalibrationFileError(path, f"cannot read file: {error.strerror or error}") from None
    finally:
        os.close(descriptor)
    if len(data) > limit_bytes:
        raise CalibrationFileError(path, f"file grew over the limit of {limit_bytes} bytes while read")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise CalibrationFileError(path, f"cannot read file: {error}") from None


def read_calibration_yaml(path: Path) -> Any:
    """Parse a YAML file, turning read and syntax errors into CalibrationFileError.

    The one place where calibration files and pointers are read: bounded size, regular files only,
    no aliases, bounded nesting (see read_bounded_text and ``bounded_yaml``).
    """
    text = read_bounded_text(path)
    try:
        return load_bounded_yaml(text, MAX_YAML_DEPTH)
    except yaml.YAMLError as error:
        where = getattr(error, "problem_mark", None)
        location = f" at line {where.line + 1}, column {where.column + 1}" if where is not None else ""
        problem = getattr(error, "problem", None) or type(error).__name__
        raise CalibrationFileError(path, f"invalid YAML{location}: {problem}") from None


def load_record(path: str | os.PathLike) -> CalibrationRecord:
    """Read and validate one calibration file.

    Parameters
    ----------
    path : str or os.PathLike
        The calibration file.

    Returns
    -------
    CalibrationRecord
        The validated record.

    Raises
    ------
    CalibrationFileError
        Naming the file and the problem: unreadable, too large, empty, invalid YAML or an invalid record.
    """
    path = Path(path)
    record = read_calibration_yaml(path)
    if record is None:
        raise CalibrationFileError(path, "file is empty")
    return CalibrationRecord(record, path)
