"""Files written so that a reader never sees half of one: atomic replace, and YAML-safe plain values."""
from __future__ import annotations

from collections.abc import Mapping
import contextlib
import dataclasses
import math
import os
from pathlib import Path
import tempfile
from typing import Any

import numpy as np


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> None:
    """Replace ``path`` by ``text`` so that readers see either the old or the whole new content.

    The text goes to a temporary file in the same directory (same file system, so the rename is
    atomic), is flushed to disk, renamed onto the target and the directory entry is flushed too.
    On any error the temporary file is removed and the error re-raised; the target is untouched.
    A new file gets mode 0644; an existing target keeps its mode.
    """
    atomic_write_bytes(path, text.encode(encoding))


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """:func:`atomic_write_text` for bytes (e.g. an NPZ archive built in memory)."""
    path = Path(path)
    require_regular_output(path)
    directory = path.parent
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
    handle = tempfile.NamedTemporaryFile(
        "wb", dir=directory, prefix=f".{path.name}.", suffix=".tmp", delete=False)
    try:
        with handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
            os.fchmod(handle.fileno(), mode)
        os.replace(handle.name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(handle.name)
        raise
    _fsync_directory(directory)


def require_regular_output(path: str | os.PathLike) -> None:
    """Raise ValueError unless ``path`` may be written as a regular file (absent or regular).

    A device, FIFO, directory or a symlink to one is refused: renaming onto it would replace it.
    """
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_file()):
        kind = "a symlink" if path.is_symlink() else "not a regular file"
        raise ValueError(f"output {path} is {kind}: refused (outputs are written as regular files only)")
    if not path.parent.is_dir():
        raise ValueError(f"output {path}: folder {path.parent} does not exist")


def _fsync_directory(directory: Path) -> None:
    """Flush a directory entry (the rename) to disk; POSIX only, a no-op where unsupported."""
    if os.name != "posix":
        return
    descriptor = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


_PLAIN_ITEM_TYPES = {float, int, bool, str, type(None)}


def to_plain(value: Any) -> Any:
    """Convert dataclass records, numpy arrays/scalars, tuples and paths inside ``value`` to YAML-safe Python types."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(key): to_plain(item) for key, item in value.items()}
    if isinstance(value, np.ndarray):
        # numbers come out of tolist() plain already; object arrays may hold anything
        return value.tolist() if value.dtype.kind in "biuf" else to_plain(value.tolist())
    if isinstance(value, (list, tuple)):
        if set(map(type, value)) <= _PLAIN_ITEM_TYPES:     # the common list of numbers, copied in one go
            return list(value)
        return [to_plain(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def nan_to_none(value: Any) -> Any:
    """Replace non-finite floats by None (used for metrics only, where 'not computable' is legitimate)."""
    if isinstance(value, dict):
        return {key: nan_to_none(item) for key, item in value.items()}
    if isinstance(value, list):
        return [nan_to_none(item) for item in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
