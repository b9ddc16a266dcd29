"""Saving and loading calibrations: atomic YAML files, a history and an ``active`` pointer.

Store layout (one directory per cell)::

    <directory>/history/calibration_<YYYYmmddTHHMMSSZ>_<nnnn>.yaml   every saved calibration, never rewritten
    <directory>/active.yaml                                          pointer: ``active: <history file name>``

The pointer scheme was chosen over copying the record: switching the active calibration is one
small atomic write, the history file stays the single copy of the data, and rolling back is a
matter of rewriting the pointer. ``save`` writes the history file first and the pointer last, both
through :func:`atomic_write_text`, so a failed save (invalid record, full disk, crash) leaves the
previous active calibration in force; at worst an unreferenced history file remains. The store
assumes a single writer (the calibration node); ``<nnnn>`` is one more than the highest number
already in the history.

A calibration record is a plain dict that round-trips through YAML (see :func:`validate_record`
for the keys). Floats are written with ``repr`` precision, so every float64 is read back bit for
bit. NaN and infinity are refused anywhere in a record; a metric that could not be computed (for
example an empty sub-field) is stored as ``null``.
"""
from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime, timezone
import os
from pathlib import Path
import re

import yaml

from gls_calibration.calibration.record_file import (CalibrationFileError, CalibrationRecord, dump_record,
                                                     load_record, read_calibration_yaml)
from gls_calibration.common.files import atomic_write_text, nan_to_none, to_plain

ACTIVE_FILE_NAME = "active.yaml"
HISTORY_DIR_NAME = "history"
_HISTORY_NAME = re.compile(r"^calibration_(\d{8}T\d{6}Z)_(\d+)\.yaml$")


def _signature(path: Path) -> tuple[int, int, int] | None:
    try:
        status = path.stat()
    except OSError:
        return None
    return status.st_ino, status.st_size, status.st_mtime_ns


class CalibrationStore:
    """A directory of calibrations: an append-only history and a pointer to the active one.

    Parameters
    ----------
    directory : str or os.PathLike
        The store's directory (made absolute); ``history/`` and ``active.yaml`` live in it.

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     store = CalibrationStore(folder)
    ...     store.active_path(), store.history()
    (None, [])
    """

    def __init__(self, directory: str | os.PathLike) -> None:
        # Absolute from the start: the paths it hands out (``save``) must name their files for
        # ``load``, which takes a relative path as a name inside the history.
        self.directory = Path(directory).absolute()
        self.history_directory = self.directory / HISTORY_DIR_NAME
        self.pointer_path = self.directory / ACTIVE_FILE_NAME
        # History files this store wrote, by name: their (inode, size, mtime) when written. Such a file,
        # unchanged since, holds a record validated before it was written: activating it needs no re-read.
        self._written: dict[str, tuple[int, int, int]] = {}

    def save(self, record: Mapping, *, activate: bool = True) -> Path:
        """Validate and store ``record`` as a new history file, then (by default) make it the active one.

        With ``activate=False`` the file is only a candidate: a calibration run saves it, validates
        it, and activates it only when the run succeeds.

        Non-finite metric values are stored as null (as in new_record); NaN elsewhere is refused.
        Returns the history file's path. Raises CalibrationFileError for an invalid record and
        OSError for write errors; in both cases the previous active calibration stays active.
        """
        if not isinstance(record, CalibrationRecord):   # a CalibrationRecord was validated when built
            plain = to_plain(record)  # a copy: the caller's record is not modified
            if isinstance(plain, dict) and "metrics" in plain:
                plain["metrics"] = nan_to_none(plain["metrics"])  # registration marks empty sub-fields NaN
            record = CalibrationRecord(plain)
        text = dump_record(record)
        self.history_directory.mkdir(parents=True, exist_ok=True)
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        target = self.history_directory / f"calibration_{stamp}_{self._next_number():04d}.yaml"
        atomic_write_text(target, text)
        self._written[target.name] = _signature(target)
        if activate:
            self.activate(target)
        return target

    def activate(self, path: str | os.PathLike) -> None:
        """Make the history file ``path`` the active calibration (one atomic pointer write)."""
        path = Path(path)
        if path.parent.resolve() != self.history_directory.resolve() or not _HISTORY_NAME.match(path.name):
            raise CalibrationFileError(path, "only a file of this store's history can be activated")
        signature = _signature(path)
        if signature is None or self._written.get(path.name) != signature:
            load_record(path)  # never point at a file that does not load (one this store wrote, unchanged, does)
        pointer = {"active": path.name, "switched_utc": datetime.now(timezone.utc).isoformat()}
        atomic_write_text(self.pointer_path, yaml.safe_dump(pointer, sort_keys=False))

    def _next_number(self) -> int:
        numbers = [int(_HISTORY_NAME.match(path.name).group(2)) for path in self.history()]
        return max(numbers, default=0) + 1

    def active_path(self) -> Path | None:
        """Path of the active history file, or None when nothing has been saved yet.

        A pointer file that is unreadable or does not name a history file raises CalibrationFileError.
        """
        if not self.pointer_path.exists():
            return None
        pointer = read_calibration_yaml(self.pointer_path)
        if not isinstance(pointer, Mapping) or "active" not in pointer:
            raise CalibrationFileError(self.pointer_path, "missing key 'active'")
        name = pointer["active"]
        # Only a bare history file name is accepted: the pointer must not lead outside the store.
        if not isinstance(name, str) or not _HISTORY_NAME.match(name):
            raise CalibrationFileError(
                self.pointer_path, f"key 'active' must name a history file calibration_<time>_<n>.yaml, got {name!r}")
        return self.history_directory / name

    def load_active(self) -> CalibrationRecord:
        """Return the active calibration record, validated; CalibrationFileError if absent or unusable."""
        path = self.active_path()
        if path is None:
            raise CalibrationFileError(self.pointer_path, "no active calibration (nothing saved yet)")
        return load_record(path)

    def history(self) -> list[Path]:
        """Every history file, oldest first (by sequence number)."""
        if not self.history_directory.is_dir():
            return []
        entries = [path for path in self.history_directory.iterdir() if _HISTORY_NAME.match(path.name)]
        return sorted(entries, key=lambda path: (int(_HISTORY_NAME.match(path.name).group(2)), path.name))

    def load(self, path: str | os.PathLike) -> CalibrationRecord:
        """Read and validate one calibration file of this store.

        Relative paths are taken inside the history; a path that leads outside the store's
        directory, even through a symlink, is refused.
        """
        return load_record(self.confined(path))

    def confined(self, path: str | os.PathLike) -> Path:
        """Resolve ``path`` inside the store's directory; CalibrationFileError if it leads outside.

        ``path`` (relative: inside the history) once resolved inside the store's directory;
        CalibrationFileError when it leads outside (``..``, absolute paths elsewhere, symlinks).

        Whether a path leads outside is decided before asking whether it exists (symlinks that exist
        are followed, a missing last part is not an error there): a path outside the store gets the
        same answer whether or not a file is there, so the service tells nothing about other folders.
        """
        path = Path(path)
        if not path.is_absolute():
            path = self.history_directory / path
        store = self.directory.resolve()
        lexical = Path(os.path.normpath(path))
        outside = CalibrationFileError(path, f"outside the calibration directory {self.directory}: refused")
        if not (lexical.is_relative_to(os.path.normpath(self.directory)) or lexical.is_relative_to(store)):
            raise outside
        try:
            followed = path.resolve(strict=False)
        except (OSError, RuntimeError) as error:  # a symlink loop inside the store
            raise CalibrationFileError(path, f"cannot read file: {getattr(error, 'strerror', None) or error}") from None
        if not followed.is_relative_to(store):
            raise outside
        try:
            return path.resolve(strict=True)
        except (OSError, RuntimeError) as error:  # missing inside the store
            raise CalibrationFileError(path, f"cannot read file: {getattr(error, 'strerror', None) or error}") from None
