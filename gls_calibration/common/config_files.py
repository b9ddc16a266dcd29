"""Where the package's config/ files are: the source tree, else the installed share folder.

The source tree serves an editable install; an installed package (colcon/ament) has them in its
share folder.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, TypeVar

import yaml

Parsed = TypeVar("Parsed")


def config_path(name: str) -> Path:
    """Path of ``config/<name>``; FileNotFoundError naming the places looked at."""
    places = [Path(__file__).resolve().parents[2] / "config"]
    try:
        from ament_index_python.packages import get_package_share_directory
        places.append(Path(get_package_share_directory("gls_calibration")) / "config")
    except (ImportError, LookupError, OSError):  # not installed through ament, or no AMENT_PREFIX_PATH
        pass
    for place in places:
        if (place / name).is_file():
            return place / name
    raise FileNotFoundError(f"config file {name} not found in {', '.join(str(p) for p in places)}")


def read_config_file(path: str | Path, what: str, parse: Callable[[Any], Parsed]) -> Parsed:
    """``parse`` the YAML document at ``path``; ValueError naming the file for any problem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise ValueError(f"cannot read {what} {path}: {error.strerror or error}") from None
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ValueError(f"cannot parse {what} {path}: {error}") from None
    try:
        return parse(document)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def require_exact_keys(block, keys, prefix: str) -> None:
    """Raise ValueError naming ``prefix.key`` for every unknown or missing key of ``block``.

    Unknown keys (in ``block``, not in ``keys``) come first, then the keys of ``keys`` that
    ``block`` lacks: a misspelt key is also a missing one.
    """
    unknown = sorted(set(block) - set(keys))
    missing = [key for key in keys if key not in block]
    if unknown:
        raise ValueError(f"unknown key(s) {', '.join(f'{prefix}.{key}' for key in unknown)}")
    if missing:
        raise ValueError(f"missing key(s) {', '.join(f'{prefix}.{key}' for key in missing)}")
