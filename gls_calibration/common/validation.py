"""Input validation shared by the core modules: one place for the exact error messages."""
from __future__ import annotations

from collections.abc import Mapping
import math
from typing import Any

import numpy as np


def as_finite_array(values, name: str, ndim: int | None = None, min_length: int = 1) -> np.ndarray:
    """Return ``values`` as a float array, or raise ValueError naming ``name`` and the problem."""
    try:
        array = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be numeric: {error}") from None
    if ndim is not None and array.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {array.shape}")
    if array.ndim > 0 and array.shape[0] < min_length:
        raise ValueError(f"{name} must hold at least {min_length} point(s), got {array.shape[0]}")
    if not np.all(np.isfinite(array)):
        bad = int(np.count_nonzero(~np.isfinite(array)))
        raise ValueError(f"{name} contains {bad} NaN or infinite value(s)")
    return array


def as_points(values, name: str, dims: int, min_length: int = 1) -> np.ndarray:
    """Return ``values`` as a finite (N, dims) float array or raise ValueError."""
    array = as_finite_array(values, name, ndim=2, min_length=min_length)
    if array.shape[1] != dims:
        raise ValueError(f"{name} must have shape (N, {dims}), got {array.shape}")
    return array


def as_coordinate_arrays(x, y, z=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate matching 1-D coordinate arrays (mm); an absent or empty ``z`` means the work plane."""
    x = as_finite_array(np.atleast_1d(x), "x", ndim=1)
    y = as_finite_array(np.atleast_1d(y), "y", ndim=1)
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same length, got {x.size} and {y.size}")
    if z is None or np.size(z) == 0:
        z = np.zeros_like(x)
    else:
        z = as_finite_array(np.atleast_1d(z), "z", ndim=1)
        if z.shape != x.shape:
            raise ValueError(f"z must be empty or have the length of x ({x.size}), got {z.size}")
    return x, y, z


def as_positive_number(value, name: str) -> float:
    """Return ``value`` as a positive finite float or raise ValueError naming ``name``."""
    number = _as_scalar(value, name)
    if not np.isfinite(number) or number <= 0.0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return number


def as_non_negative_number(value, name: str) -> float:
    """Return ``value`` as a non-negative finite float or raise ValueError naming ``name``."""
    number = _as_scalar(value, name)
    if not np.isfinite(number) or number < 0.0:
        raise ValueError(f"{name} must be a non-negative finite number, got {value!r}")
    return number


def as_integer_at_least(value, name: str, minimum: int) -> int:
    """Return ``value`` as an int >= ``minimum`` (bools and non-integral numbers refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def as_matching_points(first, second, first_name: str, second_name: str, dims: int,
                       min_length: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Validate two finite (N, dims) point arrays of the same length (paired samples)."""
    first = as_points(first, first_name, dims, min_length)
    second = as_points(second, second_name, dims, min_length)
    if first.shape[0] != second.shape[0]:
        raise ValueError(f"{first_name} and {second_name} must have the same number of points, "
                         f"got {first.shape[0]} and {second.shape[0]}")
    return first, second


def _as_scalar(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None


def require_mapping(value, what: str) -> Mapping:
    """Return ``value`` if it is a mapping, else raise ValueError naming ``what`` and the type found."""
    if not isinstance(value, Mapping):
        raise ValueError(f"{what} must be a mapping, got {type(value).__name__}")
    return value


def require_key(data: Mapping, key: str, what: str = "model description") -> Any:
    """``data[key]``, or ValueError saying that ``what`` lacks ``key``."""
    if key not in data:
        raise ValueError(f"{what} lacks key '{key}'")
    return data[key]


def require_type(data: Any, expected: str) -> Mapping:
    """Return a stored model description: a mapping whose ``type`` is ``expected`` (ValueError otherwise)."""
    require_mapping(data, "model description")
    if data.get("type") != expected:
        raise ValueError(f"model type must be '{expected}', got {data.get('type')!r}")
    return data


def as_config_number(value: Any, key: str, what: str) -> float:
    """Return a finite number read from a configuration file (bools refused); ValueError names ``what`` ``key``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{what} {key!r} must be a finite number, got {value!r}")
    return float(value)
